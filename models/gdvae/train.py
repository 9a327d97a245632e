"""Training: recipes, the point sampler, and the three resumable stages (AE, code bank, VAE).

A run lives in one folder: `checkpoint.pt` (written every `checkpoint_seconds` and at the end of
each stage; a rerun of the same command resumes from it), `recipe.json`, and `log.jsonl` (one line
per progress report). Stages:
  1. ae    - the point-cloud autoencoder (supervised: rotation predictor pretrained first);
  2. bank  - the frozen AE encodes every training mesh under several random rotations, with its
             spectrum: the VAE's training set of (q, x_c, lambda);
  3. vae   - the latent VAE on the bank.

Training runs on any torch device (`device`: "cpu", "cuda"); checkpoints are always read back onto
the CPU, so a run trained on a GPU is evaluated and exported on a machine without one. `StageLimits`
ends a stage after a wall-clock budget (a lent accelerator's minutes), and `RUN/stages.json` records
what each stage did: iterations, seconds, device, and whether its budget ended it.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .ae import AEConfig, Autoencoder, ae_loss, restore_batch_norms
from .budget import budget_spent
from .data import DepthCamera, MeshDataset
from .evaluate import beta_ranges
from .geometry import chamfer, matrix_to_quaternion, quaternion_to_matrix, random_rotation_matrices, rotate
from .loss_parts import LossParts
from .node_identity import NodeIdentityBatches, NodeIdentityData
from .paired import PairedBatches, Pairing, identity_contrast
from .pose import BodyTargets, PoseTargets, train_body, train_pose
from .surface import PointSampler
from .vae import LatentVAE, VAEConfig, vae_loss

log = logging.getLogger(__name__)
# The training-only heads of vae.omega_body: in checkpoints, never in a loaded model or a bundle.
TRAINING_HEADS = ("body_heads.",)


@dataclass
class StageLimits:
    """Wall-clock budgets per stage, in seconds (None: run the recipe's iterations). A stage that
    reaches its budget ends there, as if its iterations were done, and says so in stages.json."""

    ae_seconds: float | None = None
    vae_seconds: float | None = None

    def validate(self) -> None:
        for name, value in (("AE", self.ae_seconds), ("VAE", self.vae_seconds)):
            if value is not None and not value > 0:
                raise ValueError(f"{name} time budget {value} s: must be positive")


@dataclass
class Recipe:
    name: str
    ae: AEConfig
    vae: VAEConfig
    ae_iterations: int
    ae_pretrain_iterations: int  # rotation predictor only (supervised AEs)
    ae_batch: int
    ae_learning_rate: float = 5e-4
    ae_min_learning_rate: float = 1e-4
    bank_copies: int = 8  # random rotations per training mesh in the code bank
    # Supervised AEs: encode the code bank with the true rotation (q and x_c), as the paper does in
    # every training operation of the supervised model; False: with E_r's prediction (what this kit
    # did before; a copy whose heading E_r got wrong becomes variance the VAE cannot explain).
    bank_true_rotation: bool = True
    # Fraction of code-bank copies that are camera-like partial views, each paired with the whole
    # mesh's spectrum, so that L_S teaches z_I to name the whole shape from any side (what the node
    # sees). None: the AE's `partial_views`.
    bank_partial_views: float | None = None
    # The pose stage (pose.py; only for an AE with `pose_encoder`): iterations, batch, learning
    # rate, and how many of theta's principal components per family E_p is taught.
    pose_iterations: int = 10_000
    pose_batch: int = 32
    pose_learning_rate: float = 1e-4
    pose_components: int = 10
    # The body stage (pose.py; only for an AE with `body_encoder`), after the pose stage: E_b is
    # taught each family's beta in `pose_batch`-sized batches.
    body_iterations: int = 10_000
    body_learning_rate: float = 5e-4
    vae_iterations: int = 40000
    vae_batch: int = 264
    vae_learning_rate: float = 1e-4
    vae_min_learning_rate: float = 1e-5
    vae_weight_decay: float = 1e-4
    spectrum_count: int = 22
    # Fraction of AE input copies that are partial views (what a depth camera sees); the AE still
    # reconstructs the whole surface, so x_c learns to ignore the view. Supervised AEs only.
    partial_views: float = 0.0
    # Render those partial views (AE inputs and code-bank copies) as the node's depth camera sees
    # them (`DepthCamera`: nearest point per pixel, stereo depth noise) instead of as the faces
    # turned towards the camera (no self-occlusion, no noise).
    depth_camera_views: bool = False
    checkpoint_seconds: float = 120.0
    seed: int = 0
    # Model units per input unit (metre). None: the training dataset's own scale (its largest
    # bounding-box side becomes 1). Fixed once a model exists: a run that starts from another
    # (`--init-from`, an imported bundle) keeps that model's units, whatever dataset it trains on.
    model_units: float | None = None


    def bank_view_share(self) -> float:
        """The share of code-bank copies that are camera views: `bank_partial_views`, or the AE's
        `partial_views` when it is None."""
        return self.partial_views if self.bank_partial_views is None else self.bank_partial_views


def recipe(name: str, regime: str = "gdvae++", kind: str = "ftl") -> Recipe:
    """Named recipes. `paper`: the paper's sizes (N_p = 1600, its widths and iteration counts; a GPU
    job). `cpu`: scaled to train AE + VAE in about two hours on 2 cores. `smoke`: seconds, for tests."""
    vae = {"gdvae++": VAEConfig, "fo": VAEConfig.flow_only, "paired": VAEConfig.paired_regime}[regime]()
    if name == "paper":
        ae = AEConfig(kind=kind, latent=999 if kind == "ftl" else 600,
                      decoder_width=1250 if kind == "ftl" else 1200,
                      gamma_reconstruction=20.0 if kind == "ftl" else 250.0)
        return Recipe("paper", ae, replace(vae, latent=ae.latent), ae_iterations=150_000,
                      ae_pretrain_iterations=2000, ae_batch=36 if kind == "ftl" else 40)
    if name == "cpu":
        ae = AEConfig(kind=kind, points=256, latent=192 if kind == "ftl" else 150,
                      rotation_hidden=(32, 64, 128), shape_hidden=(64, 128, 256), decoder_width=256,
                      gamma_reconstruction=20.0 if kind == "ftl" else 250.0)
        # L_R keeps the paper's 1/n: without it the decoder reconstructs far better but S drops
        # (models/EXPERIMENTS.md, "Reconstruction normalisation"); `--relative-reconstruction` drops it.
        return Recipe("cpu", ae, replace(vae, latent=ae.latent, width_scale=0.25, flow_hidden=400),
                      ae_iterations=7700, ae_pretrain_iterations=2000, ae_batch=24, ae_learning_rate=1e-3,
                      vae_iterations=3000, vae_batch=256)
    if name == "gpu":
        # The node's model size (the cpu recipe's widths and N_p: what the node runs at 30 Hz and
        # what comes back through the device tool, whose files are limited to 16 MiB each; the
        # paper's STD decoder alone is about 150 MB) with a batch four times the CPU recipe's and
        # iterations bounded by the stage budgets (`--ae-minutes`, `--vae-minutes`) rather than by
        # count. models/README.md, "Training on a lent GPU".
        cpu = recipe("cpu", regime, kind)
        return replace(cpu, name="gpu", ae_iterations=150_000, ae_batch=96, vae_iterations=40_000,
                       checkpoint_seconds=60.0)
    if name == "smoke":
        ae = AEConfig(kind=kind, points=128, latent=48, rotation_hidden=(16, 32), shape_hidden=(16, 32),
                      decoder_width=32, copies=2)
        return Recipe("smoke", ae, replace(vae, latent=ae.latent, width_scale=0.02, flow_layers=3, n_extrinsic=4),
                      ae_iterations=4, ae_pretrain_iterations=2, ae_batch=4, bank_copies=2,
                      vae_iterations=4, vae_batch=16, checkpoint_seconds=0.0, pose_iterations=4, pose_batch=4,
                      pose_components=2, body_iterations=4)
    raise ValueError(f"unknown recipe {name!r} (known: {', '.join(RECIPES)})")


RECIPES = ("cpu", "gpu", "paper", "smoke")


def load_run(run_dir: str | Path) -> tuple[Recipe, Autoencoder, LatentVAE | None, dict]:
    """A run folder's recipe, trained AE, trained VAE (None before the VAE stage finished) and
    checkpoint state."""
    run_dir = Path(run_dir)
    checkpoint_path = run_dir / "checkpoint.pt"
    if not checkpoint_path.exists():
        raise FileNotFoundError(f"{run_dir}: no checkpoint.pt (not a training run folder)")
    raw = json.loads((run_dir / "recipe.json").read_text())
    ae_config = AEConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.pop("ae").items()})
    vae_config = VAEConfig(**raw.pop("vae"))
    chosen = Recipe(ae=ae_config, vae=vae_config, **raw)
    state = torch.load(checkpoint_path, weights_only=False, map_location="cpu")
    ae = Autoencoder(ae_config)
    load_ae_state(ae, state["ae"])
    ae.eval()
    vae = None
    # A run imported from a bundle (import_bundle.py) carries the bundle's VAE beside its AE.
    vae_state = state.get("vae", state.get("imported_vae"))
    if vae_state is not None:
        spectrum = state["bank"]["spectrum"].shape[1] if "bank" in state else vae_config.spectrum
        # vae.omega_body's heads exist only in training: the loaded model is the bundle's.
        vae = LatentVAE(replace(vae_config, latent=ae_config.latent, spectrum=spectrum, body_heads=0))
        vae.load_state_dict({k: v for k, v in vae_state.items() if not k.startswith(TRAINING_HEADS)})
        vae.eval()
    return chosen, ae, vae, state


def source_model_units(run_dir: str | Path) -> float | None:
    """The model units of an existing run: its recipe's `model_units`, else the scale of the dataset
    it trained on (its dataset.json), else None (an unknown run)."""
    run_dir = Path(run_dir)
    recipe_file, summary_file = run_dir / "recipe.json", run_dir / "dataset.json"
    units = json.loads(recipe_file.read_text()).get("model_units") if recipe_file.exists() else None
    if units is None and summary_file.exists():
        units = json.loads(summary_file.read_text()).get("scale")
    return units


def use_model_units(dataset: MeshDataset, units: float | None) -> None:
    """Puts `dataset` in a model's units (None: keeps the dataset's own scale), saying so when they
    differ: samples, spectra and the bundle's manifest all follow `dataset.scale`."""
    if units is None or units == dataset.scale:
        return
    log.info("%s: in the model's units, %.6g per input unit (the dataset's own scale would be %.6g)",
             dataset.root, units, dataset.scale)
    dataset.scale = units


