"""Where the node's identity changes happen, by the view: for each state of `gdvae-node evaluate
--states` files, the angle between the subject's true heading and the camera's line of sight to
it (0: seen end-on, from the front or the back; 90: side-on), and for each reported change
whether it is true (a true switch within `--tolerance` frames) or false. Prints the share of all
frames seen within 30 degrees of end-on beside the same share of the false and of the true
changes: a detector whose false changes crowd into end-on views is reading the view, not the
subject.

    .venv/bin/python bench/change_views.py SET-states.jsonl... [--tolerance 10]
"""
import argparse
import json
import math

import numpy as np


def end_on_degrees(truth):
    """Degrees between the body's axis and the line of sight, folded to 0 (end-on) .. 90 (side-on)."""
    camera = np.array(truth["world_from_camera"]["translation"][:2])
    where = np.array(truth["translation"][:2])
    sight = math.atan2(where[1] - camera[1], where[0] - camera[0])
    relative = abs((truth["yaw"] - sight + math.pi) % (2 * math.pi) - math.pi)
    return math.degrees(min(relative, math.pi - relative))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("states", nargs="+")
    parser.add_argument("--tolerance", type=int, default=10, help="frames (as evaluate's --tolerance-frames)")
    args = parser.parse_args()
    streams = {}
    for path in args.states:
        for line in open(path):
            row = json.loads(line)
            if row["truth"] is not None:
                streams.setdefault((path, row["state"]["stream"]), []).append(row)
    every, false, true = [], [], []
    for rows in streams.values():
        rows.sort(key=lambda r: r["truth"]["frame"])
        switches = [b["truth"]["frame"] for a, b in zip(rows, rows[1:]) if a["truth"]["subject"] != b["truth"]["subject"]]
        for row in rows:
            angle = end_on_degrees(row["truth"])
            every.append(angle)
            event = row["state"].get("event") or {}
            if event.get("kind") == "identity_change":
                found = any(abs(row["truth"]["frame"] - s) <= args.tolerance for s in switches)
                (true if found else false).append(angle)
    share = lambda a: f"{np.mean(np.array(a) < 30):.2f}" if a else "-"  # noqa: E731
    print(f"{len(every)} frames, {share(every)} of them within 30 degrees of end-on")
    print(f"false changes: {len(false)}, {share(false)} within 30 degrees of end-on; angles {sorted(round(a) for a in false)}")
    print(f"true changes found: {len(true)}, {share(true)} within 30 degrees of end-on")


if __name__ == "__main__":
    main()
