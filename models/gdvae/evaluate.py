"""Evaluation of a trained run on held-out subjects: every metric of `metrics`, one JSON."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from .data import DepthCamera, MeshDataset
from .geometry import chamfer, quaternion_to_matrix, random_rotation_matrices, rotate
from .metrics import (clustering_consistency, coverage_and_fidelity, disentanglement, heading_errors,
                      variance_calibration)
from .surface import PointSampler

log = logging.getLogger(__name__)

RETRIEVAL_DRAWS = 5  # independent point samples and rotations of the test set for retrieval and S


@torch.no_grad()
def encode_all(ae, vae, clouds: torch.Tensor, rotations: torch.Tensor, spectra: torch.Tensor | None, batch: int = 64):
    """AE and VAE codes of rotated clouds: q, x_c, posterior means of z_R, z_E, z_I, and z~_I."""
    out = {k: [] for k in ("q", "x_c", "mu_R", "mu_E", "mu_I", "lv_R", "lv_E", "lv_I")}
    for start in range(0, len(clouds), batch):
        inputs = rotate(clouds[start : start + batch], rotations[start : start + batch])
        q = ae.encode_rotation(inputs)
        rotation = quaternion_to_matrix(q)
        x_c, _ = ae.encode_shape(inputs, rotation)
        (mu_r, lv_r), (mu_e, lv_e), (mu_i, lv_i) = vae.encode(q, x_c, **ae.taught_codes(inputs, rotation))
        for key, value in zip(out, (q, x_c, mu_r, mu_e, mu_i, lv_r, lv_e, lv_i)):
            out[key].append(value)
    codes = {k: torch.cat(v) for k, v in out.items()}
    if spectra is not None:
        codes["mu_I_spectral"] = vae.flow(spectra)[0]
    return codes


def shape_code(ae, inputs: torch.Tensor) -> torch.Tensor:
    """x_c of clouds in any rotation, canonicalized by the AE's own rotation estimate."""
    return ae.encode_shape(inputs, quaternion_to_matrix(ae.encode_rotation(inputs)))[0]


def made_by_sim(dataset: MeshDataset) -> bool:
    """Pose-transfer ground truth comes from the sim, so only its datasets qualify."""
    import json

    description = dataset.root / "dataset.json"
    try:
        return json.loads(description.read_text()).get("format") == "gdvae-sim-dataset"
    except (OSError, ValueError):
        return False


@torch.no_grad()
def pose_transfer(ae, vae, dataset: MeshDataset, indices: list[int], codes: dict, sim_binary: str,
                  rng: np.random.Generator, pairs_per_family: int = 20) -> dict:
    """Pose transfer against ground truth: decode (z_E of shape A, z_I of shape B) and compare with
    the sim's mesh of subject B in A's pose (`sim pose`). Baselines: A's and B's own
    reconstructions against the same target (right pose wrong shape, right shape wrong pose)."""
    import json
    import subprocess
    import tempfile
    from pathlib import Path

    from .data import normalize, read_mesh, sample_surface

    rows_by_family: dict[str, list[int]] = {}
    for row, index in enumerate(indices):
        truth = dataset.items[index].truth
        if truth and "beta" in truth and "theta" in truth:
            rows_by_family.setdefault(truth["family"], []).append(row)
    pairs, requests = [], []
    for family, rows in rows_by_family.items():
        for _ in range(pairs_per_family):
            a, b = rng.choice(rows, size=2, replace=False)
            ta, tb = dataset.items[indices[a]].truth, dataset.items[indices[b]].truth
            if ta["subject"] == tb["subject"]:
                continue
            name = f"transfer-{len(pairs):04d}"
            pairs.append((family, int(a), int(b), name))
            requests.append({"name": name, "family": family, "beta": tb["beta"], "theta": ta["theta"]})
    if not pairs:
        return {}
    with tempfile.TemporaryDirectory() as folder:
        request_file = Path(folder) / "requests.jsonl"
        request_file.write_text("\n".join(json.dumps(r) for r in requests) + "\n")
        subprocess.run([sim_binary, "pose", "--requests", str(request_file), "--out", folder],
                       check=True, capture_output=True, timeout=600)
        targets = torch.from_numpy(np.stack([
            sample_surface(normalize(read_mesh(Path(folder) / f"{name}.ply"), dataset.scale), ae.config.points, rng)
            for *_, name in pairs]))
    a_rows = torch.tensor([a for _, a, _, _ in pairs])
    b_rows = torch.tensor([b for _, _, b, _ in pairs])
    rotation = codes["mu_R"][a_rows]

    def decode(e_rows, i_rows):
        _, x_c = vae.decode(rotation, codes["mu_E"][e_rows], codes["mu_I"][i_rows])
        return ae.decode(x_c)

    return {
        "pairs": len(pairs),
        "transfer_d_C": float(chamfer(decode(a_rows, b_rows), targets).mean()),
        "baseline_pose_source_d_C": float(chamfer(decode(a_rows, a_rows), targets).mean()),
        "baseline_shape_source_d_C": float(chamfer(decode(b_rows, b_rows), targets).mean()),
    }


