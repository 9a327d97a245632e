"""The paired regime (paired.py): the pairing and its batches, the swap and contrast terms, and a
smoke run through training, export and the node on a dataset with shared poses."""

import json

import numpy as np
import pytest
import torch

from gdvae.cli import main
from gdvae.paired import PairedBatches, Pairing, contrast_masks, identity_contrast, swap_error
from gdvae.vae import LatentVAE, VAEConfig, vae_loss


def grid_truths(families=("quadruped", "biped"), subjects=4, poses=5, drop=()):
    """Ground-truth records of a subjects x poses grid per family (minus the `drop` files)."""
    truths = []
    for family in families:
        for s in range(subjects):
            for p in range(poses):
                file = f"{family}-{s}-{p}"
                if file not in drop:
                    truths.append({"file": file, "family": family, "subject": f"{family}-{s:04d}",
                                   "pose_id": f"{family}-pose-{p:03d}"})
    return truths


def test_paired_batches_are_triples_of_one_family_with_the_right_swap_meshes():
    truths = grid_truths(drop={"biped-1-2", "quadruped-3-0"})
    pairing = Pairing.from_truths(truths)
    batches = PairedBatches(pairing, copies=3, seed=0)
    for _ in range(20):
        drawn = batches.draw(96)
        r = drawn.rows
        assert r == 32 and len(drawn.entries) == 3 * r and len(drawn.swap_meshes) == 2 * r
        meshes = drawn.entries // 3
        a, b, c = (truths_of(truths, meshes[k * r:(k + 1) * r]) for k in range(3))
        ab, ba = truths_of(truths, drawn.swap_meshes[:r]), truths_of(truths, drawn.swap_meshes[r:])
        for ta, tb, tc, tab, tba in zip(a, b, c, ab, ba):
            assert ta["family"] == tb["family"] == tc["family"]
            # B is another subject in another pose; C is A's subject in another pose.
            assert tb["subject"] != ta["subject"] and tb["pose_id"] != ta["pose_id"]
            assert tc["subject"] == ta["subject"] and tc["pose_id"] != ta["pose_id"]
            # The swaps: B's subject in A's pose, A's subject in B's pose.
            assert (tab["subject"], tab["pose_id"]) == (tb["subject"], ta["pose_id"])
            assert (tba["subject"], tba["pose_id"]) == (ta["subject"], tb["pose_id"])
    assert set(drawn.entries % 3) == {0, 1, 2}, "every copy (view) of a mesh is drawn"


def truths_of(truths, meshes):
    return [truths[m] for m in meshes]


