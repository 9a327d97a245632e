"""Which step between the kit's training clouds and the node's camera clouds makes one subject's z_I
wander as far as the step to another subject of its family? Reads a `gdvae-node evaluate --states`
file of the tracking benchmark, re-poses every k-th frame's subject from the recording's ground
truth (beta, theta) with `sim pose`, and encodes, with the bundle's encoder, clouds that add one
difference at a time to the kit's whole-surface sample:

- `whole`: 256 area-weighted points of the whole posed surface, centred on its bounding box (what
  the kit trains on);
- `view`: only the faces turned towards the recording's true camera position (the kit's partial
  views: no self-occlusion), still centred on the whole surface's box;
- `view-recentred`: the same points centred on their own box, as the node must;
- `view-fps`: 4,096 such points thinned to 256 by farthest-point sampling, as the node does;
- `camera`, `camera-noisy`: what the kit's `DepthCamera` sees from the true camera position
  (nearest point per pixel; with the stereo depth noise), thinned by farthest points;
- `camera-edges`: the same, noisy, also dropping the pixels at a depth edge as the sim's camera
  does (`DepthCamera.edge_threshold`);
- `recording`: the recording's own depth cloud prepared as the node's `config/replay.toml` does,
  in Python (a check that this script reproduces `node`);
- `recording-on-mesh`: the same, keeping only points within 5 cm of the true surface first;
- `recording-snapped`: those points moved onto the true surface (the camera's visibility, no
  depth error);
- `recording-on-mesh-uncut`, `recording-snapped-uncut`: those two without the largest-cluster
  step (every piece the camera's depth edges and shadows cut off is kept; the floor is gone
  already);
- `node`: the node's own raw z_I from the states file.

The Python streams are encoded as the node's yaw copies (`--yaw-copies`, default 4). For each it
prints, per family, the median within-subject distance between adjacent 10-frame windows (equal
weights) next to the median same-family step between subjects, and the share of those steps above
the within-subject p99, so the stream where the ratio jumps names the step to fix. Then, per stream
and family, the pose code's retrieval of the true pose across subjects (`gdvae-node evaluate`'s
figure: the true-pose distance to the frame of another subject whose z_E is nearest, over the
median), so the same ladder shows where z_E stops naming the pose; and z_E's spread over one-second
windows while the subject walks against while it stands (`evaluate`'s figure; the true pose's
beside it), so the stream where the standing spread jumps names what shakes z_E when the pose
holds still (the `stand-*` sets of `bench/tracking.sh` have standing subjects).

    .venv/bin/python bench/identity_domain.py SET-states.jsonl RECORDINGS_DIR [--every K] [--streams A,B]
"""
import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnxruntime
import torch
from mcap.reader import make_reader
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "models"))
from gdvae.data import DepthCamera, read_mesh, sample_surface  # noqa: E402
from gdvae.surface import MeshCache, depth_camera_views  # noqa: E402
from python_reference import decode_xyz, largest_cluster  # noqa: E402
from pose_probes import retrieval_ratio  # noqa: E402
from python_reference import farthest_point_sampling as farthest_points  # noqa: E402

W = 10
STREAMS = ("whole", "view", "view-recentred", "view-fps", "camera", "camera-noisy", "camera-edges", "recording",
           "recording-on-mesh", "recording-snapped", "recording-on-mesh-uncut", "recording-snapped-uncut", "node")
RECORDED = {"recording", "recording-on-mesh", "recording-snapped", "recording-on-mesh-uncut", "recording-snapped-uncut"}
CROP = np.array([-1.2, -1.2, 0.02, 1.2, 1.2, 2.5])  # config/replay.toml's
NOISY = DepthCamera(dense=30000)  # the sim's OAK-D and the benchmark's --decimation 2
EXACT = DepthCamera(dense=30000, disparity_sigma=0.0)
EDGES = DepthCamera(dense=30000, edge_threshold=0.04)  # the sim's depth-edge dropout too
SEEN = 4096  # points drawn from what the camera sees, then thinned by farthest points


def box_centred(points):
    return points - 0.5 * (points.min(0) + points.max(0))


