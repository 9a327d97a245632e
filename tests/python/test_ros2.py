"""The node as a ROS 2 node over rmw_zenoh, checked with independent tools and no ROS install:
`eclipse-zenoh` (liveliness, exact keys, attachments, `zenoh.ext` serialisation), `rosbags`
(Jazzy's message definitions, CDR and RIHS01 type hashes) and `xxhash` (publisher GIDs).

The real `gdvae-node` binary replays the sample recording with `[publish.ros2]` on. Every
liveliness token must parse by rmw_zenoh's rules (liveliness_utils.cpp); every data sample must
arrive on the exact key a ROS 2 subscriber of its type uses, carry the 33-byte attachment with
sequence numbers 1, 2, 3 ... and a constant GID, and deserialise with rosbags and re-serialise
byte for byte; its values must equal the JSON state's; after SIGTERM every token is withdrawn."""

import json
import signal
import struct
import subprocess
import time

import xxhash
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from node_paths import NODE, ROOT, client, free_port, objects_settings, sample_settings

STORE = get_typestore(Stores.ROS2_JAZZY)
# vision_msgs 4.1.1 (Jazzy's; github.com/ros-perception/vision_msgs, branch ros2, e77fa2d), which
# rosbags' store lacks: the definitions, comments stripped.
STORE.register({k: v for name, text in {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose":
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox3D bbox\nstring id\n",
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}.items() for k, v in get_types_from_msg(text, name).items()})
NAMESPACE = "/robot/gdvae"
NODE_NAME = "edge_node"
STREAM = "sample"
DOMAIN = 3

# What a ROS 2 user would subscribe to, and the type ros2 topic echo would use.
TOPICS = {
    f"{NAMESPACE}/{STREAM}/pose": "geometry_msgs/msg/PoseStamped",
    f"{NAMESPACE}/{STREAM}/markers": "visualization_msgs/msg/MarkerArray",
    f"{NAMESPACE}/{STREAM}/detections": "vision_msgs/msg/Detection3DArray",
    f"{NAMESPACE}/{STREAM}/z_e": "std_msgs/msg/Float32MultiArray",
    f"{NAMESPACE}/{STREAM}/z_i": "std_msgs/msg/Float32MultiArray",
    f"{NAMESPACE}/{STREAM}/state": "std_msgs/msg/String",
    "/tf": "tf2_msgs/msg/TFMessage",
}


def dds_name(msgtype):
    package, _, name = msgtype.split("/")
    return f"{package}::msg::dds_::{name}_"


def ros_key(topic, msgtype):
    """The key rmw_zenoh's subscriber of `msgtype` on `topic` subscribes to (TopicInfo)."""
    return f"{DOMAIN}/{topic.strip('/')}/{dds_name(msgtype)}/{STORE.hash_rihs01(msgtype)}"


def parse_token(key):
    """A liveliness token parsed as rmw_zenoh's Entity::make does; raises on what it would reject."""
    parts = key.split("/")
    assert parts[0] == "@ros2_lv", key
    assert len(parts) >= 9, f"fewer than 9 parts: {key}"
    assert all(parts), f"an empty part: {key}"
    entity = {"domain": int(parts[1]), "zid": parts[2], "nid": parts[3], "id": parts[4], "kind": parts[5],
              "enclave": parts[6].replace("%", "/"), "namespace": parts[7].replace("%", "/"),
              "node": parts[8].replace("%", "/")}
    assert entity["kind"] in ("NN", "MP", "MS", "SS", "SC"), key
    int(entity["nid"]), int(entity["id"])
    int(entity["zid"], 16)
    if entity["kind"] != "NN":
        assert len(parts) >= 13, f"an entity token needs 13 parts: {key}"
        entity.update(topic=parts[9].replace("%", "/"), type=parts[10], hash=parts[11], qos=parts[12])
        # reliability:durability:history,depth:deadline_s,ns:lifespan_s,ns:liveliness,lease_s,ns
        qos = parts[12].split(":")
        assert len(qos) == 6, f"QoS needs 6 fields: {parts[12]}"
        assert qos[0] in ("", "1", "2") and qos[1] in ("", "1", "2"), parts[12]
        history, depth = qos[2].split(",")
        assert history in ("", "1", "2") and (depth == "" or int(depth) > 0), parts[12]
        assert len(qos[3].split(",")) == 2 and len(qos[4].split(",")) == 2, parts[12]
        assert len(qos[5].split(",")) == 3, parts[12]
    return entity


