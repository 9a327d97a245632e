"""Which step between the kit's training clouds and the node's camera clouds makes one subject's z_I
wander as far as the step to another subject of its family? Reads a `gdvae-node evaluate --states`
file of the tracking benchmark, re-poses every k-th frame's subject from its ground truth (beta,
theta) with `sim pose`, and encodes, with the bundle's encoder, clouds that add one difference at a
time to the kit's whole-surface sample:

- `whole`: 256 area-weighted points of the whole posed surface, centred on its bounding box (what
  the kit trains on);
- `view`: only the faces turned towards the recording's true camera position (the kit's partial
  views: no self-occlusion), still centred on the whole surface's box;
- `view-recentred`: the same points centred on their own box, as the node must (it never sees the
  rest);
- `view-fps`: 4,096 such points thinned to 256 by farthest-point sampling, as the node's prepare
  stage does;
- `node`: the node's own raw z_I on the depth camera's cloud (noise, self-occlusion, crop).

For each it prints, per family, the within-subject spread of 10-frame fused windows next to the
same-family step between subjects (as `bench/identity_metric.py` measures them; frames are fused
with equal weights here because only the node has variances), so the stream where the ratio jumps
names the step to fix.

    .venv/bin/python bench/identity_domain.py SET-states.jsonl RECORDINGS_DIR [--every K] [--bundle DIR]
"""
import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "models"))
from gdvae.data import read_mesh, sample_surface  # noqa: E402

W = 10


def farthest_points(points, count, rng):
    chosen = [int(rng.integers(len(points)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


def box_centred(points):
    return points - 0.5 * (points.min(0) + points.max(0))


def clouds_of(mesh, camera_in_object, points, rng):
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    facing = camera_in_object - centre
    facing /= np.linalg.norm(facing)
    whole_centre = lambda p: p - centre
    view = sample_surface(mesh, points, rng, facing)
    dense = sample_surface(mesh, 4096, rng, facing)
    return {
        "whole": whole_centre(sample_surface(mesh, points, rng)),
        "view": whole_centre(view),
        "view-recentred": box_centred(view),
        "view-fps": box_centred(farthest_points(dense, points, rng)),
    }


def spread(segments):
    """Per family: median within-subject distance between adjacent 10-frame windows, median
    same-family step between consecutive subjects, and the share of steps above the within p99."""
    out = {}
    for family in sorted({s[2] for s in segments}):
        within, between = [], []
        mine = [s for s in segments if s[2] == family]
        for _, _, _, z in mine:
            for t in range(W, len(z) - W + 1):
                within.append(np.linalg.norm(z[t - W:t].mean(0) - z[t:t + W].mean(0)))
        for a, b in zip(segments, segments[1:]):
            if a[0] == b[0] and a[2] == b[2] == family and len(a[3]) >= W and len(b[3]) >= W:
                between.append(np.linalg.norm(a[3][-W:].mean(0) - b[3][:W].mean(0)))
        if within and between:
            p99 = np.quantile(within, 0.99)
            out[family] = (np.median(within), np.median(between), np.mean(np.array(between) > p99), len(between))
    return out


def ground_truth(recording):
    """frame -> the sim's full ground truth (beta, theta, ...) from the recording's truth channel."""
    from mcap.reader import make_reader
    out = {}
    with open(recording, "rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/sim/ground_truth"]):
            truth = json.loads(message.data)
            out[truth["frame"]] = truth
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("states")
    parser.add_argument("recordings", help="the folder of the set's recordings, e.g. /work/data/bench-tracking/tune")
    parser.add_argument("--every", type=int, default=2, help="use every K-th frame (default 2)")
    parser.add_argument("--bundle", default=str(ROOT / "models/bundles/cpu-fo"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    manifest = json.loads((Path(args.bundle) / "manifest.json").read_text())
    scale, points = manifest["training"]["scale"], manifest["sizes"]["points"]
    session = onnxruntime.InferenceSession(str(Path(args.bundle) / "encoder.onnx"))
    z_i_index = [o.name for o in session.get_outputs()].index("z_I_mean")

    rows, full = [], {}
    for n, line in enumerate(open(args.states)):
        row = json.loads(line)
        if row["truth"] is not None and n % args.every == 0:
            stream = row["state"]["stream"]
            if stream not in full:
                full[stream] = ground_truth(Path(args.recordings) / f"{stream}.mcap")
            row["truth"] = {**row["truth"], **full[stream][row["truth"]["frame"]]}
            rows.append(row)
    rows.sort(key=lambda r: (r["state"]["stream"], r["truth"]["frame"]))  # streams interleave
    rng = np.random.default_rng(args.seed)
    streams = {name: [] for name in ("whole", "view", "view-recentred", "view-fps", "node")}
    with tempfile.TemporaryDirectory() as work:
        requests = Path(work) / "requests.jsonl"
        with open(requests, "w") as f:
            for i, row in enumerate(rows):
                t = row["truth"]
                f.write(json.dumps({"name": f"f{i}", "family": t["family"], "beta": t["beta"], "theta": t["theta"]}) + "\n")
        subprocess.run([str(ROOT / "target/release/sim"), "pose", "--requests", str(requests), "--out", work],
                       check=True, stdout=subprocess.DEVNULL)
        for i, row in enumerate(rows):
            t = row["truth"]
            mesh = read_mesh(Path(work) / f"f{i}.ply")
            c, s = np.cos(t["yaw"]), np.sin(t["yaw"])
            object_from_world = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
            camera = object_from_world @ (np.array(t["world_from_camera"]["translation"]) - np.array(t["translation"]))
            for name, cloud in clouds_of(mesh, camera, points, rng).items():
                streams[name].append(cloud)
            if (i + 1) % 200 == 0:
                print(f"  posed and sampled {i + 1}/{len(rows)} frames", file=sys.stderr)

    keys = [(r["state"]["stream"], r["truth"]["subject"], r["truth"]["family"]) for r in rows]
    z = {"node": np.array([r["state"]["raw"]["z_i"] for r in rows])}
    for name in ("whole", "view", "view-recentred", "view-fps"):
        batch = (np.stack(streams[name]) * scale).astype(np.float32)
        z[name] = np.concatenate([session.run(None, {"points": batch[k:k + 256]})[z_i_index]
                                  for k in range(0, len(batch), 256)])
    print(f"{args.states}: {len(rows)} frames (every {args.every}), bundle {args.bundle}")
    print(f"{'stream':16s} {'family':10s} {'within':>8s} {'between':>8s} {'ratio':>6s} {'found':>6s}")
    for name, values in z.items():
        segments, start = [], 0
        for i in range(1, len(keys) + 1):
            if i == len(keys) or keys[i][:2] != keys[start][:2]:
                segments.append((*keys[start], values[start:i]))
                start = i
        for family, (within, between, found, count) in spread(segments).items():
            print(f"{name:16s} {family:10s} {within:8.4f} {between:8.4f} {within / between:6.2f} "
                  f"{found:6.2f} (of {count})")


if __name__ == "__main__":
    main()
