"""Where the node's Python checks find the repository, the built binaries and a free port."""

import os
import pathlib
import socket

ROOT = pathlib.Path(__file__).resolve().parents[2]
NODE = os.environ.get("NODE_BIN", str(ROOT / "target" / "release" / "gdvae-node"))
SIM = os.environ.get("SIM_BIN", str(ROOT / "target" / "release" / "sim"))


def free_port():
    """A TCP port on loopback that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