def clouds_of(mesh, camera_in_object, points, rng, wanted):
    """The simulated streams in `wanted`, each a cloud of `points` for the encoder (metres), drawn
    by the kit's own samplers (`gdvae.surface`) in the mesh's frame centred on its bounding box."""
    cache = MeshCache([mesh], 1.0)
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    eye = torch.as_tensor(camera_in_object - centre, dtype=torch.float32)[None]
    facing = eye / eye.norm()
    generator = torch.Generator().manual_seed(int(rng.integers(2**31)))
    one = torch.zeros(1, dtype=torch.long)

    def surface(count, towards=None):
        drawn = cache.sample(one, count, generator) if towards is None else cache.sample_facing(one, count, towards, generator)
        return drawn[0].numpy().astype(np.float64)

    def camera(model):
        at = replace(model, distance_m=(float(eye.norm()),) * 2)  # the recording's own distance
        dense = cache.sample(one, at.dense, generator)
        seen = depth_camera_views(at, dense, facing, SEEN, 1.0, generator, torch.zeros(1, 3))
        return box_centred(farthest_points(seen[0].numpy().astype(np.float64), points, rng))

    view = surface(points, facing)
    makers = {
        "whole": lambda: surface(points),
        "view": lambda: view,
        "view-recentred": lambda: box_centred(view),
        "view-fps": lambda: box_centred(farthest_points(surface(4096, facing), points, rng)),
        "camera": lambda: camera(EXACT),
        "camera-noisy": lambda: camera(NOISY),
        "camera-edges": lambda: camera(EDGES),
    }
    return {name: make() for name, make in makers.items() if name in wanted}


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


def pose_retrieval(keys, codes, theta):
    """Per family: (`pose_probes.retrieval_ratio` of the codes, the same of the true poses: the floor)."""
    out = {}
    for family in sorted({k[2] for k in keys}):
        mine = np.array([k[2] == family for k in keys])
        subjects = np.array([k[1] for k in keys])[mine]
        poses = np.stack([t for t, m in zip(theta, mine) if m])  # one joint layout per family
        if len(set(subjects)) > 1:
            out[family] = (retrieval_ratio(codes[mine], poses, subjects), retrieval_ratio(poses, poses, subjects))
    return out


def pose_spread(keys, rows, values):
    """(walking, standing) medians of the spread over one-second windows of each subject's rows
    (root-mean-square distance from the window's mean; windows of at least 5 rows), walking at a
    true speed over 0.15 m/s and standing under 0.03 m/s, as `gdvae-node evaluate` classes them."""
    walking, standing = [], []
    start = 0
    for i in range(1, len(keys) + 1):
        if i < len(keys) and keys[i][:2] == keys[start][:2]:
            continue
        times = np.array([rows[k]["truth"]["stamp_nanos"] for k in range(start, i)]) * 1e-9
        where = np.array([rows[k]["truth"]["translation"][:2] for k in range(start, i)])
        window = np.floor(times - times[0]).astype(int)
        for w in np.unique(window):
            members = np.flatnonzero(window == w)
            if len(members) < 5:
                continue
            codes = np.stack([values[start + k] for k in members])
            spread = np.sqrt(((codes - codes.mean(0)) ** 2).sum(-1).mean())
            span = times[members[-1]] - times[members[0]]
            speed = np.linalg.norm(where[members[-1]] - where[members[0]]) / span
            (walking if speed > 0.15 else standing if speed < 0.03 else []).append(spread)
        start = i
    median = lambda v: float(np.median(v)) if v else float("nan")  # noqa: E731
    return median(walking), median(standing)


def segments_of(keys, values):
    """(stream, subject, family, values) per run of rows with one stream and subject: `keys` are
    the rows' (stream, subject, family), `values` their codes, row by row."""
    segments, start = [], 0
    for i in range(1, len(keys) + 1):
        if i == len(keys) or keys[i][:2] != keys[start][:2]:
            segments.append((*keys[start], values[start:i]))
            start = i
    return segments


def ground_truth(recording):
    """frame -> the sim's full ground truth (beta, theta, ...) from the recording's truth channel."""
    out = {}
    with open(recording, "rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/sim/ground_truth"]):
            truth = json.loads(message.data)
            out[truth["frame"]] = truth
    return out