def test_pose_pairs_add_b_in_a_s_pose_as_a_fourth_row():
    truths = grid_truths(drop={"biped-1-2", "quadruped-3-0"})
    batches = PairedBatches(Pairing.from_truths(truths), copies=3, seed=0, pose_pairs=True)
    for _ in range(20):
        drawn = batches.draw(96)
        r = drawn.rows
        assert r == 24 and len(drawn.entries) == 4 * r and len(drawn.swap_meshes) == 2 * r
        a, b, _, d = (truths_of(truths, drawn.entries[k * r:(k + 1) * r] // 3) for k in range(4))
        for ta, tb, td in zip(a, b, d):
            # D shows A's pose on B's subject: a pose positive for A across subjects.
            assert (td["subject"], td["pose_id"]) == (tb["subject"], ta["pose_id"])
            assert td["subject"] != ta["subject"]


def test_a_dataset_without_shared_poses_cannot_be_paired():
    truths = grid_truths()
    del truths[3]["pose_id"]
    with pytest.raises(ValueError, match="--shared-poses"):
        Pairing.from_truths(truths, "some/dataset")
    with pytest.raises(ValueError, match="nothing to pair"):
        Pairing.from_truths(grid_truths(subjects=1))


def test_the_swap_error_is_zero_for_a_decoder_that_swaps_exactly_and_positive_otherwise():
    torch.manual_seed(0)
    rows = 8
    pose_a, pose_b, shape_a, shape_b = (torch.randn(rows, 3) for _ in range(4))
    # A code is (pose, shape); an exact decoder concatenates (z_E, z_I).
    z_e, z_i = torch.cat([pose_a, pose_b]), torch.cat([shape_a, shape_b])
    targets = torch.cat([torch.cat([pose_a, shape_b], -1), torch.cat([pose_b, shape_a], -1)])
    norm = torch.tensor(2.0)
    exact = swap_error(lambda z: z, z_e, z_i, targets, norm)
    assert exact.item() == 0.0
    # A decoder that takes the pose from z_I's owner (no swap) or ignores z_E is wrong.
    unswapped = torch.cat([torch.cat([pose_a, shape_a], -1), torch.cat([pose_b, shape_b], -1)])
    assert swap_error(lambda z: unswapped, z_e, z_i, targets, norm).item() > 0.5
    ignores_pose = swap_error(lambda z: torch.cat([torch.zeros(2 * rows, 3), z[:, 3:]], -1), z_e, z_i, targets, norm)
    assert ignores_pose.item() == pytest.approx(float(torch.cat([pose_a, pose_b]).pow(2).sum(-1).mean() / 2))


def test_the_contrast_never_pairs_two_subjects_as_positives_and_ignores_other_families():
    subject = torch.tensor([0, 0, 1, 2, 2, 3])
    family = torch.tensor([0, 0, 0, 0, 0, 1])
    positive, negative = contrast_masks(subject, family)
    for i in range(6):
        for j in range(6):
            assert bool(positive[i, j]) == (i != j and subject[i] == subject[j])
            assert bool(negative[i, j]) == (subject[i] != subject[j] and family[i] == family[j])
    assert not (positive & negative).any() and not positive.diagonal().any()
    assert not positive[5].any() and not negative[5].any(), "a lone family's row has nothing to contrast"


def test_the_contrast_is_low_when_subjects_cluster_high_when_they_do_not_and_scale_free():
    torch.manual_seed(0)
    subject = torch.arange(10).repeat_interleave(4)
    family = torch.zeros(40, dtype=torch.long)
    centres = 5 * torch.randn(10, 6)
    clustered = centres[subject] + 0.1 * torch.randn(40, 6)
    shuffled = torch.randn(40, 6)
    low = identity_contrast(clustered, subject, family, 0.1).item()
    high = identity_contrast(shuffled, subject, family, 0.1).item()
    assert low < 0.05 and high > 1.5
    assert identity_contrast(0.01 * clustered, subject, family, 0.1).item() == pytest.approx(low, rel=1e-3)


def test_the_paired_terms_train_the_vae_and_are_refused_without_a_paired_batch():
    torch.manual_seed(0)
    base = dict(latent=24, spectrum=6, n_extrinsic=3, width_scale=0.02, flow_layers=3, flow_hidden=32)
    model = LatentVAE(VAEConfig.paired_regime(**base))
    rows = 6
    q = torch.nn.functional.normalize(torch.randn(3 * rows, 4), dim=-1)
    x_c, spectra = torch.randn(3 * rows, 24), torch.rand(3 * rows, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    paired = {"targets": torch.randn(2 * rows, 24), "own_targets": torch.randn(3 * rows, 24), "subject": torch.cat([torch.arange(rows), rows + torch.arange(rows),
                                                                          torch.arange(rows)]),
              "family": torch.zeros(3 * rows, dtype=torch.long)}
    losses = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False, paired=paired)
    assert losses.parts["swap"] > 0 and losses.parts["identity_contrast"] > 0
    losses.total.backward()
    assert any(p.grad.abs().sum() > 0 for p in model.extrinsic.mean.parameters())
    # L_R aims at the meshes' whole-surface codes (own_targets), not at the views' codes.
    for own, compare in ((x_c, "equal"), (x_c + 3.0, "larger")):
        torch.manual_seed(1)
        parts = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False,
                         paired={**paired, "own_targets": own}).parts
        if compare == "equal":
            near = parts["reconstruction"]
        else:
            assert parts["reconstruction"] > near + 1.0
    model.config.reconstruct_canonical = False
    torch.manual_seed(1)
    assert vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False,
                    paired={**paired, "own_targets": x_c + 3.0}).parts["reconstruction"] == pytest.approx(near)
    model.config.reconstruct_canonical = True
    # The pose contrast is off unless asked; on, it reaches z_E's encoder through mu_E.
    assert losses.parts["pose_contrast"] == 0
    model.config.omega_pose_contrast = 50.0
    pose = torch.cat([torch.arange(rows), torch.arange(rows) + rows, torch.arange(rows) + 2 * rows])
    pose[2 * rows:] = torch.arange(rows)  # C shares A's pose here, a positive across subjects
    model.zero_grad()
    with_pose = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False,
                         paired={**paired, "pose": pose})
    assert with_pose.parts["pose_contrast"] > 0
    with_pose.total.backward()
    assert any(p.grad.abs().sum() > 0 for p in model.extrinsic.mean.parameters())
    model.config.omega_pose_contrast = 0.0
    with pytest.raises(ValueError, match="not paired"):
        vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False)
    with pytest.raises(ValueError, match="paired"):
        VAEConfig(omega_swap=1.0).validate()  # GDVAE++ reconstructs from z~_I, not from x_c


