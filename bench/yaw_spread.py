"""How well does a frame's yaw-copy scatter (`raw.yaw_spread`) tell a poor heading reading? Reads
the JSON lines of `gdvae-node evaluate ... --states FILE` (each a published state with the ground
truth it was matched to) and prints the raw heading error by quintile of the scatter: the median,
the p90 and the share of readings that took the back for the front (over 90 degrees off).

    ./target/release/gdvae-node evaluate /work/data/bench-tracking/tune/*.mcap \\
        --config config/replay.toml --states /tmp/tune.states
    .venv/bin/python bench/yaw_spread.py /tmp/tune.states [MORE ...]

docs/tracking.md "The yaw copies' scatter, and a walk's vote" has what it printed.
"""

import argparse
import json
import math
import sys

import numpy as np


def wrapped_degrees(angle: float) -> float:
    """`angle` (radians) wrapped to (-180, 180] degrees."""
    return math.degrees((angle + math.pi) % (2 * math.pi) - math.pi)


def read(paths: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(|raw yaw error| in degrees, yaw spread in degrees) of every state with truth and a spread."""
    errors, spreads = [], []
    for path in paths:
        with open(path) as lines:
            for line in lines:
                row = json.loads(line)
                truth, raw = row.get("truth"), row["state"]["raw"]
                if truth is None or raw.get("yaw_spread") is None:
                    continue
                errors.append(abs(wrapped_degrees(raw["yaw"] - truth["yaw"])))
                spreads.append(math.degrees(raw["yaw_spread"]))
    return np.array(errors), np.array(spreads)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("states", nargs="+", help="files written by `gdvae-node evaluate --states`")
    args = parser.parse_args()
    errors, spreads = read(args.states)
    if len(errors) < 5:
        print(
            f"yaw_spread.py: {len(errors)} states with truth and raw.yaw_spread in {args.states} "
            "(evaluate with yaw_copies > 1 and recordings with ground truth)",
            file=sys.stderr,
        )
        return 1
    edges = np.percentile(spreads, [0, 20, 40, 60, 80, 100])
    print(f"{len(errors)} frames; raw heading error by the yaw copies' scatter (degrees)")
    print("scatter            frames  median     p90  back for front")
    for k, (low, high) in enumerate(zip(edges[:-1], edges[1:])):
        inside = (spreads >= low) & ((spreads < high) if k < 4 else (spreads <= high))
        e = errors[inside]
        print(
            f"{low:6.1f} - {high:6.1f}  {inside.sum():7d}  {np.median(e):6.1f}  "
            f"{np.percentile(e, 90):6.1f}  {(e > 90).mean():14.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
