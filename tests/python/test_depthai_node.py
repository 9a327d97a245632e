"""The simulated OAK-D feed tests the node: the sim records a depth camera, the DepthAI harness
(the real `depthai` package's PointCloud node) turns its depth frames into millimetre point clouds
on zenoh, and the real `gdvae-node` binary with `config/depthai.toml`'s settings encodes them."""

import json
import signal
import subprocess
import sys
import time

import zenoh

from node_paths import NODE, ROOT, SIM, free_port


def test_depthai_point_clouds_are_encoded_by_the_node(tmp_path):
    recording = tmp_path / "oak.mcap"
    subprocess.run([SIM, "record", "--out", str(recording), "--duration", "0.5", "--depth-images", "--seed", "4",
                    "--decimation", "2", "--ground-extent", "1.2", "--camera-distance", "2.6"],
                   check=True, capture_output=True, timeout=120)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    shipped = (ROOT / "config" / "depthai.toml").read_text()
    settings = shipped.replace('bundle = "../models/bundles/cpu-gdvaepp"',
                               f'bundle = "{ROOT / "models/bundles/cpu-gdvaepp"}"')
    settings = settings.replace('listen = ["tcp/127.0.0.1:7447"]', f'listen = ["{endpoint}"]\nmulticast_scouting = false')
    assert settings != shipped
    config = tmp_path / "depthai.toml"
    config.write_text(settings)
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        zconfig = zenoh.Config()
        zconfig.insert_json5("connect/endpoints", json.dumps([endpoint]))
        zconfig.insert_json5("scouting/multicast/enabled", "false")
        states = []
        with zenoh.open(zconfig) as session:
            subscriber = session.declare_subscriber("gdvae/oak/depthai/state",
                                                    lambda s: states.append(json.loads(s.payload.to_bytes())))
            feed = subprocess.run(
                [sys.executable, str(ROOT / "sim" / "depthai_feed.py"), "--mcap", str(recording), "--rate", "10",
                 "--prefix", "sim/depthai", "--connect", endpoint, "--no-multicast", "--wait-for-subscriber", "30"],
                capture_output=True, text=True, timeout=120)
            assert feed.returncode == 0, feed.stderr
            deadline = time.monotonic() + 30
            while len(states) < 15 and time.monotonic() < deadline:
                time.sleep(0.05)
            subscriber.undeclare()
    finally:
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=30)
    assert node.returncode == 0, err.decode()
    assert [s["sequence"] for s in states] == list(range(15)), out.decode()
    for state in states:
        assert state["points"]["kept"] > 500, "millimetres converted, camera pose applied, subject inside the crop"
        assert state["stamps"]["sensor_ns"] is not None