def dataset_summary(dataset: MeshDataset) -> dict:
    """What a bundle records about its training data."""
    train = dataset.indices("train")
    families = sorted({(item.truth or {}).get("family", "?") for item in dataset.items})
    return {
        "dataset": str(dataset.root),
        "scale": dataset.scale,
        "meshes": len(dataset.items),
        "train_meshes": len(train),
        "train_subjects": len({dataset.items[i].subject for i in train}),
        "families": families,
        "has_ground_truth": dataset.has_ground_truth,
        "rejected": dict(dataset.rejected),
    }


@dataclass
class Progress:
    """Logs a line (and a JSON record) at most every `seconds`, with rate and ETA."""

    stage: str
    total: int
    log_file: Path
    seconds: float = 30.0
    started: float = field(default_factory=time.monotonic)
    first_iteration: int = 0
    last: float = 0.0

    def update(self, iteration: int, parts: Callable[[], dict[str, float]], force: bool = False) -> None:
        """`parts`: called for the figures only when a line is logged (reading a loss waits for
        the device)."""
        now = time.monotonic()
        if not force and now - self.last < self.seconds:
            return
        self.last = now
        done = iteration - self.first_iteration
        rate = done / max(now - self.started, 1e-9)
        eta = (self.total - iteration) / rate if rate > 0 else float("inf")
        parts = parts()
        shown = " ".join(f"{k}={v:.4g}" for k, v in parts.items())
        log.info("%s %d/%d (%.2f it/s, ETA %s) %s", self.stage, iteration, self.total, rate, _duration(eta), shown)
        with open(self.log_file, "a") as f:
            f.write(json.dumps({"stage": self.stage, "iteration": iteration, "rate": rate, "eta_s": eta, **parts}) + "\n")


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    return f"{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m{int(seconds % 60):02d}s"


