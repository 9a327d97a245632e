"""Metric sanity, and a smoke run through training, evaluation and export with ONNX parity."""

import hashlib
import json

import numpy as np
import pytest
import torch

from gdvae.cli import main
from gdvae.metrics import clustering_consistency, coverage_and_fidelity, disentanglement, retrieval_errors


def test_perfect_invariance_gives_ami_one_and_noise_gives_about_zero():
    clouds = torch.randn(30, 16, 3)
    identity = lambda inputs, _: inputs.norm(dim=-1).sort(dim=-1).values  # rotation-invariant codes  # noqa: E731
    assert clustering_consistency(identity, clouds, np.random.default_rng(0), sizes=3) == pytest.approx(1.0)
    noise = lambda inputs, _: torch.randn(len(inputs), 8)  # noqa: E731
    assert abs(clustering_consistency(noise, clouds, np.random.default_rng(0), sizes=3)) < 0.15


def test_views_as_copies_cluster_by_shape_only_when_the_code_ignores_the_view():
    clouds = torch.randn(30, 16, 3)
    views = torch.stack([clouds + 0.01 * torch.randn_like(clouds) for _ in range(4)])  # 4 samples of each shape
    mean = lambda inputs, _: inputs.norm(dim=-1).sort(dim=-1).values  # noqa: E731
    assert clustering_consistency(mean, clouds, np.random.default_rng(0), sizes=3, views=views) > 0.95
    scrambled = torch.stack([clouds[torch.randperm(30)] for _ in range(4)])  # copies are other shapes
    assert clustering_consistency(mean, clouds, np.random.default_rng(0), sizes=3, views=scrambled) < 0.3


def test_random_retrieval_scores_about_zero_and_oracle_codes_score_high():
    rng = np.random.default_rng(0)
    beta, theta = rng.normal(size=(300, 5)), rng.normal(0, 0.4, size=(300, 12))
    e_beta, e_theta = retrieval_errors(rng.normal(size=(300, 4)), beta, theta)
    assert abs(1 - e_beta) < 0.1 and abs(1 - e_theta) < 0.1
    codes = {"x_c": np.concatenate([beta, theta], 1), "z": np.concatenate([beta, theta], 1),
             "z_E": theta, "z_I": beta, "z~_I": beta}
    result = disentanglement(codes, beta, theta)
    assert result["codes"]["z_I"]["s_beta"] > 0.5 and result["codes"]["z_E"]["s_theta"] > 0.5
    assert result["S"] > 1.0


def test_posterior_statistics_tell_a_collapsed_group_from_an_informative_one():
    from gdvae.evaluate import posterior_statistics

    shapes = 200
    codes = {
        "mu_R": torch.randn(shapes, 3), "lv_R": torch.full((shapes, 3), -4.0),  # informative
        "mu_E": 1e-3 * torch.randn(shapes, 10), "lv_E": torch.zeros(shapes, 10),  # the prior: collapsed
        "mu_I": torch.cat([torch.randn(shapes, 2), torch.zeros(shapes, 20)], 1), "lv_I": torch.zeros(shapes, 22),
    }
    statistics = posterior_statistics(codes)
    assert statistics["z_R"]["active_units"] == 3 and abs(statistics["z_R"]["posterior_std_median"] - np.exp(-2)) < 1e-6
    assert statistics["z_E"]["active_units"] == 0 and statistics["z_E"]["posterior_std_median"] == 1.0
    assert statistics["z_I"]["active_units"] == 2 and statistics["z_I"]["dimensions"] == 22


