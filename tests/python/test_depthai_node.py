"""The simulated OAK-D feed tests the node: the sim records a depth camera, the DepthAI harness
(the real `depthai` package's PointCloud node) turns its depth frames into millimetre point clouds
on zenoh, and the real `gdvae-node` binary with `config/depthai.toml`'s settings encodes them."""

import json
import subprocess
import sys
import time

from node_paths import ROOT, SIM, client, free_port, running_node


def test_depthai_point_clouds_are_encoded_by_the_node(tmp_path):
    recording = tmp_path / "oak.mcap"
    subprocess.run([SIM, "record", "--out", str(recording), "--duration", "0.5", "--depth-images", "--seed", "4",
                    "--decimation", "2", "--ground-extent", "1.2", "--camera-distance", "2.6"],
                   check=True, capture_output=True, timeout=120)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    shipped = (ROOT / "config" / "depthai.toml").read_text()
    settings = shipped.replace('bundle = "../models/', f'bundle = "{ROOT / "models"}/')  # the shipped bundle
    settings = settings.replace('listen = ["tcp/127.0.0.1:7447"]', f'listen = ["{endpoint}"]\nmulticast_scouting = false')
    assert settings != shipped
    config = tmp_path / "depthai.toml"
    config.write_text(settings)
    states = []
    with running_node(config) as node, client(endpoint) as session:
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
    row = next(line.split() for line in node["stdout"].splitlines() if line.strip().startswith("depthai "))
    assert row[1:5] == ["15", "received", "15", "published"], node["stdout"]
    # The subscription may reach the node after its first states; those received are in order.
    sequences = [s["sequence"] for s in states]
    assert len(sequences) >= 10 and sequences == sorted(set(sequences)) and sequences[-1] == 14, sequences
    for state in states:
        assert state["points"]["kept"] > 500, "millimetres converted, camera pose applied, subject inside the crop"
        assert state["stamps"]["sensor_ns"] is not None