def nearest_match_share(codes: np.ndarray, query_groups: np.ndarray, candidate: np.ndarray,
                        answer: np.ndarray) -> float | None:
    """For each row, its nearest other row (Euclidean) among those `candidate[i, j]` allows; the
    share of rows whose nearest has the same `answer` label. None when no row has a candidate."""
    distance = ((codes[:, None, :] - codes[None, :, :]) ** 2).sum(-1)
    distance[~candidate] = np.inf
    rows = np.flatnonzero(np.isfinite(distance).any(1))
    if not len(rows):
        return None
    nearest = distance[rows].argmin(1)
    return float((answer[rows] == answer[nearest]).mean())


@torch.no_grad()
def paired_retrieval(ae, vae, dataset: MeshDataset, indices: list[int], seed: int = 0,
                     full_rotations: bool = False) -> dict:
    """On a held-out grid of subjects x shared poses (`sim dataset --shared-poses`), each mesh seen
    once as a whole surface and once by the depth camera (`DepthCamera`, what the node sees):
    - pose by z_E: the share of meshes whose nearest z_E among other subjects of the family is in
      the same pose (chance: 1 / poses), against the same with x_c;
    - subject by z_I: the share whose nearest z_I among other poses of the family is the same
      subject (chance: 1 / subjects), against the same with x_c.
    Empty when the split has no shared poses."""
    truths = [dataset.items[i].truth or {} for i in indices]
    if not all("pose_id" in t for t in truths):
        return {}
    family = np.array([t["family"] for t in truths])
    subject = np.array([t["subject"] for t in truths])
    pose = np.array([t["pose_id"] for t in truths])
    same_family = family[:, None] == family[None, :]
    other_subject = same_family & (subject[:, None] != subject[None, :])
    other_pose = same_family & (pose[:, None] != pose[None, :])
    chance = {"pose": float(np.mean([1 / len(set(pose[family == f])) for f in family])),
              "subject": float(np.mean([1 / len(set(subject[family == f])) for f in family]))}
    result: dict = {"meshes": len(indices), "chance": chance}
    views = {"whole": PointSampler(dataset, indices, ae.config.points, seed),
             "depth_camera": PointSampler(dataset, indices, ae.config.points, seed, DepthCamera())}
    for name, sampler in views.items():
        clouds = sampler.one_each() if name == "whole" else sampler.views(np.arange(len(indices)), 1, 1.0)
        torch.manual_seed(seed)
        codes = encode_all(ae, vae, clouds, random_rotation_matrices(len(clouds), full=full_rotations), None)
        e, i, x = codes["mu_E"].numpy(), codes["mu_I"].numpy(), codes["x_c"].numpy()
        result[name] = {
            "pose_by_z_E": nearest_match_share(e, family, other_subject, pose),
            "pose_by_x_c": nearest_match_share(x, family, other_subject, pose),
            "subject_by_z_I": nearest_match_share(i, family, other_pose, subject),
            "subject_by_x_c": nearest_match_share(x, family, other_pose, subject),
        }
    return result