def camera_clouds(recording, frames):
    """frame -> the recording's depth-camera cloud (camera frame, metres), for the given frames."""
    out = {}
    with open(recording, "rb") as f:
        messages = make_reader(f).iter_messages(topics=["/camera/depth/points"])
        for frame, (_, _, message) in enumerate(messages):
            if frame in frames:
                out[frame] = decode_xyz(message.data).astype(np.float64)
    return out


def as_the_node_prepares(points, truth, rng, points_out, near_mesh=None, snap=False, cluster=True):
    """The node's `config/replay.toml` preparation in Python (bench/python_reference.py's steps):
    the recording's camera pose, the crop, the largest 6-cm cluster, farthest points, box
    centring; with `near_mesh` (a KD-tree of the posed subject in the world frame) only the points
    within 5 cm of its surface are kept first (no floor, no strays), and with `snap` each is moved
    onto the nearest point of the surface sample (no depth noise, the camera's visibility kept);
    without `cluster`, every piece is kept."""
    pose = truth["world_from_camera"]
    world = points @ quaternion_matrix(pose["rotation_xyzw"]).T + np.array(pose["translation"])
    world = world[((world >= CROP[:3]) & (world <= CROP[3:])).all(-1)]
    if near_mesh is not None:
        distance, nearest = near_mesh.query(world)
        world = near_mesh.data[nearest[distance < 0.05]] if snap else world[distance < 0.05]
    if cluster:
        world = largest_cluster(world, 0.06)
    chosen = farthest_points(world, points_out, rng)
    # A cloud with fewer points than N_p is padded by repeating points, as the node pads it.
    return box_centred(chosen[np.arange(points_out) % len(chosen)])


def encoder_of(bundle):
    """(model units per metre, N_p, an ONNX Runtime session of the encoder, z_I_mean's and z_E_mean's
    output indices)."""
    manifest = json.loads((Path(bundle) / "manifest.json").read_text())
    session = onnxruntime.InferenceSession(str(Path(bundle) / "encoder.onnx"))
    names = [o.name for o in session.get_outputs()]
    return manifest["training"]["scale"], manifest["sizes"]["points"], session, names.index("z_I_mean"), names.index("z_E_mean")


def sampled_rows(states, recordings, every):
    """Every `every`-th row of a states file that has ground truth, the truth completed from the
    recording's truth channel, ordered by stream and frame (the streams interleave in the file)."""
    rows, full = [], {}
    for n, line in enumerate(open(states)):
        row = json.loads(line)
        if row["truth"] is not None and n % every == 0:
            stream = row["state"]["stream"]
            if stream not in full:
                full[stream] = ground_truth(Path(recordings) / f"{stream}.mcap")
            row["truth"] = {**row["truth"], **full[stream][row["truth"]["frame"]]}
            rows.append(row)
    rows.sort(key=lambda r: (r["state"]["stream"], r["truth"]["frame"]))
    return rows


