"""Two cues a tracker could add to one frame's z_I to tell two subjects of one family apart, measured
on the tracking benchmark before anything is built into the node:

- `fusion`: the subject's last K sampled camera clouds (prepared as the node does: the recording's
  camera pose, the crop, the largest 6-cm cluster) moved into the subject's own frame, by the true
  pose (`true`) or by the node's filtered yaw and centre_m (`node`), fused, thinned to N_p by
  farthest points, turned back to the frame's heading and encoded as the node's 4 yaw copies. As the
  subject turns, the fused cloud covers more of its surface than one view (whole surfaces separate
  subjects far better, bench/identity_domain.py). Printed as identity_domain.py prints its streams:
  median within-subject distance between adjacent 10-frame windows, median same-family step at a
  change, and the share of steps above the within-subject p99.
- `height`: the prepared cloud's box-centre height (the states' centre_m z; the crop starts at the
  floor, so it is half the visible height), a size cue that does not depend on the view. A CUSUM on
  it alone (the estimate: the mean of the identity's last 60 accepted frames) over a grid of noise
  scales, drifts and thresholds; the settings that find most changes on the first states file,
  with the fewest false ones, are then scored on the second.

    .venv/bin/python bench/identity_cues.py fusion SET-states.jsonl RECORDINGS_DIR [--every 2] [--ks 1,15,30]
    .venv/bin/python bench/identity_cues.py height TUNE-states.jsonl HOLDOUT-states.jsonl

The states files come from `bench/tracking.sh SET -- --states SET-states.jsonl`. Results with the
shipped bundle (2026-12-03): docs/tracking.md "Tracking benchmark", what limits identity.
"""
import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from identity_domain import CROP, ROOT, box_centred, camera_clouds, encoder_of, farthest_points
from identity_domain import largest_cluster, quaternion_matrix, sampled_rows, segments_of, spread


