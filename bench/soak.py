"""Overload soak (`make soak`): a live zenoh feed at many times what the node can process, for a
minute, against the real binary. Prints the node's resident memory every second, what it received,
dropped (drop-oldest, counted) and published, and the end-to-end latency of what it published.

    python bench/soak.py [--factor 10] [--seconds 60] [--out soak.json]

The node's capacity is measured first with `gdvae-node replay` on the same sample (frames/s); the
feed then publishes the sample's point clouds at `factor` times that rate (or as fast as this
Python publisher manages, which is reported: the factor achieved is what counts).
"""

import argparse
import json
import pathlib
import signal
import socket
import statistics
import subprocess
import sys
import time

import zenoh
from mcap.reader import make_reader

ROOT = pathlib.Path(__file__).resolve().parents[1]
NODE = ROOT / "target/release/gdvae-node"
SAMPLE = ROOT / "sim/samples/walk_switch.mcap"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mib(pid):
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def capacity_fps():
    """The node's throughput on one stream of the sample, as the replay benchmark measures it."""
    out = subprocess.run([str(NODE), "-q", "replay", str(SAMPLE), "--config", str(ROOT / "config/replay.toml"),
                          "--no-baseline", "--json"], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)["throughput_fps"]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--factor", type=float, default=10.0)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--out", type=pathlib.Path)
    args = parser.parse_args()

    capacity = capacity_fps()
    target = capacity * args.factor
    print(f"node capacity (replay, 1 stream): {capacity:.0f} frames/s; feeding at {target:.0f} frames/s "
          f"for {args.seconds:.0f} s", flush=True)
    clouds = [m.data for _, _, m in make_reader(open(SAMPLE, "rb")).iter_messages(topics=["/camera/depth/points"])]

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = pathlib.Path("/tmp") / f"gdvae-soak-{endpoint.rsplit(':', 1)[1]}.toml"
    replay = (ROOT / "config/replay.toml").read_text()
    prepare = replay[replay.index("[prepare]"):replay.index("[publish]")]
    config.write_text(f"""
[node]
name = "soak"
[model]
bundle = "{ROOT / 'models/bundles/cpu-fo'}"
[pipeline]
summary_seconds = 0.0
{prepare}
[zenoh]
listen = ["{endpoint}"]
multicast_scouting = false
[[source]]
stream = "cam"
kind = "zenoh"
key = "soak/points"
""")
    node = subprocess.Popen([str(NODE), "-q", "run", "--config", str(config)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    zc = zenoh.Config()
    zc.insert_json5("connect/endpoints", json.dumps([endpoint]))
    zc.insert_json5("scouting/multicast/enabled", "false")
    series, sent = [], 0
    with zenoh.open(zc) as session:
        publisher = session.declare_publisher("soak/points", congestion_control=zenoh.CongestionControl.DROP)
        deadline = time.monotonic() + 20
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.1)
        start = time.monotonic()
        next_sample = start
        while (now := time.monotonic()) - start < args.seconds:
            due = start + sent / target
            if now < due:
                time.sleep(min(due - now, 0.001))
            else:
                publisher.put(clouds[sent % len(clouds)])
                sent += 1
            if now >= next_sample:
                series.append(round(rss_mib(node.pid), 1))
                next_sample += 1.0
        elapsed = time.monotonic() - start
        time.sleep(1.0)
        status = None
        for reply in session.get("gdvae/soak/status", timeout=5.0):
            if reply.ok is not None:
                status = json.loads(reply.ok.payload.to_bytes())
    node.send_signal(signal.SIGTERM)
    out, err = node.communicate(timeout=60)
    if node.returncode != 0 or status is None:
        print(err, file=sys.stderr)
        sys.exit(f"the node exited {node.returncode} (status reply: {status is not None})")
    counters = status["counters"]["streams"]["cam"]
    e2e = status["counters"]["stages"].get("end_to_end", {})
    rejected = sum(counters["rejected"].values())
    report = {
        "capacity_fps": capacity,
        "fed_fps": sent / elapsed,
        "factor_achieved": sent / elapsed / capacity,
        "seconds": elapsed,
        "sent": sent,
        "received": counters["received"],
        "dropped": counters["dropped"],
        "rejected": rejected,
        "published": counters["published"],
        "in_flight_at_status": counters["received"] - counters["dropped"] - rejected - counters["published"],
        "rss_mib_series": series,
        "rss_mib_max": max(series),
        "rss_mib_median": statistics.median(series),
        "end_to_end_ms": {k: e2e.get(k) for k in ("p50_ms", "p99_ms", "max_ms")},
    }
    print(json.dumps(report, indent=1))
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
