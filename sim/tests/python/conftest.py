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


def free_port():
    """A TCP port on loopback that nothing listens on right now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def zenoh_listener():
    """A zenoh peer listening on a fresh loopback port, multicast off: (session, endpoint)."""
    import json

    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    yield session, endpoint
    session.close()
