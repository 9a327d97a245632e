"""How separable are same-subject and replaced-subject z_I streams? An oracle bound for the tracker.

For every frame t of a benchmark replay (states as JSON lines from `gdvae-node replay --jsonl`),
the statistic is the mean squared difference per dimension between the mean raw z_I of the W
frames after t and of the P frames before t. Under "same subject" (no switch in [t-P, t+W)) it
measures drift and noise; at a true switch it measures the jump. The report gives the share of
true switches whose statistic exceeds the same-subject quantile that leaves one false alarm per
1,000 frames: no detector that looks at these windows does better on this bundle.

    python bench/separability.py STATES.jsonl REC.mcap... [--past 30] [--window 10]
"""
import argparse
import json
import os

import numpy as np
from mcap.reader import make_reader


def truth(paths):
    out = {}
    for path in paths:
        stream = os.path.basename(path)[: -len(".mcap")].replace(".", "_")
        with open(path, "rb") as f:
            for _, _, message in make_reader(f).iter_messages(topics=["/sim/ground_truth"]):
                d = json.loads(message.data)
                out[(stream, d["stamp_nanos"])] = (d["subject"], d["family"])
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("states")
    parser.add_argument("recordings", nargs="+")
    parser.add_argument("--past", type=int, default=30)
    parser.add_argument("--window", type=int, default=10)
    args = parser.parse_args()
    known = truth(args.recordings)
    streams = {}
    for line in open(args.states):
        d = json.loads(line)
        if "raw" not in d:
            continue
        t = known.get((d["stream"], d["stamps"]["sensor_ns"]))
        if t is not None:
            streams.setdefault(d["stream"], []).append((t[0], t[1], np.array(d["raw"]["z_i"])))
    same, switch = [], {"same family": [], "other family": []}
    for rows in streams.values():
        subjects = [r[0] for r in rows]
        families = [r[1] for r in rows]
        z = np.array([r[2] for r in rows])
        for t in range(args.past, len(rows) - args.window + 1):
            stat = np.mean((z[t : t + args.window].mean(0) - z[t - args.past : t].mean(0)) ** 2)
            span = set(subjects[t - args.past : t + args.window])
            if len(span) == 1:
                same.append(stat)
            elif subjects[t] != subjects[t - 1]:
                kind = "same family" if families[t] == families[t - 1] else "other family"
                switch[kind].append(stat)
    same = np.array(same)
    limit = np.quantile(same, 1 - 1e-3) if len(same) else float("nan")
    print(f"same-subject windows: {len(same)}; statistic median {np.median(same):.5f}, "
          f"99.9th percentile {limit:.5f}")
    for kind, values in switch.items():
        values = np.array(values)
        if len(values):
            print(f"{kind} switches: {len(values)}; statistic {np.round(np.sort(values), 5).tolist()}; "
                  f"above the 99.9th percentile: {np.mean(values > limit):.2f}")


if __name__ == "__main__":
    main()
