"""The Foxglove live view (`[publish.foxglove]`) seen by a client of the Foxglove WebSocket protocol
(subprotocol foxglove.sdk.v1, written here with `websockets`; protobuf messages decoded with the schema
the server advertises): the advertised channels and schemas, and messages whose contents are the
JSON states' (pose, identity)."""

import asyncio
import base64
import json
import math
import signal
import struct
import subprocess
import time

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from node_paths import NODE, ROOT, free_port, objects_settings, sample_settings

TOPICS = {"/gdvae/cam/state": "gdvae.state/2", "/gdvae/cam/transform": "foxglove.FrameTransform",
          "/gdvae/cam/input": "foxglove.PointCloud", "/gdvae/cam/points": "foxglove.PointCloud",
          "/gdvae/cam/shape": "foxglove.PointCloud", "/gdvae/cam/scene": "foxglove.SceneUpdate"}


def decoder(channel):
    """A function from a message's bytes to its contents, by the channel's advertised schema."""
    if channel["encoding"] == "json":
        return json.loads
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"])).FromString


def xyz_of(cloud):
    """A foxglove.PointCloud's points (x, y, z float32 at stride 12) as tuples."""
    assert [f.name for f in cloud.fields] == ["x", "y", "z"] and cloud.point_stride == 12
    xyz = struct.unpack(f"<{len(cloud.data) // 4}f", cloud.data)
    return [xyz[i:i + 3] for i in range(0, len(xyz), 3)]


async def watch(port, wanted, topics=TOPICS):
    """Connects, subscribes to `topics`, and collects `wanted` messages of each."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                  max_size=None) as ws:
        channels, received = {}, {topic: [] for topic in topics}
        subscribed = {}
        while min(len(v) for v in received.values()) < wanted:
            message = await asyncio.wait_for(ws.recv(), timeout=30)
            if isinstance(message, str):
                op = json.loads(message)
                if op["op"] == "advertise":
                    channels.update({c["topic"]: c for c in op["channels"]})
                    todo = [t for t in topics if t in channels and t not in subscribed.values()]
                    if todo:
                        subscriptions = [{"id": len(subscribed) + i, "channelId": channels[t]["id"]}
                                         for i, t in enumerate(todo)]
                        subscribed.update({s["id"]: t for s, t in zip(subscriptions, todo)})
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            elif message[0] == 1:  # message data: subscription id, log time, payload
                subscription, log_time = struct.unpack_from("<IQ", message, 1)
                topic = subscribed[subscription]
                received[topic].append((log_time, decoder(channels[topic])(message[13:])))
        return channels, received


def test_a_foxglove_client_receives_the_states_the_object_frame_the_clouds_and_the_scene(tmp_path):
    port, jsonl = free_port(), tmp_path / "states.jsonl"
    config = tmp_path / "node.toml"
    config.write_text(f"""{sample_settings()}
