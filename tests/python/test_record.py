"""A run's results as an MCAP recording (`--record` / `[publish] mcap`), read back by the `mcap`
package: a channel per stream and kind with its schema, every state as JSON, the same states as
the JSON lines, and the view of each state in Foxglove's protobuf schemas (decoded with the
descriptors the file carries); and a node killed mid-run leaves a file that a streaming reader
reads up to its last complete chunk."""

import json
import signal
import subprocess
import time

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from node_paths import NODE, ROOT, sample_settings

SAMPLE = ROOT / "sim/samples/walk_switch.mcap"
VIEW = {"transform": "foxglove.FrameTransform", "input": "foxglove.PointCloud", "points": "foxglove.PointCloud",
        "shape": "foxglove.PointCloud", "scene": "foxglove.SceneUpdate"}


def protobuf_decoder(schema):
    """A function from a message's bytes to its contents, by the FileDescriptorSet in the file."""
    assert schema.encoding == "protobuf"
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString


def test_a_replay_recorded_to_mcap_holds_every_state_on_its_stream_channel(tmp_path):
    recording, jsonl = tmp_path / "run.mcap", tmp_path / "run.jsonl"
    subprocess.run([NODE, "-q", "replay", str(SAMPLE), "--config", str(ROOT / "config/replay.toml"),
                    "--no-baseline", "--record", str(recording), "--jsonl", str(jsonl)],
                   check=True, capture_output=True, timeout=300)
    lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
    reader = make_reader(open(recording, "rb"))
    summary = reader.get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    view = {f"/gdvae/walk_switch/{kind}": schema for kind, schema in VIEW.items()}
    assert set(channels) == {"/gdvae/walk_switch/state", "/gdvae/walk_switch/events", *view}, set(channels)
    for topic, schema in [("/gdvae/walk_switch/state", "gdvae.state/2"), ("/gdvae/walk_switch/events", "gdvae.event/1")]:
        assert channels[topic].message_encoding == "json"
        assert summary.schemas[channels[topic].schema_id].name == schema
        assert summary.schemas[channels[topic].schema_id].encoding == "jsonschema"
    decoders = {}
    for topic, schema in view.items():
        assert channels[topic].message_encoding == "protobuf"
        assert summary.schemas[channels[topic].schema_id].name == schema
        decoders[topic] = protobuf_decoder(summary.schemas[channels[topic].schema_id])
    recorded = [(channel.topic, decoders.get(channel.topic, json.loads)(message.data), message)
                for _, channel, message in reader.iter_messages()]
    states = [m for t, m, _ in recorded if t.endswith("/state")]
    assert states == [l for l in lines if l["schema"] == "gdvae.state/2"]
    assert len(states) == 150
    events = [m for t, m, _ in recorded if t.endswith("/events")]
    assert [e["event"]["identity"] for e in events] == [1], "the sample's one subject change"
    # The view: every state's frame, scene, input cloud and encoder points; the decoded shape once
    # the first is decoded (off the pipeline's path), at the state's centre.
    by_stamp = {s["stamps"]["sensor_ns"]: s for s in states}
    seen = {kind: [m for t, m, _ in recorded if t == f"/gdvae/walk_switch/{kind}"] for kind in VIEW}
    for kind in ["transform", "input", "points", "scene"]:
        assert len(seen[kind]) == 150, (kind, len(seen[kind]))
    assert 100 <= len(seen["shape"]) <= 150, len(seen["shape"])
    for shape in seen["shape"]:
        state = by_stamp[shape.timestamp.seconds * 1_000_000_000 + shape.timestamp.nanos]
        assert abs(shape.pose.position.x - state["centre_m"][0]) < 1e-5
        assert len(shape.data) >= 256 * 12
    assert all(0 < len(c.data) <= 2048 * 12 for c in seen["input"])
    # Log time is when the node published; publish time the sensor's stamp.
    first = recorded[0]
    assert first[2].log_time == first[1]["stamps"]["publish_ns"]
    assert first[2].publish_time == first[1]["stamps"]["sensor_ns"]


def test_a_node_killed_mid_run_leaves_a_recording_readable_up_to_its_last_chunk(tmp_path):
    recording = tmp_path / "killed.mcap"
    config = tmp_path / "node.toml"
    config.write_text(f"""{sample_settings()}
[publish]
zenoh = false
mcap = "{recording}"
[[source]]
stream = "cam"
kind = "mcap"
path = "{SAMPLE}"
speed = 1.0
repeat = true
""")
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        time.sleep(5.0)
        assert node.poll() is None, node.stderr.read().decode()
        node.send_signal(signal.SIGKILL)
        node.wait(timeout=30)
    finally:
        if node.poll() is None:
            node.kill()
    messages, topics, error = [], {}, None
    try:
        for record in StreamReader(open(recording, "rb")).records:
            if isinstance(record, Channel):
                topics[record.id] = record.topic
            if isinstance(record, Message):
                messages.append(record)
    except Exception as e:  # the chunk the kill cut short
        error = e
    decoded = [(m, json.loads(m.data)) for m in messages if topics[m.channel_id] == "/gdvae/cam/state"]
    states = [(m, d) for m, d in decoded if d["schema"] == "gdvae.state/2"]
    # 30 frames a second for about 5 s, less start-up and at most the last second's chunk.
    assert len(states) >= 60, (len(states), error)
    assert [d["sequence"] for _, d in states] == list(range(len(states))), "every state up to the cut, in order"
    assert [m.sequence for m, _ in states] == list(range(1, len(states) + 1))
