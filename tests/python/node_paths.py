"""Shared by the node's Python checks: the repository, the built binaries, the sample's settings,
a free port, and the node binary started on a config and stopped by SIGINT."""

import contextlib
import json
import os
import signal
import subprocess
import pathlib
import socket

ROOT = pathlib.Path(__file__).resolve().parents[2]
NODE = os.environ.get("NODE_BIN", str(ROOT / "target" / "release" / "gdvae-node"))
SIM = os.environ.get("SIM_BIN", str(ROOT / "target" / "release" / "sim"))


def sample_settings():
    """TOML for a node on the sample recording: the shipped bundle (one thread), no periodic
    summary, and the sample camera's [prepare] section as `config/replay.toml` has it."""
    replay = (ROOT / "config/replay.toml").read_text()
    prepare = replay[replay.index("[prepare]"):replay.index("[publish]")]
    return (f'[model]\nbundle = "{ROOT / "models/bundles/cpu-fo"}"\nthreads = 1\n'
            f"[pipeline]\nsummary_seconds = 0.0\n{prepare}")


def objects_settings():
    """TOML for a node tracking several objects on the two-subject sample, replayed at its own
    pace: config/objects.toml's [prepare] and [track.objects] with the shipped bundle (one thread)
    and no periodic summary (`head`), and its source (`source`), to put a [publish] between."""
    objects = (ROOT / "config/objects.toml").read_text()
    head = (f'[model]\nbundle = "{ROOT / "models/bundles/cpu-fo"}"\nthreads = 1\n'
            f'[pipeline]\nsummary_seconds = 0.0\n{objects[objects.index("[prepare]"):objects.index("[publish]")]}')
    source = objects[objects.index("[[source]]"):].replace(
        '"../sim/samples/two_subjects.mcap"', f'"{ROOT / "sim/samples/two_subjects.mcap"}"'
    ).replace("speed = 0.0", "speed = 1.0")
    return head, source


def free_port():
    """A TCP port on loopback that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def client(endpoint):
    """A zenoh session connected to `endpoint` only (no multicast scouting)."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


@contextlib.contextmanager
def running_node(config_path):
    """Runs `gdvae-node run --config config_path`; on exit sends SIGINT and checks it exits 0.
    Yields a dict that receives the node's `stdout` after it stopped."""
    node = subprocess.Popen([NODE, "-q", "run", "--config", str(config_path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    result = {}
    try:
        yield result
    finally:
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=30)
        result["stdout"] = out.decode()
    assert node.returncode == 0, err.decode()
