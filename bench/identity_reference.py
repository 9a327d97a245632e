"""Against which reference should a change detector compare the next frames' z_I? Reads
`gdvae-node evaluate --states` files of the tracking benchmark and measures, as
`bench/identity_metric.py` does, how well the fused z_I of the W = 10 frames after a true change
stands apart from its reference, against the same distance at every position within one subject:
- the last R frames of the current subject (R = 10, 30, 90, all of them): a longer memory averages
  the encoder's noise out but carries the slow wander of z_I;
- the earlier frames seen from about the same side (the subject's yaw relative to the line of
  sight within a tolerance, from the ground truth or from the node's own filtered yaw and
  centre_m), falling back to the last 10 frames: if z_I wandered with the view, this would
  remove it;
and, to read those: how far each subject's view sweeps while it is seen (a same-side reference
can only help a subject seen from one side twice), and how far z_I wanders between 10-frame
windows adjacent and 80 frames apart, for subjects turning in place and walking.

    .venv/bin/python bench/identity_reference.py SET-states.jsonl...

Result with the shipped bundle (2026-12-02): docs/tracking.md "Tracking benchmark", what limits identity.
"""
import json
import sys

import numpy as np

from identity_metric import fuse

W, SKIP, MIN_REFERENCE = 10, 30, 10


def streams(path, view_from_truth):
    out = {}
    for line in open(path):
        row = json.loads(line)
        truth = row["truth"]
        if truth is None:
            continue
        s = row["state"]
        camera = np.array(truth["world_from_camera"]["translation"])
        centre = np.array(truth["translation"]) if view_from_truth else np.array(s["centre_m"])
        yaw = truth["yaw"] if view_from_truth else s["filtered"]["yaw"]
        view = yaw - np.arctan2(centre[1] - camera[1], centre[0] - camera[0])
        out.setdefault(s["stream"], []).append(
            (truth["subject"], truth["family"], np.array(s["raw"]["z_i"]), np.array(s["raw"]["z_i_var"]), view))
    return out


def angle_between(a, b):
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def separability(path, reference, view_from_truth=True):
    within, same, cross = [], [], []
    for rows in streams(path, view_from_truth).values():
        subject = [r[0] for r in rows]
        family = [r[1] for r in rows]
        means = np.stack([r[2] for r in rows])
        variances = np.stack([r[3] for r in rows])
        views = np.array([r[4] for r in rows])
        starts = [0] + [i for i in range(1, len(rows)) if subject[i] != subject[i - 1]]
        ends = starts[1:] + [len(rows)]
        after = lambda t: fuse(means[t:t + W], variances[t:t + W])
        for k, (a, b) in enumerate(zip(starts, ends)):
            for t in range(a + SKIP, b - W + 1):
                within.append(np.linalg.norm(after(t) - reference(means, variances, views, a, t)))
            if k > 0:
                d = np.linalg.norm(after(a) - reference(means, variances, views, starts[k - 1], a))
                (same if family[a] == family[starts[k - 1]] else cross).append(d)
    within = np.sort(within)
    p999 = np.quantile(within, 0.999)
    auc = lambda c: np.mean([np.searchsorted(within, d) / len(within) for d in c])
    return (f"AUC same family {auc(same):.3f}, all {auc(same + cross):.3f}; "
            f"same-family changes above the within-subject p99.9: {sum(d > p999 for d in same)} of {len(same)}")


def last(r):
    return lambda m, v, views, a, t: fuse(m[max(a, t - r):t], v[max(a, t - r):t])


def same_side(tolerance):
    def reference(m, v, views, a, t):
        current = np.angle(np.exp(1j * views[t:t + W]).mean())
        chosen = np.where(angle_between(views[a:t], current) < tolerance)[0] + a
        if len(chosen) < MIN_REFERENCE:
            chosen = np.arange(max(a, t - 10), t)
        return fuse(m[chosen], v[chosen])
    return reference


def view_sweeps(path):
    sweeps = []
    for rows in streams(path, True).values():
        subject = [r[0] for r in rows]
        views = np.unwrap(np.array([r[4] for r in rows]))
        starts = [0] + [i for i in range(1, len(rows)) if subject[i] != subject[i - 1]]
        for a, b in zip(starts, starts[1:] + [len(rows)]):
            sweeps.append(np.degrees(views[a:b].max() - views[a:b].min()))
    return sweeps


def wander(path):
    apart = {}
    for stream, rows in streams(path, True).items():
        motion = stream.split("-")[0]
        subject = [r[0] for r in rows]
        means = np.stack([r[2] for r in rows])
        variances = np.stack([r[3] for r in rows])
        window = lambda t: fuse(means[t:t + W], variances[t:t + W])
        starts = [0] + [i for i in range(1, len(rows)) if subject[i] != subject[i - 1]]
        for a, b in zip(starts, starts[1:] + [len(rows)]):
            for t in range(a + 90, b - W + 1, 5):
                adjacent, far = apart.setdefault(motion, ([], []))
                adjacent.append(np.linalg.norm(window(t) - window(t - 10)))
                far.append(np.linalg.norm(window(t) - window(t - 90)))
    return {m: (np.median(a), np.median(f)) for m, (a, f) in apart.items()}


if __name__ == "__main__":
    for path in sys.argv[1:]:
        print(path)
        for r in (10, 30, 90, 10**6):
            print(f"  last {r if r < 10**6 else 'all'} frames: {separability(path, last(r))}")
        for truth in (True, False):
            for tolerance in (0.15, 0.3, 0.6):
                print(f"  same side within {np.degrees(tolerance):.0f} deg ({'true' if truth else 'filtered'} yaw): "
                      f"{separability(path, same_side(tolerance), truth)}")
        sweeps = view_sweeps(path)
        print(f"  view sweep while one subject is seen: {min(sweeps):.0f}-{max(sweeps):.0f} deg "
              f"(median {np.median(sweeps):.0f}) over {len(sweeps)} appearances")
        for motion, (adjacent, far) in sorted(wander(path).items()):
            print(f"  z_I wander ({motion}): median distance of 10-frame windows adjacent {adjacent:.3f}, "
                  f"80 frames apart {far:.3f}")
