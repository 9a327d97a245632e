"""z_I taught to tell subjects apart on the node's own x_c (node_identity.py, `train --node-states`)."""
import json

import pytest
import torch

from gdvae.cli import main
from gdvae.data import load_dataset
from gdvae.geometry import random_rotation_matrices, rotate
from gdvae.node_identity import FRAMES_PER_SUBJECT, NodeIdentityBatches, NodeIdentityData
from gdvae.paired import contrast_masks, identity_contrast
from gdvae.surface import PointSampler
from gdvae.train import load_run


def write_states(path, rows):
    """A `gdvae-node evaluate --states` file: per frame the node's state, the sim's truth and x_c."""
    with open(path, "w") as out:
        for number, (family, subject, x_c) in enumerate(rows):
            truth = None if subject is None else {"frame": number, "family": family, "subject": subject}
            out.write(json.dumps({"state": {"stream": "s", "sequence": number}, "truth": truth,
                                  "x_c": [float(v) for v in x_c]}) + "\n")


def node_like_states(run, dataset_root, path, copies=3):
    """x_c of the run's AE for every mesh of the dataset (each subject in its poses), `copies`
    rotations each, as the node's states would hold them."""
    _, ae, _, _ = load_run(run)
    dataset = load_dataset(dataset_root)
    indices = list(range(len(dataset.meshes)))
    torch.manual_seed(0)
    clouds = PointSampler(dataset, indices, ae.config.points, 0).views(indices, copies, 0.0)
    with torch.no_grad():
        rotations = random_rotation_matrices(len(clouds))
        x_c, _ = ae.encode_shape(rotate(clouds, rotations), rotations)
    truths = [dataset.items[i].truth for i in indices] * copies
    write_states(path, [(t["family"], t["subject"], code) for t, code in zip(truths, x_c)]
                 + [("biped", None, x_c[0])])  # a frame without truth is left out
    return x_c.shape[1]


def contrast_on(run, data: NodeIdentityData) -> float:
    _, _, vae, _ = load_run(run)
    with torch.no_grad():
        return float(identity_contrast(vae.intrinsic(data.x_c)[0], data.subject, data.family,
                                       vae.config.contrast_temperature))


def test_a_z_i_taught_on_the_node_s_states_tells_their_subjects_apart_better_and_says_so(
        paired_dataset, tmp_path, capsys):
    start, run, bundle, states = tmp_path / "start", tmp_path / "run", tmp_path / "bundle", tmp_path / "s.jsonl"
    assert main(["train", str(paired_dataset), "--out", str(start), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24"]) == 0
    width = node_like_states(start, paired_dataset, states)
    data = NodeIdentityData.from_states([str(states)], width)
    assert data.summary()["frames"] == len(data.x_c) == 3 * len(load_dataset(paired_dataset).meshes)
    taught = ["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
              "--init-from", str(start), "--set", "vae.keep_extrinsic=true", "--set", "recipe.vae_batch=24",
              "--set", "recipe.vae_iterations=80", "--set", "recipe.vae_learning_rate=0.003"]
    # The states and the weight go together; either alone is refused before any work.
    assert main([*taught, "--set", "vae.omega_node_identity=100"]) != 0
    assert "--node-states" in capsys.readouterr().err and not (run / "checkpoint.pt").exists()
    assert main([*taught, "--node-states", str(states)]) != 0
    assert "omega_node_identity" in capsys.readouterr().err and not (run / "checkpoint.pt").exists()
    assert main([*taught, "--set", "vae.omega_node_identity=100", "--node-states", str(states)]) == 0
    logged = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [row["node_identity"] for row in logged if row.get("stage") == "vae"][-1] > 0
    # The term moves z_I: the contrast on the node's frames falls below the starting VAE's.
    assert contrast_on(run, data) < contrast_on(start, data)
    recorded = json.loads((run / "dataset.json").read_text())["node_identity"]
    assert recorded["frames"] == len(data.x_c) and sum(recorded["subjects"].values()) == len(data.subject.unique())
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    card = (bundle / "MODEL_CARD.md").read_text()
    assert "taught to tell subjects apart on the node's own clouds (vae.omega_node_identity 100)" in card
    assert f"{len(data.x_c)} frames" in card and "not to stay near the unit prior" in card


def test_node_states_that_cannot_teach_the_contrast_are_refused_with_the_reason(tmp_path):
    path = tmp_path / "s.jsonl"
    write_states(path, [("biped", "b0", [0.0, 1.0]), ("biped", "b0", [0.0, 1.1]), ("biped", "b1", [1.0, 0.0]),
                        ("biped", "b1", [1.1, 0.0])])
    assert NodeIdentityData.from_states([str(path)], 2).summary()["subjects"] == {"biped": 2}
    with pytest.raises(ValueError, match="x_c has \\[2\\] numbers, this run's AE 3"):
        NodeIdentityData.from_states([str(path)], 3)
    write_states(path, [("biped", "b0", [0.0, 1.0]), ("biped", "b0", [0.0, 1.1]), ("quadruped", "q0", [1.0, 0.0]),
                        ("quadruped", "q0", [1.1, 0.0])])
    with pytest.raises(ValueError, match="family 'biped' has 1 subject"):
        NodeIdentityData.from_states([str(path)], 2)
    write_states(path, [("biped", "b0", [0.0, 1.0]), ("biped", "b1", [1.0, 0.0]), ("biped", "b1", [1.1, 0.0])])
    with pytest.raises(ValueError, match="subject 'b0' \\(biped\\) has one frame"):
        NodeIdentityData.from_states([str(path)], 2)
    write_states(path, [("biped", None, [0.0, 1.0])])
    with pytest.raises(ValueError, match="no frame with the sim's truth"):
        NodeIdentityData.from_states([str(path)], 2)


def test_node_identity_batches_give_every_row_a_positive_and_a_same_family_negative():
    subject = torch.tensor([0] * 5 + [1] * 2 + [2] * 9 + [3] * 3 + [4] * 4 + [5] * 2)
    family = torch.tensor([0] * 7 + [1] * 12 + [0] * 4 + [1] * 2)
    data = NodeIdentityData(torch.randn(len(subject), 6), subject, family, ["biped", "quadruped"], [])
    batches = NodeIdentityBatches(data, 5 * FRAMES_PER_SUBJECT, seed=0)
    for _ in range(20):
        x_c, drawn, families = next(batches)
        assert len(x_c) == 5 * FRAMES_PER_SUBJECT and len(drawn.unique()) == 5
        positive, negative = contrast_masks(drawn, families)
        # Every frame is its own subject's, with its family (a positive is never another subject).
        assert torch.equal(families, torch.tensor([0, 0, 1, 1, 0, 1])[drawn]) and bool((drawn[:, None] == drawn[None])[positive].all())
        assert bool(positive.any(1).all())
        # With five of the six subjects drawn, each family keeps two or more of its three.
        assert bool(negative.any(1).all())