def turn(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def fusion(args):
    scale, points, session, z_i_index = encoder_of(args.bundle)
    rows = sampled_rows(args.states, args.recordings, args.every)
    world = []  # each row's prepared cloud in the world frame
    for stream in sorted({r["state"]["stream"] for r in rows}):
        mine = [r for r in rows if r["state"]["stream"] == stream]
        clouds = camera_clouds(Path(args.recordings) / f"{stream}.mcap", {r["truth"]["frame"] for r in mine})
        for r in mine:
            pose = r["truth"]["world_from_camera"]
            cloud = clouds[r["truth"]["frame"]] @ quaternion_matrix(pose["rotation_xyzw"]).T + pose["translation"]
            world.append(largest_cluster(cloud[((cloud >= CROP[:3]) & (cloud <= CROP[3:])).all(-1)], 0.06))
    keys = [(r["state"]["stream"], r["truth"]["subject"], r["truth"]["family"]) for r in rows]
    rng = np.random.default_rng(args.seed)

    def encode(clouds):
        copies = []
        for angle in np.arange(4) * np.pi / 2:
            batch = (np.stack(clouds) @ turn(angle).T * scale).astype(np.float32)
            copies.append(np.concatenate([session.run(None, {"points": batch[k:k + 256]})[z_i_index]
                                          for k in range(0, len(batch), 256)]))
        return np.mean(copies, axis=0)

    print(f"{args.states}: {len(rows)} frames (every {args.every}), bundle {args.bundle}")
    for source in ("true", "node"):
        poses = [(r["truth"]["yaw"], np.array(r["truth"]["translation"])) if source == "true"
                 else (r["state"]["filtered"]["yaw"], np.array(r["state"]["centre_m"])) for r in rows]
        in_object = [(w - centre) @ turn(yaw) for w, (yaw, centre) in zip(world, poses)]
        for k in args.ks:
            if source == "node" and k == 1:
                continue  # one frame turned into its frame and back: the `true` row
            clouds = []
            for i in range(len(rows)):
                fused = np.concatenate([in_object[j] for j in range(max(0, i - k + 1), i + 1) if keys[j][:2] == keys[i][:2]])
                if len(fused) > args.pool:
                    fused = fused[rng.choice(len(fused), args.pool, replace=False)]
                if len(fused) < points:
                    fused = np.concatenate([fused, fused[rng.choice(len(fused), points - len(fused))]])
                clouds.append(box_centred(farthest_points(fused, points, rng) @ turn(poses[i][0]).T))
            z = encode(clouds)
            for family, (within, between, found, count) in spread(segments_of(keys, z)).items():
                print(f"{source:5s} K={k:3d} {family:10s} within {within:.4f} between {between:.4f} "
                      f"ratio {within / between:.2f} found {found:.2f} (of {count})", flush=True)


def heights(path):
    streams = {}
    for line in open(path):
        row = json.loads(line)
        if row["truth"] is not None:
            streams.setdefault(row["state"]["stream"], []).append(
                (row["truth"]["frame"], row["truth"]["subject"], row["state"]["centre_m"][2]))
    return [sorted(frames) for frames in streams.values()]


def height_changes(frames, sigma, drift, threshold, switch_frames=5, memory=60):
    """Frame indices where a CUSUM on the squared standardized height residual reports a change
    (clipped as the node's detector clips, frames held while suspected)."""
    accepted, held, statistic, changes = [], [], 0.0, []
    clip = drift + threshold / switch_frames
    for i, (_, _, height) in enumerate(frames):
        if len(accepted) < 3:
            accepted.append(height)
            continue
        residual = (height - np.mean(accepted[-memory:])) / sigma
        statistic = max(0.0, statistic + min(residual * residual, clip) - drift)
        if statistic >= threshold:
            changes.append(i)
            accepted, held, statistic = held[-switch_frames:] + [height], [], 0.0
        elif statistic > 0:
            held.append(height)
        else:
            accepted += held + [height]
            held = []
    return changes


def height_score(sets, settings):
    found = total = false = frames = 0
    for seq in sets:
        truth = [i for i in range(1, len(seq)) if seq[i][1] != seq[i - 1][1]]
        changes = height_changes(seq, *settings)
        frames += len(seq)
        used = set()
        for t in truth:
            total += 1
            hit = [c for c in changes if t <= c < t + 10 and c not in used]
            if hit:
                found += 1
                used.add(hit[0])
        false += len([c for c in changes if c not in used])
    return found, total, 1000 * false / frames


def height(args):
    tune, holdout = heights(args.tune), heights(args.holdout)
    grid = itertools.product([0.005, 0.0075, 0.01, 0.015, 0.02, 0.03], [1, 2, 4, 8], [10, 20, 40, 80])
    scored = sorted(((height_score(tune, s), s) for s in grid), key=lambda x: (-x[0][0], x[0][2]))
    print("sigma_m drift threshold | tune found, false per 1,000 | holdout found, false per 1,000")
    for (found, total, false), settings in scored[:5]:
        h_found, h_total, h_false = height_score(holdout, settings)
        print(f"{settings[0]:7.4f} {settings[1]:5d} {settings[2]:9d} | {found}/{total}, {false:.2f} | "
              f"{h_found}/{h_total}, {h_false:.2f}")
    allowed = [x for x in scored if x[0][2] <= 1.0]  # the false-change bound
    if allowed:
        (found, total, false), settings = allowed[0]
        h_found, h_total, h_false = height_score(holdout, settings)
        print(f"most found on tune with <= 1 false per 1,000: {settings}: tune {found}/{total}, {false:.2f}; "
              f"holdout {h_found}/{h_total}, {h_false:.2f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cues = parser.add_subparsers(dest="cue", required=True)
    f = cues.add_parser("fusion")
    f.add_argument("states")
    f.add_argument("recordings")
    f.add_argument("--every", type=int, default=2)
    f.add_argument("--ks", type=lambda s: [int(k) for k in s.split(",")], default=[1, 15, 30])
    f.add_argument("--pool", type=int, default=6000, help="points kept of a fused cloud before farthest points")
    f.add_argument("--bundle", default=str(ROOT / "models/bundles/cpu-fo"))
    f.add_argument("--seed", type=int, default=0)
    h = cues.add_parser("height")
    h.add_argument("tune")
    h.add_argument("holdout")
    args = parser.parse_args()
    fusion(args) if args.cue == "fusion" else height(args)


if __name__ == "__main__":
    sys.exit(main())