def test_recipe_overrides_are_typed_and_unknown_fields_refused():
    from gdvae.cli import apply_setting
    from gdvae.train import recipe

    chosen = recipe("smoke")
    apply_setting(chosen, "vae.omega_jacobian=2000")
    apply_setting(chosen, "vae.reconstruction_per_dimension=false")
    apply_setting(chosen, "ae.copies=2")
    assert (chosen.vae.omega_jacobian, chosen.vae.reconstruction_per_dimension, chosen.ae.copies) == (2000.0, False, 2)
    apply_setting(chosen, "recipe.bank_copies=3")
    apply_setting(chosen, "recipe.bank_partial_views=0.5")  # None by default: an optional number
    assert (chosen.bank_copies, chosen.bank_partial_views) == (3, 0.5)
    apply_setting(chosen, "ae.pose_hidden=32,64")  # widths: comma-separated integers
    assert chosen.ae.pose_hidden == (32, 64)
    for bad in ("vae.omega_jacobain=1", "vea.omega_jacobian=1", "recipe.bank_copies=many", "vae.omega_jacobian", "ae.copies=two",
                "vae.reconstruction_per_dimension=maybe", "ae.rotation_hidden=wide", "ae.pose_hidden=32,,64"):
        with pytest.raises(SystemExit):
            apply_setting(chosen, bad)


def test_coverage_and_fidelity_of_a_set_against_itself():
    real = torch.randn(10, 32, 3)
    coverage, fidelity = coverage_and_fidelity(real.clone(), real)
    assert coverage == 1.0 and fidelity < 1e-5


def test_smoke_training_evaluation_and_export(tiny_dataset, tmp_path):
    run, bundle, metrics = tmp_path / "run", tmp_path / "bundle", tmp_path / "metrics.json"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke"]) == 0
    assert (run / "checkpoint.pt").exists()
    # The AE's last progress record holds the reconstruction probe: training and held-out d_C.
    last_ae = [r for r in map(json.loads, (run / "log.jsonl").read_text().splitlines()) if r["stage"] == "ae"][-1]
    assert np.isfinite(last_ae["d_C_train"]) and np.isfinite(last_ae["d_C_heldout"]) and last_ae["d_C_heldout"] > 0
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke"]) == 0  # resumes: done
    assert main(["evaluate", str(run), str(tiny_dataset), "--out", str(metrics)]) == 0
    measured = json.loads(metrics.read_text())
    for key in ("d_C", "C_3D", "C_X", "coverage", "fidelity", "log_p_lambda", "heading_error_median_deg"):
        assert np.isfinite(measured[key]), key
    # S is null (undefined) when x_c itself retrieves beta no better than chance, as a few
    # iterations of training may leave it; otherwise it is a number.
    base = [f["codes"]["x_c"] for f in measured["retrieval"].values()]
    assert (measured["S"] is None) == any(b["s_beta"] <= 0 or b["s_theta"] <= 0 for b in base)
    assert set(measured["retrieval"]) == {"blobA", "blobB"}
    partial = measured["partial_views"]
    assert partial["views_per_shape"] == 5 and set(partial["retrieval"]) == {"blobA", "blobB"}
    assert np.isfinite(partial["C_X"]) and np.isfinite(partial["heading_error_median_deg"])
    assert len(measured["S_draws"]) == 5
    quick = tmp_path / "quick.json"
    assert main(["evaluate", str(run), str(tiny_dataset), "--retrieval-only", "--out", str(quick)]) == 0
    screened = json.loads(quick.read_text())
    assert set(screened["retrieval"]) == {"blobA", "blobB"} and len(screened["S_draws"]) == 5
    assert "C_X" not in screened and "coverage" not in screened and "posterior" in screened
    assert set(measured["posterior"]) == {"z_R", "z_E", "z_I"}
    assert measured["posterior"]["z_I"]["dimensions"] == 22
    diagnostics = measured["rotation_diagnostics"]
    assert set(diagnostics["heading"]) == {"blobA", "blobB"} and np.isfinite(diagnostics["C_X_true_rotation"])
    assert main(["export", str(run), "--out", str(bundle), "--metrics", str(metrics)]) == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["onnx_parity_max_diff"] <= 1e-4
    for name, entry in manifest["files"].items():
        assert hashlib.sha256((bundle / name).read_bytes()).hexdigest() == entry["sha256"]
    assert manifest["sizes"]["points"] == 128 and manifest["metrics"]["C_X"] == measured["C_X"]
    assert (bundle / "MODEL_CARD.md").read_text().startswith("# GDVAE++ bundle")
    assert "calibration" not in manifest, "uncalibrated unless asked"
    calibrated = tmp_path / "calibrated"
    assert main(["export", str(run), "--out", str(calibrated), "--calibrate", str(tiny_dataset)]) == 0
    calibration = json.loads((calibrated / "manifest.json").read_text())["calibration"]
    assert calibration["z_I_variance_scale"] > 0 and calibration["groups"] >= 1 and calibration["z_I_spread"] > 0
    assert "z_I variances x" in (calibrated / "MODEL_CARD.md").read_text()
    assert "z_I spread" in (calibrated / "MODEL_CARD.md").read_text()

    import onnxruntime as ort

    encoder = ort.InferenceSession(str(bundle / "encoder.onnx"))
    outputs = encoder.run(None, {"points": np.random.default_rng(0).normal(size=(4, 300, 3)).astype(np.float32)})
    assert [o.shape for o in outputs] == [(4, 4), (4, 48), (4, 3), (4, 3), (4, 4), (4, 4), (4, 22), (4, 22)]