class Plateau:
    """The paper's schedule: multiply the learning rate by 0.95 when the windowed mean loss stops
    improving, down to a floor."""

    def __init__(self, optimizer, minimum: float, window: int = 100, patience: int = 3):
        self.optimizer, self.minimum, self.window, self.patience = optimizer, minimum, window, patience
        self.values: list[float] = []
        self.best, self.bad = float("inf"), 0

    def step(self, loss: float | torch.Tensor) -> None:
        """`loss`: a float or a detached tensor (summed on its device; read once per window)."""
        self.values.append(loss)
        if len(self.values) < self.window:
            return
        mean = float(sum(self.values)) / len(self.values)
        self.values.clear()
        if mean < self.best * 0.999:
            self.best, self.bad = mean, 0
            return
        self.bad += 1
        if self.bad >= self.patience:
            self.bad = 0
            for group in self.optimizer.param_groups:
                group["lr"] = max(self.minimum, group["lr"] * 0.95)

    def state_dict(self):
        return {"best": self.best, "bad": self.bad, "values": [float(v) for v in self.values]}

    def load_state_dict(self, state):
        self.best, self.bad, self.values = state["best"], state["bad"], list(state["values"])


def train(dataset: MeshDataset, spectra: np.ndarray, run_dir: str | Path, chosen: Recipe,
          stop_after: str | None = None, init_from: str | Path | None = None, rebuild_bank: bool = False,
          continue_ae: int = 0, device: str = "cpu", limits: StageLimits | None = None,
          loader_workers: int = 0, pose_dataset: MeshDataset | None = None,
          body_dataset: MeshDataset | None = None, reteach: tuple[str, ...] = (),
          node_identity: NodeIdentityData | None = None) -> dict:
    """Runs (or resumes) the stages: AE, pose (with a pose encoder), body (with a body encoder),
    code bank, VAE. Returns the trained modules.

    `init_from`: another run whose AE and code bank this run reuses (it starts at the VAE stage),
    so that two VAE regimes can be compared on exactly the same autoencoder. `rebuild_bank`: reuse
    only its AE and encode a new bank with this recipe's bank settings. `continue_ae`: train the
    source's AE that many more iterations first (an undertrained AE; the bank is then rebuilt).
    `device`: where the networks train and their batches are made; `limits`: per-stage wall-clock
    budgets; `loader_workers`: processes that make AE batches ahead of the training step on a CPU
    (0: in the training process, on its device). `pose_dataset`: the pose stage's meshes (its
    training split; default `dataset`'s), e.g. many distinct poses where `dataset` is a paired grid
    of few; `body_dataset` likewise the body stage's (many distinct subjects). `reteach` ("pose",
    "body"): with `init_from`, teach the source's E_p or E_b again (new targets or data; each starts
    as a new one does), then a new code bank. `node_identity`: x_c of the node's frames with their
    subjects, which `vae.omega_node_identity` teaches z_I to tell apart (node_identity.py).
    """
    limits = limits or StageLimits()
    limits.validate()
    chosen.vae.validate()  # the VAE's settings are refused before the AE stage, not after it
    device = torch.device(device)
    if loader_workers < 0:
        raise ValueError(f"loader workers {loader_workers}: must be >= 0")
    if loader_workers > 0 and device.type != "cpu":
        raise ValueError(f"loader workers ({loader_workers}) make batches on the CPU; on {device} the batches "
                         "are made on the device by the training process: leave --loader-workers out")
    if (node_identity is None) != (chosen.vae.omega_node_identity == 0):
        raise ValueError("the node's states (--node-states) and vae.omega_node_identity > 0 go together: "
                         + ("give the states the term is taught on" if node_identity is None
                            else "set the weight of the term they are for"))
    if chosen.partial_views > 0 and not chosen.ae.supervised:
        raise ValueError("partial views need the supervised AE (its target is the whole canonical cloud)")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if init_from is not None:  # the reused AE is the source's: its configuration and how it was trained
        check_source_bank(init_from, dataset, bool(continue_ae > 0 or rebuild_bank or reteach))
        source_recipe = json.loads((Path(init_from) / "recipe.json").read_text())
        source_ae = AEConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in source_recipe["ae"].items()})
        # A pose encoder may be added to the source's AE (the pose stage trains it here), not removed.
        source_has_pose = source_ae.pose_encoder
        if chosen.ae.pose_encoder and not source_ae.pose_encoder:
            source_ae = replace(source_ae, pose_encoder=True, pose_hidden=chosen.ae.pose_hidden)
        source_has_body = source_ae.body_encoder  # and a body encoder likewise
        if chosen.ae.body_encoder and not source_ae.body_encoder:
            source_ae = replace(source_ae, body_encoder=True, body_hidden=chosen.ae.body_hidden)
        if source_ae != chosen.ae:
            log.info("the AE configuration is %s's (reused with its weights)", init_from)
        chosen.ae = source_ae
        chosen.vae = replace(chosen.vae, latent=source_ae.latent)
        chosen.ae_iterations = source_recipe["ae_iterations"]
        chosen.ae_pretrain_iterations = source_recipe.get("ae_pretrain_iterations", chosen.ae_pretrain_iterations)
        chosen.partial_views = source_recipe.get("partial_views", 0.0)
        chosen.bank_true_rotation = source_recipe.get("bank_true_rotation", False)
        source_iterations = chosen.ae_pretrain_iterations + chosen.ae_iterations
        chosen.ae_iterations += continue_ae
    chosen.vae = replace(chosen.vae, pose_input=chosen.ae.latent if chosen.ae.pose_encoder else 0,
                         body_input=chosen.ae.latent if chosen.ae.body_encoder else 0)
    check_reteach(reteach, chosen, init_from)
    if node_identity is not None and node_identity.x_c.shape[1] != chosen.ae.latent:
        raise ValueError(f"the node's states hold x_c of {node_identity.x_c.shape[1]} numbers, this run's AE makes "
                         f"{chosen.ae.latent}: write them with a bundle exported from this run's autoencoder")
    (run_dir / "recipe.json").write_text(json.dumps(asdict(chosen), indent=2, default=str))
    summary = dataset_summary(dataset)
    if chosen.ae.pose_encoder:  # what E_p was taught on (the bundle's manifest and model card say it)
        posed = pose_dataset or dataset
        summary["pose_stage"] = {"dataset": str(posed.root), "train_meshes": len(posed.indices("train")),
                                 "iterations": chosen.pose_iterations, "components": chosen.pose_components}
        if init_from is not None and source_has_pose and "pose" not in reteach:  # E_p is the source's
            summary["pose_stage"] = source_stage(init_from, "pose_stage")
    if chosen.ae.body_encoder:  # what E_b was taught on, likewise
        bodies = body_dataset or dataset
        summary["body_stage"] = {"dataset": str(bodies.root), "train_meshes": len(bodies.indices("train")),
                                 "iterations": chosen.body_iterations}
        if init_from is not None and source_has_body and "body" not in reteach:
            summary["body_stage"] = source_stage(init_from, "body_stage")
    if init_from is not None:  # a code kept from the source was taught there (the model card says how)
        source_vae = source_recipe.get("vae", {})
        if chosen.vae.keep_extrinsic:
            summary["z_E_kept_from"] = {"run": str(init_from), "omega_pose": source_vae.get("omega_pose", 0.0)}
        if chosen.vae.keep_intrinsic:
            summary["z_I_kept_from"] = {"run": str(init_from), "omega_body": source_vae.get("omega_body", 0.0),
                                        "body_direct": source_vae.get("body_direct", False)}
    if node_identity is not None:
        summary["node_identity"] = node_identity.summary()
    (run_dir / "dataset.json").write_text(json.dumps(summary, indent=2))
    torch.manual_seed(chosen.seed)
    checkpoint_path = run_dir / "checkpoint.pt"
    imported = False
    if checkpoint_path.exists():
        state = torch.load(checkpoint_path, weights_only=False, map_location="cpu")
        log.info("resuming from %s: stage %s, iteration %d", checkpoint_path, state["stage"], state["iteration"])
    elif init_from is not None:
        source = torch.load(Path(init_from) / "checkpoint.pt", weights_only=False, map_location="cpu")
        imported = "imported_from" in source  # batch norms folded by the export (import_bundle.py)
        if source.get("stage") == "ae":
            raise ValueError(f"{init_from}: its AE stage has not finished; nothing to start from")
        if "bank" not in source and not (continue_ae > 0 or rebuild_bank or reteach):  # reteach builds a new bank
            raise ValueError(f"{init_from}: it has no code bank (an imported bundle?): "
                             "start from its AE with --rebuild-bank or --continue-ae N")
        if chosen.vae.keeps_start and continue_ae > 0:
            raise ValueError("keep_intrinsic / keep_extrinsic keep one of the source's code encoders, which reads "
                             "its AE's codes: the AE cannot be continued in the same run")
        adds_pose = chosen.ae.pose_encoder and not any(k.startswith("pose_encoder.") for k in source["ae"])
        adds_body = chosen.ae.body_encoder and not any(k.startswith("body_encoder.") for k in source["ae"])
        if (adds_pose or adds_body) and not (continue_ae > 0 or rebuild_bank or reteach):
            raise ValueError(f"{init_from}: its AE has no {'pose' if adds_pose else 'body'} encoder; one is trained "
                             "here before a new code bank: add --rebuild-bank")
        if continue_ae > 0:
            state = {"stage": "ae", "iteration": source_iterations, "ae": source["ae"]}
            log.info("continuing the AE of %s for %d iterations (new code bank)", init_from, continue_ae)
        elif rebuild_bank or reteach:
            teach = [stage for stage, added in (("pose", adds_pose), ("body", adds_body))
                     if added or stage in reteach]
            first = stage_after("ae", teach)
            state = {"stage": first, "iteration": 0, "ae": source["ae"], "teach": teach}
            log.info("starting from the AE of %s (%snew code bank)", init_from,
                     "".join(f"{stage} stage, " for stage in teach))
        else:
            state = {"stage": "vae", "iteration": 0, "ae": source["ae"], "bank": source["bank"]}
            log.info("starting from the AE and code bank of %s", init_from)
        if chosen.vae.keeps_start and {"vae", "imported_vae"} & source.keys():
            state["start_vae"] = source.get("vae", source.get("imported_vae"))
            log.info("%s and the rotation branch are %s's, held fixed",
                     "z_I's encoder, the flow" if chosen.vae.keep_intrinsic else "z_E's encoder", init_from)
    else:
        state = {"stage": "ae", "iteration": 0}
    if chosen.vae.keeps_start and "vae" not in state and "start_vae" not in state:
        raise ValueError("vae.keep_intrinsic / keep_extrinsic keep a trained VAE's code encoder: start from a run "
                         "(or an imported bundle) that has one, with --init-from")
    train_indices = dataset.indices("train")
    if not train_indices:
        raise ValueError(f"{dataset.root}: no training meshes (check splits.json)")

    ae = Autoencoder(chosen.ae)
    if "ae" in state:
        load_ae_state(ae, state["ae"])
    if state["stage"] == "body" and state["iteration"] == 0 and "body" in reteach:
        for module in ae.body_encoder.modules():  # a retaught E_b starts from random weights, as a new one
            if hasattr(module, "reset_parameters"):
                module.reset_parameters()
    teach = state.get("teach", taught_stages(chosen.ae))
    stages = StageRecord(run_dir / "stages.json", str(device))
    sampler = None
    if state["stage"] in ("ae", "pose", "body", "bank"):  # the VAE trains on the code bank, without clouds
        started = time.monotonic()
        sampler = PointSampler(dataset, train_indices, chosen.ae.points, chosen.seed + state["iteration"],
                               DepthCamera() if chosen.depth_camera_views else None, device)
        log.info("%d training meshes on %s for sampling (%.0f MB, %.1f s)", len(sampler), device,
                 sampler.cache.bytes() / 1e6, time.monotonic() - started)
    if imported and state["stage"] == "ae":
        chosen_meshes, _ = sampler.batch(64)
        restore_batch_norms(ae, sampler.views(chosen_meshes, 3, chosen.partial_views).cpu())
        log.info("batch norms of the imported AE set to the statistics of %d training clouds", 3 * 64)

    def save(extra: dict) -> None:
        temporary = checkpoint_path.with_suffix(".tmp")
        torch.save({**extra, "ae": ae.state_dict()}, temporary)
        temporary.replace(checkpoint_path)

    ae.to(device)
    if state["stage"] == "ae":
        probe = ReconstructionProbe(dataset, train_indices, chosen, device)
        train_ae(ae, sampler, chosen, state, save, run_dir, device, limits.ae_seconds, loader_workers, stages, probe)
        state = {"stage": stage_after("ae", teach), "iteration": 0}
        save(state)
    if stop_after == "ae":
        return {"ae": ae}
    if state["stage"] == "pose":
        progress = Progress("pose", chosen.pose_iterations, run_dir / "log.jsonl", first_iteration=state["iteration"])
        carried = {key: state[key] for key in ("start_vae", "teach") if key in state}
        posed, posed_indices, pose_sampler = taught_meshes("pose", pose_dataset, dataset, train_indices, sampler,
                                                           chosen, state["iteration"], device)
        train_pose(ae, pose_sampler, [posed.items[i].truth for i in posed_indices], chosen, state,
                   lambda extra: save({**extra, **carried}), progress, device, stages)
        state = {"stage": stage_after("pose", teach), "iteration": 0, **carried}
        save(state)
    if state["stage"] == "body":
        progress = Progress("body", chosen.body_iterations, run_dir / "log.jsonl", first_iteration=state["iteration"])
        carried = {key: state[key] for key in ("start_vae", "teach") if key in state}
        bodies, body_indices, body_sampler = taught_meshes("body", body_dataset, dataset, train_indices, sampler,
                                                           chosen, state["iteration"], device)
        train_body(ae, body_sampler, [bodies.items[i].truth for i in body_indices], beta_ranges(bodies.root), chosen,
                   state, lambda extra: save({**extra, **carried}), progress, device, stages)
        state = {"stage": "bank", "iteration": 0, **({"start_vae": state["start_vae"]} if "start_vae" in state else {})}
        save(state)

    pairing = None
    if chosen.vae.paired:
        pairing = Pairing.from_truths([dataset.items[i].truth for i in train_indices], str(dataset.root))
    if state["stage"] == "bank":
        bank = encode_bank(ae, sampler, spectra[train_indices], chosen, device, pairing)
        state = {"stage": "vae", "iteration": 0, "bank": bank,
                 **({"start_vae": state["start_vae"]} if "start_vae" in state else {})}
        save(state)
    if stop_after == "bank":
        return {"ae": ae}
    bank = state["bank"]
    if pairing is not None and "target" not in bank:
        raise ValueError(f"{init_from}: its code bank has no paired targets (it was built for another regime): "
                         "start from its AE with --rebuild-bank")

    taught = {}  # mu_I taught beta (vae.omega_body), mu_E theta (vae.omega_pose): one row per training mesh
    truths = [dataset.items[i].truth for i in train_indices]
    if chosen.vae.omega_body > 0:
        taught["body"] = BodyTargets(truths, beta_ranges(dataset.root))
    if chosen.vae.omega_pose > 0:
        taught["pose"] = PoseTargets(truths, chosen.vae.n_extrinsic, whitened=False)
    heads = taught["body"].components * len(taught["body"].families) if "body" in taught else 0
    if chosen.vae.body_direct and "body" in taught:  # (without omega_body, the VAE's validation refuses it)
        if taught["body"].components > chosen.vae.n_intrinsic:
            raise ValueError(f"vae.body_direct: beta has {taught['body'].components} parameters, z_I only "
                             f"{chosen.vae.n_intrinsic} units")
        heads = 0
    vae = LatentVAE(replace(chosen.vae, latent=chosen.ae.latent, spectrum=spectra.shape[1], body_heads=heads))
    if "vae" in state:
        vae.load_state_dict(state["vae"])
    else:
        if "start_vae" in state:  # keep_*: the source's VAE, its flow's input scaling included
            load_start_vae(vae, state["start_vae"], chosen.vae.keep_extrinsic, chosen.vae.keep_intrinsic)
        else:
            vae.flow.input.fit(bank["spectrum"])
        vae.code_norm.fill_(float(bank["x_c"].pow(2).sum(-1).mean()))
    vae.to(device)
    if state["stage"] == "vae":
        train_vae(vae, bank, chosen, state, lambda extra: save({**extra, "bank": bank}), run_dir, len(train_indices),
                  device, limits.vae_seconds, stages, taught, node_identity)
        save({"stage": "done", "iteration": 0, "bank": bank, "vae": vae.state_dict()})
    return {"ae": ae.eval().cpu(), "vae": vae.eval().cpu()}


