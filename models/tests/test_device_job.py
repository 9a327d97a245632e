"""The GPU recipe's device job (models/device/run.sh) run end to end on this CPU at smoke size:
the same script, its smoke step, dataset generation, training with stage budgets (and loader
workers, which only a CPU uses), export and the files that come back, so that a lent
accelerator's minutes are not spent finding its bugs."""

import json
import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SIM = ROOT / "target" / "release" / "sim"


@pytest.mark.skipif(not SIM.exists(), reason="needs the sim binary (make binaries)")
@pytest.mark.parametrize("init", ["", "models/bundles/cpu-fo"], ids=["fresh", "continued"])
def test_the_device_job_runs_at_smoke_size_and_returns_at_most_eight_files(tmp_path, init):
    out = tmp_path / "out"
    # The continued job runs its smoke step first, as on a device; the fresh one skips it and has
    # asked for more AE minutes than its deadline leaves, so its AE budget gives way.
    extra = {"SMOKE_FIRST": "1"} if init else {"SMOKE_FIRST": "0", "AE_MINUTES": "5", "DEADLINE_S": "1"}
    done = subprocess.run(["bash", "models/device/run.sh"], cwd=ROOT, env=job_environment(tmp_path, init, extra),
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert ("smoke step passed" in done.stdout) == bool(init)
    assert "AE budget: 0.05 min" in done.stdout
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert len(files) <= 8, files  # the device tool returns at most 8 files
    assert {"bundle/manifest.json", "bundle/encoder.onnx", "train.log", "run.json"} <= set(files)
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    record = json.loads((out / "run.json").read_text())
    assert record["stages"]["ae"]["device"] == "cpu" and manifest["training"]["ae_device"] == "cpu"
    assert manifest["calibration"]["z_I_variance_scale"] > 0
    if init:  # the shipped AE, continued: its sizes, trained on until the budget ended it
        assert manifest["sizes"]["points"] == 256 and record["stages"]["ae"]["ended_by_time_budget"]
    assert max(p.stat().st_size for p in out.rglob("*") if p.is_file()) < 16 * 2**20


def job_environment(tmp_path, init: str, extra: dict) -> dict:
    return {
        **os.environ, "OUT": str(tmp_path / "out"), "DEVICE": "cpu", "RECIPE": "smoke", "SUBJECTS": "5",
        "POSES": "2", "AE_MINUTES": "0.05", "VAE_MINUTES": "0.02", "WORKERS": "1", "INIT": init,
        "PYTHON": str(ROOT / ".venv" / "bin" / "python"), "WORK": str(tmp_path / "work"), "SIM": str(SIM), **extra,
    }


@pytest.mark.skipif(not SIM.exists(), reason="needs the sim binary (make binaries)")
def test_a_failing_smoke_step_stops_the_job_before_it_trains_and_returns_its_log(tmp_path):
    done = subprocess.run(["bash", "models/device/run.sh"], cwd=ROOT,
                          env=job_environment(tmp_path, "models/bundles/no-such-bundle", {}),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "the smoke step failed" in done.stdout
    assert not (tmp_path / "work" / "run").exists()  # nothing trained
    out = tmp_path / "out"
    assert "no-such-bundle" in (out / "smoke.log").read_text()
    assert not (out / "bundle").exists()