def test_training_on_partial_views(tiny_dataset, tmp_path):
    run = tmp_path / "partial"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", "--partial-views", "0.5",
                 "--stop-after", "ae"]) == 0
    assert json.loads((run / "recipe.json").read_text())["partial_views"] == 0.5
    metrics = tmp_path / "ae.json"
    assert main(["evaluate", str(run), str(tiny_dataset)]) != 0  # the VAE stage has not run
    assert main(["evaluate", str(run), str(tiny_dataset), "--ae-only", "--partial-views", "2", "--out",
                 str(metrics)]) == 0
    measured = json.loads(metrics.read_text())
    assert "S" not in measured and measured["partial_views"]["views_per_shape"] == 2
    assert np.isfinite(measured["C_X"]) and np.isfinite(measured["partial_views"]["C_X"])
    camera = tmp_path / "camera"
    assert main(["train", str(tiny_dataset), "--out", str(camera), "--recipe", "smoke", "--partial-views", "0.5",
                 "--set", "recipe.depth_camera_views=true", "--stop-after", "ae"]) == 0
    assert json.loads((camera / "recipe.json").read_text())["depth_camera_views"] is True
    refused = main(["train", str(tiny_dataset), "--out", str(tmp_path / "u"), "--recipe", "smoke", "--partial-views",
                    "0.5", "--unsupervised"])
    assert refused != 0 and not (tmp_path / "u" / "checkpoint.pt").exists()


def test_beta_is_normalised_per_parameter_by_its_familys_range(tmp_path):
    import json
    from gdvae.evaluate import beta_ranges, normalised_beta
    (tmp_path / "dataset.json").write_text(json.dumps({"families": {"biped": {"beta": [
        {"name": "height", "min": 1.0, "max": 2.0}, {"name": "toe", "min": 0.01, "max": 0.03}]}}}))
    ranges = beta_ranges(tmp_path)
    beta = np.array([[1.5, 0.02], [2.0, 0.01]])
    assert np.allclose(normalised_beta(beta, "biped", ranges), [[0.5, 0.5], [1.0, 0.0]])
    # Without a range for the family: the observed range.
    assert np.allclose(normalised_beta(beta, "quadruped", ranges), [[0.0, 1.0], [1.0, 0.0]])
    assert beta_ranges(tmp_path / "missing") == {}


