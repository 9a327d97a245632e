"""Live feeds on loopback zenoh: `sim feed` (ROS 2 CDR point clouds + JSON ground truth) and the
DepthAI harness (DepthAI's own host PointCloud node), each received by a real zenoh subscriber."""

import json
import os
import queue
import subprocess
import sys

import numpy as np
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from conftest import ROOT, SIM

POINT_CLOUD2_MSG = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
    "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    "================================================================================\n"
    "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    "================================================================================\n"
    "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    "================================================================================\n"
    "MSG: sensor_msgs/PointField\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n"
)
TIMEOUT = 120


def collect(session, key):
    samples = queue.Queue()
    subscriber = session.declare_subscriber(key, lambda s: samples.put(
        (str(s.key_expr), str(s.encoding), bytes(s.payload.to_bytes()),
         None if s.attachment is None else bytes(s.attachment.to_bytes()))))
    return subscriber, samples


def drain(samples):
    out = []
    while not samples.empty():
        out.append(samples.get())
    return out


def test_sim_feed_reaches_a_loopback_subscriber(zenoh_listener):
    session, endpoint = zenoh_listener
    points_sub, points = collect(session, "test/feed/points")
    truth_sub, truths = collect(session, "test/feed/ground_truth")
    run = subprocess.run(
        [SIM, "feed", "--key-prefix", "test/feed", "--connect", endpoint, "--no-multicast",
         "--wait-for-subscriber", "20", "--duration", "1", "--decimation", "4", "--seed", "3"],
        capture_output=True, text=True, timeout=TIMEOUT)
    assert run.returncode == 0, run.stderr
    assert "published 30 frames" in run.stdout
    import time
    time.sleep(0.5)  # the last samples are in flight when the publisher exits
    clouds, truth = drain(points), drain(truths)
    points_sub.undeclare()
    truth_sub.undeclare()
    assert len(clouds) == 30 and len(truth) == 30

    decode = DecoderFactory().decoder_for("cdr", Schema(
        id=1, name="sensor_msgs/msg/PointCloud2", encoding="ros2msg", data=POINT_CLOUD2_MSG.encode()))
    for (key, encoding, payload, _), (_, truth_encoding, truth_payload, _) in zip(clouds, truth):
        assert key == "test/feed/points"
        assert encoding == "application/cdr;sensor_msgs/msg/PointCloud2"
        assert truth_encoding == "application/json"
        cloud = decode(payload)
        gt = json.loads(truth_payload)
        assert cloud.header.stamp.sec * 10**9 + cloud.header.stamp.nanosec == gt["stamp_nanos"]
        assert cloud.width == gt["points"] > 1000
        xyz = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
        assert np.isfinite(xyz).all() and (xyz[:, 2] > 0.3).all()
    assert [json.loads(t[2])["frame"] for t in truth] == list(range(30))


def test_depthai_harness_publishes_depthai_point_clouds(zenoh_listener, tmp_path):
    session, endpoint = zenoh_listener
    recording = tmp_path / "depth.mcap"
    subprocess.run([SIM, "record", "--out", str(recording), "--duration", "0.5", "--depth-images", "--seed", "4"],
                   check=True, capture_output=True, timeout=TIMEOUT)
    subscriber, samples = collect(session, "test/depthai/points")
    run = subprocess.run(
        [sys.executable, str(ROOT / "sim" / "depthai_feed.py"), "--mcap", str(recording), "--rate", "0",
         "--prefix", "test/depthai", "--connect", endpoint, "--no-multicast", "--wait-for-subscriber", "20"],
        capture_output=True, text=True, timeout=TIMEOUT)
    assert run.returncode == 0, run.stderr
    import time
    time.sleep(0.5)
    received = drain(samples)
    subscriber.undeclare()
    assert len(received) == 15

    # The same frames as the recording's own PointCloud2 channel, in millimetres.
    expected = []
    with open(recording, "rb") as f:
        for _, _, _, cloud in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/camera/depth/points"]):
            expected.append(np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3))
    for (_, encoding, payload, attachment), metres in zip(received, expected):
        assert encoding == "application/octet-stream;depthai/PointCloudData;xyz_f32_mm"
        meta = json.loads(attachment)
        millimetres = np.frombuffer(payload, dtype="<f4").reshape(-1, 3)
        assert meta["unit"] == "mm" and meta["points"] == len(millimetres) == len(metres)
        order = np.lexsort(millimetres.T)
        np.testing.assert_allclose(millimetres[order] / 1000.0, metres[np.lexsort(metres.T)], atol=2e-4)


def test_depthai_harness_converts_a_live_sim_feed(zenoh_listener):
    """sim feed --depth-images -> depthai_feed.py --from-prefix -> subscriber, all on loopback."""
    from conftest import free_port

    session, endpoint = zenoh_listener
    subscriber, samples = collect(session, "test/live/points")
    harness_endpoint = f"tcp/127.0.0.1:{free_port()}"
    harness = subprocess.Popen(
        [sys.executable, str(ROOT / "sim" / "depthai_feed.py"), "--from-prefix", "test/oak", "--prefix", "test/live",
         "--listen", harness_endpoint, "--connect", endpoint, "--no-multicast", "--frames", "10"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        feed = subprocess.run(
            [SIM, "feed", "--key-prefix", "test/oak", "--depth-images", "--connect", harness_endpoint,
             "--no-multicast", "--wait-for-subscriber", "30", "--duration", "1", "--seed", "6"],
            capture_output=True, text=True, timeout=TIMEOUT)
        assert feed.returncode == 0, feed.stderr
        out, err = harness.communicate(timeout=TIMEOUT)
        assert harness.returncode == 0, err
    finally:
        harness.kill()
    import time
    time.sleep(0.5)
    received = drain(samples)
    subscriber.undeclare()
    assert len(received) == 10, out
    for _, encoding, payload, attachment in received:
        millimetres = np.frombuffer(payload, dtype="<f4").reshape(-1, 3)
        assert json.loads(attachment)["points"] == len(millimetres) > 50_000
        assert (millimetres[:, 2] > 300).all() and (millimetres[:, 2] < 10_000).all()
