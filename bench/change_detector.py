"""The node's identity-change detectors replayed offline, to compare detectors in seconds.

Reads `gdvae-node evaluate --states` files (every published state with its ground truth) and runs
replicas of the shape filter of src/track/shape.rs over each stream's raw z_I, first checking the
replica of the detector the states were made with (`--node-detector`, default the node's `step`)
against the node: every frame's published figure (the step's statistic; the CUSUM's distance to
the estimate) must be the replica's, or the script stops with an error. Then, for each detector
variant, it sweeps its settings on the `--choice` files, chooses those that find the most true
changes with at most `--budget` false ones per 1,000 frames (then the fewest false), and reports
them on the `--report` files (which nothing is chosen on):

- `step`: the node's default detector on z_I: the last few frames' precision-weighted mean
  against the frames before them, a frame's variance floored at each of `--step-floor` (squared
  z_I spreads, one variant each) and each frame clipped as the node clips it (`step_clip`);
  window, reference length and threshold swept;
- `cusum`: the CUSUM on z_I (precision-weighted fusion, the gate, the held frames), the encoder's
  variances as the node scales them; threshold h and drift k swept;
- `view`: the CUSUM with a frame's variances widened up to `--view-widen` times as the subject is
  seen end-on (within 30 degrees of the line of sight, by the node's filtered heading and centre
  and the recording's camera position: what the node could compute itself);
- `discriminant`: the encoder's x_c (`--fit-input x_c`, what the node's identity projection reads;
  `python -m gdvae fit-identity` fits the same) or z_I projected onto its `--directions` most
  discriminant directions for subjects of one family, whitened by the within-subject scatter,
  fitted on the `--fit` files' node clouds (each frame's variance 1 in that space; `--ridge`
  shrinks the within-subject scatter towards its mean variance), through the CUSUM. The fit files
  must be apart from both other sets (bench/tracking.sh fit-N). `--directions` and `--ridge` take
  comma-separated lists: each pair is a variant, and the one that finds the most on `--choice`
  (then the fewest false) is named.
- with `discriminant`, `hetero`: the same projected code with a variance per frame and direction,
  log-linear in what the node knows of the frame (points kept and received, heading confidence,
  the yaw copies' scatter, the encoder's mean log-variances of z_I and z_E), fitted by maximum
  likelihood on the `--fit` files;
- with `discriminant`, `step`: the same projected code through the step detector.

    .venv/bin/python bench/change_detector.py --choice A-states.jsonl,... --report C-states.jsonl,... \
        [--variants step,cusum,view,discriminant,hetero] [--budget 0.3] [--front] \
        [--fit F-states.jsonl,... --fit-input x_c --directions 5 --ridge 0.03]

`--front` also prints each variant's found/false trade-off over its whole grid on the report files
(a measurement, not a choice). The node's other settings (`shape_gate`, `switch_frames`,
`min_shape_variance`, `min_identity_variance`, the step's clip) are config/default.toml's, z_I's
floors in the `--bundle`'s z_I spread (default: the default bundle); a change is found when
reported within 10 frames of the true one (`gdvae-node evaluate`'s rule). The states must be
written with identity changes on z_I (`use_identity_projection = false`, the default).
"""
import argparse
import functools
import itertools
import json
import math
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "models"))
from gdvae.identity import fit_projection  # noqa: E402  (the kit's fit, which the bundle gets)

GATE, SWITCH, MAX_HELD, MATURE, TOLERANCE = 2.0, 5, 300, 30, 10
# The node's change detectors' defaults (config/default.toml), the step's floor in squared z_I spreads.
CUSUM_DRIFT, CUSUM_THRESHOLD = 3.0, 10.0
STEP_WINDOW, STEP_REFERENCE, STEP_THRESHOLD, STEP_MIN_VARIANCE, STEP_CLIP = 5, 15, 7.0, 0.1, 4.0
# The fused variance's floors (config/default.toml): z_I's in squared z_I spreads (the bundle's
# calibration.z_I_spread; 0.3413 for a bundle without one), a projected code's in its own units.
MIN_SHAPE_VARIANCE, MIN_IDENTITY_VARIANCE, UNCALIBRATED_Z_I_SPREAD = 3.434e-3, 4e-4, 0.3413
DEFAULT_BUNDLE = pathlib.Path(__file__).resolve().parents[1] / "models" / "bundles" / "h200-fo-nodeid"


