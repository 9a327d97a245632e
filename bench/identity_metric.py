"""Would a metric learned from within-subject scatter separate subjects better than the encoder's
own per-dimension variances? Reads `gdvae-node evaluate --states` files of the tracking benchmark,
estimates metrics on one set and measures the separability (as src/evaluate/metrics.rs does) on
the others.

    .venv/bin/python bench/identity_metric.py TUNE-states.jsonl OTHER-states.jsonl...

The states files come from `bench/tracking.sh SET -- --states OUT/SET-states.jsonl`. Result with
the shipped bundle (2026-12-02): docs/tracking.md "Tracking benchmark", what limits identity.
"""
import json
import sys

import numpy as np


def load(path):
    streams = {}
    for line in open(path):
        row = json.loads(line)
        truth = row["truth"]
        if truth is None:
            continue
        s = row["state"]
        streams.setdefault(s["stream"], []).append(
            (truth["subject"], truth["family"], np.array(s["raw"]["z_i"]), np.array(s["raw"]["z_i_var"])))
    segments = []  # (stream, subject, family, means [T, n], variances [T, n])
    for stream, rows in streams.items():
        start = 0
        for i in range(1, len(rows) + 1):
            if i == len(rows) or rows[i][0] != rows[start][0]:
                chunk = rows[start:i]
                segments.append((stream, chunk[0][0], chunk[0][1], np.stack([c[2] for c in chunk]),
                                 np.stack([c[3] for c in chunk])))
                start = i
    return segments


def fuse(means, variances):
    p = 1.0 / np.maximum(variances, 1e-12)
    return (p * means).sum(0) / p.sum(0)


def separability(segments, transform, w):
    within, between, same = [], [], []
    fused = lambda m, v: transform(fuse(m, v))
    for _, _, _, m, v in segments:
        for t in range(w, len(m) - w + 1):
            within.append(np.linalg.norm(fused(m[t - w:t], v[t - w:t]) - fused(m[t:t + w], v[t:t + w])))
    for a, b in zip(segments, segments[1:]):
        if a[0] != b[0] or len(a[3]) < w or len(b[3]) < w:
            continue
        d = np.linalg.norm(fused(a[3][-w:], a[4][-w:]) - fused(b[3][:w], b[4][:w]))
        between.append(d)
        if a[2] == b[2]:
            same.append(d)
    within = np.sort(within)
    p999 = np.quantile(within, 0.999)
    auc = lambda c: np.mean([(np.searchsorted(within, d, "left") + np.searchsorted(within, d, "right")) / 2
                             / len(within) for d in c])
    return dict(auc=auc(between), auc_same=auc(same), found=np.mean(np.array(between) > p999),
                found_same=f"{int(np.sum(np.array(same) > p999))}/{len(same)}")


def scatter(segments, w):
    """Pooled within-subject covariance of frames, of window differences, and between-subject."""
    frames, diffs, centres = [], [], []
    for _, _, _, m, v in segments:
        frames.append(m - m.mean(0))
        centres.append(m.mean(0))
        for t in range(w, len(m) - w + 1, max(1, w // 2)):
            diffs.append(fuse(m[t - w:t], v[t - w:t]) - fuse(m[t:t + w], v[t:t + w]))
    frames = np.concatenate(frames)
    diffs = np.array(diffs)
    centres = np.array(centres)
    return frames.T @ frames / len(frames), diffs.T @ diffs / len(diffs), np.cov(centres.T)


def inverse_sqrt(c, shrink):
    c = (1 - shrink) * c + shrink * np.trace(c) / len(c) * np.eye(len(c))
    values, vectors = np.linalg.eigh(c)
    return vectors @ np.diag(values ** -0.5) @ vectors.T


def main():
    tune = load(sys.argv[1])
    others = [(p, load(p)) for p in sys.argv[2:]]
    w = 10
    sw, sd, sb = scatter(tune, w)
    metrics = {"euclidean": lambda x: x,
               "diag within": lambda x, s=1 / np.sqrt(np.diag(sw)): x * s}
    for shrink in (0.0, 0.1, 0.3):
        metrics[f"whiten frames, shrink {shrink}"] = (lambda x, m=inverse_sqrt(sw, shrink): m @ x)
        metrics[f"whiten diffs, shrink {shrink}"] = (lambda x, m=inverse_sqrt(sd, shrink): m @ x)
    # LDA: directions of most between- per within-subject variance.
    m = inverse_sqrt(sw, 0.1)
    values, vectors = np.linalg.eigh(m @ sb @ m.T)
    for k in (4, 8, 12):
        metrics[f"lda {k}"] = (lambda x, p=vectors[:, -k:].T @ m: p @ x)
    print("within-subject frame scatter eigenvalues (tune):", np.round(np.linalg.eigvalsh(sw)[::-1][:8], 5))
    for name, data in [(sys.argv[1], tune)] + others:
        print(f"\n{name}: {len(data)} segments")
        for label, transform in metrics.items():
            for ww in (1, 10):
                r = separability(data, transform, ww)
                print(f"  {label:28s} W={ww:2d} AUC {r['auc']:.3f} same {r['auc_same']:.3f} "
                      f"found {r['found']:.2f} same-family found {r['found_same']}")


if __name__ == "__main__":
    main()