class StageRecord:
    """RUN/stages.json: per stage, the iterations it ran to, its seconds in this process, the
    device, and whether its time budget ended it (merged over resumed runs)."""

    def __init__(self, path: Path, device: str):
        self.path, self.device = path, device
        self.stages = json.loads(path.read_text()) if path.exists() else {}

    def finish(self, stage: str, iteration: int, planned: int, seconds: float, budget_ended: bool) -> None:
        previous = self.stages.get(stage, {})
        self.stages[stage] = {
            "iterations": iteration, "planned": planned, "device": self.device,
            "seconds": round(previous.get("seconds", 0.0) + seconds, 1), "ended_by_time_budget": budget_ended,
        }
        self.path.write_text(json.dumps(self.stages, indent=2))


class AEBatches(torch.utils.data.IterableDataset):
    """Endless AE training batches: canonical clouds and, with partial views, each copy's view.
    With loader workers each process draws from its own generator (seeded by the run's seed, the
    iteration it started at and its worker number), so sampling keeps up with an accelerator."""

    def __init__(self, sampler: PointSampler, batch: int, copies: int, partial: float, seed: int):
        self.sampler, self.batch, self.copies, self.partial, self.seed = sampler, batch, copies, partial, seed

    def __iter__(self):
        worker = torch.utils.data.get_worker_info()
        if worker is not None:
            self.sampler.reseed(self.seed * 1000 + worker.id)
        while True:
            indices, clouds = self.sampler.batch(self.batch)
            views = self.sampler.views(indices, self.copies, self.partial) if self.partial > 0 else None
            yield clouds, views


