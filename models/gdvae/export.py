"""Bundles: the contract between the kit and the node (documented in models/README.md).

A bundle is one folder:
- `encoder.onnx`: points [B, N, 3] (model units, centred) -> q [B, 4], x_c [B, n], and the posterior
  mean and log-variance of z_R, z_E, z_I; dynamic batch and point count.
- `decoder.onnx`: z_E [B, n_E], z_I [B, n_I], z_R [B, n_R] -> canonical points [B, N_p, 3],
  rotated points [B, N_p, 3] (canonical rotated by R(D_q(z_R))), and that quaternion q [B, 4].
- `flow.onnx`: spectrum lambda [B, N_lambda] -> z~_I = f_lambda(lambda) [B, n_I] and log P_lambda [B].
- `manifest.json`: schema version, sizes, units, conventions, training settings, file hashes,
  measured metrics. `MODEL_CARD.md`: the same for people.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .geometry import quaternion_to_matrix, rotate

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
OPSET = 17


class EncoderGraph(nn.Module):
    def __init__(self, ae, vae):
        super().__init__()
        self.ae, self.vae = ae, vae

    def forward(self, points):
        q = self.ae.encode_rotation(points)
        rotation = quaternion_to_matrix(q)
        x_c, _ = self.ae.encode_shape(points, rotation)
        (mu_r, lv_r), (mu_e, lv_e), (mu_i, lv_i) = self.vae.encode(q, x_c, **self.ae.taught_codes(points, rotation))
        return q, x_c, mu_r, lv_r, mu_e, lv_e, mu_i, lv_i


class DecoderGraph(nn.Module):
    def __init__(self, ae, vae):
        super().__init__()
        self.ae, self.vae = ae, vae

    def forward(self, z_e, z_i, z_r):
        q, x_c = self.vae.decode(z_r, z_e, z_i)
        canonical = self.ae.decode(x_c)
        return canonical, rotate(canonical, quaternion_to_matrix(q)), q


class FlowGraph(nn.Module):
    def __init__(self, vae):
        super().__init__()
        self.vae = vae

    def forward(self, spectrum):
        return self.vae.flow(spectrum)[0], self.vae.flow.log_prob(spectrum)


ENCODER_OUTPUTS = ["q", "x_c", "z_R_mean", "z_R_logvar", "z_E_mean", "z_E_logvar", "z_I_mean", "z_I_logvar"]
DECODER_OUTPUTS = ["canonical_points", "rotated_points", "q"]
FLOW_OUTPUTS = ["z_I", "log_p_lambda"]


def example_inputs(ae, vae, batch: int = 2):
    c = vae.config
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(batch, ae.config.points, 3, generator=generator) - 0.5
    latents = tuple(torch.randn(batch, size, generator=generator) for size in (c.n_extrinsic, c.n_intrinsic, c.n_rotation))
    # Spectra from the training distribution the flow's first layer was fitted to (its log-eigenvalue
    # mean and spread), sorted as eigenvalues are: far outside it the flow extrapolates to huge
    # values whose float32 rounding says nothing about the export.
    logs = vae.flow.input.mean + vae.flow.input.std * torch.randn(batch, c.spectrum, generator=generator)
    spectrum = torch.exp(logs).sort(dim=-1).values
    return points, latents, spectrum


def export_onnx(ae, vae, folder: Path) -> None:
    ae.eval()
    vae.eval()
    points, latents, spectrum = example_inputs(ae, vae)
    batch = {0: "batch"}
    # Wrappers are put in eval mode themselves: the exporter restores each module's mode after
    # tracing, and a wrapper left in training mode would switch the batch norms back to training.
    torch.onnx.export(EncoderGraph(ae, vae).eval(), (points,), folder / "encoder.onnx", dynamo=False, opset_version=OPSET,
                      input_names=["points"], output_names=ENCODER_OUTPUTS,
                      dynamic_axes={"points": {0: "batch", 1: "points"}, **{n: batch for n in ENCODER_OUTPUTS}})
    torch.onnx.export(DecoderGraph(ae, vae).eval(), latents, folder / "decoder.onnx", dynamo=False, opset_version=OPSET,
                      input_names=["z_E", "z_I", "z_R"], output_names=DECODER_OUTPUTS,
                      dynamic_axes={n: batch for n in ["z_E", "z_I", "z_R", *DECODER_OUTPUTS]})
    torch.onnx.export(FlowGraph(vae).eval(), (spectrum,), folder / "flow.onnx", dynamo=False, opset_version=OPSET,
                      input_names=["spectrum"], output_names=FLOW_OUTPUTS,
                      dynamic_axes={n: batch for n in ["spectrum", *FLOW_OUTPUTS]})


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def parity(ae, vae, folder: Path) -> float:
    """Largest difference between ONNX Runtime and PyTorch over every output: absolute, or
    relative where the value's magnitude exceeds 1.

    Outputs computed from other outputs of the same graph are compared with PyTorch run on the
    graph's own values of those (the encoder's z from its q and x_c; the decoder's rotated points
    from its canonical points and q), so each stage is checked on its own arithmetic. Otherwise a
    rounding difference of another machine's CPU upstream, amplified by a steep stage downstream,
    reads as a mismatch: the H200 bundle's q differed by 5e-7 here, its z_R_mean by 1.4e-4 (the
    VAE's rotation encoder multiplies q's differences about 300-fold). A wrong weight in any stage
    still shows in that stage's outputs."""
    import onnxruntime as ort

    points, latents, spectrum = example_inputs(ae, vae, batch=3)
    feeds = {
        "encoder.onnx": {"points": points.numpy()},
        "decoder.onnx": {"z_E": latents[0].numpy(), "z_I": latents[1].numpy(), "z_R": latents[2].numpy()},
        "flow.onnx": {"spectrum": spectrum.numpy()},
    }
    got = {name: ort.InferenceSession(str(folder / name), providers=["CPUExecutionProvider"]).run(None, feed)
           for name, feed in feeds.items()}
    with torch.no_grad():
        q, x_c = (torch.from_numpy(value) for value in got["encoder.onnx"][:2])
        canonical, decoded_q = torch.from_numpy(got["decoder.onnx"][0]), torch.from_numpy(got["decoder.onnx"][2])
        expected = {
            "encoder.onnx": [*EncoderGraph(ae, vae).eval()(points)[:2],
                             *(value for pair in vae.encode(q, x_c, **ae.taught_codes(points, quaternion_to_matrix(q)))
                               for value in pair)],
            "decoder.onnx": [DecoderGraph(ae, vae).eval()(*latents)[0],
                             rotate(canonical, quaternion_to_matrix(decoded_q)),
                             DecoderGraph(ae, vae).eval()(*latents)[2]],
            "flow.onnx": list(FlowGraph(vae).eval()(spectrum)),
        }
    worst = 0.0
    for name, outputs in expected.items():
        for value, reference in zip(got[name], outputs, strict=True):
            # Absolute difference, relative for magnitudes above 1 (log P_lambda is ~ -100).
            scale = np.maximum(1.0, np.abs(reference.numpy()))
            worst = max(worst, float((np.abs(value - reference.numpy()) / scale).max()))
    return worst


