"""`python -m gdvae fit-identity`: the identity projection finds the directions in which subjects of
one family differ, not those in which one subject wanders, and writes them into the bundle."""

import json

import numpy as np
import pytest

from gdvae.cli import main
from gdvae.identity import fit_projection, read_states

WIDTH = 12


def write_states(path, rng, subjects=6, frames=60, x_c=True):
    """Two families; a subject differs from its family's others only along x_c's dimensions 0 and 1
    (spread 1), while every frame wanders far more along 2-5 (spread 3) and a little elsewhere."""
    with open(path, "w") as out:
        for family in ("biped", "quadruped"):
            for s in range(subjects):
                offset = np.zeros(WIDTH)
                offset[:2] = rng.normal(0.0, 1.0, 2)
                for frame in range(frames):
                    wander = rng.normal(0.0, 0.2, WIDTH)
                    wander[2:6] = rng.normal(0.0, 3.0, 4)
                    row = {"state": {"stream": f"{family}-{s}"}, "truth": {"family": family, "subject": f"{family}-{s}",
                                                                           "frame": frame}}
                    if x_c:
                        row["x_c"] = list(offset + wander)
                    out.write(json.dumps(row) + "\n")
        out.write(json.dumps({"state": {}, "truth": None, "x_c": [0.0] * WIDTH}) + "\n")


def test_the_projection_reads_the_subject_not_the_wander(tmp_path):
    write_states(tmp_path / "states.jsonl", np.random.default_rng(0))
    by_subject, unmatched = read_states([str(tmp_path / "states.jsonl")])
    assert unmatched == 1 and len(by_subject) == 12
    fitted = fit_projection(by_subject, directions=2, ridge=0.0)
    matrix = fitted["matrix"]
    # The two directions read the subjects' plane (dimensions 0 and 1), not the wander: what the
    # wander's dimensions add to a projection (weight x their spread 3) is a small part of it.
    weight = np.abs(matrix)
    assert np.all(weight[:, :2].sum(1) > 10 * 3.0 * weight[:, 2:6].sum(1))
    # Unit spread within a subject along each direction, and subjects far apart in those units.
    within = np.concatenate([(np.stack(codes) - np.stack(codes).mean(0)) @ matrix.T for codes in by_subject.values()])
    assert np.allclose(within.std(0), 1.0, atol=0.05)
    assert fitted["between_within"][0] > 10
    assert fitted["subjects"] == {"biped": 6, "quadruped": 6}


def test_fit_identity_writes_the_projection_into_the_manifest_and_keeps_the_rest(tmp_path, capsys):
    write_states(tmp_path / "states.jsonl", np.random.default_rng(1))
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    manifest = {"sizes": {"x_c": WIDTH}, "calibration": {"z_I_variance_scale": 0.5},
                "files": {"encoder.onnx": {"sha256": "ab12"}}}
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    assert main(["fit-identity", str(bundle), str(tmp_path / "states.jsonl"), "--directions", "3"]) == 0
    written = json.loads((bundle / "manifest.json").read_text())
    projection = written["calibration"]["identity_projection"]
    assert projection["input"] == "x_c" and len(projection["matrix"]) == 3
    assert projection["encoder_sha256"] == "ab12"
    assert all(len(row) == WIDTH for row in projection["matrix"])
    assert projection["fitted_on"]["subjects"] == {"biped": 6, "quadruped": 6}
    assert written["calibration"]["z_I_variance_scale"] == 0.5 and written["files"] == manifest["files"]
    assert "3 directions of x_c fitted on 6 bipeds, 6 quadrupeds" in capsys.readouterr().out
    assert not (bundle / "MODEL_CARD.md").exists()  # a card is rewritten, never made up
    # An exported bundle's card is rewritten to name the projection.
    manifest.update({"model": {"regime": "fo", "ae_type": "std", "supervision": "supervised", "recipe": "cpu"},
                     "sizes": {"points": 256, "spectrum": 22, "x_c": WIDTH, "z_R": 3, "z_E": 10, "z_I": 22},
                     "units": {"model_units_per_metre": 0.5, "up_axis": "+z", "rotation_mode": "yaw"},
                     "training": {}, "metrics": {},
                     "calibration": {"z_I_variance_scale": 0.5, "ratio_p10": 0.4, "ratio_p90": 0.6, "measured_on": "x"}})
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    (bundle / "MODEL_CARD.md").write_text("an old card")
    assert main(["fit-identity", str(bundle), str(tmp_path / "states.jsonl"), "--directions", "3"]) == 0
    card = (bundle / "MODEL_CARD.md").read_text()
    assert "Identity projection" in card and "3 directions of x_c" in card and "fitted on 12 sim subjects" in card


def test_states_without_x_c_or_a_lone_subject_are_refused_with_the_reason(tmp_path, capsys):
    write_states(tmp_path / "old.jsonl", np.random.default_rng(2), x_c=False)
    with pytest.raises(ValueError, match="line 1: no x_c"):
        read_states([str(tmp_path / "old.jsonl")])
    write_states(tmp_path / "one.jsonl", np.random.default_rng(3), subjects=1)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps({"sizes": {"x_c": WIDTH}, "files": {"encoder.onnx": {"sha256": "ab"}}}))
    assert main(["fit-identity", str(bundle), str(tmp_path / "one.jsonl")]) == 2
    assert "family 'biped' has 1 subject" in capsys.readouterr().err
    # Nothing was written on failure.
    assert "calibration" not in json.loads((bundle / "manifest.json").read_text())
