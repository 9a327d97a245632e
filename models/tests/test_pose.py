"""The pose stage (pose.py): its targets, and a smoke run that adds a pose encoder to a trained
model, whose z_E then reads it, through export, import and the node."""

import json
import shutil

import numpy as np
import pytest
import torch

from gdvae.cli import main
from gdvae.import_bundle import import_bundle
from gdvae.pose import BodyTargets, PoseTargets
from gdvae.train import load_run


def truths(rng, family, count, joints):
    return [{"family": family, "theta": list(rng.normal(size=joints) * np.arange(1, joints + 1))} for _ in range(count)]


def test_pose_targets_are_each_family_s_top_components_in_units_of_their_spread():
    rng = np.random.default_rng(0)
    # The families have skeletons of different sizes: each is projected on its own axes.
    records = truths(rng, "quadruped", 40, 9) + truths(rng, "biped", 30, 6)
    targets = PoseTargets(records, components=3)
    assert targets.families == ["biped", "quadruped"]
    rows = targets.rows.numpy()
    for f in range(2):
        mine = rows[targets.family == f]
        np.testing.assert_allclose(mine.mean(0), 0, atol=1e-5)
        np.testing.assert_allclose(mine.std(0), 1, atol=1e-4)
    # The largest joint's variance dominates: the first component is mostly that joint.
    assert 0.5 < targets.explained["quadruped"] < 1.0
    with pytest.raises(ValueError, match="ground truth"):
        PoseTargets([{"family": "biped"}] * 20, components=3)
    with pytest.raises(ValueError, match="more than 3 training meshes"):
        PoseTargets(truths(rng, "biped", 3, 6), components=3)


def test_pose_targets_of_every_joint_angle_are_each_in_units_of_its_spread_and_padded_per_family():
    rng = np.random.default_rng(1)
    records = truths(rng, "quadruped", 40, 9) + truths(rng, "biped", 30, 6)
    records[0]["theta"][4] = records[1]["theta"][4] = 0.0  # a joint a family never bends has no target
    for record in records:
        if record["family"] == "biped":
            record["theta"][2] = 0.5
    targets = PoseTargets(records, components=0)
    assert targets.components == 9
    rows, mask = targets.rows.numpy(), targets.mask.numpy()
    biped, quadruped = targets.family == 0, targets.family == 1
    assert (mask[biped][:, [0, 1, 3, 4, 5]] == 1).all() and (mask[biped][:, [2, 6, 7, 8]] == 0).all()
    assert (mask[quadruped] == 1).all()
    np.testing.assert_allclose(rows[quadruped].std(0), 1, atol=1e-4)
    np.testing.assert_allclose(rows[biped][:, [0, 1, 3, 4, 5]].std(0), 1, atol=1e-4)
    assert (rows[biped][:, [2, 6, 7, 8]] == 0).all()
    # Each column is its own joint angle (not a mix of them): it follows that angle exactly.
    theta = np.array([r["theta"] for r in records if r["family"] == "quadruped"])
    assert np.corrcoef(rows[quadruped][:, 7], theta[:, 7])[0, 1] > 0.9999
    with pytest.raises(ValueError, match=">= 0"):
        PoseTargets(records, components=-1)


def test_pose_coordinates_keep_the_components_relative_sizes_so_code_distances_are_pose_distances():
    rng = np.random.default_rng(2)
    records = truths(rng, "quadruped", 60, 9) + truths(rng, "biped", 50, 6)
    targets = PoseTargets(records, components=4, whitened=False)
    rows = targets.rows.numpy()
    for f, name in enumerate(targets.families):
        mine = rows[targets.family == f]
        theta = np.array([r["theta"] for r in records if r["family"] == name])
        assert (mine ** 2).sum(1).mean() == pytest.approx(4.0, rel=1e-4)  # total variance = components
        assert mine[:, 0].std() > 1.3 * mine[:, 3].std()  # not whitened (whitened: equal)
        # Distances between rows are one scale times distances between poses on the principal axes.
        centred = theta - theta.mean(0)
        _, _, axes = np.linalg.svd(centred, full_matrices=False)
        ratio = np.linalg.norm(mine[0] - mine[1:], axis=1) / np.linalg.norm((centred[0] - centred[1:]) @ axes[:4].T, axis=1)
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-4)
    with pytest.raises(ValueError, match="whitened only"):
        PoseTargets(records, components=0, whitened=False)