def write_config(tmp_path, endpoint):
    config = tmp_path / "node.toml"
    config.write_text(f"""
[node]
name = "ros"
{sample_settings()}
[publish]
zenoh = false
[publish.ros2]
enabled = true
domain_id = {DOMAIN}
namespace = "{NAMESPACE}"
node_name = "{NODE_NAME}"
frame_id = "world"
shape_rate_hz = 5.0
[zenoh]
listen = ["{endpoint}"]
multicast_scouting = false
[[source]]
stream = "{STREAM}"
kind = "mcap"
path = "{ROOT / 'sim/samples/walk_switch.mcap'}"
repeat = true
""")
    return config


def test_ros2_output_follows_rmw_zenoh_and_round_trips_through_rosbags(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(write_config(tmp_path, endpoint))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    samples = {topic: [] for topic in TOPICS}
    token_events = []
    try:
        with client(endpoint) as session:
            # The node and its publishers, as `ros2 node list` / `ros2 topic list` find them.
            deadline = time.monotonic() + 60
            tokens = []
            while time.monotonic() < deadline and len(tokens) < 2 + len(TOPICS):
                tokens = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=2.0)
                          if r.ok is not None]
                time.sleep(0.2)
            watcher = session.liveliness().declare_subscriber(
                "@ros2_lv/**", lambda s: token_events.append((str(s.kind), str(s.key_expr))))
            subscribers = [session.declare_subscriber(ros_key(topic, msgtype),
                                                      lambda s, t=topic: samples[t].append(s))
                           for topic, msgtype in TOPICS.items()]
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and min(len(v) for v in samples.values()) < 40:
                time.sleep(0.05)
            for s in subscribers:
                s.undeclare()
            # A TF listener that starts now (as rviz2's, TRANSIENT_LOCAL over rmw_zenoh: an
            # AdvancedSubscriber asking the publishers' caches) still receives /tf_static.
            static = zenoh.ext.declare_advanced_subscriber(
                session, ros_key("/tf_static", "tf2_msgs/msg/TFMessage"),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=100),
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
            deadline, tf_static = time.monotonic() + 30, None
            while tf_static is None and time.monotonic() < deadline:
                tf_static = static.try_recv()
                time.sleep(0.05)
            assert tf_static is not None, "/tf_static reaches a listener that joined late"
            node.send_signal(signal.SIGTERM)
            out, err = node.communicate(timeout=30)
            assert node.returncode == 0, err.decode()
            time.sleep(1.0)
            after = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=2.0)
                     if r.ok is not None]
            watcher.undeclare()
    finally:
        if node.poll() is None:
            node.kill()

    entities = [parse_token(t) for t in tokens]
    nodes = [e for e in entities if e["kind"] == "NN"]
    assert len(nodes) == 1 and nodes[0]["namespace"] == NAMESPACE and nodes[0]["node"] == NODE_NAME
    assert nodes[0]["domain"] == DOMAIN and nodes[0]["enclave"] == "/"
    publishers = {e["topic"]: e for e in entities if e["kind"] == "MP"}
    for topic, msgtype in TOPICS.items():
        publisher = publishers[topic]
        assert publisher["type"] == dds_name(msgtype) and publisher["hash"] == STORE.hash_rihs01(msgtype)
        assert publisher["zid"] == nodes[0]["zid"] and publisher["nid"] == nodes[0]["nid"]
    assert publishers["/tf"]["qos"] == "::,100:,:,:,,", "tf2's broadcaster QoS: reliable, volatile, keep last 100"
    assert publishers["/tf_static"]["qos"] == ":1:,1:,:,:,,", "tf2's static broadcaster: transient local, keep last 1"
    assert publishers["/tf_static"]["type"] == dds_name("tf2_msgs/msg/TFMessage")
    ids = [e["id"] for e in entities]
    assert len(set(ids)) == len(ids), "entity ids are unique in the session"

    token_of = {e["topic"]: t for e, t in zip(entities, tokens) if e["kind"] == "MP"}
    for topic, msgtype in TOPICS.items():
        received = samples[topic]
        assert len(received) >= 40, f"{topic}: {len(received)} samples"
        sequences, gids = [], set()
        for sample in received:
            attachment = sample.attachment.to_bytes()
            assert len(attachment) == 33, f"{topic}: attachment of {len(attachment)} bytes"
            sequence, stamp = struct.unpack_from("<qq", attachment)
            gid = attachment[17:]
            # zenoh-ext's own serialiser gives exactly these bytes.
            assert zenoh.ext.z_serialize((zenoh.ext.Int64(sequence), zenoh.ext.Int64(stamp), gid)).to_bytes() \
                == attachment
            assert abs(stamp / 1e9 - time.time()) < 120
            sequences.append(sequence)
            gids.add(gid)
            payload = sample.payload.to_bytes()
            message = STORE.deserialize_cdr(payload, msgtype)
            assert bytes(STORE.serialize_cdr(message, msgtype)) == payload, f"{topic}: CDR round trip"
        assert sequences == list(range(sequences[0], sequences[0] + len(sequences))), topic
        assert len(gids) == 1, f"{topic}: one GID"
        digest = xxhash.xxh3_128_intdigest(token_of[topic].encode())
        expected = (digest & (2**64 - 1)).to_bytes(8, "little") + (digest >> 64).to_bytes(8, "little")
        assert gids == {expected}, f"{topic}: GID is the XXH3-128 of its token"
        assert str(received[0].encoding) == "zenoh/bytes", "rmw_zenoh sets no encoding"

    # The values are the JSON state's, matched by header stamp.
    states = {}
    for sample in samples[f"{NAMESPACE}/{STREAM}/state"]:
        state = json.loads(STORE.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String").data)
        states[state["stamps"]["sensor_ns"]] = state

    def with_states(what, msgtype):
        """The messages on <namespace>/<stream>/<what> whose header stamp is a state's, with it."""
        for sample in samples[f"{NAMESPACE}/{STREAM}/{what}"]:
            message = STORE.deserialize_cdr(sample.payload.to_bytes(), msgtype)
            state = states.get(message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec)
            if state is not None:
                yield message, state

    matched = 0
    for pose, state in with_states("pose", "geometry_msgs/msg/PoseStamped"):
        matched += 1
        assert pose.header.frame_id == "world"
        assert [pose.pose.position.x, pose.pose.position.y, pose.pose.position.z] == \
            [float(v) for v in struct.unpack("<3f", struct.pack("<3f", *state["centre_m"]))]
        w, x, y, z = state["filtered"]["q"]
        o = pose.pose.orientation
        assert [o.x, o.y, o.z, o.w] == [float(v) for v in struct.unpack("<4f", struct.pack("<4f", x, y, z, w))]
    assert matched >= 20
    # Detections: one object, at the pose's centre and rotation, id its identity, a box of its size.
    detected = 0
    for array, state in with_states("detections", "vision_msgs/msg/Detection3DArray"):
        detected += 1
        assert array.header.frame_id == "world" and len(array.detections) == 1
        d = array.detections[0]
        assert d.id == str(state["shape"]["identity"]) and len(d.results) == 1
        assert d.results[0].hypothesis.class_id == "object"
        assert abs(d.results[0].hypothesis.score - state["shape"]["confidence"]) < 1e-6
        centre = d.bbox.center.position
        assert all(abs(a - b) < 1e-5 for a, b in zip([centre.x, centre.y, centre.z], state["centre_m"]))
        assert d.results[0].pose.pose == d.bbox.center
        size = [d.bbox.size.x, d.bbox.size.y, d.bbox.size.z]
        assert all(0.05 < v < 3.0 for v in size), size
    assert detected >= 20
    z_e = [STORE.deserialize_cdr(s.payload.to_bytes(), "std_msgs/msg/Float32MultiArray")
           for s in samples[f"{NAMESPACE}/{STREAM}/z_e"]]
    assert all(len(m.data) == 10 and m.layout.dim[0].label == "z_e" for m in z_e)
    tf = STORE.deserialize_cdr(samples["/tf"][-1].payload.to_bytes(), "tf2_msgs/msg/TFMessage")
    assert tf.transforms[0].header.frame_id == "world" and tf.transforms[0].child_frame_id == STREAM
    # /tf_static: the gravity frame -> the frame the sample's clouds name, at the configured sensor
    # pose (config/replay.toml's [prepare]), with rmw_zenoh's attachment.
    assert len(tf_static.attachment.to_bytes()) == 33
    static = STORE.deserialize_cdr(tf_static.payload.to_bytes(), "tf2_msgs/msg/TFMessage").transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in static] == [("world", "camera_depth_optical_frame")]
    t, r = static[0].transform.translation, static[0].transform.rotation
    assert all(abs(a - b) < 1e-6 for a, b in zip([t.x, t.y, t.z], [2.6, 0.0, 1.3]))
    rotation = [[1 - 2 * (r.y ** 2 + r.z ** 2), 2 * (r.x * r.y - r.z * r.w), 2 * (r.x * r.z + r.y * r.w)],
                [2 * (r.x * r.y + r.z * r.w), 1 - 2 * (r.x ** 2 + r.z ** 2), 2 * (r.y * r.z - r.x * r.w)],
                [2 * (r.x * r.z - r.y * r.w), 2 * (r.y * r.z + r.x * r.w), 1 - 2 * (r.x ** 2 + r.y ** 2)]]
    expected = [[0.0, 0.188847, -0.982006], [1.0, 0.0, 0.0], [0.0, -0.982006, -0.188847]]
    assert all(abs(rotation[i][j] - expected[i][j]) < 1e-5 for i in range(3) for j in range(3)), rotation
    markers = [STORE.deserialize_cdr(s.payload.to_bytes(), "visualization_msgs/msg/MarkerArray")
               for s in samples[f"{NAMESPACE}/{STREAM}/markers"]]
    last = markers[-1].markers
    assert last[0].type == 9 and "identity" in last[0].text
    assert last[1].type == 0
    shapes = [m.markers[2] for m in markers if len(m.markers) == 3]
    assert shapes, "the decoded canonical shape appears"
    assert shapes[-1].type == 8 and len(shapes[-1].points) == 256
    extent = max(p.z for p in shapes[-1].points) - min(p.z for p in shapes[-1].points)
    assert 0.2 < extent < 3.0, f"the decoded shape is in metres ({extent:.2f} m tall)"

    # Withdrawn on shutdown: nothing of the node is left, and each token's removal was seen.
    assert not [t for t in after if t.split("/")[2] == nodes[0]["zid"]], after
    deleted = {key for kind, key in token_events if kind == "SampleKind.DELETE"}
    assert set(tokens) <= deleted, set(tokens) - deleted


