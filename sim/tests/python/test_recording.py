"""`sim record` output read back by independent tools: the `mcap` reader and the
`mcap-ros2-support` CDR decoder (the libraries Foxglove and rosbag2 users rely on).

The checks go beyond "it parses": the point cloud must be exactly the unprojection of the depth
image through the CameraInfo intrinsics, and, moved into the world with the recorded camera pose,
the subject's points must sit where the ground truth says the subject stands.
"""

import json
import subprocess

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import SIM

POINTS = "/camera/depth/points"
DEPTH = "/camera/depth/image_raw"
INFO = "/camera/depth/camera_info"
TRUTH = "/sim/ground_truth"


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "walk.mcap"
    subprocess.run(
        [SIM, "record", "--out", str(path), "--duration", "1", "--switch-at", "0.5",
         "--families", "quadruped,biped", "--decimation", "2", "--depth-images", "--seed", "5"],
        check=True, capture_output=True, timeout=300,
    )
    return path


def read_all(path):
    frames = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        header = reader.get_header()
        for schema, channel, message in reader.iter_messages():
            entry = frames.setdefault(message.log_time, {})
            if channel.topic == TRUTH:
                entry[TRUTH] = json.loads(message.data)
            else:
                entry[channel.topic] = DecoderFactory().decoder_for(channel.message_encoding, schema)(message.data)
    return header, summary, frames


def test_channels_schemas_and_counts(recording):
    header, summary, frames = read_all(recording)
    assert header.profile == "ros2"
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == {POINTS, DEPTH, INFO, TRUTH}
    expected = {POINTS: ("sensor_msgs/msg/PointCloud2", "ros2msg", "cdr"),
                DEPTH: ("sensor_msgs/msg/Image", "ros2msg", "cdr"),
                INFO: ("sensor_msgs/msg/CameraInfo", "ros2msg", "cdr"),
                TRUTH: ("gdvae_sim/GroundTruth", "jsonschema", "json")}
    for topic, (name, schema_encoding, message_encoding) in expected.items():
        channel = topics[topic]
        schema = summary.schemas[channel.schema_id]
        assert (schema.name, schema.encoding, channel.message_encoding) == (name, schema_encoding, message_encoding)
        assert summary.statistics.channel_message_counts[channel.id] == 30
    assert len(frames) == 30 and all(len(entry) == 4 for entry in frames.values())


def test_points_are_the_unprojected_depth_image(recording):
    _, _, frames = read_all(recording)
    for stamp, entry in frames.items():
        cloud, image, info, truth = entry[POINTS], entry[DEPTH], entry[INFO], entry[TRUTH]
        assert truth["stamp_nanos"] == stamp
        for message in (cloud, image, info):
            assert message.header.stamp.sec * 10**9 + message.header.stamp.nanosec == stamp
            assert message.header.frame_id == "camera_depth_optical_frame"
        assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
            ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]
        assert cloud.point_step == 12 and cloud.height == 1 and cloud.row_step == 12 * cloud.width
        points = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
        assert len(points) == cloud.width == truth["points"]

        assert (image.encoding, image.width, image.height, image.step) == ("16UC1", 640, 400, 1280)
        depth = np.frombuffer(bytes(image.data), dtype="<u2").reshape(400, 640)
        fx, _, cx, _, fy, cy, _, _, _ = info.k
        assert (fx, fy, cx, cy) == (441.25, 441.25, 319.5, 199.5)
        v, u = np.nonzero(depth[::2, ::2])
        z = depth[::2, ::2][v, u] / 1000.0
        expected = np.stack([(2 * u - cx) * z / fx, (2 * v - cy) * z / fy, z], axis=1)
        np.testing.assert_allclose(points, expected, atol=1e-5)


def test_subject_points_are_where_the_ground_truth_puts_the_subject(recording):
    _, _, frames = read_all(recording)
    subjects = []
    for entry in frames.values():
        truth = entry[TRUTH]
        pose = truth["world_from_camera"]
        x, y, z, w = pose["rotation_xyzw"]
        rotation = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        points = np.frombuffer(bytes(entry[POINTS].data), dtype="<f4").reshape(-1, 3).astype(float)
        world = points @ rotation.T + np.array(pose["translation"])
        ground = np.abs(world[:, 2]) < 0.03
        assert ground.mean() > 0.3, "most points are on the ground plane z = 0"
        above = world[world[:, 2] > 0.1]
        assert len(above) > 500
        centre = np.median(above[:, :2], axis=0)
        assert np.linalg.norm(centre - np.array(truth["translation"][:2])) < 0.35
        subjects.append((truth["subject"], truth["family"], tuple(truth["beta"])))
    assert len(set(subjects)) == 2, "one identity switch"
    assert [s[1] for s in subjects[:15]] == ["quadruped"] * 15
    assert [s[1] for s in subjects[15:]] == ["biped"] * 15