def test_a_paired_smoke_run_trains_exports_and_the_node_loads_it(paired_dataset, tmp_path, inspect_with_node):
    run, bundle = tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(paired_dataset), "--out", str(run), "--recipe", "smoke", "--regime", "paired",
                 "--ae", "std", "--set", "recipe.vae_batch=24", "--set", "recipe.depth_camera_views=true"]) == 0
    lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    vae = [line for line in lines if line["stage"] == "vae"]
    assert vae and vae[-1]["swap"] > 0 and vae[-1]["identity_contrast"] > 0
    # A live pose code added to a trained VAE: z_I's encoder, the flow and the rotation branch stay
    # exactly the source's, z_E's encoder and the decoder train.
    kept = tmp_path / "kept"
    assert main(["train", str(paired_dataset), "--out", str(kept), "--recipe", "smoke", "--regime", "paired",
                 "--init-from", str(run), "--set", "recipe.vae_batch=24", "--set", "vae.keep_intrinsic=true",
                 "--set", "vae.omega_pose_contrast=50"]) == 0
    before = torch.load(run / "checkpoint.pt", weights_only=False)["vae"]
    after = torch.load(kept / "checkpoint.pt", weights_only=False)["vae"]
    for name, value in after.items():
        same = torch.equal(value, before[name])
        if name.split(".")[0] in ("intrinsic", "flow", "rotation", "decode_rotation"):
            assert same, f"{name} was trained"
        elif name.startswith(("extrinsic.mean", "decode_shape")) and name.endswith("weight"):
            assert not same, f"{name} did not train"
    # The converse: a shape code retrained beside a kept pose code (z_E's encoder and the rotation
    # branch exactly the source's; z_I's encoder, the flow and the decoder train).
    reshaped = tmp_path / "reshaped"
    assert main(["train", str(paired_dataset), "--out", str(reshaped), "--recipe", "smoke", "--regime", "paired",
                 "--init-from", str(run), "--rebuild-bank", "--set", "recipe.vae_batch=24",
                 "--set", "vae.keep_extrinsic=true"]) == 0
    after = torch.load(reshaped / "checkpoint.pt", weights_only=False)["vae"]
    for name, value in after.items():
        same = torch.equal(value, before[name])
        if name.split(".")[0] in ("extrinsic", "rotation", "decode_rotation"):
            assert same, f"{name} was trained"
        elif name.startswith(("intrinsic.mean", "decode_shape")) and name.endswith("weight"):
            assert not same, f"{name} did not train"
    for keep in ("keep_intrinsic", "keep_extrinsic"):
        assert main(["train", str(paired_dataset), "--out", str(tmp_path / f"fresh-{keep}"), "--recipe", "smoke",
                     "--regime", "paired", "--set", f"vae.{keep}=true"]) != 0
    with pytest.raises(ValueError, match="decoder alone"):
        VAEConfig(regime="fo", keep_intrinsic=True, keep_extrinsic=True).validate()
    quick = tmp_path / "quick.json"
    assert main(["evaluate", str(run), str(paired_dataset), "--retrieval-only", "--out", str(quick)]) == 0
    paired = json.loads(quick.read_text())["paired_retrieval"]
    assert paired["chance"] == {"pose": pytest.approx(1 / 3), "subject": pytest.approx(1 / 2)}
    for view in ("whole", "depth_camera"):
        assert set(paired[view]) == {"pose_by_z_E", "pose_by_x_c", "subject_by_z_I", "subject_by_x_c"}
        assert all(0.0 <= value <= 1.0 for value in paired[view].values())
    assert main(["export", str(run), "--out", str(bundle), "--calibrate", str(paired_dataset)]) == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["model"]["regime"] == "paired"
    # A run trained on depth-camera views is calibrated on them: what the node's tracker sees.
    assert "depth-camera view" in manifest["calibration"]["measured_on"]
    assert manifest["calibration"]["z_I_variance_scale"] > 0
    # The run that kept z_I's encoder may take that bundle's calibration (checked on both encoders).
    kept_bundle = tmp_path / "kept-bundle"
    assert main(["export", str(kept), "--out", str(kept_bundle), "--calibration-from", str(bundle)]) == 0
    taken = json.loads((kept_bundle / "manifest.json").read_text())["calibration"]
    assert taken["z_I_variance_scale"] == manifest["calibration"]["z_I_variance_scale"]
    assert str(bundle) in taken["measured_on"]
    assert main(["export", str(kept), "--out", str(tmp_path / "both"), "--calibration-from", str(bundle),
                 "--calibrate", str(paired_dataset)]) != 0
    assert "paired regime" in inspect_with_node(bundle)


def test_the_paired_regime_refuses_a_dataset_without_shared_poses(tiny_dataset, tmp_path, capsys):
    assert main(["train", str(tiny_dataset), "--out", str(tmp_path / "run"), "--recipe", "smoke",
                 "--regime", "paired"]) != 0
    assert "--shared-poses" in capsys.readouterr().err


def test_nearest_match_share_counts_rows_whose_allowed_nearest_shares_the_answer():
    from gdvae.evaluate import nearest_match_share

    codes = np.array([[0.0], [0.1], [5.0], [5.2], [9.0]])
    answer = np.array(["p", "p", "q", "p", "r"])
    allowed = np.ones((5, 5), dtype=bool)
    np.fill_diagonal(allowed, False)
    # Nearest: 0->1 (p=p), 1->0 (p=p), 2->3 (q!=p), 3->2 (p!=q), 4->3 (r!=p).
    assert nearest_match_share(codes, answer, allowed, answer) == pytest.approx(2 / 5)
    allowed[0, 1] = False  # row 0 may not use row 1: its nearest allowed is 2 (q)
    allowed[4, :] = False  # row 4 has no candidate and is left out
    assert nearest_match_share(codes, answer, allowed, answer) == pytest.approx(1 / 4)
    assert nearest_match_share(codes, answer, np.zeros((5, 5), dtype=bool), answer) is None
