#!/usr/bin/env python3
"""DepthAI harness: turn the simulator's depth frames into genuine DepthAI point clouds and
publish them over zenoh, so the node is tested against what an OAK-D pipeline actually emits.

The depth frames (uint16 millimetres, 640x400, with their CameraInfo) come either from an MCAP
recording made with `sim record --depth-images` or live from `sim feed --depth-images`. Each one
becomes a DepthAI `ImgFrame` (RAW16) carrying the camera's intrinsics and extrinsics on a concrete
socket (CAM_B, the left camera the sim renders from), and goes through DepthAI's own `PointCloud`
node, run on the host (no device needed). Its output, `PointCloudData.getPoints()`, is published
unchanged.

Wire format on `<prefix>/points` (documented in sim/README.md):
  payload     float32 little-endian x, y, z triplets, millimetres, in the camera's optical frame
              (x right, y down, z forward): exactly the bytes of `getPoints()`; invalid pixels are
              already left out by DepthAI (a sparse cloud)
  encoding    application/octet-stream, schema `depthai/PointCloudData;xyz_f32_mm`
  attachment  JSON: {"sequence": n, "stamp_nanos": t, "points": N, "unit": "mm",
                     "socket": "CAM_B", "frame_id": "camera_depth_optical_frame"}

Usage:
  python sim/depthai_feed.py --mcap walk.mcap [--rate 30] --connect tcp/127.0.0.1:7447
  python sim/depthai_feed.py --from-prefix sim/oak --connect tcp/127.0.0.1:7447
"""

import argparse
import datetime
import json
import queue
import sys
import time

import numpy as np

DEFAULT_PREFIX = "sim/depthai"
ENCODING_SCHEMA = "depthai/PointCloudData;xyz_f32_mm"
DEPTH_TOPIC = "/camera/depth/image_raw"
INFO_TOPIC = "/camera/depth/camera_info"
FRAME_ID = "camera_depth_optical_frame"