def test_screen_trains_one_vae_per_cell_on_the_same_bank_and_tabulates_them(tiny_dataset, tmp_path):
    import json

    from gdvae.cli import main

    ae_run = tmp_path / "ae"
    assert main(["train", str(tiny_dataset), "--out", str(ae_run), "--recipe", "smoke", "--stop-after", "bank"]) == 0
    state = __import__("torch").load(ae_run / "checkpoint.pt", weights_only=False)
    assert state["stage"] == "vae" and "bank" in state and "vae" not in state  # stopped with the bank built
    screen_dir = tmp_path / "screen"
    assert main(["screen", str(ae_run), str(tiny_dataset), "--out", str(screen_dir), "--recipe", "smoke",
                 "--iterations", "2", "--factors", "CJ", "--jobs", "1", "--set", "vae.beta_inter_tc=8"]) == 0
    result = json.loads((screen_dir / "screen.json").read_text())
    assert [c["cell"] for c in result["cells"]] == ["C0-J0", "C0-J1", "C1-J0", "C1-J1"]
    for cell in result["cells"]:
        recipe = json.loads((screen_dir / cell["cell"] / "recipe.json").read_text())
        assert recipe["vae"]["covariance_form"] == ("correlation" if cell["levels"]["C"] else "covariance")
        assert recipe["vae"]["omega_jacobian"] == (0.0 if cell["levels"]["J"] else 200.0)
        assert recipe["vae_iterations"] == 2 and recipe["vae"]["beta_inter_tc"] == 8.0
        assert cell["z_E_active"] >= 0 and set(cell["S_by_family"]) == {"blobA", "blobB"}
    assert set(result["main_effects"]) == {"C", "J"}
    # A VAE on the same AE with a new bank of partial views (3 copies per mesh, not the source's 2).
    rebuilt = tmp_path / "rebuilt"
    assert main(["train", str(tiny_dataset), "--out", str(rebuilt), "--recipe", "smoke", "--init-from", str(ae_run),
                 "--rebuild-bank", "--set", "recipe.bank_copies=3", "--set", "recipe.bank_partial_views=1"]) == 0
    rebuilt_state = __import__("torch").load(rebuilt / "checkpoint.pt", weights_only=False)
    assert rebuilt_state["bank"]["x_c"].shape[0] == 3 / 2 * state["bank"]["x_c"].shape[0]
    assert rebuilt_state["stage"] == "done"
    with pytest.raises(SystemExit, match="--rebuild-bank goes with --init-from"):
        main(["train", str(tiny_dataset), "--out", str(tmp_path / "r2"), "--recipe", "smoke", "--rebuild-bank"])
    # The same AE trained 3 iterations more: its weights move, its log goes on from where it stopped.
    continued = tmp_path / "continued"
    assert main(["train", str(tiny_dataset), "--out", str(continued), "--recipe", "smoke", "--init-from", str(ae_run),
                 "--continue-ae", "3"]) == 0
    continued_state = __import__("torch").load(continued / "checkpoint.pt", weights_only=False)
    assert continued_state["stage"] == "done"
    assert any((continued_state["ae"][k] != state["ae"][k]).any() for k in state["ae"])
    recipe = json.loads((continued / "recipe.json").read_text())
    source = json.loads((ae_run / "recipe.json").read_text())
    assert recipe["ae_iterations"] == source["ae_iterations"] + 3
    ae_rows = [json.loads(line) for line in (continued / "log.jsonl").read_text().splitlines()]
    ae_rows = [r for r in ae_rows if r.get("stage") == "ae"]
    assert ae_rows and min(r["iteration"] for r in ae_rows) > source["ae_iterations"] + source["ae_pretrain_iterations"]
    with pytest.raises(SystemExit, match="--continue-ae goes with --init-from"):
        main(["train", str(tiny_dataset), "--out", str(tmp_path / "r3"), "--recipe", "smoke", "--continue-ae", "2"])
    assert "| C | J |" in (screen_dir / "screen.md").read_text()
    refused = main(["screen", str(ae_run), str(tiny_dataset), "--out", str(screen_dir), "--factors", "X"])
    assert refused != 0


