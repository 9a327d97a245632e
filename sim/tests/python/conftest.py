"""Shared set-up for the sim's Python checks: where the `sim` binary is (built by `make test`)."""

import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[3]
SIM = os.environ.get("SIM_BIN", str(ROOT / "target" / "release" / "sim"))


@pytest.fixture(scope="session", autouse=True)
def sim_binary_exists():
    if not pathlib.Path(SIM).is_file():
        pytest.fail(f"sim binary not found at {SIM}: run `cargo build --release -p gdvae-sim` or set SIM_BIN")
