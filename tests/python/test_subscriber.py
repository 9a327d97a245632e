"""A Python eclipse-zenoh client reads the node's states, status and liveliness, as README.md
shows: the real `gdvae-node` binary (built by `make test`) replays the sample recording at 30 Hz."""

import time

import json

from node_paths import ROOT, client, free_port, running_node, sample_settings


def test_a_python_subscriber_gets_states_status_and_liveliness(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "node.toml"
    config.write_text(f"""
[node]
name = "py"
{sample_settings()}
[zenoh]
listen = ["{endpoint}"]
multicast_scouting = false
[[source]]
stream = "sample"
kind = "mcap"
path = "{ROOT / 'sim/samples/walk_switch.mcap'}"
repeat = true
""")
    states = []
    with running_node(config) as node, client(endpoint) as session:
        subscriber = session.declare_subscriber("gdvae/*/*/state",
                                                lambda sample: states.append(json.loads(sample.payload.to_bytes())))
        deadline = time.monotonic() + 60
        while len(states) < 30 and time.monotonic() < deadline:
            time.sleep(0.05)
        status = None
        while status is None and time.monotonic() < deadline:
            for reply in session.get("gdvae/py/status", timeout=2.0):
                if reply.ok is not None:
                    status = json.loads(reply.ok.payload.to_bytes())
        alive = [str(reply.ok.key_expr) for reply in session.liveliness().get("gdvae/py/alive", timeout=5.0)
                 if reply.ok is not None]
        subscriber.undeclare()
    assert alive == ["gdvae/py/alive"], "the node's liveliness token"
    assert len(states) >= 30, f"{len(states)} states within 60 s"
    sequences = [s["sequence"] for s in states]
    assert sequences == sorted(sequences) and len(set(sequences)) == len(sequences)
    last = states[-1]
    assert last["schema"] == "gdvae.state/2" and last["stream"] == "sample"
    assert len(last["shape"]["z_i"]) == 22 and len(last["filtered"]["z_e"]) == 10
    assert status["schema"] == "gdvae.status/1" and status["node"] == "py"
    assert status["counters"]["streams"]["sample"]["published"] >= 30
    assert "streams:" in node["stdout"]
