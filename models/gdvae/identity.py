"""The bundle's identity projection: the directions of the encoder's x_c that tell two subjects of
one family apart on the node's own clouds, where the node's tracker detects identity changes.

The kit's views are not the node's clouds (a stereo camera's shadows and depth edges cut pieces
off, prepare crops and clusters), and on the node's clouds one subject's z_I wanders about as far
as it steps at a change between two subjects of a family. x_c, the autoencoder's code that z_I is
read from, holds more of the subject; which of it survives the node's clouds is measured on them:
`gdvae-node evaluate SIM-RECORDINGS --states FILE` writes every frame's x_c beside its ground
truth, and this fits, over many subjects, the linear discriminant of subjects within each family
(the between-subject scatter of the subjects' mean x_c, per family, against the within-subject
scatter of x_c about them), keeping its leading directions scaled to unit within-subject spread.
The node projects each frame's x_c on them and detects changes there (src/track/shape.rs).

    python -m gdvae fit-identity BUNDLE STATES.jsonl... [--directions 5] [--ridge 0.03]
"""
from __future__ import annotations

import json
import pathlib

import numpy as np


def read_states(paths: list[str]) -> tuple[dict[tuple[str, str], list[np.ndarray]], int]:
    """x_c per (family, subject) from `evaluate --states` files; also the frames without truth."""
    by_subject: dict[tuple[str, str], list[np.ndarray]] = {}
    unmatched = 0
    for path in paths:
        with open(path) as lines:
            for number, line in enumerate(lines, 1):
                row = json.loads(line)
                if "x_c" not in row:
                    raise ValueError(f"{path} line {number}: no x_c (states written by a node older than "
                                     f"fit-identity; write them again with `gdvae-node evaluate ... --states`)")
                truth = row.get("truth")
                if truth is None:
                    unmatched += 1
                    continue
                by_subject.setdefault((truth["family"], truth["subject"]), []).append(np.asarray(row["x_c"], float))
    return by_subject, unmatched


def fit_projection(by_subject: dict[tuple[str, str], list[np.ndarray]], directions: int, ridge: float) -> dict:
    """The `directions` leading discriminant directions (rows, unit within-subject spread each)."""
    families = sorted({family for family, _ in by_subject})
    for family in families:
        count = sum(1 for f, _ in by_subject if f == family)
        if count < 2:
            raise ValueError(f"family '{family}' has {count} subject in the states: a discriminant needs two or more")
    width = len(next(iter(by_subject.values()))[0])
    if not 1 <= directions <= width:
        raise ValueError(f"--directions {directions}: x_c has {width} dimensions")
    if ridge < 0:
        raise ValueError(f"--ridge {ridge} must be at least 0")
    within, frames, means = np.zeros((width, width)), 0, {}
    for key, codes in by_subject.items():
        codes = np.stack(codes)
        means[key] = codes.mean(0)
        centred = codes - means[key]
        within += centred.T @ centred
        frames += len(codes)
    within /= frames
    between = np.zeros((width, width))
    for family in families:
        centred = np.stack([m for (f, _), m in means.items() if f == family])
        centred -= centred.mean(0)
        between += centred.T @ centred / len(centred)
    between /= len(families)
    # Shrunk towards the mean variance: directions in which no subject varied in the fit set are
    # not taken for perfectly quiet ones.
    within += ridge * np.trace(within) / width * np.eye(width)
    inverse_root = np.linalg.inv(np.linalg.cholesky(within))
    values, vectors = np.linalg.eigh(inverse_root @ between @ inverse_root.T)
    order = np.argsort(values)[::-1][:directions]
    matrix = vectors[:, order].T @ inverse_root
    return {
        "matrix": matrix,
        "between_within": values[order],
        "subjects": {family: sum(1 for f, _ in by_subject if f == family) for family in families},
        "frames": frames,
    }


def write_projection(bundle: str | pathlib.Path, fitted: dict, states: list[str], directions: int,
                     ridge: float) -> pathlib.Path:
    """Writes `calibration.identity_projection` into the bundle's manifest (the other keys kept)."""
    manifest_path = pathlib.Path(bundle) / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    x_c = manifest["sizes"]["x_c"]
    if fitted["matrix"].shape[1] != x_c:
        raise ValueError(f"the states' x_c has {fitted['matrix'].shape[1]} dimensions, the bundle's {x_c}: "
                         f"states of another bundle")
    encoder = manifest.get("files", {}).get("encoder.onnx", {}).get("sha256")
    if not encoder:
        raise ValueError(f"{manifest_path} lists no encoder.onnx sha256: not a bundle written by `export`")
    manifest.setdefault("calibration", {})["identity_projection"] = {
        "input": "x_c",
        "matrix": [[float(w) for w in row] for row in fitted["matrix"]],
        # The node refuses the projection beside any other encoder.
        "encoder_sha256": encoder,
        "fitted_on": {
            "states": [pathlib.Path(p).name for p in states],
            "subjects": fitted["subjects"],
            "frames": fitted["frames"],
            "directions": directions,
            "ridge": ridge,
            "between_within": [round(float(v), 3) for v in fitted["between_within"]],
        },
    }
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    card = pathlib.Path(bundle) / "MODEL_CARD.md"
    if card.exists():  # an exported bundle's card says what its manifest now holds
        from .export import model_card

        card.write_text(model_card(manifest))
    return manifest_path