def calibration_kept_from(ae, vae, bundle: Path) -> dict:
    """The z_I variance calibration of `bundle`, for a model that kept its z_I encoder
    (`vae.keep_intrinsic`): checked by running both encoders on the same clouds, since a z_I that
    differs in any way needs its own calibration (`--calibrate`)."""
    import onnxruntime as ort

    manifest = json.loads((bundle / "manifest.json").read_text())
    calibration = manifest.get("calibration")
    if not calibration:
        raise ValueError(f"{bundle}: its manifest has no calibration to take")
    points = example_inputs(ae, vae, batch=4)[0]
    session = ort.InferenceSession(str(bundle / "encoder.onnx"), providers=["CPUExecutionProvider"])
    theirs = dict(zip((o.name for o in session.get_outputs()), session.run(None, {"points": points.numpy()})))
    with torch.no_grad():
        ours = dict(zip(ENCODER_OUTPUTS, EncoderGraph(ae, vae).eval()(points)))
    for name in (n for n in ENCODER_OUTPUTS if n.startswith("z_I")):
        gap = float(np.abs(theirs[name] - ours[name].numpy()).max())
        if gap > 1e-4:
            raise ValueError(f"{bundle}: its {name} differs from this model's by {gap:.3g}: the calibration "
                             "belongs to another z_I encoder (measure this one's with --calibrate)")
    return {**calibration, "measured_on": f"{calibration['measured_on']} (taken from {bundle}, whose z_I "
                                          "encoder this model keeps)"}