def ae_batches(sampler: PointSampler, chosen: Recipe, copies: int, start: int, workers: int):
    """An iterator over AE batches: in this process (workers = 0, the sampler's own generator, as
    before loader workers existed) or from `workers` processes."""
    stream = AEBatches(sampler, chosen.ae_batch, copies, chosen.partial_views, chosen.seed + start)
    if workers == 0:
        return iter(stream)
    loader = torch.utils.data.DataLoader(stream, batch_size=None, num_workers=workers, prefetch_factor=4,
                                         collate_fn=lambda item: item, multiprocessing_context="fork")
    return iter(loader)


class ReconstructionProbe:
    """d_C of the AE's reconstructions of fixed clouds of `meshes` training meshes and of as many
    held-out ones (the validation split, else the test split), each seen as training sees it (a
    camera view with the recipe's `partial_views` share, else the whole surface) in a fixed
    rotation, against a fresh whole-surface sample: what `evaluate` calls d_C. Logged with every
    progress line: while the training figure falls and the held-out one does not, the autoencoder
    is memorising its training subjects, and more subjects will help it more than more iterations."""

    def __init__(self, dataset: MeshDataset, train_indices: list[int], chosen: Recipe, device, meshes: int = 64,
                 seed: int = 12345):
        rng = np.random.default_rng(seed)
        held_out = dataset.indices("validation") or dataset.indices("test")
        groups = {"train": train_indices, "heldout": held_out}
        camera = DepthCamera() if chosen.depth_camera_views else None
        generator = torch.Generator().manual_seed(seed)
        self.sets = {}
        for name, indices in groups.items():
            if not indices:
                continue
            chosen_indices = sorted(rng.choice(indices, size=min(meshes, len(indices)), replace=False).tolist())
            sampler = PointSampler(dataset, chosen_indices, chosen.ae.points, seed, camera, device)
            everyone = torch.arange(len(chosen_indices))
            rotations = random_rotation_matrices(len(chosen_indices), generator, chosen.ae.full_rotations).to(device)
            inputs = rotate(sampler.views(everyone, 1, chosen.partial_views), rotations)
            self.sets[name] = (inputs, rotate(sampler.clouds(everyone), rotations))

    @torch.no_grad()
    def measure(self, ae) -> dict[str, float]:
        was_training = ae.training
        ae.eval()
        figures = {f"d_C_{name}": float(chamfer(ae(inputs).reconstruction, targets).mean())
                   for name, (inputs, targets) in self.sets.items()}
        ae.train(was_training)
        return figures