[publish]
zenoh = false
jsonl = "{jsonl}"
[publish.foxglove]
enabled = true
port = {port}
[[source]]
stream = "cam"
kind = "mcap"
path = "{ROOT / 'sim/samples/walk_switch.mcap'}"
speed = 1.0
repeat = true
""")
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                channels, received = asyncio.run(watch(port, 20))
                break
            except OSError:
                assert time.monotonic() < deadline and node.poll() is None, node.stderr.read().decode()
                time.sleep(0.2)
        node.send_signal(signal.SIGINT)
        _, err = node.communicate(timeout=60)
        assert node.returncode == 0, err.decode()
    finally:
        if node.poll() is None:
            node.kill()
    for topic, schema in TOPICS.items():
        assert channels[topic]["schemaName"] == schema
        assert channels[topic]["encoding"] == ("json" if topic.endswith("/state") else "protobuf")
    states = {s["stamps"]["sensor_ns"]: s for s in map(json.loads, jsonl.read_text().splitlines())
              if s["schema"] == "gdvae.state/2"}
    # The live states are the published ones.
    for _, state in received["/gdvae/cam/state"]:
        assert state == states[state["stamps"]["sensor_ns"]]
    # The object's frame: at the estimated centre, turned by the filtered heading.
    for _, transform in received["/gdvae/cam/transform"]:
        stamp = transform.timestamp.seconds * 1_000_000_000 + transform.timestamp.nanos
        state = states[stamp]
        assert (transform.parent_frame_id, transform.child_frame_id) == ("gravity", "gdvae/cam")
        centre = [transform.translation.x, transform.translation.y, transform.translation.z]
        assert all(abs(a - b) < 1e-5 for a, b in zip(centre, state["centre_m"]))
        yaw = state["filtered"]["yaw"]
        assert abs(transform.rotation.z - math.sin(yaw / 2)) < 1e-5
    # The points the encoder saw: N_p of them in metres in the gravity frame, their box centred on
    # the state's centre (the prepare step centres on the bounding box).
    for _, cloud in received["/gdvae/cam/points"]:
        stamp = cloud.timestamp.seconds * 1_000_000_000 + cloud.timestamp.nanos
        state = states[stamp]
        assert cloud.frame_id == "gravity" and cloud.point_stride == 12
        assert [f.name for f in cloud.fields] == ["x", "y", "z"]
        points = xyz_of(cloud)
        assert len(points) == 256
        for axis in range(3):
            low, high = min(p[axis] for p in points), max(p[axis] for p in points)
            assert abs((low + high) / 2 - state["centre_m"][axis]) < 1e-3
            assert 0.05 < high - low < 3.0, "an object's size in metres"
    # The input cloud, decimated to at most [publish.view] input_points, in the gravity frame: the
    # object's centre lies inside its box.
    for _, cloud in received["/gdvae/cam/input"]:
        state = states[cloud.timestamp.seconds * 1_000_000_000 + cloud.timestamp.nanos]
        points = xyz_of(cloud)
        assert cloud.frame_id == "gravity" and 500 < len(points) <= 2048
        for axis in range(3):
            assert min(p[axis] for p in points) - 1e-3 <= state["centre_m"][axis] <= max(p[axis] for p in points) + 1e-3
    # The decoded shape: placed at the estimated centre and rotation, an object's size.
    for _, cloud in received["/gdvae/cam/shape"]:
        state = states[cloud.timestamp.seconds * 1_000_000_000 + cloud.timestamp.nanos]
        position, q = cloud.pose.position, cloud.pose.orientation
        assert all(abs(a - b) < 1e-5 for a, b in zip([position.x, position.y, position.z], state["centre_m"]))
        assert all(abs(a - b) < 1e-5 for a, b in zip([q.w, q.x, q.y, q.z], state["filtered"]["q"]))
        points = xyz_of(cloud)
        assert len(points) >= 256
        assert 0.05 < max(max(p) - min(p) for p in zip(*points)) < 3.0, "an object's size in metres"
    # The scene: a heading arrow and the identity's label in that frame.
    for _, scene in received["/gdvae/cam/scene"]:
        entity = scene.entities[0]
        stamp = entity.timestamp.seconds * 1_000_000_000 + entity.timestamp.nanos
        assert entity.frame_id == "gdvae/cam" and len(entity.arrows) == 1
        assert f"identity {states[stamp]['shape']['identity']} " in entity.texts[0].text


def test_with_several_objects_each_track_has_its_own_channels_and_frame(tmp_path):
    """`[track.objects] enabled` on the two-subject sample: each track's view on channels of its own
    (`/gdvae/<stream>/<track>/...`, advertised when the track appears), its own object frame and
    scene entity, at its state's centre."""
    head, source = objects_settings()
    port, jsonl = free_port(), tmp_path / "states.jsonl"
    config = tmp_path / "node.toml"
    config.write_text(f"""{head}
[publish]
zenoh = false
jsonl = "{jsonl}"
[publish.foxglove]
enabled = true
port = {port}
{source}
""")
    topics = [f"/gdvae/two/{track}/{what}" for track in (1, 2) for what in ("transform", "scene", "points")]
    topics.append("/gdvae/two/input")
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                channels, received = asyncio.run(watch(port, 8, topics))
                break
            except OSError:
                assert time.monotonic() < deadline and node.poll() is None, node.stderr.read().decode()
                time.sleep(0.2)
        _, err = node.communicate(timeout=60)
        assert node.returncode == 0, err.decode()
    finally:
        if node.poll() is None:
            node.kill()
    states = {(s["stamps"]["sensor_ns"], s["track"]): s for s in map(json.loads, jsonl.read_text().splitlines())
              if s["schema"] == "gdvae.state/2"}
    for track in (1, 2):
        for _, transform in received[f"/gdvae/two/{track}/transform"]:
            stamp = transform.timestamp.seconds * 1_000_000_000 + transform.timestamp.nanos
            state = states[(stamp, track)]
            assert (transform.parent_frame_id, transform.child_frame_id) == ("gravity", f"gdvae/two/{track}")
            centre = [transform.translation.x, transform.translation.y, transform.translation.z]
            assert all(abs(a - b) < 1e-5 for a, b in zip(centre, state["centre_m"]))
        for _, scene in received[f"/gdvae/two/{track}/scene"]:
            (entity,) = scene.entities
            assert entity.id == f"two/{track}" and entity.frame_id == f"gdvae/two/{track}"
        assert channels[f"/gdvae/two/{track}/points"]["schemaName"] == "foxglove.PointCloud"
    # The input cloud is the stream's, once a frame, on the stream's channel.
    inputs = received["/gdvae/two/input"]
    assert inputs and all(500 < len(xyz_of(cloud)) <= 2048 for _, cloud in inputs)
