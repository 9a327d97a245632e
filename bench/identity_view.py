"""Is the wander of one subject's z_I a bias that the view explains, the same for every subject of a
family? If so, a table learned once per bundle could take it out before the shape filter fuses.

Reads `gdvae-node evaluate --states` files of the tracking benchmark. For every frame, the view is
the subject's yaw relative to the line of sight from the camera (from the ground truth, or from the
node's own filtered yaw and centre_m, as the node would have it). On the first file (tune) it fits,
per family, z_I's deviation from its subject's mean as a Fourier series of the view (K harmonics;
both sides demeaned within each appearance, so subjects' own offsets do not leak in), and then
measures on every file, with z_I corrected by that fit or not:
- the share of z_I's within-appearance variance the view explains (R^2),
- the separability of identity as bench/identity_metric.py measures it (AUC of the change's step
  against within-subject steps; same-family changes above the within-subject p99.9).
The family of each frame is the ground truth's in the fit, and in the correction the family whose
tune centroid is nearer the frame's z_I (as a node would tell them apart).

    .venv/bin/python bench/identity_view.py TUNE-states.jsonl OTHER-states.jsonl... [--harmonics K]
"""
import argparse
import json

import numpy as np

from identity_metric import separability


def load(path):
    """Appearances: (stream, subject, family, z_i [T, n], z_i_var [T, n], true view [T], node view [T])."""
    streams = {}
    for line in open(path):
        row = json.loads(line)
        truth = row["truth"]
        if truth is None or truth.get("world_from_camera") is None:
            continue
        s = row["state"]
        camera = np.array(truth["world_from_camera"]["translation"])
        true_centre = np.array(truth["translation"])
        node_centre = np.array(s["centre_m"])
        # evaluate puts the sensor where the recording's world_from_camera says: centre_m is in the world frame.
        true_view = truth["yaw"] - np.arctan2(true_centre[1] - camera[1], true_centre[0] - camera[0])
        node_view = s["filtered"]["yaw"] - np.arctan2(node_centre[1] - camera[1], node_centre[0] - camera[0])
        streams.setdefault(s["stream"], []).append(
            (truth["subject"], truth["family"], s["raw"]["z_i"], s["raw"]["z_i_var"], true_view, node_view))
    appearances = []
    for stream, rows in streams.items():
        start = 0
        for i in range(1, len(rows) + 1):
            if i == len(rows) or rows[i][0] != rows[start][0]:
                chunk = rows[start:i]
                columns = list(zip(*chunk))
                appearances.append((stream, chunk[0][0], chunk[0][1], np.array(columns[2]), np.array(columns[3]),
                                    np.array(columns[4]), np.array(columns[5])))
                start = i
    return appearances


def features(view, harmonics):
    return np.stack([f(k * view) for k in range(1, harmonics + 1) for f in (np.cos, np.sin)], axis=-1)


def demeaned(x):
    return x - x.mean(0)


def fit(appearances, harmonics, which):
    """Per family, W with z_I - mean ~ (F - mean F) W, least squares (ridge 1e-3)."""
    weights, centroids = {}, {}
    for family in sorted({a[2] for a in appearances}):
        mine = [a for a in appearances if a[2] == family]
        f = np.concatenate([demeaned(features(a[which], harmonics)) for a in mine])
        z = np.concatenate([demeaned(a[3]) for a in mine])
        weights[family] = np.linalg.solve(f.T @ f + 1e-3 * np.eye(f.shape[1]), f.T @ z)
        centroids[family] = np.concatenate([a[3] for a in mine]).mean(0)
    return weights, centroids


def corrected(appearances, model, harmonics, which):
    weights, centroids = model
    families = sorted(centroids)
    out = []
    for stream, subject, family, z, v, *views in appearances:
        nearest = np.argmin([np.linalg.norm(z - centroids[f], axis=1) for f in families], axis=0)
        bias = np.stack([features(views[which - 5][t], harmonics) @ weights[families[k]]
                         for t, k in enumerate(nearest)])
        out.append((stream, subject, family, z - bias, v))
    return out


def explained(appearances, model, harmonics, which):
    weights = model[0]
    total = residual = 0.0
    for a in appearances:
        z = demeaned(a[3])
        r = z - demeaned(features(a[which], harmonics)) @ weights[a[2]]
        total += (z ** 2).sum()
        residual += (r ** 2).sum()
    return 1 - residual / total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tune")
    parser.add_argument("others", nargs="*")
    parser.add_argument("--harmonics", type=int, default=2)
    args = parser.parse_args()
    tune = load(args.tune)
    models = {"true view": (5, fit(tune, args.harmonics, 5)), "node view": (6, fit(tune, args.harmonics, 5))}
    for path in [args.tune] + args.others:
        data = load(path)
        print(f"{path}: {len(data)} appearances, {args.harmonics} harmonics fitted on {args.tune} (true view)")
        plain = [(a[0], a[1], a[2], a[3], a[4]) for a in data]
        rows = [("uncorrected", plain)]
        for label, (which, model) in models.items():
            print(f"  z_I variance within an appearance explained by the {label}: "
                  f"{explained(data, model, args.harmonics, which):.3f}")
            rows.append((f"corrected by the {label}", corrected(data, model, args.harmonics, which)))
        for label, segments in rows:
            for w in (1, 10):
                r = separability(segments, lambda x: x, w)
                print(f"  {label:28s} W={w:2d} AUC {r['auc']:.3f} same family {r['auc_same']:.3f}, "
                      f"same-family changes above the within-subject p99.9 {r['found_same']}")


if __name__ == "__main__":
    main()
