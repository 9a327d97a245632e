"""A Python reference for the node's replay (docs/benchmarks.md): what a user might write
for the same job with the usual tools, measured on the same recordings, bundle, batch and threads.

    python bench/python_reference.py REC... [--config config/replay.toml] [--batch 8] [--threads 2]

Per frame: read the MCAP (mcap), decode the PointCloud2 x/y/z fields (numpy), sensor-to-gravity
transform and crop (numpy), the voxel grid's centroids (numpy, the node's `voxel_grid_m`), the
largest Euclidean cluster (scipy's cKDTree + connected components: the same clusters as the node's
`cluster_m`), farthest point sampling to N_p (numpy, vectorised), bounding-box centring and
scaling; then onnxruntime on batches of `--batch` frames, each frame turned into the node's
`yaw_copies` (the encoder sees batch x copies clouds, as the node's does). No fusion of the copies,
no tracking and no publishing: a lower bound on what the node's job costs in Python. Prints
frames/s from the first read to the last encoding, and the time per step.
"""

import argparse
import json
import pathlib
import time
import tomllib

import numpy as np
import onnxruntime as ort
from mcap.reader import make_reader

ROOT = pathlib.Path(__file__).resolve().parents[1]


def decode_xyz(data):
    """x, y, z (float32) of a CDR PointCloud2, read by its field table as numpy does it."""
    view = memoryview(data)
    at = 4

    def u32():
        nonlocal at
        at = (at - 4 + 3) // 4 * 4 + 4
        value = int.from_bytes(view[at:at + 4], "little")
        at += 4
        return value

    def string():
        nonlocal at
        n = u32()
        s = bytes(view[at:at + n - 1]).decode()
        at += n
        return s

    u32(), u32(), string()  # stamp, frame_id
    height, width = u32(), u32()
    offsets = {}
    for _ in range(u32()):
        name = string()
        offset = u32()
        at += 1  # datatype
        u32()  # count
        offsets[name] = offset
    at += 1  # is_bigendian
    point_step, _row_step = u32(), u32()
    n = u32()
    raw = np.frombuffer(view[at:at + n], dtype=np.uint8).reshape(height * width, point_step)
    xyz = np.stack([raw[:, offsets[a]:offsets[a] + 4].copy().view(np.float32)[:, 0] for a in "xyz"], -1)
    return xyz[np.isfinite(xyz).all(-1)]


def voxel_grid(points, edge):
    """The centroid of the points in each occupied cube of side `edge`, cubes in the order first met."""
    keys = np.floor(points / edge).astype(np.int64)
    _, first, inverse, counts = np.unique(keys, axis=0, return_index=True, return_inverse=True, return_counts=True)
    sums = np.zeros((len(first), 3), dtype=np.float64)
    np.add.at(sums, inverse.reshape(-1), points)
    centroids = (sums / counts[:, None]).astype(np.float32)
    return centroids[np.argsort(first)]


def turned(cloud, angle):
    c, s = np.cos(angle), np.sin(angle)
    return cloud @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float32).T


def largest_cluster(points, radius):
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    import scipy.sparse
    graph = scipy.sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    return points[labels == np.bincount(labels).argmax()]


def farthest_point_sampling(points, count, rng):
    if len(points) <= count:
        return points
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = rng.integers(len(points))
    nearest = np.full(len(points), np.inf, dtype=np.float32)
    for k in range(1, count):
        nearest = np.minimum(nearest, ((points - points[chosen[k - 1]]) ** 2).sum(-1))
        chosen[k] = nearest.argmax()
    return points[chosen]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recordings", nargs="+", type=pathlib.Path)
    parser.add_argument("--config", type=pathlib.Path, default=ROOT / "config/replay.toml")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    config = tomllib.loads(args.config.read_text())
    prepare = config["prepare"]
    bundle = (args.config.parent / config["model"]["bundle"]).resolve()
    manifest = json.loads((bundle / "manifest.json").read_text())
    n_p, scale = manifest["sizes"]["points"], manifest["units"]["model_units_per_metre"]
    rotation = np.array(prepare["sensor_to_gravity_rotation"], dtype=np.float32)
    translation = np.array(prepare["sensor_to_gravity_translation"], dtype=np.float32)
    low, high = np.array(prepare["crop"][:3]), np.array(prepare["crop"][3:])
    cluster_m = prepare.get("cluster_m", 0.0)
    voxel_grid_m = prepare.get("voxel_grid_m", 0.0)
    copies = config.get("model", {}).get("yaw_copies", 4)  # default.toml's default
    angles = [k * 2 * np.pi / copies for k in range(copies)]
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = args.threads, 1
    session = ort.InferenceSession(str(bundle / "encoder.onnx"), options, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    steps = dict.fromkeys(["read", "decode", "transform_crop", "voxel_grid", "cluster", "sampling", "encode"], 0.0)
    batch, frames = [], 0

    def encode():
        started = time.perf_counter()
        session.run(None, {"points": np.stack([turned(cloud, a) for cloud in batch for a in angles])})
        steps["encode"] += time.perf_counter() - started
        batch.clear()

    started = time.perf_counter()
    for recording in args.recordings:
        with open(recording, "rb") as f:
            tick = time.perf_counter()
            for _, channel, message in make_reader(f).iter_messages(topics=["/camera/depth/points"]):
                t0 = time.perf_counter()
                steps["read"] += t0 - tick
                points = decode_xyz(message.data)
                t1 = time.perf_counter()
                points = points @ rotation.T + translation
                points = points[((points >= low) & (points <= high)).all(-1)]
                t2 = time.perf_counter()
                if voxel_grid_m > 0:
                    points = voxel_grid(points, voxel_grid_m)
                t2v = time.perf_counter()
                if cluster_m > 0:
                    points = largest_cluster(points, cluster_m)
                t3 = time.perf_counter()
                chosen = farthest_point_sampling(points, n_p, rng)
                chosen = np.resize(chosen, (n_p, 3)) if len(chosen) < n_p else chosen
                centre = (chosen.min(0) + chosen.max(0)) / 2
                batch.append(((chosen - centre) * scale).astype(np.float32))
                t4 = time.perf_counter()
                steps["decode"] += t1 - t0
                steps["transform_crop"] += t2 - t1
                steps["voxel_grid"] += t2v - t2
                steps["cluster"] += t3 - t2v
                steps["sampling"] += t4 - t3
                frames += 1
                if len(batch) == args.batch:
                    encode()
                tick = time.perf_counter()
    if batch:
        encode()
    elapsed = time.perf_counter() - started
    print(json.dumps({
        "frames": frames, "seconds": elapsed, "frames_per_second": frames / elapsed,
        "ms_per_frame": {k: 1000 * v / frames for k, v in steps.items()},
        "batch": args.batch, "threads": args.threads, "yaw_copies": copies,
    }, indent=1))


if __name__ == "__main__":
    main()