def fused_adam(device) -> bool:
    """Adam's fused kernel on a GPU: one launch for all parameters, where the default updates
    them in a few launches per parameter group (the VAE has 162 parameter tensors)."""
    return torch.device(device or "cpu").type == "cuda"


def train_ae(ae, sampler, chosen: Recipe, state, save, run_dir, device, budget_seconds, workers, stages,
             probe: ReconstructionProbe | None = None) -> None:
    optimizer = torch.optim.Adam(ae.parameters(), lr=chosen.ae_learning_rate, fused=fused_adam(device))
    schedule = Plateau(optimizer, chosen.ae_min_learning_rate)
    if "optimizer" in state:
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
    pretrain = chosen.ae_pretrain_iterations if chosen.ae.supervised else 0
    total = pretrain + chosen.ae_iterations
    start = state["iteration"]
    progress = Progress("ae", total, run_dir / "log.jsonl", first_iteration=start)
    last_save = started = time.monotonic()
    batches = ae_batches(sampler, chosen, ae.config.copies, start, workers)
    ae.train()
    iteration, budget_ended = start, False
    for iteration in range(start, total):
        if budget_spent("ae", budget_seconds, started, iteration, total):
            budget_ended = True
            break
        clouds, views = next(batches)
        clouds = clouds.to(device, non_blocking=True)
        views = views.to(device, non_blocking=True) if views is not None else None
        losses, _ = ae_loss(ae, clouds, rotation_only=iteration < pretrain, views=views)
        optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        optimizer.step()
        if iteration >= pretrain:
            schedule.step(losses.parts.tensor("total"))
        progress.update(iteration + 1, lambda: {**losses.parts, "lr": optimizer.param_groups[0]["lr"],
                                                **(probe.measure(ae) if probe and iteration >= pretrain else {})},
                        force=iteration + 1 == total)
        if time.monotonic() - last_save > chosen.checkpoint_seconds and iteration + 1 < total:
            save({"stage": "ae", "iteration": iteration + 1, "optimizer": optimizer.state_dict(),
                  "schedule": schedule.state_dict()})
            last_save = time.monotonic()
    else:
        iteration = total
    stages.finish("ae", iteration, total, time.monotonic() - started, budget_ended)
    ae.eval()


def check_source_bank(init_from: str | Path, dataset: MeshDataset, builds_bank: bool) -> None:
    """A run that starts from `init_from`'s code bank (no --rebuild-bank, --continue-ae or
    --reteach) trains its VAE on the source's encoded training meshes, row for row with this
    dataset's ground truth: refused, before any work, when the two datasets are not the same."""
    if builds_bank:
        return
    recorded = Path(init_from) / "dataset.json"
    if not recorded.exists():
        return  # an imported bundle: it has no bank, which train() says
    source = json.loads(recorded.read_text())
    here = {"dataset": str(Path(dataset.root).resolve()), "train_meshes": len(dataset.indices("train"))}
    there = {"dataset": str(Path(source["dataset"]).resolve()), "train_meshes": source.get("train_meshes")}
    if here != there:
        raise ValueError(f"{init_from}'s code bank holds the codes of {there['train_meshes']} training meshes of "
                         f"{there['dataset']}, not of {dataset.root} ({here['train_meshes']}): add --rebuild-bank "
                         "to encode this dataset's meshes with its AE")


def source_stage(init_from: str | Path, key: str) -> dict:
    """What the source run says of a taught stage (`pose_stage`, `body_stage`) whose encoder this
    run reuses: its `dataset.json`, or for an imported bundle its `imported.json` (the manifest's)."""
    for name in ("dataset.json", "imported.json"):
        path = Path(init_from) / name
        if path.exists() and key in (recorded := json.loads(path.read_text())):
            return recorded[key]
    return {"dataset": f"(the AE of {init_from})"}


def taught_meshes(stage: str, own: MeshDataset | None, dataset: MeshDataset, train_indices: list[int],
                  sampler: PointSampler, chosen: Recipe, iteration: int, device) -> tuple:
    """A taught stage's (dataset, training indices, sampler): its own dataset's (`--pose-data`,
    `--body-data`) when it has one, else the run's."""
    if own is None:
        return dataset, train_indices, sampler
    indices = own.indices("train")
    log.info("%s stage on %s: %d training meshes", stage, own.root, len(indices))
    return own, indices, PointSampler(own, indices, chosen.ae.points, chosen.seed + iteration,
                                      DepthCamera() if chosen.depth_camera_views else None, device)


def taught_stages(ae: AEConfig) -> list[str]:
    """The taught stages a new AE of this configuration goes through after its AE stage."""
    return [stage for stage, present in (("pose", ae.pose_encoder), ("body", ae.body_encoder)) if present]


def stage_after(stage: str, teach: list[str]) -> str:
    """The stage that follows `stage` ("ae" or a taught stage) when the taught stages `teach` run."""
    order = ["ae", *teach, "bank"]
    return order[order.index(stage) + 1]