def test_variance_calibration_is_the_within_subject_spread_over_the_reported_variance():
    from gdvae.metrics import variance_calibration

    rng = np.random.default_rng(0)
    subjects = np.repeat(np.arange(40), 50)
    centres = rng.normal(0.0, 3.0, size=(40, 6))
    means = centres[subjects] + rng.normal(0.0, 0.1, size=(len(subjects), 6))  # within-subject variance 0.01
    reported = np.full((len(subjects), 6), np.log(0.04))  # the encoder says 0.04: 4 times too wide
    measured = variance_calibration(means, reported, subjects)
    assert abs(measured["z_I_variance_scale"] - 0.25) < 0.02, measured
    # A subject's codes lie 0.1 x sqrt(6) from its centre (root mean square over 6 dimensions).
    assert abs(measured["z_I_spread"] - 0.1 * np.sqrt(6)) < 0.01, measured
    assert measured["groups"] == 40 and measured["codes"] == 2000
    # Subjects seen once say nothing about the spread.
    with pytest.raises(ValueError, match="two or more"):
        variance_calibration(means[:3], reported[:3], [0, 1, 2])


@pytest.mark.parametrize("architecture", [[], ["--ae", "std", "--set", "ae.rotation_head=yaw"]],
                         ids=["ftl-quaternion", "std-yaw"])
def test_a_bundle_imports_back_into_a_run_that_computes_the_same_and_trains_on(tiny_dataset, tmp_path, architecture):
    from gdvae.export import EncoderGraph
    from gdvae.train import load_run

    run, bundle, imported = tmp_path / "run", tmp_path / "bundle", tmp_path / "imported"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", *architecture]) == 0
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    assert main(["import-bundle", str(bundle), "--out", str(imported)]) == 0
    _, ae, vae, _ = load_run(run)
    _, ae_back, vae_back, state = load_run(imported)
    assert state["stage"] == "bank" and vae_back is not None
    points = torch.rand(3, 200, 3) - 0.5
    with torch.no_grad():
        for a, b in zip(EncoderGraph(ae, vae).eval()(points), EncoderGraph(ae_back, vae_back).eval()(points)):
            assert torch.allclose(a, b, atol=1e-5), "the imported model computes what the bundle's run computed"
        codes = torch.randn(3, ae.config.latent)
        assert torch.allclose(ae.decode(codes), ae_back.decode(codes), atol=1e-5)
    # Its autoencoder trains a new code bank and VAE like any run's.
    again = tmp_path / "again"
    assert main(["train", str(tiny_dataset), "--out", str(again), "--recipe", "smoke", "--init-from", str(imported)]) == 2
    assert main(["train", str(tiny_dataset), "--out", str(again), "--recipe", "smoke", "--init-from", str(imported),
                 "--rebuild-bank"]) == 0
    assert load_run(again)[2] is not None
    # In the imported model's units (the bundle's manifest), not the new dataset's own scale.
    units = json.loads((bundle / "manifest.json").read_text())["units"]["model_units_per_metre"]
    assert json.loads((imported / "recipe.json").read_text())["model_units"] == units
    recipe_file = imported / "recipe.json"
    recipe_file.write_text(json.dumps({**json.loads(recipe_file.read_text()), "model_units": 2 * units}))
    scaled = tmp_path / "scaled"
    assert main(["train", str(tiny_dataset), "--out", str(scaled), "--recipe", "smoke", "--init-from", str(imported),
                 "--rebuild-bank", "--stop-after", "bank"]) == 0
    assert json.loads((scaled / "dataset.json").read_text())["scale"] == pytest.approx(2 * units)
    # Continuing the AE: its batch norms normalise again (restored from sample clouds), the same
    # function in eval mode and about the same on a training batch.
    from gdvae.ae import restore_batch_norms

    clouds = torch.rand(16, 200, 3) - 0.5
    with torch.no_grad():
        before = ae_back.encode_rotation(clouds)
        restore_batch_norms(ae_back, torch.rand(64, 200, 3) - 0.5)
        assert torch.allclose(before, ae_back.encode_rotation(clouds), atol=1e-5)
        norm = next(m for m in ae_back.modules() if isinstance(m, torch.nn.BatchNorm1d))
        features = torch.randn(8, norm.num_features, 200) * norm.weight[None, :, None] + norm.bias[None, :, None]
        assert not torch.allclose(norm.weight, torch.ones_like(norm.weight)), "set from the clouds"
        norm.train()
        assert (norm(features) - features).abs().mean() < 0.1 * features.std()
    continued = tmp_path / "continued"
    assert main(["train", str(tiny_dataset), "--out", str(continued), "--recipe", "smoke", "--init-from",
                 str(imported), "--continue-ae", "2"]) == 0
    assert load_run(continued)[2] is not None