def beta_ranges(root) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each family's beta range per parameter, from the dataset's `dataset.json` (the sim writes
    its families' BETA tables there); empty when the dataset has none."""
    path = Path(root) / "dataset.json"
    if not path.exists():
        return {}
    families = json.loads(path.read_text()).get("families", {})
    return {name: (np.array([p["min"] for p in f["beta"]], dtype=float), np.array([p["max"] for p in f["beta"]], dtype=float))
            for name, f in families.items() if f.get("beta")}


def normalised_beta(beta: np.ndarray, family: str, ranges: dict) -> np.ndarray:
    """beta mapped to [0, 1] per parameter by its family's range, so that E_beta weighs every
    parameter alike (a raw MSE is dominated by the parameters with the widest ranges in metres);
    by the observed range when the dataset gives none."""
    low, high = ranges.get(family, (beta.min(0), beta.max(0)))
    if low.shape != beta.shape[1:]:
        low, high = beta.min(0), beta.max(0)
    return (beta - low) / np.maximum(high - low, 1e-12)


def family_retrieval(dataset: MeshDataset, indices: list[int], codes: dict) -> dict:
    """Pose-aware retrieval scores and S per family (families with at least 5 shapes), with beta
    normalised per parameter by its family's range."""
    truths = [dataset.items[i].truth for i in indices]
    ranges = beta_ranges(dataset.root)
    retrieval = {}
    for family in sorted({t["family"] for t in truths if t}):
        rows = [k for k, t in enumerate(truths) if t and t["family"] == family]
        if len(rows) < 5:
            continue
        beta = normalised_beta(np.array([truths[k]["beta"] for k in rows], dtype=float), family, ranges)
        theta = np.array([truths[k]["theta"] for k in rows])
        pick = lambda key: codes[key][rows].numpy()  # noqa: E731
        family_codes = {
            "x_c": pick("x_c"),
            "z": np.concatenate([pick("mu_R"), pick("mu_E"), pick("mu_I")], 1),
            "z_E": pick("mu_E"),
            "z_I": pick("mu_I"),
        }
        if "mu_I_spectral" in codes:
            family_codes["z~_I"] = pick("mu_I_spectral")
        retrieval[family] = disentanglement(family_codes, beta, theta)
    return retrieval


def leafwise_mean(values: list):
    """The mean of structurally equal nested dicts of numbers, leaf by leaf."""
    if isinstance(values[0], dict):
        return {key: leafwise_mean([value[key] for value in values]) for key in values[0]}
    return float(np.mean(values))


def mean_s(retrieval: dict) -> float | None:
    return float(np.mean([r["S"] for r in retrieval.values()])) if retrieval else None


@torch.no_grad()
def evaluate(ae, vae, dataset: MeshDataset, spectra: np.ndarray | None, split: str = "test", seed: int = 0,
             full_rotations: bool = False, sim_binary: str | None = None, partial_views: int = 5,
             retrieval_only: bool = False) -> dict:
    """Every metric on one split. `vae` None: the AE's metrics only. `partial_views`: view
    directions per mesh for the camera-like partial-view metrics (0: skip them). `retrieval_only`:
    only retrieval, S, the posterior statistics and (with the sim) pose transfer: minutes, for
    comparing runs."""
    ae.eval()
    if vae is not None:
        vae.eval()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    indices = dataset.indices(split)
    if len(indices) < 4:
        raise ValueError(f"split {split!r} has {len(indices)} meshes; at least 4 are needed")
    points = ae.config.points
    sampler = PointSampler(dataset, indices, points, seed)
    clouds = sampler.one_each()
    metrics: dict = {"split": split, "shapes": len(indices), "points": points}
    if retrieval_only:
        if vae is None or not dataset.has_ground_truth:
            raise ValueError("retrieval needs the VAE and a dataset with ground truth")
        spectrum = torch.from_numpy(spectra[indices]).float()
        codes = encode_all(ae, vae, clouds, random_rotation_matrices(len(clouds), full=full_rotations), spectrum)
        metrics["posterior"] = posterior_statistics(codes)
        metrics.update(retrieval_metrics(ae, vae, dataset, indices, codes, spectrum, rng, full_rotations))
        if sim_binary and made_by_sim(dataset):
            metrics["pose_transfer"] = pose_transfer(ae, vae, dataset, indices, codes, sim_binary, rng)
        metrics["paired_retrieval"] = paired_retrieval(ae, vae, dataset, indices, seed, full_rotations)
        return metrics
    fresh = sampler.one_each()

    # AE: reconstruction, canonicalization, heading, over five rotated copies.
    chamfers, headings, canonicals = [], [], []
    for _ in range(5):
        rotations = random_rotation_matrices(len(clouds), full=full_rotations)
        output = ae(rotate(clouds, rotations))
        chamfers.append(chamfer(output.reconstruction, rotate(fresh, rotations)))
        headings.append(heading_errors(output.q, rotations))
        canonicals.append(output.canonical)
    metrics["d_C"] = float(torch.cat(chamfers).mean())
    metrics["C_3D"] = float(torch.stack([chamfer(canonicals[i], canonicals[j])
                                         for i in range(3) for j in range(3) if i != j]).mean())
    metrics["heading_error_median_deg"] = float(np.median(np.concatenate(headings)))

    metrics["C_X"] = clustering_consistency(lambda inputs, _: shape_code(ae, inputs), clouds, rng,
                                            full_rotations=full_rotations)

    if vae is not None:
        metrics.update(vae_metrics(ae, vae, dataset, indices, clouds, fresh, spectra, rng, full_rotations, sim_binary))
        metrics["paired_retrieval"] = paired_retrieval(ae, vae, dataset, indices, seed, full_rotations)
    if partial_views:
        metrics["partial_views"] = partial_view_metrics(ae, vae, dataset, indices, clouds, rng, seed, partial_views,
                                                        full_rotations)
    metrics["rotation_diagnostics"] = rotation_diagnostics(ae, dataset, indices, clouds, rng, full_rotations)
    return metrics


@torch.no_grad()
def rotation_diagnostics(ae, dataset: MeshDataset, indices: list[int], clouds: torch.Tensor,
                         rng: np.random.Generator, full_rotations: bool) -> dict:
    """Where C_X is lost: the heading error's spread per family, and C_X when the shape encoder is
    given the true rotation instead of E_r's estimate (the part of C_X an exact E_r would recover;
    what remains is the shape encoder's own lack of invariance)."""
    rotations = random_rotation_matrices(len(clouds), full=full_rotations)
    errors = heading_errors(ae.encode_rotation(rotate(clouds, rotations)), rotations)
    families = np.array([(dataset.items[i].truth or {}).get("family", "all") for i in indices])
    heading = {}
    for family in sorted(set(families)):
        chosen = errors[families == family]
        heading[family] = {"median_deg": float(np.median(chosen)), "p90_deg": float(np.percentile(chosen, 90)),
                           "over_90deg_fraction": float((chosen > 90).mean())}
    true_rotation = clustering_consistency(lambda inputs, applied: ae.encode_shape(inputs, applied)[0], clouds, rng,
                                           full_rotations=full_rotations)
    return {"heading": heading, "C_X_true_rotation": true_rotation}


@torch.no_grad()
def z_i_variance_calibration(ae, vae, dataset: MeshDataset, indices: list[int], seed: int = 0,
                             full_rotations: bool = False, depth_camera: bool = False) -> dict:
    """What the node's tracker needs of z_I's variances: how far one subject's z_I spreads over its
    poses, each seen from one camera-like view in a random rotation, against the variance the
    encoder reports (`variance_calibration`). Written into the bundle by `export --calibrate`.
    `depth_camera`: the views are the sim's depth camera's (self-occlusion and stereo noise, what
    the node sees) rather than the faces turned towards a camera; a run trained on such views is
    calibrated on them."""
    if not dataset.has_ground_truth:
        raise ValueError(f"{dataset.root}: no ground truth (subjects) to calibrate against")
    torch.manual_seed(seed)  # the rotations: the same bundle gets the same calibration
    sampler = PointSampler(dataset, indices, ae.config.points, seed, DepthCamera() if depth_camera else None)
    views = sampler.views(np.arange(len(indices)), 1, 1.0)
    codes = encode_all(ae, vae, views, random_rotation_matrices(len(views), full=full_rotations), None)
    subjects = [dataset.items[i].subject for i in indices]
    kind = "one depth-camera view each" if depth_camera else "one camera-like view each"
    return {**variance_calibration(codes["mu_I"].numpy(), codes["lv_I"].numpy(), subjects),
            "measured_on": f"{dataset.root}, {len(indices)} held-out meshes, {kind}"}


def partial_view_metrics(ae, vae, dataset: MeshDataset, indices: list[int], clouds: torch.Tensor,
                         rng: np.random.Generator, seed: int, count: int, full_rotations: bool) -> dict:
    """What the node sees: the side of each mesh facing a camera above the ground, `count` view
    directions per mesh. Heading error and C_X (the copies of a mesh are different views, not one
    cloud rotated), and with a VAE the retrieval scores and S (z~_I skipped: a view has no spectrum)."""
    sampler = PointSampler(dataset, indices, clouds.shape[1], seed + 1)
    views = sampler.views(np.arange(len(indices)), count, 1.0).reshape(count, *clouds.shape)
    rotations = random_rotation_matrices(len(clouds), full=full_rotations)
    q = ae.encode_rotation(rotate(views[0], rotations))

    metrics = {
        "views_per_shape": count,
        "heading_error_median_deg": float(np.median(heading_errors(q, rotations))),
        "C_X": clustering_consistency(lambda inputs, _: shape_code(ae, inputs), clouds, rng,
                                      full_rotations=full_rotations, views=views),
    }
    if vae is not None and dataset.has_ground_truth:
        codes = encode_all(ae, vae, views[0], rotations, None)
        metrics["retrieval"] = family_retrieval(dataset, indices, codes)
        if metrics["retrieval"]:
            metrics["S"] = mean_s(metrics["retrieval"])
    return metrics


def retrieval_metrics(ae, vae, dataset: MeshDataset, indices: list[int], codes: dict, spectrum: torch.Tensor,
                      rng: np.random.Generator, full_rotations: bool) -> dict:
    """Pose-aware retrieval and S per family. One draw of point samples and rotations moves S by
    about 0.2 on 240 shapes, so the scores are averaged over RETRIEVAL_DRAWS draws (`codes` is the
    first) and the per-draw S and their spread are reported."""
    draws = [family_retrieval(dataset, indices, codes)]
    for _ in range(RETRIEVAL_DRAWS - 1):
        sampler = PointSampler(dataset, indices, ae.config.points, int(rng.integers(1 << 31)))
        redrawn = sampler.one_each()
        redrawn_codes = encode_all(ae, vae, redrawn, random_rotation_matrices(len(redrawn), full=full_rotations),
                                   spectrum)
        draws.append(family_retrieval(dataset, indices, redrawn_codes))
    metrics: dict = {"retrieval": leafwise_mean(draws)}
    if metrics["retrieval"]:
        per_draw = [mean_s(draw) for draw in draws]
        metrics.update(S=mean_s(metrics["retrieval"]), S_draws=per_draw, S_std=float(np.std(per_draw)))
    return metrics


def posterior_statistics(codes: dict, active_threshold: float = 0.01) -> dict:
    """Per latent group, how much the encoder's posterior says about its input: the median
    posterior standard deviation, the median spread of the means across shapes, and the active
    units (dimensions whose means vary across shapes by more than `active_threshold` in variance,
    Burda et al. 2016). A group whose posterior deviation is the prior's (1) and whose means do
    not move has collapsed: the decoder cannot use it."""
    statistics = {}
    for group in ("R", "E", "I"):
        mean, log_variance = codes[f"mu_{group}"], codes[f"lv_{group}"]
        spread = mean.var(0)
        statistics[f"z_{group}"] = {
            "posterior_std_median": float(torch.exp(0.5 * log_variance).median()),
            "mean_std_across_shapes_median": float(spread.sqrt().median()),
            "active_units": int((spread > active_threshold).sum()),
            "dimensions": int(mean.shape[1]),
        }
    return statistics


@torch.no_grad()
def vae_metrics(ae, vae, dataset: MeshDataset, indices: list[int], clouds: torch.Tensor, fresh: torch.Tensor,
                spectra: np.ndarray, rng: np.random.Generator, full_rotations: bool, sim_binary: str | None) -> dict:
    """The VAE's metrics: reconstruction, log P_lambda, shape from spectrum, generation, retrieval
    and S, pose transfer."""
    metrics: dict = {}

    # VAE: codes of one rotated copy per shape.
    spectrum = torch.from_numpy(spectra[indices]).float()
    rotations = random_rotation_matrices(len(clouds), full=full_rotations)
    codes = encode_all(ae, vae, clouds, rotations, spectrum)
    q_hat, x_hat = vae.decode(codes["mu_R"], codes["mu_E"], codes["mu_I"])
    recon = rotate(ae.decode(x_hat), quaternion_to_matrix(q_hat))
    metrics["vae_d_C"] = float(chamfer(recon, rotate(fresh, rotations)).mean())
    metrics["log_p_lambda"] = float(vae.flow.log_prob(spectrum).mean())
    metrics["posterior"] = posterior_statistics(codes)

    # Shape from spectrum: decode (z_E = 0, z_I = f(lambda)), compare with the canonical shape.
    _, x_spectral = vae.decode(codes["mu_R"], torch.zeros_like(codes["mu_E"]), codes["mu_I_spectral"])
    metrics["shape_from_spectrum_d_C"] = float(chamfer(ae.decode(x_spectral), fresh).mean())

    # Generation: coverage and fidelity against rotated test clouds, 5x as many samples, two runs.
    c = vae.config
    coverages, fidelities = [], []
    for _ in range(2):
        count = 5 * len(clouds)
        z = [torch.randn(count, size) for size in (c.n_rotation, c.n_extrinsic, c.n_intrinsic)]
        q_gen, x_gen = vae.decode(*z)
        generated = rotate(ae.decode(x_gen), quaternion_to_matrix(q_gen))
        real = rotate(fresh, random_rotation_matrices(len(fresh), full=full_rotations))
        coverage, fidelity = coverage_and_fidelity(generated, real)
        coverages.append(coverage)
        fidelities.append(fidelity)
    metrics["coverage"] = float(np.mean(coverages))
    metrics["fidelity"] = float(np.mean(fidelities))

    # Pose-aware retrieval and the disentanglement score, per family.
    if dataset.has_ground_truth:
        metrics.update(retrieval_metrics(ae, vae, dataset, indices, codes, spectrum, rng, full_rotations))
        if not sim_binary:
            log.info("no sim binary: the pose-transfer error is skipped")
        elif not made_by_sim(dataset):
            log.info("%s was not written by `sim dataset`: the pose-transfer error is skipped", dataset.root)
        else:
            metrics["pose_transfer"] = pose_transfer(ae, vae, dataset, indices, codes, sim_binary, rng)
    else:
        log.info("no ground truth: retrieval and the disentanglement score S are skipped")
    return metrics