def write_bundle(ae, vae, folder: str | Path, *, scale: float, recipe_name: str, training: dict,
                 metrics: dict | None, calibration: dict | None = None) -> dict:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    export_onnx(ae, vae, folder)
    worst = parity(ae, vae, folder)
    if worst > 1e-4:
        raise RuntimeError(f"ONNX Runtime differs from PyTorch by {worst:.2e} (> 1e-4): export is broken")
    c, a = vae.config, ae.config
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "format": "gdvae-bundle",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "model": {
            "ae_type": a.kind,
            "supervision": "supervised" if a.supervised else "unsupervised",
            "regime": c.regime,
            "recipe": recipe_name,
            "pose_encoder": a.pose_encoder,
            **({"pose_hidden": list(a.pose_hidden)} if a.pose_encoder and a.pose_hidden else {}),
            "body_encoder": a.body_encoder,
            **({"body_hidden": list(a.body_hidden)} if a.body_encoder else {}),
        },
        "sizes": {"points": a.points, "spectrum": c.spectrum, "x_c": a.latent, "z_R": c.n_rotation,
                  "z_E": c.n_extrinsic, "z_I": c.n_intrinsic},
        "units": {
            "input_unit": "metre",
            "model_units_per_metre": scale,
            "centering": "bounding-box centre",
            "up_axis": "+z",
            "rotation_mode": "so3" if a.full_rotations else "yaw",
        },
        "conventions": {
            "quaternion": "w, x, y, z; R(q) carries the canonical shape onto the observed one",
            "points": "rows; observed = canonical @ R(q)^T",
            "canonical_frame": "the training meshes' frame: x forward, y left, z up",
        },
        "files": {name: {"sha256": sha256(folder / name)} for name in ("encoder.onnx", "decoder.onnx", "flow.onnx")},
        "io": {
            "encoder.onnx": {"inputs": {"points": ["batch", "points", 3]}, "outputs": ENCODER_OUTPUTS},
            "decoder.onnx": {"inputs": {"z_E": ["batch", c.n_extrinsic], "z_I": ["batch", c.n_intrinsic],
                                        "z_R": ["batch", c.n_rotation]}, "outputs": DECODER_OUTPUTS},
            "flow.onnx": {"inputs": {"spectrum": ["batch", c.spectrum]}, "outputs": FLOW_OUTPUTS},
        },
        "onnx_parity_max_diff": worst,
        **({"calibration": calibration} if calibration else {}),
        "training": training,
        "metrics": metrics or {},
    }
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=2, allow_nan=False) + "\n")
    (folder / "MODEL_CARD.md").write_text(model_card(manifest))
    log.info("bundle written to %s (ONNX parity %.2e)", folder, worst)
    return manifest


def taught_pose(components) -> str:
    """What the pose stage taught E_p, in words (`recipe.pose_components`; 0: every joint angle)."""
    return "each of the sim's joint angles (in units of its spread)" if components == 0 else \
        f"the top {components} principal components of the sim's joint angles"