def test_a_python_rmw_zenoh_publisher_feeds_the_node_by_topic_name(tmp_path):
    """A publisher speaking rmw_zenoh's conventions (its node and publisher tokens, the exact key,
    the attachment, no encoding) that waits for a subscriber, as `ros2 topic pub
    --wait-matching-subscriptions` does: the node declares a matching subscription token, then
    turns the point clouds into states. A sample of another type and one with a malformed
    attachment are counted rejections, and the node keeps going."""
    from mcap.reader import make_reader

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    jsonl = tmp_path / "states.jsonl"
    config = tmp_path / "node.toml"
    config.write_text(f"""
[model]
bundle = "{ROOT / 'models/bundles/cpu-fo'}"
threads = 1
[pipeline]
summary_seconds = 0.0
[publish]
zenoh = false
jsonl = "{jsonl}"
[publish.ros2]
enabled = true
markers = false
domain_id = {DOMAIN}
node_name = "listener"
[zenoh]
listen = ["{endpoint}"]
multicast_scouting = false
[[source]]
stream = "cam"
kind = "ros2"
topic = "/camera/depth/points"
[[source]]
stream = "raw"
kind = "zenoh"
key = "{DOMAIN}/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/*"
""")
    clouds = [message.data for _, _, message in
              make_reader(open(ROOT / "sim/samples/walk_switch.mcap", "rb")).iter_messages(
                  topics=["/camera/depth/points"])][:12]
    cloud_type = "sensor_msgs/msg/PointCloud2"
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        with client(endpoint) as session:
            zid = str(session.zid())
            qos = "::,10:,:,:,,"
            # Before any camera exists, the node's output topics for the stream are declared.
            deadline = time.monotonic() + 60
            outputs = []
            while len(outputs) < 7 and time.monotonic() < deadline:
                outputs = [parse_token(str(r.ok.key_expr)) for r in session.liveliness().get(
                    f"@ros2_lv/{DOMAIN}/*/*/*/MP/**", timeout=1.0) if r.ok is not None]
                outputs = [e for e in outputs if e["topic"].startswith("/gdvae/cam/")]
            assert sorted(e["topic"] for e in outputs) == sorted(
                f"/gdvae/cam/{what}" for what in ["pose", "detections", "z_e", "z_i", "state", "events", "rejected"]), outputs
            # And so is its input subscription, of the configured type (PointCloud2 by default).
            deadline = time.monotonic() + 30
            inputs = []
            while not inputs and time.monotonic() < deadline:
                inputs = [parse_token(str(r.ok.key_expr)) for r in session.liveliness().get(
                    f"@ros2_lv/{DOMAIN}/*/*/*/MS/*/*/*/%camera%depth%points/**", timeout=1.0) if r.ok is not None]
            assert [(e["type"], e["hash"]) for e in inputs] == [
                (dds_name(cloud_type), STORE.hash_rihs01(cloud_type))], inputs
            # A publisher of a type the node does not read on its input topic gets no subscription.
            wrong_type = "std_msgs/msg/String"
            wrong_token = session.liveliness().declare_token(
                f"@ros2_lv/{DOMAIN}/{zid}/0/2/MP/%/%/talker/%camera%depth%points/{dds_name(wrong_type)}/"
                f"{STORE.hash_rihs01(wrong_type)}/{qos}")
            node_token = session.liveliness().declare_token(f"@ros2_lv/{DOMAIN}/{zid}/0/0/NN/%/%/talker")
            pub_token = (f"@ros2_lv/{DOMAIN}/{zid}/0/1/MP/%/%/talker/%camera%depth%points/{dds_name(cloud_type)}/"
                         f"{STORE.hash_rihs01(cloud_type)}/{qos}")
            publisher_token = session.liveliness().declare_token(pub_token)
            # Wait for a matching subscription, as a publisher that waits for subscribers does.
            pattern = f"@ros2_lv/{DOMAIN}/*/*/*/MS/*/*/*/%camera%depth%points/{dds_name(cloud_type)}/*/*"
            deadline = time.monotonic() + 60
            matched = []
            while not matched and time.monotonic() < deadline:
                matched = [str(r.ok.key_expr) for r in session.liveliness().get(pattern, timeout=1.0)
                           if r.ok is not None]
            assert matched, "the node declared a subscription token for the topic"
            subscriptions = [parse_token(str(r.ok.key_expr)) for r in session.liveliness().get(
                f"@ros2_lv/{DOMAIN}/*/*/*/MS/*/*/*/%camera%depth%points/**", timeout=1.0) if r.ok is not None]
            assert [e["type"] for e in subscriptions] == [dds_name(cloud_type)], "one subscription, of the type read"

            wrong_token.undeclare()
            subscription = parse_token(matched[0])
            assert subscription["node"] == "listener" and subscription["hash"] == STORE.hash_rihs01(cloud_type)

            publisher = session.declare_publisher(ros_key("/camera/depth/points", cloud_type))
            gid = bytes(range(16))
            for sequence, cloud in enumerate(clouds, start=1):
                attachment = zenoh.ext.z_serialize((zenoh.ext.Int64(sequence), zenoh.ext.Int64(time.time_ns()), gid))
                publisher.put(cloud, attachment=attachment)
                time.sleep(0.05)
            # Another type on the topic, and a cloud with a malformed attachment.
            session.put(ros_key("/camera/depth/points", "std_msgs/msg/String"),
                        bytes(STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")),
                        attachment=zenoh.ext.z_serialize((zenoh.ext.Int64(99), zenoh.ext.Int64(0), gid)))
            publisher.put(clouds[0], attachment=b"\x01\x02\x03")
            # A buffer-aware publisher's CPU key (rmw_zenoh 0.10.5 on, when every subscriber is
            # buffer-aware): the same CDR and attachment, on <key>/_buf_cpu.
            session.put(ros_key("/camera/depth/points", cloud_type) + "/_buf_cpu", clouds[2],
                        attachment=zenoh.ext.z_serialize((zenoh.ext.Int64(100), zenoh.ext.Int64(time.time_ns()), gid)))
            # A plain zenoh source under format "auto" takes rmw_zenoh's encoding-less samples.
            session.put(f"{DOMAIN}/lidar/points/{dds_name(cloud_type)}/{STORE.hash_rihs01(cloud_type)}", clouds[1])
            deadline = time.monotonic() + 60
            lines = []
            while time.monotonic() < deadline:
                lines = [json.loads(l) for l in jsonl.read_text().splitlines()] if jsonl.exists() else []
                if sum(1 for l in lines if l["stream"] == "cam") >= len(clouds) + 3 and \
                        any(l["stream"] == "raw" for l in lines):
                    break
                time.sleep(0.1)
            node.send_signal(signal.SIGTERM)
            out, err = node.communicate(timeout=30)
            publisher_token.undeclare()
            node_token.undeclare()
    finally:
        if node.poll() is None:
            node.kill()
    assert node.returncode == 0, err.decode()
    cam = [l for l in lines if l["stream"] == "cam"]
    states = [l for l in cam if l["schema"] == "gdvae.state/2"]
    rejected = [l for l in cam if l["schema"] == "gdvae.rejected/1"]
    assert len(states) == len(clouds) + 1, (len(states), [r["reason"] for r in rejected])
    assert [s["stamps"]["sensor_ns"] for s in states[:-1]] == sorted(s["stamps"]["sensor_ns"] for s in states[:-1])
    reasons = [r["reason"] for r in rejected]
    assert len(reasons) == 2, reasons
    assert any("std_msgs::msg::dds_::String_" in r and "is not one the node reads" in r for r in reasons), reasons
    assert any("attachment" in r for r in reasons), reasons
    assert [l["schema"] for l in lines if l["stream"] == "raw"] == ["gdvae.state/2"]
    row = next(l for l in out.decode().splitlines() if l.strip().startswith("cam "))
    assert f"{len(clouds) + 3} received" in " ".join(row.split()), row


def test_several_objects_give_one_detection_array_per_frame_and_a_frame_per_track(tmp_path):
    """With `[track.objects] enabled` (config/objects.toml's settings) on the two-subject sample,
    replayed at its own pace: each frame's Detection3DArray holds one detection per tracked
    object, id = its track, at that state's centre; /tf names one child frame per track; the
    markers of each track carry ids of their own."""
    head, source = objects_settings()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "objects.toml"
    config.write_text(f"""
[node]
name = "ros"
{head}
[publish]
zenoh = false
[publish.ros2]
enabled = true
domain_id = {DOMAIN}
namespace = "{NAMESPACE}"
frame_id = "world"
shape_rate_hz = 0.0
[zenoh]
listen = ["{endpoint}"]
multicast_scouting = false
{source}
""")
    topics = {f"{NAMESPACE}/two/detections": "vision_msgs/msg/Detection3DArray",
              f"{NAMESPACE}/two/state": "std_msgs/msg/String",
              f"{NAMESPACE}/two/markers": "visualization_msgs/msg/MarkerArray",
              "/tf": "tf2_msgs/msg/TFMessage"}
    samples = {topic: [] for topic in topics}
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        with client(endpoint) as session:
            subscribers = [session.declare_subscriber(ros_key(topic, msgtype),
                                                      lambda s, t=topic: samples[t].append(s))
                           for topic, msgtype in topics.items()]
            out, err = node.communicate(timeout=60)
            assert node.returncode == 0, err.decode()
            time.sleep(0.5)
            for s in subscribers:
                s.undeclare()
    finally:
        if node.poll() is None:
            node.kill()
    decoded = {topic: [STORE.deserialize_cdr(s.payload.to_bytes(), msgtype) for s in samples[topic]]
               for topic, msgtype in topics.items()}
    for topic, msgtype in topics.items():
        for sample, message in zip(samples[topic], decoded[topic]):
            assert bytes(STORE.serialize_cdr(message, msgtype)) == sample.payload.to_bytes(), topic
    states = {}
    for message in decoded[f"{NAMESPACE}/two/state"]:
        state = json.loads(message.data)
        assert state["schema"] == "gdvae.state/2" and isinstance(state["track"], int)
        states.setdefault(state["stamps"]["sensor_ns"], {})[state["track"]] = state
    arrays = decoded[f"{NAMESPACE}/two/detections"]
    assert len(arrays) >= 20, len(arrays)
    both = 0
    for array in arrays:
        stamp = array.header.stamp.sec * 1_000_000_000 + array.header.stamp.nanosec
        tracks = states[stamp]
        assert sorted(d.id for d in array.detections) == sorted(str(t) for t in tracks), "one per track"
        for d in array.detections:
            centre = d.bbox.center.position
            expected = tracks[int(d.id)]["centre_m"]
            assert all(abs(a - b) < 1e-5 for a, b in zip([centre.x, centre.y, centre.z], expected))
        both += len(array.detections) == 2
    assert both >= 20, f"{both} frames with both subjects"
    track_ids = {t for tracks in states.values() for t in tracks}
    assert len(track_ids) == 2, track_ids
    children = {t.child_frame_id for m in decoded["/tf"] for t in m.transforms}
    assert children == {f"two/{t}" for t in track_ids}, children
    marker_ids = {(m.ns, m.id) for array in decoded[f"{NAMESPACE}/two/markers"] for m in array.markers}
    assert marker_ids == {(ns, 3 * t + k) for t in track_ids for k, ns in [(0, "identity"), (1, "heading")]}, \
        marker_ids
