"""The paper-structured evaluation set (`make eval-split`, models/README.md "Evaluation split"):
`sim dataset --poses 1 --split 0,0,1` with its own seed gives one pose per subject, every subject
in the test split, and subjects disjoint from a training set made with another seed (checked by
their beta: subject names restart at 0000 in every dataset)."""

import json
import subprocess

from conftest import SIM


def dataset(path, seed, subjects, poses, split):
    subprocess.run([SIM, "dataset", "--out", str(path), "--subjects", str(subjects), "--poses", str(poses),
                    "--split", split, "--vertices", "800", "--seed", str(seed)], check=True, capture_output=True)
    return [json.loads(line) for line in (path / "ground_truth.jsonl").read_text().splitlines()]


def test_the_evaluation_split_is_one_pose_per_subject_and_subject_disjoint(tmp_path):
    evaluation = dataset(tmp_path / "eval", 9000, 4, 1, "0,0,1")
    training = dataset(tmp_path / "train", 0, 4, 2, "0.5,0.25,0.25")
    assert len(evaluation) == 8, "4 subjects x 2 families"
    assert all(t["split"] == "test" for t in evaluation)
    subjects = [(t["family"], t["subject"]) for t in evaluation]
    assert len(set(subjects)) == len(subjects), "one pose per subject"
    seen = {tuple(t["beta"]) for t in training}
    assert not any(tuple(t["beta"]) in seen for t in evaluation), "no training subject in the evaluation set"
    description = json.loads((tmp_path / "eval" / "dataset.json").read_text())
    assert all(f["beta"] for f in description["families"].values()), "beta ranges for E_beta's normalisation"
