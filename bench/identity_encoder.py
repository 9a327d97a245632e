"""Does an identity encoder trained on the node's own clouds tell subjects apart better than the
shipped identity projection of x_c? A measurement, replayed in the node's change detector.

The shipped projection (`python -m gdvae fit-identity`) is linear in the autoencoder's x_c, and
fitting it on more subjects barely helps (docs/tracking.md, "An identity code fitted on the node's
clouds"): the limit is what x_c holds. This trains, on the `--train` sets' node clouds
(`gdvae-node evaluate --states S-states.jsonl --clouds S-clouds.npy`, both in `--data`), a small
PointNet (`--input cloud`: the N_p points turned back by the node's raw heading) or an MLP on x_c
(`--input x_c`) to name each training subject (cross-entropy over all of them); its code is then
read as the node reads x_c: the kit's same-family discriminant (`gdvae.identity.fit_projection`,
5 directions, ridge 0.03), fitted on the `--whiten` sets (subjects the encoder never saw). The
shipped kind of projection, x_c's discriminant fitted on the same `--whiten` subjects, is measured
beside it. Both go through bench/change_detector.py's replica of the node's shape filter with
unit variances: threshold and drift chosen on `--choice` (most found at <= 0.6 false per 1,000
frames), reported on `--report` with the whole found / false trade-off there.

    .venv/bin/python bench/identity_encoder.py --train fit-1,...,fit-12 --whiten fit-13,...,fit-16 \
        --choice tune,stand-tune,extra-1,idle-tune,still-tune --report holdout,final,... \
        --data FOLDER [--input cloud|x_c] [--epochs 12] [--seed 0]

The states must be written with `--set use_identity_projection=false` (the replica checks the
node's z_I detector, not used here, so this is not checked again). Prints the encoder's training
curve, then per code: the between / within-subject ratios of its directions on the `--whiten`
subjects, the chosen point on `--choice`, and on `--report` the total, the idle / still sets'
false changes, `holdout` + `final` pooled, and the trade-off ("found@false").
"""
import argparse
import itertools
import math
import pathlib
import sys
import time

import numpy as np
import torch

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "models"))
import change_detector  # noqa: E402  (the node's shape filter, replayed)
from gdvae.identity import fit_projection  # noqa: E402
from gdvae.nets import PointNet  # noqa: E402

GRID = list(itertools.product([30, 20, 14, 10, 6], [24.0, 16.0, 12.0, 9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0]))


def load(folder: pathlib.Path, name: str):
    """(clouds [states, N_p, 3], the states' streams as change_detector.load reads them; each
    frame's `line` is its row in the clouds)."""
    clouds = np.load(folder / f"{name}-clouds.npy")
    streams = change_detector.load(str(folder / f"{name}-states.jsonl"))
    states = sum(len(frames) for _, frames, _ in streams)
    if states != len(clouds):
        sys.exit(f"{name}: {states} states but {len(clouds)} clouds: write both with one evaluate run")
    return clouds, streams