def z_i_spread(bundle) -> float:
    """The bundle's calibration.z_I_spread, or the one the node assumes for a bundle without it."""
    calibration = json.loads((pathlib.Path(bundle) / "manifest.json").read_text()).get("calibration") or {}
    return calibration.get("z_I_spread", UNCALIBRATED_Z_I_SPREAD)


class ShapeFilter:
    """src/track/shape.rs with the CUSUM detector, on variances already scaled; `floor`: the fused
    variance's floor (a projected code's by default; z_I's for z_I, `MIN_SHAPE_VARIANCE` times the
    squared z_I spread)."""

    def __init__(self, threshold, drift, floor=MIN_IDENTITY_VARIANCE):
        self.threshold, self.drift, self.floor = threshold, drift, floor
        self.frames, self.statistic, self.held = 0, 0.0, []

    def restart(self, frames):
        self.mean = np.zeros(len(frames[0][0]))
        self.precision = np.zeros(len(frames[0][0]))
        self.frames = 0
        for mean, variance in frames:
            self.fuse(mean, variance)

    def fuse(self, mean, variance):
        precision = 1.0 / np.maximum(variance, 1e-12)
        total = self.precision + precision
        self.mean = (self.mean * self.precision + mean * precision) / total
        self.precision = np.minimum(total, 1.0 / self.floor)
        self.frames += 1

    def update(self, mean, variance):
        """(distance, whether this frame completed a change)."""
        if self.frames == 0:
            self.restart([(mean, variance)])
            return 0.0, False
        distance = float(np.mean((mean - self.mean) ** 2 / (variance + 1.0 / self.precision)))
        inlier = distance <= GATE
        clip = self.drift + self.threshold / SWITCH
        self.statistic = max(0.0, self.statistic + min(distance, clip) - self.drift)
        if self.statistic <= 0.0:
            for held_mean, held_variance, held_inlier, fused in self.held:
                if held_inlier and not fused:
                    self.fuse(held_mean, held_variance)
            self.held = []
            if inlier:
                self.fuse(mean, variance)
            return distance, False
        fused = inlier and self.frames < MATURE
        if fused:
            self.fuse(mean, variance)
        self.held.append((mean, variance, inlier, fused))
        if len(self.held) > MAX_HELD:
            held_mean, held_variance, held_inlier, held_fused = self.held.pop(0)
            if held_inlier and not held_fused:
                self.fuse(held_mean, held_variance)
        if self.statistic >= self.threshold and len(self.held) >= SWITCH:
            self.restart([(m, v) for m, v, _, _ in self.held])
            self.held, self.statistic = [], 0.0
            return distance, True
        return distance, False


def end_on_degrees(state, truth):
    """Angle between the node's filtered heading and its line of sight to the object, folded to
    0 (end-on) .. 90 (side-on); the camera position is the recording's (the node's sensor pose)."""
    camera = truth["world_from_camera"]["translation"]
    centre = state["centre_m"]
    sight = math.atan2(centre[1] - camera[1], centre[0] - camera[0])
    relative = abs((state["filtered"]["yaw"] - sight + math.pi) % (2 * math.pi) - math.pi)
    return math.degrees(min(relative, math.pi - relative))


FEATURES = ["log points kept", "heading confidence", "yaw copies' scatter", "mean log z_I variance",
            "mean log z_E variance", "log points received"]


def frame_features(state):
    """What the node knows of a frame besides its codes (the `hetero` variant's inputs)."""
    raw = state["raw"]
    return np.array([
        math.log(max(state["points"]["kept"], 1)), raw["q_confidence"], raw["yaw_spread"],
        float(np.mean(np.log(raw["z_i_var"]))), float(np.mean(np.log(raw["z_e_var"]))),
        math.log(max(state["points"]["received"], 1)),
    ])