def check_reteach(reteach: tuple[str, ...], chosen: Recipe, init_from) -> None:
    """`reteach` names taught stages of the source's AE, and keeps no VAE encoder that reads their code."""
    for stage in reteach:
        if stage not in ("pose", "body"):
            raise ValueError(f"reteach {stage!r}: the taught stages are pose and body")
        if init_from is None:
            raise ValueError(f"reteach {stage}: it teaches a source run's encoder again; it goes with init_from")
        if not getattr(chosen.ae, f"{stage}_encoder"):
            raise ValueError(f"reteach {stage}: the AE has no {stage} encoder (ae.{stage}_encoder)")
        kept = {"pose": ("keep_extrinsic", "z_E"), "body": ("keep_intrinsic", "z_I")}[stage]
        if getattr(chosen.vae, kept[0]):
            raise ValueError(f"reteach {stage} changes the code {kept[1]}'s encoder reads, which vae.{kept[0]} keeps: "
                             "train that encoder here (leave vae." + kept[0] + " out)")


def load_ae_state(ae: Autoencoder, weights: dict) -> None:
    """An AE's weights; a pose or body encoder the weights lack stays as built (its stage trains
    it), anything else missing or left over is an error."""
    missing, unexpected = ae.load_state_dict(weights, strict=False)
    if unexpected or any(not key.startswith(("pose_encoder.", "body_encoder.")) for key in missing):
        raise ValueError(f"the AE's weights do not fit its configuration: missing {missing}, unexpected {unexpected}")


def load_start_vae(vae: LatentVAE, weights: dict, keep_extrinsic: bool = False, keep_intrinsic: bool = False) -> None:
    """keep_intrinsic's or keep_extrinsic's starting VAE. When this VAE's z_E encoder reads a pose
    code (or its z_I encoder a body code) the source's did not, that encoder starts afresh (only
    where it is trained here: not under keep_extrinsic, or keep_intrinsic); everything else must fit."""
    own = vae.state_dict()
    weights = {k: v for k, v in weights.items() if not k.startswith(TRAINING_HEADS) or k in own}  # training-only
    fresh = {key for key, value in weights.items()
             if key.startswith(("extrinsic.", "intrinsic.")) and key in own and own[key].shape != value.shape}
    fresh |= {key for key in own if key.startswith(TRAINING_HEADS) and key not in weights}  # vae.omega_body's
    for prefix, kept, flag, latent in (("extrinsic.", keep_extrinsic, "keep_extrinsic", "z_E"),
                                       ("intrinsic.", keep_intrinsic, "keep_intrinsic", "z_I")):
        changed = sorted(key for key in fresh if key.startswith(prefix))
        if changed and kept:
            raise ValueError(f"{flag} keeps the starting VAE's {latent} encoder, but it reads another input "
                             f"({changed[0]} differs in shape): start from a VAE trained on this AE's codes")
    missing, unexpected = vae.load_state_dict({k: v for k, v in weights.items() if k not in fresh}, strict=False)
    if unexpected or set(missing) != fresh:
        raise ValueError(f"the starting VAE's weights do not fit: missing {sorted(set(missing) - fresh)}, "
                         f"unexpected {unexpected}")
    for prefix, code, latent in (("extrinsic.", "pose", "z_E"), ("intrinsic.", "body", "z_I")):
        if any(key.startswith(prefix) for key in fresh):
            log.info("%s's encoder reads the %s code as well: its first layers start afresh", latent, code)


@torch.no_grad()
def encode_bank(ae, sampler: PointSampler, spectra: np.ndarray, chosen: Recipe, device=None,
                pairing: Pairing | None = None) -> dict:
    """(q, x_c, lambda) for every training mesh under `bank_copies` random rotations; the
    rotation is the true one for a supervised AE with `bank_true_rotation`, else E_r's. A share
    `bank_partial_views` of the copies are camera-like views, with the whole mesh's spectrum.
    With a `pairing` (the paired regime) the bank also holds each mesh's target code (x_c of its
    whole surface in the canonical frame, the mean of `TARGET_SAMPLES` samples) and the pairing.
    Encoded on `device` (default: the AE's), kept on the CPU."""
    ae.eval()
    device = device or next(ae.parameters()).device
    partial = chosen.bank_view_share()
    if not 0.0 <= partial <= 1.0:
        raise ValueError(f"bank_partial_views {partial}: must be within 0..1")
    qs, codes, taught = [], [], {"x_p": [], "x_b": []}
    for meshes in torch.arange(len(sampler)).split(BANK_CHUNK):
        clouds = sampler.views(meshes.repeat_interleave(chosen.bank_copies), 1, partial).to(device)
        rotations = random_rotation_matrices(len(clouds), full=chosen.ae.full_rotations, device=device)
        inputs = rotate(clouds, rotations)
        true_rotation = chosen.bank_true_rotation and ae.config.supervised
        if true_rotation:
            q, used = matrix_to_quaternion(rotations), rotations
        else:
            q = ae.encode_rotation(inputs)
            used = quaternion_to_matrix(q)
        x_c, _ = ae.encode_shape(inputs, used)
        if ae.pose_encoder is not None or ae.body_encoder is not None:
            # turned back by E_r's estimate, as the bundle's encoder does
            estimated = quaternion_to_matrix(ae.encode_rotation(inputs)) if true_rotation else used
            for key, value in ae.taught_codes(inputs, estimated).items():
                if value is not None:
                    taught[key].append(value.cpu())
        qs.append(q.cpu())
        codes.append(x_c.cpu())
    spectrum = torch.from_numpy(np.repeat(spectra, chosen.bank_copies, 0)).float()
    log.info("bank: %d training meshes x %d rotations encoded (%.0f%% partial views)", len(sampler),
             chosen.bank_copies, 100 * partial)
    bank = {"q": torch.cat(qs), "x_c": torch.cat(codes), "spectrum": spectrum, "copies": chosen.bank_copies}
    bank.update({key: torch.cat(values) for key, values in taught.items() if values})
    if pairing is not None:
        targets = []
        for meshes in torch.arange(len(sampler)).split(BANK_CHUNK):
            clouds = sampler.clouds(meshes.repeat_interleave(TARGET_SAMPLES)).to(device)
            x_c, _ = ae.encode_shape(clouds, torch.eye(3, device=device).expand(len(clouds), 3, 3))
            targets.append(x_c.view(len(meshes), TARGET_SAMPLES, -1).mean(1).cpu())
        bank["target"] = torch.cat(targets)
        bank["pairing"] = pairing
        log.info("bank: target codes of %d meshes for the paired terms", len(sampler))
    return bank


BANK_CHUNK = 64  # meshes encoded together (their copies in one batch)
TARGET_SAMPLES = 4  # whole-surface samples averaged into a mesh's target code (paired regime)


