"""A shipped bundle back into a training run folder.

Training runs live outside the repository and machines are not kept, so the PyTorch weights of a
shipped model can be gone while its bundle is still in git. The ONNX files hold every weight the
model's inference uses, under the PyTorch names (the exporter keeps them), except the PointNets'
batch norms, which the exporter folds into the 1x1 convolutions before them. This module reads the
initializers back into an `Autoencoder` and a `LatentVAE`: a folded convolution keeps its folded
weights and its batch norm becomes the identity (weight 1, bias 0, mean 0, variance 1 - eps), which
computes the same function in eval mode. The result is checked against the bundle itself with the
export's parity check before anything is written.

Training on from there (`--continue-ae`) needs batch norms that normalise again: in training mode a
batch norm divides by its batch's statistics, so an identity one would change the function at the
first step. `ae.restore_batch_norms` sets each to the statistics of its input over sample clouds
(weight = std, bias = running mean = mean, running variance = std^2 - eps): still exactly the
identity in eval mode, and about the identity on a training batch.

What cannot come back: the optimizer state, and GDVAE++'s training-only posterior variance of the
spectral code (Sigma~_I(lambda), not in any ONNX graph; freshly initialised). Use the run with
`train --init-from RUN --rebuild-bank` (a new code bank and VAE on the imported autoencoder) or
`--continue-ae N`, and `evaluate RUN` / `export RUN` as with any run.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from .ae import Autoencoder
from .train import recipe
from .vae import LatentVAE

log = logging.getLogger(__name__)

BATCH_NORM_EPS = 1e-5  # torch.nn.BatchNorm1d's default, which the PointNets use


class BundleImportError(ValueError):
    """A bundle whose graphs do not fit the architecture its manifest names."""


def onnx_initializers(path: Path) -> tuple[dict[str, np.ndarray], list]:
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    return {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}, list(model.graph.node)


def folded_convolutions(values: dict[str, np.ndarray], nodes: list) -> list[tuple[np.ndarray, np.ndarray]]:
    """(weight, bias) of each Conv node of a graph, in graph order (the PointNets' layers)."""
    convolutions = []
    for node in nodes:
        if node.op_type == "Conv":
            weight = values[node.input[1]]
            bias = values[node.input[2]] if len(node.input) > 2 else np.zeros(weight.shape[0], np.float32)
            convolutions.append((weight, bias))
    return convolutions


def state_from_bundle(bundle: Path, ae: Autoencoder, vae: LatentVAE) -> tuple[dict, dict, list[str]]:
    """The AE's and the VAE's state dicts read from the bundle's graphs, and the VAE names no graph
    holds (left at their initial values)."""
    encoder_values, encoder_nodes = onnx_initializers(bundle / "encoder.onnx")
    named: dict[str, np.ndarray] = dict(encoder_values)
    for name in ("decoder.onnx", "flow.onnx"):
        named.update(onnx_initializers(bundle / name)[0])
    convolutions = iter(folded_convolutions(encoder_values, encoder_nodes))
    ae_state = {}
    # The order the encoder graph runs them in: encode_rotation, encode_shape, then the taught codes
    # (encode_pose, encode_body).
    taught = [name for name in ("pose_encoder", "body_encoder") if getattr(ae, name) is not None]
    for encoder in ("rotation_encoder", "shape_encoder", *taught):
        module = getattr(ae, encoder)
        for index, layer in enumerate(module.shared):
            prefix = f"{encoder}.shared.{index}"
            if isinstance(layer, torch.nn.Conv1d):
                try:
                    weight, bias = next(convolutions)
                except StopIteration:
                    raise BundleImportError(f"{bundle}/encoder.onnx has fewer convolutions than the architecture") from None
                ae_state[f"{prefix}.weight"], ae_state[f"{prefix}.bias"] = weight, bias
            elif isinstance(layer, torch.nn.BatchNorm1d):
                width = layer.num_features
                ae_state.update({f"{prefix}.weight": np.ones(width), f"{prefix}.bias": np.zeros(width),
                                 f"{prefix}.running_mean": np.zeros(width),
                                 f"{prefix}.running_var": np.full(width, 1.0 - BATCH_NORM_EPS),
                                 f"{prefix}.num_batches_tracked": np.array(0)})
    if next(convolutions, None) is not None:
        raise BundleImportError(f"{bundle}/encoder.onnx has more convolutions than the architecture")
    missing = []
    for key in ae.state_dict():
        if key not in ae_state:
            if f"ae.{key}" not in named:
                missing.append(f"ae.{key}")
                continue
            ae_state[key] = named[f"ae.{key}"]
    if missing:
        raise BundleImportError(f"{bundle}: no initializer for {', '.join(missing[:5])}"
                           f"{' ...' if len(missing) > 5 else ''}")
    vae_state, absent = {}, []
    for key, value in vae.state_dict().items():
        if f"vae.{key}" in named:
            vae_state[key] = named[f"vae.{key}"]
        elif key.endswith(".initialized"):  # an ActNorm that the bundle's training initialised
            vae_state[key] = np.array(True)
        elif key.endswith(".inverse_order") and f"vae.{key[:-len('inverse_order')]}order" in named:
            vae_state[key] = np.argsort(named[f"vae.{key[:-len('inverse_order')]}order"])
        else:
            vae_state[key] = value.numpy()
            absent.append(key)
    for reference, state, part in ((ae.state_dict(), ae_state, "ae"), (vae.state_dict(), vae_state, "vae")):
        for key, value in reference.items():
            if tuple(np.shape(state[key])) != tuple(value.shape):
                raise BundleImportError(f"{bundle}: {part}.{key} is {tuple(np.shape(state[key]))} in the bundle, "
                                   f"{tuple(value.shape)} in the architecture")
    as_tensors = lambda state, reference: {k: torch.as_tensor(np.array(v)).to(reference[k].dtype)
                                           for k, v in state.items()}
    return as_tensors(ae_state, ae.state_dict()), as_tensors(vae_state, vae.state_dict()), absent


def architecture(manifest: dict, rotation_head: str):
    """The recipe a manifest names, with its sizes."""
    model, sizes, training = manifest["model"], manifest["sizes"], manifest.get("training", {})
    chosen = recipe(model["recipe"], regime=model["regime"], kind=model["ae_type"])
    chosen.ae = replace(chosen.ae, points=sizes["points"], latent=sizes["x_c"], rotation_head=rotation_head,
                        supervised=model.get("supervision", "supervised") == "supervised",
                        full_rotations=manifest["units"].get("rotation_mode") == "so3",
                        pose_encoder=bool(model.get("pose_encoder", False)),
                        pose_hidden=tuple(model["pose_hidden"]) if model.get("pose_hidden") else None,
                        body_encoder=bool(model.get("body_encoder", False)),
                        **({"body_hidden": tuple(model["body_hidden"])} if model.get("body_hidden") else {}))
    chosen.vae = replace(chosen.vae, latent=sizes["x_c"], spectrum=sizes["spectrum"], n_extrinsic=sizes["z_E"],
                         n_rotation=sizes["z_R"], pose_input=sizes["x_c"] if chosen.ae.pose_encoder else 0,
                         body_input=sizes["x_c"] if chosen.ae.body_encoder else 0)
    chosen.spectrum_count = sizes["spectrum"]
    chosen.model_units = manifest["units"]["model_units_per_metre"]  # what its AE was trained in
    for field, key in (("ae_iterations", "ae_iterations"), ("vae_iterations", "vae_iterations"),
                       ("ae_batch", "ae_batch"), ("vae_batch", "vae_batch"), ("partial_views", "partial_views"),
                       ("bank_partial_views", "bank_partial_views"), ("depth_camera_views", "depth_camera_views")):
        if training.get(key) is not None:
            setattr(chosen, field, training[key])
    return chosen


def import_bundle(bundle: str | Path, out: str | Path) -> dict:
    """Writes `out/recipe.json` and `out/checkpoint.pt` (stage "bank": the AE trained, with the
    bundle's VAE beside it) from `bundle`; returns a summary."""
    from .export import parity

    bundle, out = Path(bundle), Path(out)
    manifest_path = bundle / "manifest.json"
    if not manifest_path.exists():
        raise BundleImportError(f"{bundle}: no manifest.json (not a bundle folder)")
    manifest = json.loads(manifest_path.read_text())
    head = named_rotation_head(bundle)
    chosen = architecture(manifest, head)
    ae, vae = Autoencoder(chosen.ae), LatentVAE(chosen.vae)
    ae_state, vae_state, absent = state_from_bundle(bundle, ae, vae)
    ae.load_state_dict(ae_state)
    vae.load_state_dict(vae_state)
    ae.eval()
    vae.eval()
    worst = parity(ae, vae, bundle)  # the check export makes, against the bundle's own graphs
    if worst > 1e-4:
        raise BundleImportError(f"{bundle}: the imported model differs from the bundle's graphs by {worst:.3g} (> 1e-4)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.json").write_text(json.dumps(asdict(chosen), indent=2, default=str))
    torch.save({"stage": "bank", "iteration": 0, "ae": ae.state_dict(), "imported_vae": vae.state_dict(),
                "imported_from": str(bundle)}, out / "checkpoint.pt")
    summary = {"bundle": str(bundle), "run": str(out), "ae": chosen.ae.kind, "rotation_head": head,
               "regime": chosen.vae.regime, "parity_max_diff": worst, "vae_not_in_bundle": absent,
               # what the bundle's taught encoders were taught on, for a run that reuses them (train.py)
               **{key: value for key, value in manifest.get("training", {}).items()
                  if key in ("pose_stage", "body_stage")}}
    (out / "imported.json").write_text(json.dumps(summary, indent=2))
    return summary


def named_rotation_head(bundle: Path) -> str:
    """E_r's head regresses 2 numbers for the yaw head, 4 for a quaternion."""
    values, _ = onnx_initializers(bundle / "encoder.onnx")
    weight = values.get("ae.rotation_encoder.head.weight")
    if weight is None:
        raise BundleImportError(f"{bundle}/encoder.onnx: no ae.rotation_encoder.head.weight (not a kit bundle?)")
    heads = {2: "yaw", 4: "quaternion"}
    if weight.shape[0] not in heads:
        raise BundleImportError(f"{bundle}: E_r's head has shape {tuple(weight.shape)}: neither yaw (2) nor quaternion (4)")
    return heads[weight.shape[0]]
