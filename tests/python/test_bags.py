"""Bags a ROS user owns, written by `rosbags` (not by the project): the sample recording's point
clouds re-serialised by rosbags into a rosbag2 bag in each storage (sqlite3, Humble's default, and
mcap) replay through the real `gdvae-node` binary to the same states as the original recording; a
cut MCAP replays its complete prefix and counts the rest; a bag with an unknown storage plugin or a
damaged database is a clear error naming the file."""

import json
import subprocess

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from node_paths import NODE, ROOT

SAMPLE = ROOT / "sim/samples/walk_switch.mcap"
POINTS = "/camera/depth/points"
CLOUD = "sensor_msgs/msg/PointCloud2"


def write_bag(folder, storage):
    """The sample's point clouds, deserialised and serialised again by rosbags, into a rosbag2 bag."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    reader = make_reader(open(SAMPLE, "rb"))
    count = 0
    with Writer(folder, version=8 if storage == StoragePlugin.SQLITE3 else 9, storage_plugin=storage) as writer:
        connection = writer.add_connection(POINTS, CLOUD, typestore=store)
        for _, channel, message in reader.iter_messages(topics=[POINTS]):
            cloud = store.deserialize_cdr(message.data, CLOUD)
            writer.write(connection, message.log_time, store.serialize_cdr(cloud, CLOUD))
            count += 1
    return count


def replay(path, tmp_path, name):
    """States of `gdvae-node replay` (every timing field removed), the process's result."""
    out = tmp_path / f"{name}.jsonl"
    config = tmp_path / "replay.toml"
    config.write_text((ROOT / "config/replay.toml").read_text().replace(
        'bundle = "../models/', f'bundle = "{ROOT / "models"}/'))  # the shipped bundle
    result = subprocess.run([NODE, "replay", str(path), "--config", str(config), "--speed", "0",
                             "--jsonl", str(out), "--no-baseline", "--json"],
                            capture_output=True, text=True, timeout=300)
    states = []
    if out.exists():
        for line in out.read_text().splitlines():
            state = json.loads(line)
            if "stamps" in state:
                state["stamps"] = {"sensor_ns": state["stamps"].get("sensor_ns")}
            state.pop("latency", None)
            state.pop("stream", None)
            states.append(state)
    return states, result


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("original")
    states, result = replay(SAMPLE, tmp, "original")
    assert result.returncode == 0, result.stderr
    return states


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_a_rosbags_bag_replays_to_the_same_states_as_the_recording(tmp_path, original, storage):
    bag = tmp_path / "bag"
    written = write_bag(bag, storage)
    states, result = replay(bag, tmp_path, "bag")
    assert result.returncode == 0, result.stderr
    assert written == sum(s["schema"] == "gdvae.state/2" for s in states) == 150
    assert states == original, "the same states and identity events"


def test_a_cut_mcap_bag_replays_its_complete_prefix_and_counts_the_rest(tmp_path, original):
    bag = tmp_path / "bag"
    write_bag(bag, StoragePlugin.MCAP)
    (mcap_file,) = bag.glob("*.mcap")
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: int(len(data) * 0.6)])
    states, result = replay(bag, tmp_path, "cut")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    counters = report["counters"]["streams"]["bag"]
    assert 0 < len(states) < len(original)
    published = sum(s["schema"] == "gdvae.state/2" for s in states)
    assert counters["published"] == published
    assert counters["rejected"] == {"source": 1}, "the cut rest is one counted rejection"
    assert counters["received"] == published + 1
    assert "rest of file skipped" in result.stderr
    # The complete prefix is exactly what the whole recording gives for those frames.
    assert states[-1]["schema"] == "gdvae.rejected/1"
    assert states[:-1] == original[: len(states) - 1]


def test_an_unknown_storage_plugin_is_an_error_naming_the_metadata(tmp_path):
    bag = tmp_path / "bag"
    write_bag(bag, StoragePlugin.SQLITE3)
    metadata = bag / "metadata.yaml"
    metadata.write_text(metadata.read_text().replace("storage_identifier: sqlite3", "storage_identifier: rosbag_v2"))
    _, result = replay(bag, tmp_path, "unknown")
    assert result.returncode != 0
    assert str(metadata) in result.stderr and "storage plugin 'rosbag_v2' is not supported" in result.stderr


def test_a_damaged_database_is_an_error_naming_the_file(tmp_path):
    bag = tmp_path / "bag"
    write_bag(bag, StoragePlugin.SQLITE3)
    (database,) = bag.glob("*.db3")
    data = bytearray(database.read_bytes())
    # Keep the 100-byte header's magic, damage the page size and the schema page.
    data[16:4096] = b"\xff" * (4096 - 16)
    database.write_bytes(bytes(data))
    _, result = replay(bag, tmp_path, "damaged")
    assert result.returncode != 0
    assert str(database) in result.stderr, result.stderr