def paired_inputs(batches: PairedBatches, bank: dict, batch_size: int, device) -> tuple[torch.Tensor, dict]:
    """A paired batch's bank entries and what `vae_loss` needs for the paired terms."""
    drawn = batches.draw(batch_size)
    meshes = drawn.entries // batches.copies
    pairing = batches.pairing
    extra = {
        "targets": bank["target"][torch.from_numpy(drawn.swap_meshes).to(device)],
        "own_targets": bank["target"][torch.from_numpy(meshes).to(device)],
        "subject": torch.from_numpy(pairing.subject[meshes]).to(device),
        "pose": torch.from_numpy(pairing.pose[meshes]).to(device),
        "family": torch.from_numpy(pairing.family[meshes]).to(device),
    }
    return torch.from_numpy(drawn.entries).to(device), extra


def bank_batch(size: int, batch: int, copies: int, paired: bool, generator: torch.Generator) -> torch.Tensor:
    """Indices of a VAE batch drawn from the code bank (mesh by mesh, `copies` entries each). With
    `paired`, the second half is another copy (view) of the first half's meshes, row by row, for
    the view-consistency term; a mesh's copy may be drawn twice."""
    if not paired:
        return torch.randint(0, size, (min(batch, size),), generator=generator)
    first = torch.randint(0, size, (max(1, min(batch, size) // 2),), generator=generator)
    partner = first // copies * copies + torch.randint(0, copies, first.shape, generator=generator)
    return torch.cat([first, partner])


def train_vae(vae, bank, chosen: Recipe, state, save, run_dir, meshes: int, device=None, budget_seconds=None,
              stages=None, taught: dict | None = None, node_identity: NodeIdentityData | None = None) -> None:
    """The VAE stage on the code bank. `taught` ({"body": pose.BodyTargets, "pose": PoseTargets(whitened=False)} of
    the bank's meshes, in its order): what `vae.omega_body` teaches mu_I and `omega_pose` mu_E.
    `node_identity`: the node's frames, on which `vae.omega_node_identity` adds an identity contrast
    to every step (a batch of the VAE's batch size beside the bank's)."""
    optimizer = torch.optim.Adam(vae.trained_parameters(), lr=chosen.vae_learning_rate, weight_decay=chosen.vae_weight_decay,
                                 fused=fused_adam(device))
    schedule = Plateau(optimizer, chosen.vae_min_learning_rate)
    if "optimizer" in state:
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
    generator = torch.Generator().manual_seed(chosen.seed + 1 + state["iteration"])
    total = chosen.vae_iterations
    start = state["iteration"]
    progress = Progress("vae", total, run_dir / "log.jsonl", first_iteration=start)
    last_save = started = time.monotonic()
    device = device or torch.device("cpu")
    size = len(bank["q"])
    copies = bank.get("copies", chosen.bank_copies)  # banks saved before it was recorded
    if (vae.config.omega_view > 0 or vae.config.paired) and size % copies:
        raise ValueError(f"the code bank has {size} entries, not a multiple of its {copies} copies per mesh")
    keys = ("q", "x_c", "spectrum", "target") if vae.config.paired else ("q", "x_c", "spectrum")
    for key, width, name in (("x_p", vae.config.pose_input, "z_E reads the pose code"),
                             ("x_b", vae.config.body_input, "z_I reads the body code")):
        if width and key not in bank:
            raise ValueError(f"this VAE's {name}, but the code bank has none: rebuild it (--rebuild-bank)")
        if width:
            keys += (key,)
    on_device = {key: bank[key].to(device) for key in keys}
    triples = (PairedBatches(bank["pairing"], copies, chosen.seed + 1 + state["iteration"],
                             pose_pairs=vae.config.omega_pose_contrast > 0) if vae.config.paired else None)
    taught_on_device = {}
    for name, targets in (taught or {}).items():
        if len(targets.rows) * copies != size:
            raise ValueError(f"the {name} targets hold {len(targets.rows)} meshes, the code bank {size // copies}")
        taught_on_device[name] = {"rows": targets.rows.to(device), "mask": targets.mask.to(device),
                                  "family": torch.from_numpy(targets.family).to(device)}
    node_batches = None  # (train() has checked that the states and omega_node_identity go together)
    if node_identity is not None:
        node_batches = NodeIdentityBatches(node_identity.to(device), chosen.vae_batch, chosen.seed + 2 + state["iteration"])
    vae.train()
    iteration, budget_ended = start, False
    for iteration in range(start, total):
        if budget_spent("vae", budget_seconds, started, iteration, total):
            budget_ended = True
            break
        if triples is not None:
            batch, paired = paired_inputs(triples, on_device, chosen.vae_batch, device)
        else:
            batch, paired = bank_batch(size, chosen.vae_batch, copies, vae.config.omega_view > 0, generator).to(device), None
        warmup = vae.config.beta_warmup_iterations
        beta_scale = min(1.0, iteration / warmup) if warmup > 0 else 1.0
        meshes_of = batch // copies
        rows = {name: {key: value[meshes_of] for key, value in targets.items()}
                for name, targets in taught_on_device.items()}
        losses = vae_loss(vae, on_device["q"][batch], on_device["x_c"][batch], on_device["spectrum"][batch],
                          dataset_size=size, beta_scale=beta_scale, paired=paired,
                          x_p=on_device["x_p"][batch] if "x_p" in on_device else None,
                          x_b=on_device["x_b"][batch] if "x_b" in on_device else None, taught=rows)
        total_loss, parts = losses.total, losses.parts
        if node_batches is not None:
            node_x_c, node_subject, node_family = next(node_batches)
            node_term = identity_contrast(vae.intrinsic(node_x_c)[0], node_subject, node_family,
                                          vae.config.contrast_temperature)
            total_loss = total_loss + vae.config.omega_node_identity * node_term
            parts = LossParts({**parts.terms, "total": total_loss, "node_identity": node_term})
        optimizer.zero_grad(set_to_none=True)
        total_loss.backward()
        torch.nn.utils.clip_grad_norm_(vae.trained_parameters(), 100.0)
        optimizer.step()
        schedule.step(parts.tensor("total"))
        progress.update(iteration + 1, lambda: {**parts, "lr": optimizer.param_groups[0]["lr"]},
                        force=iteration + 1 == total)
        if time.monotonic() - last_save > chosen.checkpoint_seconds and iteration + 1 < total:
            save({"stage": "vae", "iteration": iteration + 1, "vae": vae.state_dict(),
                  "optimizer": optimizer.state_dict(), "schedule": schedule.state_dict()})
            last_save = time.monotonic()
    else:
        iteration = total
    if stages is not None:
        stages.finish("vae", iteration, total, time.monotonic() - started, budget_ended)
    vae.eval()