def turned_back(clouds: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Each cloud turned by minus its heading about +z (the node's canonical frame's up)."""
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x, y = clouds[..., 0], clouds[..., 1]
    return np.stack([c * x + s * y, -s * x + c * y, clouds[..., 2]], -1).astype(np.float32)


def inputs(clouds, streams, kind):
    """The encoder's input for every frame of `streams` (in their order) and the frames."""
    frames = [f for _, fs, _ in streams for f in fs]
    if kind == "x_c":
        return np.stack([f["x_c"] for f in frames]).astype(np.float32), frames
    rows = [f["line"] for f in frames]
    return turned_back(clouds[rows], np.array([f["yaw"] for f in frames])), frames


class Encoder(torch.nn.Module):
    def __init__(self, kind, width, embed, subjects, mean, scale):
        super().__init__()
        self.kind = kind
        if kind == "cloud":
            self.net = PointNet((64, 128, 256), embed)
        else:
            self.net = torch.nn.Sequential(
                torch.nn.Linear(width, 256), torch.nn.GELU(), torch.nn.Dropout(0.1),
                torch.nn.Linear(256, 256), torch.nn.GELU(), torch.nn.Dropout(0.1), torch.nn.Linear(256, embed))
        self.register_buffer("mean", torch.as_tensor(mean))
        self.register_buffer("scale", torch.as_tensor(scale))
        self.classes = torch.nn.Linear(embed, subjects)

    def forward(self, x):
        return self.net((x - self.mean) / self.scale)

    def logits(self, x):
        code = self(x)
        return self.classes(torch.relu(code) if self.kind == "cloud" else code)


def train(x, labels, kind, epochs, seed):
    torch.manual_seed(seed)
    if kind == "cloud":
        mean, scale = np.zeros(3, np.float32), np.ones(3, np.float32)
    else:
        mean, scale = x.mean(0), x.std(0) + 1e-6
    model = Encoder(kind, x.shape[-1], 64 if kind == "cloud" else 32, int(labels.max()) + 1, mean, scale)
    x, labels = torch.as_tensor(x), torch.as_tensor(labels)
    batch = 128 if kind == "cloud" else 512
    steps = max(1, epochs * (len(x) // batch))
    learning_rate = 2e-3
    optimizer = torch.optim.AdamW(model.parameters(), lr=learning_rate, weight_decay=1e-4 if kind == "cloud" else 1e-3)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, learning_rate, total_steps=steps)
    started = time.time()
    for epoch in range(epochs):
        model.train()
        order, total, right = torch.randperm(len(x)), 0.0, 0.0
        for b in range(len(x) // batch):
            pick = order[b * batch:(b + 1) * batch]
            batch_x = x[pick]
            if kind == "cloud":
                batch_x = batch_x + 0.005 * torch.randn_like(batch_x)  # sensor-like jitter
            logits = model.logits(batch_x)
            loss = torch.nn.functional.cross_entropy(logits, labels[pick])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()
            total += loss.item()
            right += (logits.argmax(1) == labels[pick]).float().mean().item()
        n = len(x) // batch
        print(f"  epoch {epoch + 1}/{epochs}: loss {total / n:.3f}, training subjects named {right / n:.3f} "
              f"({time.time() - started:.0f} s)", flush=True)
    model.eval()
    return model


def codes(model, x):
    with torch.no_grad():
        return torch.cat([model(torch.as_tensor(x[i:i + 1024])) for i in range(0, len(x), 1024)]).numpy().astype(float)


def replay(label, by_subject, key, choice, report):
    fitted = fit_projection(by_subject, 5, 0.03)
    rows = fitted["matrix"]
    for _, frames, _ in choice + [s for streams in report.values() for s in streams]:
        for f in frames:
            f["projected"] = rows @ f[key]
    unit = np.ones(len(rows))

    def code(f):
        return f["projected"], unit

    best = change_detector.choose(choice, GRID, code)
    everything = [s for streams in report.values() for s in streams]
    print(f"\n{label}: between/within ratios {np.round(fitted['between_within'], 1)}")
    if best is None:
        print("  nothing on the grid keeps within 0.6 false per 1,000 frames on --choice")
    else:
        h, k, (found, true, false, _) = best
        on_choice = f"{found}/{true} found, {false} false"
        found, true, false, frames = change_detector.count(everything, h, k, code)
        idle = sum(change_detector.count(report[n], h, k, code)[2] for n in report if n.startswith(("idle", "still")))
        pooled = [change_detector.count(report[n], h, k, code) for n in ("holdout", "final") if n in report]
        print(f"  chosen threshold {h}, drift {k} ({on_choice} on --choice); --report {found}/{true} found, "
              f"{false} false = {1000 * false / frames:.2f} per 1,000 (idle/still sets {idle}); holdout + final "
              f"{sum(p[0] for p in pooled)}/{sum(p[1] for p in pooled)} with {sum(p[2] for p in pooled)} false")
    front = change_detector.trade_off(everything, GRID, code)
    print("  --report trade-off (found@false): " + " ".join(f"{found}@{false}" for found, false, _ in front))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name in ("train", "whiten", "choice", "report"):
        parser.add_argument(f"--{name}", required=True, help="set names, comma-separated")
    parser.add_argument("--data", required=True, type=pathlib.Path,
                        help="folder of SET-states.jsonl and SET-clouds.npy (evaluate --states / --clouds)")
    parser.add_argument("--input", default="cloud", choices=["cloud", "x_c"])
    parser.add_argument("--epochs", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(2)
    held = {n for key in ("whiten", "choice", "report") for n in getattr(args, key).split(",")}
    if held & set(args.train.split(",")):
        sys.exit(f"--train shares {sorted(held & set(args.train.split(',')))} with --whiten/--choice/--report: "
                 f"the encoder must not have seen the subjects it is measured on")
    sets = {n: load(args.data, n) for key in ("train", "whiten", "choice", "report") for n in getattr(args, key).split(",")}

    train_x, train_frames = [], []
    for name in args.train.split(","):
        x, frames = inputs(*sets[name], args.input)
        train_x.append(x)
        train_frames += frames
    subjects = sorted({(f["family"], f["subject"]) for f in train_frames})
    index = {s: i for i, s in enumerate(subjects)}
    labels = np.array([index[(f["family"], f["subject"])] for f in train_frames])
    print(f"training on {len(labels)} frames of {len(subjects)} subjects ({args.input})", flush=True)
    model = train(np.concatenate(train_x), labels, args.input, args.epochs, args.seed)

    for name, (clouds, streams) in sets.items():
        if name in args.train.split(","):
            continue
        x, frames = inputs(clouds, streams, args.input)
        for f, c in zip(frames, codes(model, x)):
            f["encoder"] = c
    encoder_fit, x_c_fit = {}, {}
    for name in args.whiten.split(","):
        for _, frames, _ in sets[name][1]:
            for f in frames:
                encoder_fit.setdefault((f["family"], f["subject"]), []).append(f["encoder"])
                x_c_fit.setdefault((f["family"], f["subject"]), []).append(f["x_c"].astype(float))
    choice = [s for n in args.choice.split(",") for s in sets[n][1]]
    report = {n: sets[n][1] for n in args.report.split(",")}
    print(f"\nwhitened on {len(encoder_fit)} subjects of --whiten")
    replay("x_c's discriminant (the shipped kind of projection)", x_c_fit, "x_c", choice, report)
    replay(f"the {args.input} encoder's discriminant", encoder_fit, "encoder", choice, report)


if __name__ == "__main__":
    main()