def quaternion_matrix(xyzw):
    x, y, z, w = xyzw
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("states")
    parser.add_argument("recordings", help="the folder of the set's recordings, e.g. /work/data/bench-tracking/tune")
    parser.add_argument("--every", type=int, default=2, help="use every K-th frame (default 2)")
    parser.add_argument("--bundle", default=str(ROOT / "models/bundles/cpu-fo"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--yaw-copies", type=int, default=4, help="as the node's model.yaw_copies (default 4)")
    parser.add_argument("--streams", default=",".join(STREAMS), help=f"comma-separated, of {', '.join(STREAMS)}")
    args = parser.parse_args()
    scale, points, session, z_i_index, z_e_index = encoder_of(args.bundle)
    rows = sampled_rows(args.states, args.recordings, args.every)
    rng = np.random.default_rng(args.seed)
    streams = {name: [] for name in args.streams.split(",")}
    clouds = {}
    if RECORDED & set(streams):
        for stream in sorted({r["state"]["stream"] for r in rows}):
            frames = {r["truth"]["frame"] for r in rows if r["state"]["stream"] == stream}
            clouds[stream] = camera_clouds(Path(args.recordings) / f"{stream}.mcap", frames)
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
            world_from_object = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            translation = np.array(t["translation"])
            camera = world_from_object.T @ (np.array(t["world_from_camera"]["translation"]) - translation)
            made = clouds_of(mesh, camera, points, rng, set(streams))
            if RECORDED & set(streams):
                cloud = clouds[row["state"]["stream"]][t["frame"]]
                if "recording" in streams:
                    made["recording"] = as_the_node_prepares(cloud, t, rng, points)
                surface = cKDTree(sample_surface(mesh, 30000, rng) @ world_from_object.T + translation)
                if "recording-on-mesh" in streams:
                    made["recording-on-mesh"] = as_the_node_prepares(cloud, t, rng, points, surface)
                if "recording-snapped" in streams:
                    made["recording-snapped"] = as_the_node_prepares(cloud, t, rng, points, surface, snap=True)
                if "recording-on-mesh-uncut" in streams:
                    made["recording-on-mesh-uncut"] = as_the_node_prepares(cloud, t, rng, points, surface,
                                                                           cluster=False)
                if "recording-snapped-uncut" in streams:
                    made["recording-snapped-uncut"] = as_the_node_prepares(cloud, t, rng, points, surface, snap=True,
                                                                           cluster=False)
            for name, cloud in made.items():
                streams[name].append(cloud)
            if (i + 1) % 200 == 0:
                print(f"  posed and sampled {i + 1}/{len(rows)} frames", file=sys.stderr)

    keys = [(r["state"]["stream"], r["truth"]["subject"], r["truth"]["family"]) for r in rows]
    z, z_e = {}, {}
    for name in streams:
        if name == "node":
            z[name] = np.array([r["state"]["raw"]["z_i"] for r in rows])
            z_e[name] = np.array([r["state"]["raw"]["z_e"] for r in rows])
            continue
        # As the node's yaw copies (src/yaw_copies.rs): z_I averaged over K turned copies (all of
        # them here, the node averages the copies its rotation vote keeps).
        copies, pose_copies = [], []
        for angle in np.arange(args.yaw_copies) * 2 * np.pi / args.yaw_copies:
            c, s = np.cos(angle), np.sin(angle)
            turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            batch = (np.stack(streams[name]) @ turn.T * scale).astype(np.float32)
            outputs = [session.run(None, {"points": batch[k:k + 256]}) for k in range(0, len(batch), 256)]
            copies.append(np.concatenate([o[z_i_index] for o in outputs]))
            pose_copies.append(np.concatenate([o[z_e_index] for o in outputs]))
        z[name], z_e[name] = np.mean(copies, axis=0), np.mean(pose_copies, axis=0)
    print(f"{args.states}: {len(rows)} frames (every {args.every}), bundle {args.bundle}, "
          f"{args.yaw_copies} yaw copies")
    print(f"{'stream':16s} {'family':10s} {'within':>8s} {'between':>8s} {'ratio':>6s} {'found':>6s}")
    for name, values in z.items():
        for family, (within, between, found, count) in spread(segments_of(keys, values)).items():
            print(f"{name:16s} {family:10s} {within:8.4f} {between:8.4f} {within / between:6.2f} "
                  f"{found:6.2f} (of {count})")
    theta = [np.array(r["truth"]["theta"]) for r in rows]
    print("pose retrieval by z_E (as `gdvae-node evaluate`: the true-pose distance to the nearest z_E among the "
          "family's other subjects over the median; 1 says nothing of the pose; the nearest true pose in brackets)")
    for name, values in z_e.items():
        for family, (ratio, floor) in pose_retrieval(keys, values, theta).items():
            print(f"{name:16s} {family:10s} {ratio:6.2f} ({floor:.2f})")
    print("z_E's spread over 1 s, walking / standing (ratio); the true pose's first")
    for name, values in [("true pose", theta), *z_e.items()]:
        walking, standing = pose_spread(keys, rows, values)
        print(f"{name:16s} {walking:8.3f} / {standing:8.3f} ({walking / standing:.2f})")


if __name__ == "__main__":
    main()