class DepthAIPointCloud:
    """DepthAI's PointCloud node running on the host, fed with RAW16 ImgFrames."""

    def __init__(self):
        import depthai as dai

        self.dai = dai
        self.pipeline = dai.Pipeline(False)
        node = self.pipeline.create(dai.node.PointCloud)
        node.setRunOnHost(True)
        node.sync.setRunOnHost(True)
        self.input = node.inputDepth.createInputQueue()
        self.output = node.outputPointCloud.createOutputQueue()
        self.pipeline.start()

    def points(self, depth_mm, k, sequence, stamp_nanos):
        """Millimetre points (N x 3 float32) of one depth image with camera matrix `k` (row-major 9)."""
        dai = self.dai
        height, width = depth_mm.shape
        frame = dai.ImgFrame()
        frame.setType(dai.ImgFrame.Type.RAW16)
        frame.setWidth(width)
        frame.setHeight(height)
        frame.setStride(2 * width)
        frame.setData(np.ascontiguousarray(depth_mm, dtype="<u2").tobytes())
        frame.setInstanceNum(int(dai.CameraBoardSocket.CAM_B))
        frame.setSequenceNum(sequence)
        frame.setTimestamp(datetime.timedelta(microseconds=stamp_nanos // 1000))
        extrinsics = dai.Extrinsics()
        extrinsics.rotationMatrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        extrinsics.toCameraSocket = dai.CameraBoardSocket.CAM_B
        matrix = [list(map(float, k[0:3])), list(map(float, k[3:6])), list(map(float, k[6:9]))]
        transformation = dai.ImgTransformation(width, height, matrix)
        transformation.setExtrinsics(extrinsics)
        frame.setTransformation(transformation)
        self.input.send(frame)
        cloud = self.output.get()
        return np.asarray(cloud.getPoints(), dtype="<f4").reshape(-1, 3)

    def close(self):
        self.pipeline.stop()


def mcap_frames(path):
    """(depth uint16 HxW, k, stamp_nanos) from a recording made with `sim record --depth-images`,
    each image paired with the CameraInfo of the same stamp."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    images, infos = {}, {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros in reader.iter_decoded_messages(topics=[DEPTH_TOPIC, INFO_TOPIC]):
            if channel.topic == INFO_TOPIC:
                infos[message.log_time] = list(ros.k)
            elif ros.encoding != "16UC1":
                raise ValueError(f"{path}: {DEPTH_TOPIC} has encoding {ros.encoding!r}, expected 16UC1")
            else:
                images[message.log_time] = depth_array(ros)
            for stamp in sorted(set(images) & set(infos)):
                yield images.pop(stamp), infos.pop(stamp), stamp
    if not infos and not images:
        return
    raise ValueError(f"{path}: {len(images)} depth images without CameraInfo, {len(infos)} CameraInfo without image")


def depth_array(image):
    """A decoded 16UC1 sensor_msgs/Image as a uint16 array (rows may be padded: honour `step`)."""
    rows = np.frombuffer(bytes(image.data), dtype="<u2").reshape(image.height, image.step // 2)
    return rows[:, : image.width]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--mcap", help="recording made with `sim record --depth-images`")
    source.add_argument("--from-prefix", help="key prefix of a live `sim feed --depth-images` (e.g. sim/oak)")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help=f"output key prefix (default {DEFAULT_PREFIX})")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second when replaying an MCAP (0: as fast as possible)")
    parser.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    parser.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on (repeatable)")
    parser.add_argument("--no-multicast", action="store_true", help="disable zenoh multicast scouting")
    parser.add_argument("--wait-for-subscriber", type=float, default=0.0, help="seconds to wait for a subscriber first")
    parser.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: all)")
    args = parser.parse_args(argv)
    if args.rate < 0:
        parser.error("--rate must be non-negative")

    import zenoh

    config = zenoh.Config()
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        config.insert_json5("listen/endpoints", json.dumps(args.listen))
    if args.no_multicast:
        config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    key = f"{args.prefix.rstrip('/')}/points"
    encoding = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(ENCODING_SCHEMA)
    publisher = session.declare_publisher(key, encoding=encoding, congestion_control=zenoh.CongestionControl.BLOCK)
    if args.wait_for_subscriber > 0:
        deadline = time.monotonic() + args.wait_for_subscriber
        while not publisher.matching_status.matching:
            if time.monotonic() > deadline:
                print(f"depthai_feed: no subscriber to {key} within {args.wait_for_subscriber} s", file=sys.stderr)
                return 1
            time.sleep(0.02)

    converter = DepthAIPointCloud()
    published = 0
    try:
        if args.mcap:
            frames = mcap_frames(args.mcap)
        else:
            frames = live_frames(session, args.from_prefix)
        started = time.monotonic()
        for sequence, (depth, k, stamp) in enumerate(frames):
            if args.mcap and args.rate > 0:
                delay = started + sequence / args.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            points = converter.points(depth, k, sequence, stamp)
            attachment = {"sequence": sequence, "stamp_nanos": stamp, "points": len(points), "unit": "mm",
                          "socket": "CAM_B", "frame_id": FRAME_ID}
            publisher.put(points.tobytes(), attachment=json.dumps(attachment).encode())
            published += 1
            if args.frames and published >= args.frames:
                break
    finally:
        converter.close()
        session.close()
    print(f"depthai_feed: published {published} DepthAI point clouds on {key}")
    return 0


def live_frames(session, prefix):
    """Depth images and their CameraInfo from a live `sim feed --depth-images`, paired by stamp."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    image_schema = Schema(id=1, name="sensor_msgs/msg/Image", encoding="ros2msg", data=IMAGE_MSG.encode())
    info_schema = Schema(id=2, name="sensor_msgs/msg/CameraInfo", encoding="ros2msg", data=CAMERA_INFO_MSG.encode())
    decode_image = DecoderFactory().decoder_for("cdr", image_schema)
    decode_info = DecoderFactory().decoder_for("cdr", info_schema)
    samples = queue.Queue(maxsize=64)
    prefix = prefix.rstrip("/")
    subscribers = [
        session.declare_subscriber(f"{prefix}/depth", lambda s: samples.put(("depth", bytes(s.payload)))),
        session.declare_subscriber(f"{prefix}/camera_info", lambda s: samples.put(("info", bytes(s.payload)))),
    ]
    images, infos = {}, {}
    timeout = 60.0  # the feed may take a while to start (it renders its first frame); then 5 s of silence ends it
    try:
        while True:
            try:
                kind, payload = samples.get(timeout=timeout)
            except queue.Empty:
                return
            timeout = 5.0
            if kind == "depth":
                image = decode_image(payload)
                stamp = image.header.stamp.sec * 10**9 + image.header.stamp.nanosec
                images[stamp] = depth_array(image)
            else:
                info = decode_info(payload)
                infos[info.header.stamp.sec * 10**9 + info.header.stamp.nanosec] = list(info.k)
            for stamp in sorted(set(images) & set(infos)):
                yield images.pop(stamp), infos.pop(stamp), stamp
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()


_HEADER = (
    "================================================================================\n"
    "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    "================================================================================\n"
    "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
IMAGE_MSG = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
    "uint32 step\nuint8[] data\n" + _HEADER
)
CAMERA_INFO_MSG = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
    "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n"
    + _HEADER
    + "================================================================================\n"
    "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
    "bool do_rectify\n"
)


if __name__ == "__main__":
    sys.exit(main())