def test_a_trained_pose_encoder_is_taught_again_on_every_joint_angle_with_reteach(paired_dataset, tmp_path, capsys):
    source, run = tmp_path / "source", tmp_path / "run"
    assert main(["train", str(paired_dataset), "--out", str(source), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "ae.pose_encoder=true", "--set", "ae.body_encoder=true",
                 "--set", "recipe.vae_batch=24"]) == 0
    again = ["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
             "--init-from", str(source), "--reteach", "pose", "--set", "recipe.pose_components=0",
             "--set", "recipe.vae_batch=24"]
    # keep_extrinsic keeps z_E's encoder, which reads the code being taught again.
    assert main([*again[:3], str(tmp_path / "kept"), *again[4:], "--set", "vae.keep_extrinsic=true"]) != 0
    assert "which vae.keep_extrinsic keeps" in capsys.readouterr().err
    assert main(["train", str(paired_dataset), "--out", str(tmp_path / "fresh"), "--recipe", "smoke",
                 "--reteach", "pose"]) != 0  # nothing to teach again
    assert "it goes with init_from" in capsys.readouterr().err
    source_bank = torch.load(source / "checkpoint.pt", weights_only=False)["bank"]
    without_bank = tmp_path / "without-bank"  # as an imported bundle's run is: a new bank is built anyway
    shutil.copytree(source, without_bank)
    state = torch.load(without_bank / "checkpoint.pt", weights_only=False)
    del state["bank"]
    torch.save(state, without_bank / "checkpoint.pt")
    assert main([*again[:9], str(without_bank), *again[10:]]) == 0
    stages = [json.loads(line)["stage"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert "pose" in stages and "body" not in stages and stages.index("pose") < stages.index("vae")
    _, ae, _, state = load_run(run)
    _, source_ae, _, _ = load_run(source)
    assert not torch.equal(ae.pose_encoder.head.weight, source_ae.pose_encoder.head.weight)
    assert torch.equal(ae.body_encoder.head.weight, source_ae.body_encoder.head.weight)
    assert torch.equal(ae.shape_encoder.head.weight, source_ae.shape_encoder.head.weight)
    assert not torch.equal(state["bank"]["x_p"], source_bank["x_p"])  # a new bank
    recorded = json.loads((run / "dataset.json").read_text())["pose_stage"]
    assert recorded["components"] == 0 and recorded["dataset"] == str(paired_dataset)


def test_a_pose_encoder_added_to_a_trained_model_feeds_z_e_and_survives_export_and_import(paired_dataset, tmp_path,
                                                                                          inspect_with_node):
    source, run, bundle = tmp_path / "source", tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(source), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24", "--set", "recipe.depth_camera_views=true"]) == 0
    added = ["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
             "--init-from", str(source), "--set", "ae.pose_encoder=true", "--set", "vae.keep_intrinsic=true",
             "--set", "recipe.vae_batch=24", "--set", "vae.omega_pose_contrast=50"]
    assert main(added) != 0  # the bank must be rebuilt with the pose code
    with pytest.raises(SystemExit, match="pose_encoder"):  # a pose dataset without a pose encoder
        main(["train", str(paired_dataset), "--out", str(tmp_path / "no"), "--recipe", "smoke", "--init-from",
              str(source), "--rebuild-bank", "--pose-data", str(paired_dataset)])
    # The pose stage may learn from another dataset's meshes (here the same one, by its own path).
    assert main([*added, "--rebuild-bank", "--pose-data", str(paired_dataset)]) == 0
    stages = [json.loads(line)["stage"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert "pose" in stages and stages.index("pose") < stages.index("vae")
    _, ae, vae, state = load_run(run)
    _, source_ae, _, _ = load_run(source)
    assert state["bank"]["x_p"].shape == state["bank"]["x_c"].shape
    # E_p trained away from E_x's weights; E_x and E_r are the source's.
    assert not torch.equal(ae.pose_encoder.head.weight, ae.shape_encoder.head.weight)
    assert torch.equal(ae.shape_encoder.head.weight, source_ae.shape_encoder.head.weight)
    assert torch.equal(ae.rotation_encoder.head.weight, source_ae.rotation_encoder.head.weight)
    # z_E reads the pose code and z_I does not.
    points = torch.randn(3, ae.config.points, 3) * 0.2
    with torch.no_grad():
        q = ae.encode_rotation(points)
        x_c, _ = ae.encode_shape(points, torch.eye(3).expand(3, 3, 3))
        x_p = ae.encode_pose(points, torch.eye(3).expand(3, 3, 3))
        (_, (e1, _), (i1, _)), (_, (e2, _), (i2, _)) = vae.encode(q, x_c, x_p), vae.encode(q, x_c, x_p + 1.0)
    assert not torch.allclose(e1, e2) and torch.equal(i1, i2)
    with pytest.raises(ValueError, match="pose code"):
        vae.encode(q, x_c)
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["model"]["pose_encoder"] is True
    assert manifest["training"]["pose_stage"]["dataset"] == str(paired_dataset)
    assert "pose encoder's code" in (bundle / "MODEL_CARD.md").read_text()
    summary = import_bundle(bundle, tmp_path / "imported")  # parity checked inside
    assert summary["parity_max_diff"] < 1e-4
    _, imported_ae, _, _ = load_run(tmp_path / "imported")
    assert imported_ae.pose_encoder is not None
    assert "z_E from a pose encoder" in inspect_with_node(bundle)


def test_a_narrower_pose_encoder_starts_afresh_and_its_widths_travel_in_the_bundle(paired_dataset, tmp_path):
    source, run, bundle = tmp_path / "source", tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(source), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24", "--stop-after", "bank"]) == 0
    assert main(["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
                 "--init-from", str(source), "--rebuild-bank", "--set", "ae.pose_encoder=true",
                 "--set", "ae.pose_hidden=8,12", "--set", "recipe.vae_batch=24"]) == 0
    _, ae, _, _ = load_run(run)
    assert [layer.out_channels for layer in ae.pose_encoder.shared if isinstance(layer, torch.nn.Conv1d)] == [8, 12]
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    assert json.loads((bundle / "manifest.json").read_text())["model"]["pose_hidden"] == [8, 12]
    assert import_bundle(bundle, tmp_path / "imported")["parity_max_diff"] < 1e-4
    _, imported, _, _ = load_run(tmp_path / "imported")
    assert imported.config.pose_hidden == (8, 12)


def test_body_targets_are_each_family_s_normalised_beta_in_units_of_its_spread():
    rng = np.random.default_rng(1)
    records = ([{"family": "biped", "beta": list(rng.uniform(0, 2, 3))} for _ in range(30)]
               + [{"family": "quadruped", "beta": list(rng.uniform(5, 9, 5))} for _ in range(40)])
    targets = BodyTargets(records, ranges={})
    assert targets.families == ["biped", "quadruped"] and targets.components == 5
    rows, mask = targets.rows.numpy(), targets.mask.numpy()
    biped = targets.family == 0
    # A family with fewer parameters is padded, and the padding is masked out of the loss.
    np.testing.assert_array_equal(mask[biped], np.tile([1, 1, 1, 0, 0], (30, 1)))
    np.testing.assert_array_equal(rows[biped][:, 3:], 0)
    for f in range(2):
        own = rows[targets.family == f][:, : int(mask[targets.family == f][0].sum())]
        np.testing.assert_allclose(own.mean(0), 0, atol=1e-5)
        np.testing.assert_allclose(own.std(0), 1, atol=1e-4)
    with pytest.raises(ValueError, match="ground truth"):
        BodyTargets([{"family": "biped"}] * 5, ranges={})
    with pytest.raises(ValueError, match="beta differs"):
        BodyTargets([{"family": "biped", "beta": [1.0, 2.0]}] * 5, ranges={})


def test_a_body_encoder_added_to_a_pose_model_feeds_z_i_only_and_survives_export_and_import(
        paired_dataset, tmp_path, inspect_with_node):
    source, run, bundle = tmp_path / "source", tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(source), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "ae.pose_encoder=true", "--set", "recipe.vae_batch=24"]) == 0
    added = ["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
             "--init-from", str(source), "--set", "ae.body_encoder=true", "--set", "ae.body_hidden=8,12",
             "--set", "vae.keep_extrinsic=true", "--set", "recipe.vae_batch=24"]
    assert main(added) != 0  # the bank must be rebuilt with the body code
    with pytest.raises(SystemExit, match="body_encoder"):  # a body dataset without a body encoder
        main(["train", str(paired_dataset), "--out", str(tmp_path / "no"), "--recipe", "smoke", "--init-from",
              str(source), "--rebuild-bank", "--body-data", str(paired_dataset)])
    # keep_intrinsic keeps z_I's encoder, which cannot then read a new code.
    assert main(["train", str(paired_dataset), "--out", str(tmp_path / "kept"), "--recipe", "smoke", "--regime",
                 "paired", "--init-from", str(source), "--rebuild-bank", "--set", "ae.body_encoder=true",
                 "--set", "vae.keep_intrinsic=true", "--set", "recipe.vae_batch=24"]) != 0
    assert main([*added, "--rebuild-bank", "--body-data", str(paired_dataset)]) == 0
    stages = [json.loads(line)["stage"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert "body" in stages and "pose" not in stages and stages.index("body") < stages.index("vae")
    _, ae, vae, state = load_run(run)
    _, source_ae, source_vae, _ = load_run(source)
    assert state["bank"]["x_b"].shape == state["bank"]["x_c"].shape == state["bank"]["x_p"].shape
    assert [layer.out_channels for layer in ae.body_encoder.shared if isinstance(layer, torch.nn.Conv1d)] == [8, 12]
    # E_p, E_x and z_E's encoder are the source's (keep_extrinsic); z_I's encoder trained.
    assert torch.equal(ae.pose_encoder.head.weight, source_ae.pose_encoder.head.weight)
    assert torch.equal(ae.shape_encoder.head.weight, source_ae.shape_encoder.head.weight)
    for key, value in source_vae.extrinsic.state_dict().items():
        assert torch.equal(vae.extrinsic.state_dict()[key], value)
    # z_I reads the body code and z_E does not.
    points = torch.randn(3, ae.config.points, 3) * 0.2
    eye = torch.eye(3).expand(3, 3, 3)
    with torch.no_grad():
        q = ae.encode_rotation(points)
        x_c, _ = ae.encode_shape(points, eye)
        codes = ae.taught_codes(points, eye)
        (_, (e1, _), (i1, _)) = vae.encode(q, x_c, **codes)
        (_, (e2, _), (i2, _)) = vae.encode(q, x_c, codes["x_p"], codes["x_b"] + 1.0)
    assert torch.equal(e1, e2) and not torch.allclose(i1, i2)
    with pytest.raises(ValueError, match="body code"):
        vae.encode(q, x_c, codes["x_p"])
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["model"]["body_encoder"] is True and manifest["model"]["body_hidden"] == [8, 12]
    assert manifest["training"]["body_stage"]["dataset"] == str(paired_dataset)
    assert "body encoder's code" in (bundle / "MODEL_CARD.md").read_text()
    assert import_bundle(bundle, tmp_path / "imported")["parity_max_diff"] < 1e-4
    _, imported_ae, _, _ = load_run(tmp_path / "imported")
    assert imported_ae.body_encoder is not None and imported_ae.config.body_hidden == (8, 12)
    assert "z_I from a body encoder" in inspect_with_node(bundle)


def test_mu_i_taught_beta_and_mu_e_theta_train_on_the_bank_s_meshes_and_leave_no_heads_in_the_bundle(
        paired_dataset, tmp_path):
    run, bundle = tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24", "--set", "vae.omega_body=10",
                 "--set", "vae.omega_pose=10"]) == 0
    logged = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    for name in ("body", "pose"):
        values = [row[name] for row in logged if row.get("stage") == "vae" and name in row]
        assert values and all(value > 0 for value in values)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert any(key.startswith("body_heads.") for key in state["vae"])  # trained, and resumable
    _, _, vae, _ = load_run(run)
    assert vae.body_heads is None  # the trained model is the bundle's: the heads exist only in training
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    assert import_bundle(bundle, tmp_path / "imported")["parity_max_diff"] < 1e-4
    # A run that starts from this one's VAE drops its heads (keep_intrinsic: z_E trained on, taught theta again).
    assert main(["train", str(paired_dataset), "--out", str(tmp_path / "next"), "--recipe", "smoke", "--regime",
                 "paired", "--init-from", str(run), "--set", "vae.keep_intrinsic=true", "--set", "vae.omega_pose=5",
                 "--set", "recipe.vae_batch=24"]) == 0


def test_a_run_started_from_another_run_s_code_bank_on_another_dataset_is_refused_before_any_work(
        paired_dataset, tmp_path, capsys):
    run, other = tmp_path / "run", tmp_path / "other"
    assert main(["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24"]) == 0
    shutil.copytree(paired_dataset, other)  # the bank's rows are the source's training meshes, row for row
    shutil.rmtree(other / ".spectra", ignore_errors=True)
    started = ["train", str(other), "--out", str(tmp_path / "next"), "--recipe", "smoke", "--regime", "paired",
               "--init-from", str(run), "--set", "vae.keep_intrinsic=true", "--set", "recipe.vae_batch=24"]
    assert main(started) != 0
    error = capsys.readouterr().err
    assert "code bank holds the codes of" in error and "--rebuild-bank" in error
    assert not (other / ".spectra").exists() and not (tmp_path / "next" / "checkpoint.pt").exists()
    assert main([*started, "--rebuild-bank"]) == 0  # a new bank of this dataset's meshes


def test_mu_i_taught_beta_directly_has_no_heads_and_the_model_card_says_so(paired_dataset, tmp_path, capsys):
    run, bundle = tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24", "--set", "vae.omega_body=10",
                 "--set", "vae.body_direct=true"]) == 0
    logged = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [row["body"] for row in logged if row.get("stage") == "vae" and "body" in row][-1] > 0
    assert not any(key.startswith("body_heads.") for key in torch.load(run / "checkpoint.pt", weights_only=False)["vae"])
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    assert "mu_I was taught the body shape (vae.omega_body 10) directly" in (bundle / "MODEL_CARD.md").read_text()
    capsys.readouterr()
    assert main(["train", str(paired_dataset), "--out", str(tmp_path / "no"), "--recipe", "smoke",
                 "--set", "vae.body_direct=true"]) != 0  # how omega_body teaches: nothing without it
    assert "body_direct says how omega_body teaches mu_I" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()  # refused before any work, not after the AE stage