class StepDetector:
    """src/track/shape.rs's `step` detector: the last `window` frames against up to `reference`
    frames before them, each side fused as its precision-weighted mean (a frame's variance floored
    at `floor`), a change when their mean squared standardized distance exceeds the threshold; the
    new subject's frames begin the next reference. Slow wander moves both sides together; a change
    between subjects is a step. On a projected code (unit variances) the sides are plain means.
    A frame enters clipped to within `clip` standard deviations (its own and the reference mean's)
    of the reference mean, per dimension, so that one wild frame moves the window's mean a bounded
    amount and, later, the reference's; after a change the new subject's frames count unclipped."""

    def __init__(self, threshold, shape, floor=0.0, clip=math.inf):
        self.threshold, (self.window, self.reference), self.floor, self.clip = threshold, shape, floor, clip
        self.precision, self.value, self.raw, self.start = [], [], [], 0

    def side(self, begin, end):
        precision = np.sum(self.precision[begin:end], 0)
        return np.sum(np.multiply(self.precision[begin:end], self.value[begin:end]), 0) / precision, precision

    def update(self, mean, variance):
        precision = 1.0 / np.maximum(variance, max(self.floor, 1e-12))
        t = len(self.precision)
        first = t - self.window + 1
        begin = max(self.start, first - self.reference)
        value = mean
        if first - self.start >= SWITCH and math.isfinite(self.clip):
            before, before_precision = self.side(begin, first)
            limit = self.clip * np.sqrt(1 / precision + 1 / before_precision)
            value = before + np.clip(mean - before, -limit, limit)
        self.precision.append(precision)
        self.value.append(value)
        self.raw.append(mean)
        if first - self.start < SWITCH:
            return 0.0, False
        recent, recent_precision = self.side(first, t + 1)
        before, before_precision = self.side(begin, first)
        distance = float(np.mean((recent - before) ** 2 / (1 / recent_precision + 1 / before_precision)))
        if distance > self.threshold:
            self.start = first
            self.value[first:] = self.raw[first:]
            return distance, True
        return distance, False


def load(path):
    """Per stream: frames (raw z_I mean, scaled variance, end-on angle, truth frame, subject,
    family, the node's distance, raw heading, x_c, the frame's features, its line in the file) and
    the true change frames."""
    streams = {}
    for number, line in enumerate(open(path)):
        row = json.loads(line)
        row["line"] = number
        streams.setdefault(row["state"]["stream"], []).append(row)
    out = []
    for stream, rows in streams.items():
        rows.sort(key=lambda r: r["state"]["sequence"])
        if any(r["truth"] is None for r in rows):
            sys.exit(f"{path}: stream '{stream}' has states without ground truth (a sim recording's states are needed)")
        first = rows[0]["state"]
        # The node's variance scale (bundle calibration x shape_variance_scale), from the first
        # frame, whose fused variance is its own scaled variance.
        scale = first["shape"]["z_i_var"][0] / first["raw"]["z_i_var"][0]
        frames = [
            dict(
                mean=np.array(r["state"]["raw"]["z_i"]),
                variance=np.array(r["state"]["raw"]["z_i_var"]) * scale,
                end_on=end_on_degrees(r["state"], r["truth"]),
                frame=r["truth"]["frame"],
                subject=r["truth"]["subject"],
                family=r["truth"]["family"],
                node_distance=r["state"]["shape"]["distance"],
                node_statistic=r["state"]["shape"].get("change_statistic", 0.0),
                yaw=r["state"]["raw"]["yaw"],
                line=r["line"],
                x_c=np.array(r["x_c"]) if "x_c" in r else None,
                features=frame_features(r["state"]),
            )
            for r in rows
        ]
        switches = [b["frame"] for a, b in zip(frames, frames[1:]) if a["subject"] != b["subject"]]
        out.append((f"{path}:{stream}", frames, switches))
    return out


def node_detector(kind, bundle, threshold=None, drift=CUSUM_DRIFT):
    """The replica of the node's `kind` detector on z_I with the node's defaults (or `threshold`,
    `drift`) for `bundle`: ((threshold, drift or (window, reference), detector class), the state's
    figure it reproduces)."""
    if kind == "step":
        step = functools.partial(StepDetector, floor=STEP_MIN_VARIANCE * z_i_spread(bundle) ** 2, clip=STEP_CLIP)
        return (threshold or STEP_THRESHOLD, (STEP_WINDOW, STEP_REFERENCE), step), "node_statistic"
    cusum = functools.partial(ShapeFilter, floor=MIN_SHAPE_VARIANCE * z_i_spread(bundle) ** 2)
    return (threshold or CUSUM_THRESHOLD, drift, cusum), "node_distance"