def test_importing_what_is_not_a_matching_bundle_is_refused_with_the_reason(tiny_dataset, tmp_path, capsys):
    run, bundle = tmp_path / "run", tmp_path / "bundle"
    assert main(["import-bundle", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "no manifest.json" in capsys.readouterr().err
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke"]) == 0
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["sizes"]["x_c"] += 3  # a manifest that does not describe its graphs
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    assert main(["import-bundle", str(bundle), "--out", str(tmp_path / "y")]) == 2
    assert "in the bundle" in capsys.readouterr().err and not (tmp_path / "y" / "checkpoint.pt").exists()


def test_a_run_still_training_its_vae_is_not_exported(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke"]) == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    torch.save({**state, "stage": "vae", "iteration": 2}, run / "checkpoint.pt")  # as a checkpoint mid-VAE
    assert main(["export", str(run), "--out", str(tmp_path / "bundle")]) == 2
    assert "has not finished (stage 'vae', iteration 2)" in capsys.readouterr().err
    assert not (tmp_path / "bundle" / "manifest.json").exists()


def test_loader_workers_and_time_budgets_end_stages_and_say_so(tiny_dataset, tmp_path):
    """Batches sampled in worker processes train as in-process ones do; a stage whose wall-clock
    budget runs out ends there, stages.json says so, and the bundle records the iterations run."""
    run = tmp_path / "budgeted"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", "--partial-views", "0.5",
                 "--ae-iterations", "100000", "--ae-minutes", "0.05", "--vae-iterations", "100000",
                 "--vae-minutes", "0.03", "--loader-workers", "2", "--device", "cpu"]) == 0
    stages = json.loads((run / "stages.json").read_text())
    assert stages["ae"]["ended_by_time_budget"] and stages["vae"]["ended_by_time_budget"]
    assert 2 < stages["ae"]["iterations"] < 100_000 and 0 < stages["vae"]["iterations"] < 100_000
    assert stages["ae"]["device"] == "cpu" and stages["ae"]["seconds"] >= 3.0
    bundle = tmp_path / "bundle"
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    training = json.loads((bundle / "manifest.json").read_text())["training"]
    assert training["ae_iterations"] == stages["ae"]["iterations"] - 2  # less the smoke recipe's pretraining
    assert training["vae_iterations"] == stages["vae"]["iterations"] and training["ae_device"] == "cpu"

    whole = tmp_path / "whole"  # no budget: the recipe's count, not ended by time
    assert main(["train", str(tiny_dataset), "--out", str(whole), "--recipe", "smoke", "--loader-workers", "1"]) == 0
    stages = json.loads((whole / "stages.json").read_text())
    assert stages["ae"] == {**stages["ae"], "iterations": 6, "planned": 6, "ended_by_time_budget": False}


def test_a_device_that_is_not_there_is_refused_before_training(tiny_dataset, tmp_path):
    import torch

    run = tmp_path / "nowhere"
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(SystemExit, match="--device cuda: this machine's torch sees no CUDA device"):
        main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", "--device", "cuda"])
    with pytest.raises(SystemExit, match="--device tpu"):
        main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", "--device", "tpu"])
    assert not (run / "checkpoint.pt").exists()


def test_a_checkpoint_written_on_another_device_is_read_onto_the_cpu(tiny_dataset, tmp_path, monkeypatch):
    """load_run maps every tensor onto the CPU (a GPU run is evaluated and exported without one)."""
    import torch

    from gdvae import train as training

    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke"]) == 0
    seen = {}
    real_load = torch.load

    def load(*args, **kwargs):
        seen.update(kwargs)
        return real_load(*args, **kwargs)

    monkeypatch.setattr(training.torch, "load", load)
    training.load_run(run)
    assert seen.get("map_location") == "cpu"


def perturb_output(graph_path, output: str, offset: float) -> None:
    """Adds `offset` to one node output of an ONNX graph, where every consumer reads it: what a
    stage computing slightly (or very) differently would give."""
    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(graph_path)
    nodes = model.graph.node
    producer = next(k for k, node in enumerate(nodes) if output in node.output)
    nodes[producer].output[list(nodes[producer].output).index(output)] = f"{output}_unperturbed"
    offset_name = f"{output}_offset"
    model.graph.initializer.append(numpy_helper.from_array(np.array(offset, dtype=np.float32), offset_name))
    nodes.insert(producer + 1, helper.make_node("Add", [f"{output}_unperturbed", offset_name], [output]))
    onnx.save(model, graph_path)


@pytest.mark.parametrize("output, offset, imports", [
    ("q", 3e-5, True),  # upstream rounding: q a little off, and every stage downstream fed with it
    ("q", 1e-3, False),  # the rotation stage computes something else
    ("z_E_mean", 1e-3, False),  # a downstream stage computes something else
])
def test_import_tolerates_another_machines_rounding_but_not_a_different_graph(tiny_dataset, tmp_path, capsys,
                                                                              output, offset, imports):
    run, bundle = tmp_path / "run", tmp_path / "bundle"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--recipe", "smoke", "--ae", "std"]) == 0
    assert main(["export", str(run), "--out", str(bundle)]) == 0
    perturb_output(bundle / "encoder.onnx", output, offset)
    code = main(["import-bundle", str(bundle), "--out", str(tmp_path / "imported")])
    assert (code == 0) == imports, capsys.readouterr().err
    if not imports:
        assert "differs from the bundle's graphs" in capsys.readouterr().err


def test_the_reconstruction_probe_measures_training_and_held_out_meshes_apart(tiny_dataset):
    import torch

    from gdvae.ae import Autoencoder
    from gdvae.data import load_dataset
    from gdvae.train import ReconstructionProbe, recipe

    dataset = load_dataset(tiny_dataset)
    chosen = recipe("smoke")
    probe = ReconstructionProbe(dataset, dataset.indices("train"), chosen, "cpu", meshes=5)
    # The tiny dataset holds out whole subjects (its test split): 5 meshes of each side.
    assert {name: len(inputs) for name, (inputs, _) in probe.sets.items()} == {"train": 5, "heldout": 5}
    ae = Autoencoder(chosen.ae).train()
    figures = probe.measure(ae)
    assert set(figures) == {"d_C_train", "d_C_heldout"} and all(v > 0 for v in figures.values())
    assert ae.training  # left as it was found
    assert probe.measure(ae) == figures  # fixed clouds: the same model measures the same
    # The figure is the distance to the set's own targets: targets moved away measure higher.
    inputs, targets = probe.sets["heldout"]
    probe.sets["heldout"] = (inputs, targets * 5.0)
    assert probe.measure(ae)["d_C_heldout"] > figures["d_C_heldout"]
