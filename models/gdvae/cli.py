"""The kit's commands. Each one is a thin wrapper over a module; errors are reported once, here."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("gdvae")


def spectra_command(args) -> int:
    from .data import load_dataset
    from .spectral_report import dataset_spectra, spectral_report
    from .spectrum import SpectrumCache

    dataset = load_dataset(args.dataset, limit=args.limit)
    log.info("%s: %d meshes, scale %.4f model units per input unit", args.dataset, len(dataset.meshes), dataset.scale)
    cache = SpectrumCache(args.cache or Path(args.dataset) / ".spectra")
    spectra = dataset_spectra(dataset, args.count, cache)
    report = spectral_report(dataset, spectra)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"d_lambda (first {args.count} eigenvalues) within vs between subjects")
        print(f"{'family':<10} {'meshes':>7} {'subjects':>8} {'within':>9} {'between':>9} {'ratio':>7} {'1-NN same':>9}")
        for family, row in report.items():
            print(f"{family:<10} {row['meshes']:>7} {row['subjects']:>8} {row['within_subject_mean']:>9.4f} "
                  f"{row['between_subject_mean']:>9.4f} {row['ratio_between_to_within']:>7.2f} "
                  f"{row['nearest_spectrum_same_subject']:>9.3f}")
    return 0


def apply_setting(chosen, assignment: str) -> None:
    """`--set ae.KEY=VALUE` / `vae.KEY=VALUE` / `recipe.KEY=VALUE`: override one recipe field (an
    experiment's knob), converted to the field's type; unknown sections or fields are an error, not
    ignored."""
    import dataclasses

    name, separator, text = assignment.partition("=")
    section, _, field = name.partition(".")
    target = {"ae": chosen.ae, "vae": chosen.vae, "recipe": chosen}.get(section)
    if not separator or target is None or not field:
        raise SystemExit(f"--set {assignment!r}: expected ae.FIELD=VALUE, vae.FIELD=VALUE or recipe.FIELD=VALUE")
    fields = {f.name: f for f in dataclasses.fields(target)}
    if field not in fields:
        raise SystemExit(f"--set {assignment!r}: {section} has no field {field!r} (fields: {', '.join(fields)})")
    current = getattr(target, field)
    try:
        if "tuple" in str(fields[field].type):  # widths: comma-separated integers
            value = tuple(int(part) for part in text.split(","))
        elif isinstance(current, bool):
            if text.lower() not in ("true", "false"):
                raise ValueError("expected true or false")
            value = text.lower() == "true"
        elif isinstance(current, (int, float, str)):
            value = type(current)(text)
        elif current is None:  # optional numbers (None: follow another field)
            value = float(text)
        else:
            raise ValueError(f"{type(current).__name__} fields cannot be set from the command line")
    except ValueError as error:
        raise SystemExit(f"--set {assignment!r}: {error}") from None
    setattr(target, field, value)
    log.info("recipe override: %s.%s = %r (was %r)", section, field, value, current)


def train_command(args) -> int:
    from .data import load_dataset
    from .spectral_report import dataset_spectra
    from .spectrum import SpectrumCache
    from .train import StageLimits, check_source_bank, recipe, source_model_units, train, use_model_units

    chosen = recipe(args.recipe, regime=args.regime, kind=args.ae)
    if args.ae_iterations is not None:
        chosen.ae_iterations = args.ae_iterations
    if args.vae_iterations is not None:
        chosen.vae_iterations = args.vae_iterations
    if args.partial_views is not None:
        if not 0.0 <= args.partial_views <= 1.0:
            raise SystemExit(f"--partial-views {args.partial_views}: must be within 0..1")
        chosen.partial_views = args.partial_views
    if args.relative_reconstruction:
        chosen.vae.reconstruction_per_dimension = False
    for assignment in args.set or []:
        apply_setting(chosen, assignment)
    chosen.ae.supervised = not args.unsupervised
    chosen.ae.full_rotations = args.full_rotations
    chosen.vae.validate()  # refused now, not after the spectra and the AE stage
    dataset = load_dataset(args.dataset, limit=args.limit)
    if args.init_from and chosen.model_units is None:
        chosen.model_units = source_model_units(args.init_from)
    use_model_units(dataset, chosen.model_units)
    log.info("%s: %d meshes (%d train), scale %.4f model units per input unit", args.dataset, len(dataset.meshes),
             len(dataset.indices("train")), dataset.scale)
    if args.init_from:  # before the spectra, which take minutes on a new dataset
        check_source_bank(args.init_from, dataset, bool(args.continue_ae > 0 or args.rebuild_bank or args.reteach))
    spectra = dataset_spectra(dataset, chosen.spectrum_count, SpectrumCache(Path(args.dataset) / ".spectra"))
    taught = {}  # the pose and body stages' own datasets
    source_ae = json.loads((Path(args.init_from) / "recipe.json").read_text())["ae"] if args.init_from else {}
    for flag, path, stage in (("--pose-data", args.pose_data, "pose"), ("--body-data", args.body_data, "body")):
        if path:  # the stage's encoder is added here (--set) or comes with --init-from's AE
            if not (getattr(chosen.ae, f"{stage}_encoder") or source_ae.get(f"{stage}_encoder")):
                raise SystemExit(f"{flag} is the {stage} stage's dataset: it goes with --set ae.{stage}_encoder=true")
            if source_ae.get(f"{stage}_encoder") and stage not in (args.reteach or ()):
                raise SystemExit(f"{flag}: {args.init_from}'s {stage} encoder is reused as it is (no {stage} stage "
                                 f"runs): add --reteach {stage} to teach it again on {path}")
            taught[stage] = load_dataset(path)
            use_model_units(taught[stage], chosen.model_units or dataset.scale)
    node_identity = None
    if args.node_states:  # read and checked before any training, as the datasets are
        from .node_identity import NodeIdentityData

        node_identity = NodeIdentityData.from_states(args.node_states, source_ae.get("latent", chosen.ae.latent))
        log.info("node states: %(frames)d frames of %(subjects)s subjects (by family)", node_identity.summary())
    if args.rebuild_bank and not args.init_from:
        raise SystemExit("--rebuild-bank goes with --init-from (a fresh run builds its own bank)")
    if args.continue_ae and not args.init_from:
        raise SystemExit("--continue-ae goes with --init-from (the AE to continue)")
    if args.continue_ae < 0:
        raise SystemExit(f"--continue-ae {args.continue_ae}: must be a number of iterations >= 0")
    device = training_device(args.device)
    limits = StageLimits(ae_seconds=None if args.ae_minutes is None else 60.0 * args.ae_minutes,
                         vae_seconds=None if args.vae_minutes is None else 60.0 * args.vae_minutes)
    train(dataset, spectra, args.out, chosen, stop_after=args.stop_after, init_from=args.init_from,
          rebuild_bank=args.rebuild_bank, continue_ae=args.continue_ae, device=device, limits=limits,
          loader_workers=args.loader_workers, pose_dataset=taught.get("pose"),
          body_dataset=taught.get("body"), reteach=tuple(args.reteach or ()), node_identity=node_identity)
    log.info("training finished: %s", args.out)
    return 0


def training_device(name: str) -> str:
    """The torch device to train on; a clear error when it is not there (no silent CPU fallback:
    a GPU job that quietly ran on a CPU would spend its whole budget for a fraction of the work)."""
    import torch

    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {name}: this machine's torch sees no CUDA device")
    try:
        torch.empty(0, device=name)
    except (RuntimeError, ValueError) as error:
        raise SystemExit(f"--device {name}: {error}") from None
    if name.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        log.info("training on %s (%s)", name, torch.cuda.get_device_name(torch.device(name)))
    return name


def finite_or_null(value):
    """NaN and infinities become null: strict JSON (the node's parser) has no NaN. A NaN score
    means the quantity is undefined, e.g. S when x_c retrieves no better than chance."""
    import math

    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite_or_null(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def default_sim_binary() -> str | None:
    """The workspace's release build of the sim, when present."""
    candidate = Path(__file__).resolve().parents[2] / "target" / "release" / "sim"
    return str(candidate) if candidate.is_file() else None


def evaluate_command(args) -> int:
    from .data import load_dataset
    from .evaluate import evaluate
    from .spectral_report import dataset_spectra
    from .spectrum import SpectrumCache
    from .train import load_run, source_model_units, use_model_units

    chosen, ae, vae, state = load_run(args.run)
    if args.ae_only:
        vae = None
    elif vae is None:
        raise ValueError(f"{args.run}: the VAE stage has not finished (stage {state['stage']!r}); "
                         "--ae-only evaluates its autoencoder")
    if args.figures and vae is None:
        raise ValueError("--figures needs the VAE; drop --ae-only")
    if args.retrieval_only and (args.ae_only or args.figures):
        raise ValueError("--retrieval-only goes with neither --ae-only nor --figures")
    if args.partial_views < 0:
        raise ValueError(f"--partial-views must be 0 or more, got {args.partial_views}")
    dataset = load_dataset(args.dataset, limit=args.limit)
    use_model_units(dataset, source_model_units(args.run))
    spectra = None
    if vae is not None:
        spectra = dataset_spectra(dataset, vae.config.spectrum, SpectrumCache(Path(args.dataset) / ".spectra"))
    sim = args.sim or default_sim_binary()
    metrics = evaluate(ae, vae, dataset, spectra, split=args.split, full_rotations=chosen.ae.full_rotations,
                       sim_binary=sim, partial_views=args.partial_views, retrieval_only=args.retrieval_only)
    if state["stage"] != "done":  # a run still training: say how far it was
        metrics["checkpoint"] = {"stage": state["stage"], "iteration": state["iteration"]}
    metrics = finite_or_null(metrics)
    metrics["run"] = str(args.run)
    metrics["dataset"] = str(args.dataset)
    metrics["command"] = "python -m gdvae " + " ".join(args.argv)
    if args.figures:
        from .figures import make_figures

        for path in make_figures(ae, vae, dataset, spectra, args.figures, split=args.split):
            log.info("figure %s", path)
    text = json.dumps(metrics, indent=2, allow_nan=False)
    if args.out:
        Path(args.out).write_text(text + "\n")
        log.info("metrics written to %s", args.out)
    print(text)
    return 0


def trained_iterations(run: Path, chosen) -> dict:
    """What RUN/stages.json says the stages did, where a time budget ended them before the
    recipe's count (the iterations actually run), and the device each trained on."""
    path = run / "stages.json"
    if not path.exists():
        return {}
    stages = json.loads(path.read_text())
    found = {}
    pretrain = chosen.ae_pretrain_iterations if chosen.ae.supervised else 0
    for stage, key, offset in (("ae", "ae_iterations", pretrain), ("vae", "vae_iterations", 0)):
        record = stages.get(stage)
        if record is None:
            continue
        if record.get("ended_by_time_budget"):
            found[key] = max(0, record["iterations"] - offset)
        found[f"{stage}_device"] = record.get("device", "cpu")
    return found


def export_command(args) -> int:
    from .export import write_bundle
    from .train import dataset_summary, load_run, source_model_units, use_model_units

    chosen, ae, vae, state = load_run(args.run)
    # A run still training has a VAE checkpoint, not a trained VAE: a bundle is made of finished
    # runs (or of one imported from a bundle).
    if vae is None or (state["stage"] != "done" and "imported_vae" not in state):
        raise ValueError(f"{args.run}: the VAE stage has not finished (stage {state['stage']!r}, "
                         f"iteration {state['iteration']}); export a finished run")
    summary_file = Path(args.run) / "dataset.json"
    if summary_file.exists():
        summary = json.loads(summary_file.read_text())
    elif args.dataset:
        from .data import load_dataset

        dataset = load_dataset(args.dataset)
        use_model_units(dataset, source_model_units(args.run))
        summary = dataset_summary(dataset)
    else:
        raise ValueError(f"{args.run} has no dataset.json: pass --dataset (the training dataset) for its scale")
    metrics = json.loads(Path(args.metrics).read_text()) if args.metrics else None
    training = {**summary, "ae_iterations": chosen.ae_iterations, "vae_iterations": chosen.vae_iterations,
                "ae_batch": chosen.ae_batch, "vae_batch": chosen.vae_batch, "partial_views": chosen.partial_views,
                "depth_camera_views": chosen.depth_camera_views,
                "bank_partial_views": chosen.bank_view_share(),
                # what the VAE taught its codes from the sim's truth (0: nothing), for the model card
                # (a code kept from the run this one started from was taught there)
                "omega_pose": chosen.vae.omega_pose or summary.get("z_E_kept_from", {}).get("omega_pose", 0.0),
                "omega_body": chosen.vae.omega_body or summary.get("z_I_kept_from", {}).get("omega_body", 0.0),
                "body_direct": chosen.vae.body_direct or summary.get("z_I_kept_from", {}).get("body_direct", False),
                "omega_node_identity": chosen.vae.omega_node_identity}
    training.update(trained_iterations(Path(args.run), chosen))
    calibration = None
    if args.calibrate and args.calibration_from:
        raise ValueError("--calibrate measures a calibration, --calibration-from takes one: give one of them")
    if args.calibration_from:
        from .export import calibration_kept_from

        calibration = calibration_kept_from(ae, vae, Path(args.calibration_from))
        log.info("z_I variance calibration x %.4g, from %s", calibration["z_I_variance_scale"], args.calibration_from)
    if args.calibrate:
        from .data import load_dataset
        from .evaluate import z_i_variance_calibration

        dataset = load_dataset(args.calibrate)
        use_model_units(dataset, summary["scale"])
        held_out = dataset.indices("test")
        if not held_out:
            raise ValueError(f"{args.calibrate}: no held-out meshes to calibrate on (check splits.json)")
        calibration = z_i_variance_calibration(ae, vae, dataset, held_out, full_rotations=chosen.ae.full_rotations,
                                              depth_camera=chosen.depth_camera_views)
        log.info("z_I variance calibration: x %.4g (per-dimension ratios p10 %.3g, p90 %.3g; %d subjects); "
                 "a subject's z_I spread %.4g", calibration["z_I_variance_scale"], calibration["ratio_p10"],
                 calibration["ratio_p90"], calibration["groups"], calibration["z_I_spread"])
    write_bundle(ae, vae, args.out, scale=summary["scale"], recipe_name=chosen.name, training=training,
                 metrics=metrics, calibration=calibration)
    print(f"bundle written to {args.out}")
    return 0


def bench_command(args) -> int:
    import json
    import resource
    import time

    import torch

    from .bench import bench, report
    from .data import load_dataset
    from .train import recipe, use_model_units

    chosen = recipe(args.recipe, regime=args.regime, kind=args.ae)
    if args.partial_views is not None:
        chosen.partial_views = args.partial_views
    for assignment in args.set or []:
        apply_setting(chosen, assignment)
    device = torch.device(training_device(args.device))
    started = time.perf_counter()
    dataset = load_dataset(args.dataset, limit=args.limit)
    load_seconds = time.perf_counter() - started
    use_model_units(dataset, chosen.model_units)
    figures = bench(dataset, chosen, device, seconds=args.seconds)
    figures["dataset"] = {"meshes": len(dataset.meshes), "load_seconds": load_seconds}
    figures["peak_resident_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB
    figures["command"] = "python -m gdvae " + " ".join(args.argv)
    print(json.dumps(figures, indent=2) if args.json else report(figures) + f"\n  command: {figures['command']}")
    return 0


def import_bundle_command(args) -> int:
    from .import_bundle import import_bundle

    summary = import_bundle(args.bundle, args.out)
    print(f"{args.bundle} -> {args.out}: {summary['ae']} autoencoder ({summary['rotation_head']} head) and "
          f"{summary['regime']} VAE, matching the bundle's graphs to {summary['parity_max_diff']:.2g}")
    if summary["vae_not_in_bundle"]:
        print(f"not in the bundle (initial values): {', '.join(summary['vae_not_in_bundle'])}")
    return 0


def fit_identity_command(args) -> int:
    from .identity import fit_projection, read_states, write_projection

    by_subject, unmatched = read_states(args.states)
    fitted = fit_projection(by_subject, args.directions, args.ridge)
    path = write_projection(args.bundle, fitted, args.states, args.directions, args.ridge)
    subjects = ", ".join(f"{n} {family}s" for family, n in fitted["subjects"].items())
    print(f"{path}: identity projection, {args.directions} directions of x_c fitted on {subjects} "
          f"({fitted['frames']} frames; {unmatched} without ground truth left out); between/within "
          f"subject ratio along them {', '.join(f'{v:.2f}' for v in fitted['between_within'])}")
    return 0


def screen_command(args) -> int:
    from .screen import screen

    text = screen(args.ae_run, args.dataset, args.out, args.recipe, args.iterations, args.factors, args.jobs,
                  args.sim or default_sim_binary(), "python -m gdvae " + " ".join(args.argv), fixed=args.set or [])
    print(text)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gdvae", description="GDVAE++ training kit")
    parser.add_argument("-v", "--verbose", action="store_true")
    commands = parser.add_subparsers(dest="command", required=True)

    spectra = commands.add_parser("spectra", help="spectral learning-signal report: d_lambda within vs between subjects")
    spectra.add_argument("dataset", help="dataset folder (e.g. written by `sim dataset`)")
    spectra.add_argument("--count", type=int, default=24, help="eigenvalues N_lambda (default 24)")
    spectra.add_argument("--limit", type=int, help="use only the first N meshes")
    spectra.add_argument("--cache", help="spectrum cache folder (default DATASET/.spectra)")
    spectra.add_argument("--json", action="store_true")
    spectra.set_defaults(handler=spectra_command)

    training = commands.add_parser("train", help="train (or resume) the AE and the VAE on a mesh dataset")
    training.add_argument("dataset", help="dataset folder (meshes, optional ground_truth.jsonl and splits.json)")
    training.add_argument("--out", required=True, help="run folder (checkpoint, logs); rerun to resume")
    training.add_argument("--recipe", default="cpu", choices=["cpu", "gpu", "paper", "smoke"])
    training.add_argument("--regime", default="gdvae++", choices=["gdvae++", "fo", "paired"],
                          help="the paper's GDVAE++ or GDVAE-FO, or the paired regime (FO + swap reconstruction "
                               "and identity contrast from a `sim dataset --shared-poses` dataset)")
    training.add_argument("--ae", default="ftl", choices=["ftl", "std"], help="autoencoder architecture")
    training.add_argument("--unsupervised", action="store_true", help="no rotation supervision (unaligned data)")
    training.add_argument("--full-rotations", action="store_true", help="rotations over SO(3), not about the up axis")
    training.add_argument("--ae-iterations", type=int, help="override the recipe's AE iterations")
    training.add_argument("--vae-iterations", type=int, help="override the recipe's VAE iterations")
    training.add_argument("--partial-views", type=float,
                          help="fraction of AE inputs that are the side a camera sees (0..1; supervised AE)")
    training.add_argument("--relative-reconstruction", action="store_true",
                          help="VAE L_R without the paper's 1/dim(x_c) (better reconstruction, lower S)")
    training.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE",
                          help="override a recipe field, e.g. vae.omega_jacobian=2000 (repeatable; recorded in recipe.json)")
    training.add_argument("--stop-after", choices=["ae", "bank"],
                          help="stop after this stage (bank: the AE and its code bank, for VAEs that --init-from this run)")
    training.add_argument("--init-from", help="reuse another run's trained AE and code bank (compare VAE regimes)")
    training.add_argument("--continue-ae", type=int, default=0, metavar="N",
                          help="with --init-from: train its AE N more iterations (this recipe's learning rate, "
                               "a fresh optimizer), then build a new code bank and train the VAE")
    training.add_argument("--rebuild-bank", action="store_true",
                          help="with --init-from: reuse only the AE and encode a new code bank with this run's "
                               "bank settings (recipe.bank_copies, recipe.bank_partial_views)")
    training.add_argument("--pose-data", metavar="DATASET",
                          help="with ae.pose_encoder: the pose stage learns from this sim dataset's training "
                               "meshes (many distinct poses) instead of DATASET's (default)")
    training.add_argument("--body-data", metavar="DATASET",
                          help="with ae.body_encoder: the body stage learns from this sim dataset's training "
                               "meshes (many distinct subjects) instead of DATASET's (default)")
    training.add_argument("--reteach", action="append", choices=["pose", "body"],
                          help="with --init-from: teach its AE's pose (or body) encoder again, from the start, "
                               "on this run's settings (recipe.pose_components, --pose-data), then a new code "
                               "bank (repeatable)")
    training.add_argument("--node-states", nargs="+", metavar="STATES",
                          help="`gdvae-node evaluate SIM-RECORDINGS --states` files (x_c of this run's AE): "
                               "vae.omega_node_identity teaches z_I to tell their subjects apart")
    training.add_argument("--limit", type=int, help="use only the first N meshes")
    training.add_argument("--device", default="cpu", help="torch device to train on: cpu (default), cuda, cuda:1")
    training.add_argument("--ae-minutes", type=float, metavar="M",
                          help="end the AE stage after M minutes of training even if its iterations are not done "
                               "(recorded in RUN/stages.json)")
    training.add_argument("--vae-minutes", type=float, metavar="M", help="the same for the VAE stage")
    training.add_argument("--loader-workers", type=int, default=0, metavar="N",
                          help="processes that sample AE batches ahead of the training step (default 0: in this "
                               "process; on a GPU, most of the machine's cores)")
    training.set_defaults(handler=train_command)

    evaluation = commands.add_parser("evaluate", help="the paper's metrics of a trained run on held-out shapes")
    evaluation.add_argument("run", help="run folder written by `train`")
    evaluation.add_argument("dataset", help="dataset folder (the held-out split is used)")
    evaluation.add_argument("--split", default="test")
    evaluation.add_argument("--out", help="write the metrics JSON here")
    evaluation.add_argument("--figures", help="also write PNG figures into this folder")
    evaluation.add_argument("--sim", help="sim binary for pose-transfer ground truth (default: target/release/sim)")
    evaluation.add_argument("--limit", type=int)
    evaluation.add_argument("--ae-only", action="store_true",
                            help="only the autoencoder's metrics (also for a run still in its AE stage)")
    evaluation.add_argument("--retrieval-only", action="store_true",
                            help="only retrieval, S (five draws), the posterior statistics and pose transfer: minutes, for comparing runs")
    evaluation.add_argument("--partial-views", type=int, default=5, metavar="N",
                            help="camera-like views per mesh for the partial-view metrics (0: skip them)")
    evaluation.set_defaults(handler=evaluate_command)

    screening = commands.add_parser("screen", help="2^k screen of the VAE objective's terms on one AE and code bank")
    screening.add_argument("ae_run", help="run folder with a trained AE and code bank (train --stop-after bank)")
    screening.add_argument("dataset", help="the dataset the AE was trained on (its test split is measured)")
    screening.add_argument("--out", required=True, help="screen folder: one run per cell, screen.md, screen.json")
    screening.add_argument("--recipe", default="cpu", choices=["cpu", "paper", "smoke"],
                           help="the VAE's recipe (the AE and code bank are the run's)")
    screening.add_argument("--iterations", type=int, default=1000, help="VAE iterations per cell (default 1000)")
    screening.add_argument("--factors", default="RBCJ",
                           help="factors to vary, by letter: R (L_R's 1/n), B (beta_4), C (L_Sigma's form), "
                                "J (L_J), K (beta_2); the others keep the recipe's values (default RBCJ)")
    screening.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE",
                           help="a recipe override for every cell, e.g. vae.omega_jacobian=0 (repeatable)")
    screening.add_argument("--jobs", type=int, default=2, help="cells trained at once (default 2)")
    screening.add_argument("--sim", help="sim binary for pose transfer (default: target/release/sim)")
    screening.set_defaults(handler=screen_command)

    export = commands.add_parser("export", help="write a run as an ONNX bundle (the node's model format)")
    export.add_argument("run", help="run folder written by `train`")
    export.add_argument("--out", required=True, help="bundle folder")
    export.add_argument("--metrics", help="metrics JSON from `evaluate`, recorded in the manifest")
    export.add_argument("--dataset", help="training dataset, if the run has no dataset.json")
    export.add_argument("--calibrate", metavar="DATASET",
                        help="measure z_I's variance calibration on DATASET's held-out subjects (the node's "
                             "tracker scales the encoder's variances by it); without it the bundle has none (1)")
    export.add_argument("--calibration-from", metavar="BUNDLE",
                        help="take the z_I variance calibration of BUNDLE, whose z_I encoder this run kept "
                             "(vae.keep_intrinsic; checked on the two encoders' outputs)")
    export.set_defaults(handler=export_command)

    benchmark = commands.add_parser(
        "bench", help="throughput of the training path: batch maker clouds/s, AE and VAE step it/s (figures)")
    benchmark.add_argument("dataset", help="dataset folder whose training meshes the batch maker samples")
    benchmark.add_argument("--recipe", default="cpu", choices=["cpu", "gpu", "paper", "smoke"])
    benchmark.add_argument("--regime", default="fo", choices=["gdvae++", "fo", "paired"])
    benchmark.add_argument("--ae", default="std", choices=["ftl", "std"])
    benchmark.add_argument("--partial-views", type=float, help="share of AE copies that are camera-like views")
    benchmark.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE", help="as for train")
    benchmark.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:1")
    benchmark.add_argument("--seconds", type=float, default=10.0, help="seconds timed per part (default 10)")
    benchmark.add_argument("--limit", type=int, help="load only the first N meshes")
    benchmark.add_argument("--json", action="store_true")
    benchmark.set_defaults(handler=bench_command)

    importing = commands.add_parser(
        "import-bundle", help="a shipped bundle back into a run folder (its AE and VAE weights, read from the ONNX graphs)")
    importing.add_argument("bundle", help="bundle folder written by `export`")
    importing.add_argument("--out", required=True, help="run folder to write (recipe.json, checkpoint.pt)")
    importing.set_defaults(handler=import_bundle_command)

    identity = commands.add_parser(
        "fit-identity", help="fit a bundle's identity projection on the node's clouds (evaluate --states of sim recordings)")
    identity.add_argument("bundle", help="bundle folder whose manifest gets calibration.identity_projection")
    identity.add_argument("states", nargs="+", help="`gdvae-node evaluate ... --states` files of sim recordings, made "
                                                     "with this bundle, apart from the sets you report on")
    identity.add_argument("--directions", type=int, default=5, help="directions kept (default 5)")
    identity.add_argument("--ridge", type=float, default=0.03,
                          help="within-subject scatter shrunk towards its mean variance by this share (default 0.03)")
    identity.set_defaults(handler=fit_identity_command)

    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S", stream=sys.stderr)
    try:
        return args.handler(args)
    except (ValueError, FileNotFoundError) as error:
        print(f"gdvae: error: {error}", file=sys.stderr)
        return 2
