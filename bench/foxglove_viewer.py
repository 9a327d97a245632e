"""The Foxglove live view's cost (`[publish.foxglove]`): `gdvae-node replay` of COPIES copies of the
sample with the view off, on with no viewer, on with a viewer that receives everything, and on with
a viewer that subscribes to every channel and then stops reading (a stalled Foxglove app). Prints, per case and
round, the replay's frames/s and the node's peak memory (VmHWM), and what the viewer received.

    python bench/foxglove_viewer.py [--copies 16] [--rounds 2] [--input-points N] [--max-rate HZ]
        [--cases off,unwatched,reading,stalled] [--out viewer.json]

The viewer is a Python client of the Foxglove WebSocket protocol (subprotocol foxglove.sdk.v1) on
the same machine; it connects while the node loads its bundle, before the first state.
"""

import argparse
import asyncio
import json
import pathlib
import socket
import subprocess
import sys
import tempfile
import time

import websockets

ROOT = pathlib.Path(__file__).resolve().parents[1]
NODE = ROOT / "target/release/gdvae-node"
SAMPLE = ROOT / "sim/samples/walk_switch.mcap"
# The view off; on with no viewer; on with a viewer reading everything; on with a stalled viewer.
CASES = ["off", "unwatched", "reading", "stalled"]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def viewer(port, stall, deadline):
    """Connects (retrying until the server is up), subscribes to every channel advertised, then
    reads every message until the server closes, or (`stall`) stops reading once subscribed."""
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                          max_size=None, max_queue=None if not stall else 1)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.02)
    received, subscribed = 0, set()
    async with ws:
        try:
            while True:
                message = await ws.recv()
                if isinstance(message, str):
                    op = json.loads(message)
                    if op["op"] == "advertise":
                        new = [c for c in op["channels"] if c["id"] not in subscribed]
                        subscribed.update(c["id"] for c in new)
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in new]}))
                        if stall and new:
                            # Holds the connection open without reading: the server's queue and
                            # the socket's buffers fill.
                            await asyncio.sleep(3600)
                else:
                    received += 1
        except websockets.ConnectionClosed:
            pass
    return received


def replay(copies, case, port, input_points, max_rate):
    """One replay; returns its figures and what the viewer received."""
    # Beside config/replay.toml, whose relative paths it keeps.
    with tempfile.NamedTemporaryFile("w", dir=ROOT / "config", prefix=".viewer-", suffix=".toml") as file:
        config = pathlib.Path(file.name)
        config.write_text((ROOT / "config/replay.toml").read_text())
        if case != "off":
            with open(config, "a") as f:
                f.write(f"\n[publish.foxglove]\nenabled = true\nport = {port}\n")
                if max_rate is not None:
                    f.write(f"max_rate_hz = {max_rate}\n")
                if input_points is not None:
                    f.write(f"[publish.view]\ninput_points = {input_points}\n")
        command = [str(NODE), "-q", "replay", *[str(SAMPLE)] * copies, "--config", str(config),
                   "--no-baseline", "--json"]
        node = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        received = None
        if case in ("reading", "stalled"):
            async def watch():
                task = asyncio.create_task(viewer(port, case == "stalled", time.monotonic() + 60))
                while node.poll() is None:
                    await asyncio.sleep(0.05)
                if case == "stalled":
                    task.cancel()
                    return None
                return await asyncio.wait_for(task, 30)
            received = asyncio.run(watch())
        out, err = node.communicate(timeout=600)
        if node.returncode != 0:
            sys.exit(f"{' '.join(command)} failed: {err.decode()}")
        report = json.loads(out)
        return {"case": case, "frames_per_second": report["throughput_fps"],
                "peak_memory_mib": report["peak_memory_mib"], "viewer_received": received,
                "not_shown": err.decode().count("not shown")}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--input-points", type=int, help="[publish.view] input_points (default: the config's)")
    parser.add_argument("--max-rate", type=float, help="[publish.foxglove] max_rate_hz (default: the config's)")
    parser.add_argument("--cases", default=",".join(CASES), help="which of " + ", ".join(CASES))
    parser.add_argument("--out")
    args = parser.parse_args()
    rows = []
    for round_ in range(args.rounds):
        for case in args.cases.split(","):
            row = replay(args.copies, case, free_port(), args.input_points, args.max_rate) | {"round": round_}
            rows.append(row)
            print(f"round {round_} {case:8s} {row['frames_per_second']:7.1f} frames/s  peak memory "
                  f"{row['peak_memory_mib']:6.1f} MiB  viewer received {row['viewer_received']}", flush=True)
    for case in args.cases.split(","):
        fps = [r["frames_per_second"] for r in rows if r["case"] == case]
        mem = [r["peak_memory_mib"] for r in rows if r["case"] == case]
        print(f"{case:8s} frames/s {' / '.join(f'{f:.0f}' for f in fps)}, peak memory "
              f"{' / '.join(f'{m:.0f}' for m in mem)} MiB")
    extra = f" --input-points {args.input_points}" if args.input_points is not None else ""
    extra += f" --max-rate {args.max_rate}" if args.max_rate is not None else ""
    extra += f" --cases {args.cases}" if args.cases != ",".join(CASES) else ""
    print(f"command: python bench/foxglove_viewer.py --copies {args.copies} --rounds {args.rounds}{extra}")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