def check_replica(streams, make, key):
    """The replica at the node's settings must give every frame the figure the node published:
    the distance to the estimate (`node_distance`, the CUSUM's input) or the step detector's
    statistic (`node_statistic`)."""
    for name, frames, _ in streams:
        detector = make()
        for f in frames:
            figure, _ = detector.update(f["mean"], f["variance"])
            if abs(figure - f[key]) > 1e-3 * max(1.0, figure):
                sys.exit(
                    f"{name} frame {f['frame']}: the replica's {key} {figure:.5f} is not the node's "
                    f"{f[key]:.5f}: src/track/shape.rs changed, or the states were made with other [track] "
                    f"settings than --node-detector and its settings, or with another bundle than --bundle"
                )


def count(streams, threshold, drift, code, detector=ShapeFilter):
    """(found, true changes, false, frames) of the detector on `code(frame) -> (mean, variance)`."""
    found = true = false = frames_seen = 0
    for _, frames, switches in streams:
        detector_now = detector(threshold, drift)
        reported = [f["frame"] for f in frames if detector_now.update(*code(f))[1]]
        used = [False] * len(reported)
        for k, t in enumerate(switches):
            end = min(t + TOLERANCE, (switches[k + 1] - 1) if k + 1 < len(switches) else t + TOLERANCE)
            for j, r in enumerate(reported):
                if not used[j] and t <= r <= end:
                    used[j] = True
                    found += 1
                    break
        true += len(switches)
        false += used.count(False)
        frames_seen += len(frames)
    return found, true, false, frames_seen


def discriminant(streams, directions, ridge, key):
    """Rows: the `directions` most discriminant directions of frame[key] for same-family subjects,
    scaled so that the within-subject scatter is 1 along each: the kit's fit-identity fit."""
    by_subject = {}
    for _, frames, _ in streams:
        for f in frames:
            by_subject.setdefault((f["family"], f["subject"]), []).append(f[key])
    fitted = fit_projection(by_subject, directions, ridge)
    return fitted["matrix"], len(by_subject), fitted["between_within"]


def choose(streams, grid, code, detector=ShapeFilter, budget=0.6):
    """The grid point that finds the most changes with at most `budget` false per 1,000 frames
    (then the fewest false): (threshold, drift, (found, true, false, frames)), or None."""
    best = None
    for threshold, drift in grid:
        figures = count(streams, threshold, drift, code, detector)
        found, _, false, frames = figures
        if 1000 * false / frames <= budget and (best is None or (found, -false) > (best[2][0], -best[2][2])):
            best = (threshold, drift, figures)
    return best


def trade_off(streams, grid, code, detector=ShapeFilter):
    """The found / false trade-off over the grid: (found, false, grid point) for each grid point
    that finds more than every point with fewer false changes."""
    points = []
    for index, (threshold, drift) in enumerate(grid):
        found, _, false, _ = count(streams, threshold, drift, code, detector)
        points.append((false, -found, index))
    front, most = [], -1
    for false, minus_found, index in sorted(points):
        if -minus_found > most:
            most = -minus_found
            front.append((most, false, grid[index]))
    return front