def model_card(manifest: dict) -> str:
    m, s, u, t = manifest["model"], manifest["sizes"], manifest["units"], manifest["training"]
    metrics = manifest["metrics"]
    partial = t.get("partial_views") or 0.0
    lines = [
        f"# GDVAE++ bundle: {m['regime']}, {m['ae_type'].upper()} autoencoder ({m['supervision']}), recipe `{m['recipe']}`",
        "",
        "Encodes a point cloud of one object into a rotation q, a pose code z_E and a shape code z_I",
        "(paper: \"Disentangling Geometric Deformation Spaces in Generative Latent Shape Models\").",
        "",
        "## Inputs",
        f"- {s['points']} points (any count works; trained with {s['points']}), metres times "
        f"{u['model_units_per_metre']:.6g}, centred on their bounding box, {u['up_axis']} up.",
        f"- Rotations seen in training: {'all of SO(3)' if u['rotation_mode'] == 'so3' else 'about the up axis only'}.",
        "",
        "## Sizes",
        f"x_c {s['x_c']}, z_R {s['z_R']}, z_E {s['z_E']}, z_I {s['z_I']}, spectrum {s['spectrum']} eigenvalues.",
        "",
        "## Training data",
        f"{t.get('dataset', '?')}: {t.get('train_meshes', '?')} training meshes of {t.get('train_subjects', '?')} "
        f"subjects; families {', '.join(t.get('families', [])) or '?'}.",
        f"AE iterations {t.get('ae_iterations', '?')}, VAE iterations {t.get('vae_iterations', '?')}.",
        *([f"z_E's encoder reads a pose encoder's code: E_p, which sees the cloud turned back by the estimated "
           f"rotation, was taught {taught_pose(t['pose_stage'].get('components', '?'))} "
           f"per family for {t['pose_stage'].get('iterations', '?')} iterations on "
           f"{t['pose_stage'].get('train_meshes', '?')} training meshes of {t['pose_stage'].get('dataset', '?')}."]
          if t.get("pose_stage") else []),
        *([f"z_I's encoder reads a body encoder's code: E_b, in the same frame, was taught the sim's body-shape "
           f"parameters (beta) per family for {t['body_stage'].get('iterations', '?')} iterations on "
           f"{t['body_stage'].get('train_meshes', '?')} training meshes of {t['body_stage'].get('dataset', '?')}."]
          if t.get("body_stage") else []),
        *([f"mu_E was taught the pose directly (vae.omega_pose {t['omega_pose']:g}): each training mesh's joint "
           "angles on its family's top principal axes, one coordinate per dimension of z_E."]
          if t.get("omega_pose") else []),
        *([f"mu_I was taught the body shape (vae.omega_body {t['omega_body']:g}) "
           + ("directly: its first units are each training mesh's body-shape parameters, normalised per family."
              if t.get("body_direct") else "through linear heads.")]
          if t.get("omega_body") else []),
        *([f"mu_I was also taught to tell subjects apart on the node's own clouds (vae.omega_node_identity "
           f"{t['omega_node_identity']:g}): an identity contrast on the x_c the node computed in "
           f"{t['node_identity'].get('frames', '?')} frames of sim recordings of "
           f"{sum(t['node_identity'].get('subjects', {}).values())} subjects "
           f"({', '.join(f'{n} {f}s' for f, n in t['node_identity'].get('subjects', {}).items())})."]
          if t.get("omega_node_identity") and t.get("node_identity") else []),
        f"Partial views: {partial:.0%} of the AE's input copies were the side a camera sees"
        f"{', as the depth camera renders it (self-occlusion, stereo noise)' if t.get('depth_camera_views') else ''} "
        "(the AE still reconstructs the whole surface)." if partial else "Partial views: none (whole surfaces only).",
        "",
        "## Measured on held-out subjects",
    ]
    if metrics:
        for key in ("S", "C_X", "d_C", "C_3D", "vae_d_C", "coverage", "fidelity", "log_p_lambda",
                    "heading_error_median_deg", "shape_from_spectrum_d_C"):
            if metrics.get(key) is not None:
                spread = f" (mean of {len(metrics['S_draws'])} draws, standard deviation {metrics['S_std']:.2g})" \
                    if key == "S" and metrics.get("S_std") is not None else ""
                lines.append(f"- {key}: {metrics[key]:.4g}{spread}")
        views = metrics.get("partial_views")
        if views:
            shown = {key: "n/a" if views.get(key) is None else f"{views[key]:.4g}"
                     for key in ("S", "C_X", "heading_error_median_deg")}
            lines.append(f"- from single camera-like views ({views['views_per_shape']} per mesh): "
                         f"S {shown['S']}, C_X {shown['C_X']}, heading error median {shown['heading_error_median_deg']} deg")
        lines.append(f"- command: `{metrics.get('command', 'python -m gdvae evaluate')}`")
    else:
        lines.append("- not evaluated")
    calibration = manifest.get("calibration")
    lines += ["", "## Calibration"]
    if calibration:
        lines.append(f"- z_I variances x {calibration['z_I_variance_scale']:.4g}: one subject's z_I spreads over its poses "
                     f"and views by this times the variance the encoder reports (median over dimensions; p10 "
                     f"{calibration['ratio_p10']:.3g}, p90 {calibration['ratio_p90']:.3g}); measured on "
                     f"{calibration['measured_on']}. The node's tracker applies it.")
        if "z_I_spread" in calibration:
            lines.append(f"- z_I spread {calibration['z_I_spread']:.4g}: how far one subject's z_I lies from its mean "
                         "over those poses and views (root mean square, median over subjects). The node measures "
                         "z_I distances between tracks in this unit (`[track.objects]` shape_scale, reid_distance).")
    else:
        lines.append("- none: the node takes the encoder's z_I variances as reported (`export --calibrate`).")
    projection = (calibration or {}).get("identity_projection")
    if projection:
        fitted = projection.get("fitted_on", {})
        subjects = sum(fitted.get("subjects", {}).values()) if isinstance(fitted.get("subjects"), dict) else "?"
        ratios = ", ".join(f"{v:.3g}" for v in fitted.get("between_within", []))
        lines.append(f"- Identity projection (`python -m gdvae fit-identity`): {len(projection['matrix'])} directions "
                     f"of x_c that tell subjects of one family apart on the node's own clouds, fitted on {subjects} "
                     f"sim subjects ({fitted.get('frames', '?')} frames; between/within-subject ratios {ratios}). "
                     "The node's tracker detects identity changes on it (models/README, \"Identity projection\").")
    lines += [
        "",
        "## Limits",
        "- Trained on synthetic surfaces (the sim's quadruped and biped families) only.",
        "- Single-view depth clouds are partial: codes from them are noisier than from whole surfaces"
        + (" (the single-view figures above say by how much)." if partial else ", and this bundle never saw one."),
        *(["- z_I was taught to tell subjects apart, not to stay near the unit prior: it is several times "
            "wider than the paper's, and the spectral flow's log-likelihood of it (log_p_lambda) and the shape "
            "decoded from the spectrum alone (shape_from_spectrum_d_C) are worse than a prior-bound z_I's."]
          if t.get("omega_node_identity") else []),
        "- Not for safety-critical decisions.",
        "",
    ]
    return "\n".join(lines)