def frame_variances(fit, rows, key, used=None, iterations=50):
    """The `hetero` variant's per-direction variance of the projected code, log-linear in the
    frame's FEATURES (standardised), fitted by maximum likelihood (a Gaussian about each fit
    subject's mean code, Newton's method): (weights [directions, features + 1], centre, scale)."""
    by_subject = {}
    for _, frames, _ in fit:
        for f in frames:
            by_subject.setdefault((f["family"], f["subject"]), []).append(f)
    features, squares = [], []
    for frames in by_subject.values():
        codes = np.stack([rows @ f[key] for f in frames])
        squares.append((codes - codes.mean(0)) ** 2)
        features += [f["features"] for f in frames]
    features, squares = np.array(features), np.concatenate(squares)
    if used is not None:  # the features left out weigh nothing
        features = features * np.asarray(used, float)
    centre, scale = features.mean(0), features.std(0) + 1e-9
    scale[scale < 1e-6] = 1.0
    design = np.c_[(features - centre) / scale, np.ones(len(features))]
    weights = []
    for square in squares.T:
        w = np.zeros(design.shape[1])
        w[-1] = math.log(square.mean())
        for _ in range(iterations):
            ratio = square * np.exp(-(design @ w))
            hessian = (design * ratio[:, None]).T @ design + 1e-6 * np.eye(len(w))
            w -= np.linalg.solve(hessian, design.T @ (1 - ratio))
        weights.append(w)
    return np.array(weights), centre, scale


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--choice", required=True, help="states files the thresholds are chosen on (comma-separated)")
    parser.add_argument("--report", required=True, help="states files the choice is reported on (comma-separated)")
    parser.add_argument("--fit", help="states files the discriminant is fitted on (comma-separated)")
    parser.add_argument("--variants", default="cusum,step")
    parser.add_argument("--budget", type=float, default=0.6, help="false changes per 1,000 frames allowed on --choice")
    parser.add_argument("--view-widen", type=float, default=4.0)
    parser.add_argument("--hetero-without", default="", help="FEATURES the hetero variant leaves out (comma-separated names)")
    parser.add_argument("--fit-input", default="x_c", choices=["x_c", "z_I"], help="what the discriminant projects")
    parser.add_argument("--step-floor", default="0.1,0.34,1",
                        help="the z_I step variant's floors on a frame's variance, in squared z_I spreads (comma-separated)")
    parser.add_argument("--directions", default="5", help="comma-separated")
    parser.add_argument("--ridge", default="0.03", help="comma-separated")
    parser.add_argument("--node-detector", default="step", choices=["step", "cusum"],
                        help="the [track] change_detector the states were made with (on z_I; default: the node's)")
    parser.add_argument("--node-threshold", type=float, help="the [track] cusum_threshold or step_threshold the states were "
                        f"made with (default: the node's, {CUSUM_THRESHOLD:g} or {STEP_THRESHOLD:g})")
    parser.add_argument("--node-drift", type=float, default=CUSUM_DRIFT, help="the [track] cusum_drift the states were made with")
    parser.add_argument("--front", action="store_true", help="also print each variant's trade-off on --report")
    parser.add_argument("--bundle", default=str(DEFAULT_BUNDLE),
                        help="the bundle the states were made with: its z_I spread sets z_I's variance floor "
                             "(default: the default bundle)")
    args = parser.parse_args()

    unknown = [name for name in args.hetero_without.split(",") if name and name not in FEATURES]
    if unknown:
        sys.exit(f"--hetero-without {unknown}: the features are {FEATURES}")
    choice = {p: load(p) for p in args.choice.split(",")}
    report = {p: load(p) for p in args.report.split(",")}
    z_i_filter = node_detector("cusum", args.bundle)[0][2]  # the node's CUSUM on z_I, for the variants
    node_settings, node_figure = node_detector(args.node_detector, args.bundle, args.node_threshold, args.node_drift)
    for streams in [*choice.values(), *report.values()]:
        check_replica(streams, lambda: node_settings[2](node_settings[0], node_settings[1]), node_figure)
    print(f"replica of the node's {args.node_detector} detector checked against its published figures on "
          f"{len(choice) + len(report)} files")

    variants = {}
    plain_grid = list(itertools.product([10, 6, 4, 3], [3.5, 3.0, 2.5, 2.25, 2.0, 1.75]))
    names = args.variants.split(",")
    if "cusum" in names:
        variants["cusum"] = (lambda f: (f["mean"], f["variance"]), plain_grid, z_i_filter)
    if "view" in names:
        widen = args.view_widen

        def view(f):
            return f["mean"], f["variance"] * (1.0 + (widen - 1.0) * max(0.0, (30.0 - f["end_on"]) / 30.0))

        variants[f"view (x{widen:g} end-on)"] = (view, plain_grid, z_i_filter)
    step_shapes = list(itertools.product([3, 5, 8], [15, 30, 60]))
    if "step" in names:
        spread = z_i_spread(args.bundle)
        for floor in [float(f) for f in args.step_floor.split(",")]:
            variants[f"z_I, step (frame variance floor {floor:g} squared z_I spreads)"] = (
                lambda f: (f["mean"], f["variance"]),
                list(itertools.product([2, 2.5, 3, 3.5, 4, 5, 6, 6.5, 7, 7.5, 8, 10], step_shapes)),
                functools.partial(StepDetector, floor=floor * spread**2, clip=STEP_CLIP),
            )
    if "discriminant" in names:
        if not args.fit:
            sys.exit("the discriminant variant needs --fit states files (apart from --choice and --report)")
        key = "x_c" if args.fit_input == "x_c" else "mean"
        fit = [s for p in args.fit.split(",") for s in load(p)]
        if any(f[key] is None for _, frames, _ in fit for f in frames):
            sys.exit("--fit states without x_c: write them with a node that adds it (gdvae-node evaluate --states)")
        for directions, ridge in itertools.product(
            [int(d) for d in args.directions.split(",")], [float(r) for r in args.ridge.split(",")]
        ):
            rows, subjects, values = discriminant(fit, directions, ridge, key)
            name = f"discriminant of {args.fit_input} ({directions} directions, ridge {ridge:g})"
            print(f"{name}: {subjects} subjects fitted; between/within ratio along its directions {np.round(values, 2)}")
            unit = np.ones(len(rows))
            cusum_grid = list(itertools.product([20, 10, 6], [24.0, 16.0, 12.0, 9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0]))
            variants[name] = (lambda f, rows=rows, unit=unit: (rows @ f[key], unit), cusum_grid, ShapeFilter)
            if "hetero" in names:
                used = [name not in args.hetero_without.split(",") for name in FEATURES]
                weights, centre, scale = frame_variances(fit, rows, key, used)
                print(f"  hetero: log-variance per direction from {', '.join(f for f, u in zip(FEATURES, used) if u)} (standardised; "
                      f"every feature's weight, 0 for those left out): "
                      f"{np.round(weights[:, :-1], 2).tolist()}")

                def hetero(f, rows=rows, weights=weights, centre=centre, scale=scale):
                    return rows @ f[key], np.exp(weights @ np.r_[(f["features"] - centre) / scale, 1.0])

                variants[f"{name}, hetero"] = (hetero, cusum_grid, ShapeFilter)
            if "step" in names:
                variants[f"{name}, step"] = (
                    lambda f, rows=rows, unit=unit: (rows @ f[key], unit),
                    list(itertools.product([4, 6, 8, 10, 12, 15, 20, 25, 30, 40], step_shapes)),
                    StepDetector,
                )

    choice_streams = [s for streams in choice.values() for s in streams]
    report_streams = [s for streams in report.values() for s in streams]
    for label, streams in [("--choice", choice_streams), ("--report", report_streams)]:
        found, true, false, frames = count(streams, node_settings[0], node_settings[1], lambda f: (f["mean"], f["variance"]),
                                           node_settings[2])
        print(
            f"the node's own settings ({args.node_detector}, threshold {node_settings[0]:g}, {node_settings[1]}) on {label}: "
            f"{found}/{true} found, {false} false in {frames} frames = {1000 * false / frames:.2f} per 1,000"
        )
    chosen = {}
    for name, (code, grid, detector) in variants.items():
        best = choose(choice_streams, grid, code, detector, args.budget)
        if best is None:
            print(f"{name}: nothing on the grid keeps within {args.budget} false per 1,000 frames on --choice")
            continue
        threshold, drift, (found, true, false, frames) = best
        chosen[name] = (found, -false)
        stepped = detector is StepDetector or getattr(detector, "func", None) is StepDetector
        settings = (f"threshold {threshold}, (window, reference) {drift}" if stepped
                    else f"cusum_threshold {threshold}, cusum_drift {drift}")
        print(f"\n{name}: chosen {settings} ({found}/{true} found, {false} false in {frames} frames on --choice)")
        total = np.zeros(4, dtype=int)
        for path, streams in report.items():
            figures = count(streams, threshold, drift, code, detector)
            total += figures
            print(f"  {path}: {figures[0]}/{figures[1]} found, {figures[2]} false")
        print(
            f"  report total: {total[0]}/{total[1]} found, {total[2]} false in {total[3]} frames "
            f"= {1000 * total[2] / total[3]:.2f} per 1,000"
        )
        if args.front:
            front = trade_off(report_streams, grid, code, detector)
            print("  report trade-off: " + "; ".join(f"{found} found at {false} false ({h:g}, {k})" for found, false, (h, k) in front))
    discriminants = {name: score for name, score in chosen.items()
                     if name.startswith("discriminant") and not name.endswith(("hetero", "step"))}
    if len(discriminants) > 1:
        print(f"\nthe discriminant that finds the most on --choice (then the fewest false): "
              f"{max(discriminants, key=discriminants.get)}")


if __name__ == "__main__":
    main()
