"""What would lift the kit's disentanglement score S (issue 32's target: 2.0 on the paper-structured
split)? S adds z_I's shape retrieval and z_E's pose retrieval, each relative to x_c's, and takes
away their cross terms (models/gdvae/metrics.py). Two probes against a trained run, on an
evaluation split of fresh subjects in the sim's random poses (`make eval-split`, or the same
command with another seed to choose on):

- `oracle RUN SPLIT`: S with the sim's truth in place of a code (z_E = theta, z_I = beta, each
  alone and both), and with the taught encoders' own codes x_p and x_b (where the run has them) in
  place of z_E and z_I, beside the run's own: how far each half of S can go, and what the VAE loses;
- `taught RUN SPLIT --train DATASETS --target beta|theta --seconds S`: a narrow PointNet (32, 64,
  128) reading each cloud turned back by the run's own rotation estimate (E_p's frame) is taught
  the sim's normalised beta or its standardised theta (every joint angle, padded per family) for S
  seconds on the training meshes of DATASETS; every two minutes it prints its held-out R2 and S with
  its prediction in place of the run's z_I (beta) or z_E (theta). One draw of points and rotations
  (the kit's S averages five).

    .venv/bin/python bench/s_probe.py oracle RUN /work/data/sim-eval-tune
    .venv/bin/python bench/s_probe.py taught RUN /work/data/sim-eval-tune --train /work/data/sim-many \
        --target theta --seconds 720
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "models"))
from gdvae.data import load_dataset  # noqa: E402
from gdvae.evaluate import PointSampler, beta_ranges, encode_all, normalised_beta  # noqa: E402
from gdvae.geometry import quaternion_to_matrix, random_rotation_matrices, rotate  # noqa: E402
from gdvae.metrics import disentanglement  # noqa: E402
from gdvae.nets import PointNet  # noqa: E402
from gdvae.train import load_run  # noqa: E402

FAMILIES = ("biped", "quadruped")
WIDTH = 128  # padded target columns per family (the sim's skeletons have fewer joint angles)


def split_codes(ae, vae, root: str) -> dict:
    """The run's codes of one whole-surface sample per test mesh, in a random yaw, with the truth."""
    dataset = load_dataset(root)
    indices = dataset.indices("test")
    torch.manual_seed(0)
    clouds = PointSampler(dataset, indices, ae.config.points, 0).one_each()
    rotations = random_rotation_matrices(len(clouds))
    codes = encode_all(ae, vae, clouds, rotations, None)
    with torch.no_grad():
        inputs = rotate(clouds, rotations)
        estimate = quaternion_to_matrix(ae.encode_rotation(inputs))
        canonical = rotate(inputs, estimate.transpose(-1, -2))
        codes.update(ae.taught_codes(inputs, estimate))  # x_p, x_b: what z_E's and z_I's encoders read
    truths = [dataset.items[i].truth for i in indices]
    ranges = beta_ranges(dataset.root)
    families = {}
    for family in FAMILIES:
        rows = [k for k, t in enumerate(truths) if t["family"] == family]
        families[family] = {
            "rows": rows,
            "beta": normalised_beta(np.array([truths[k]["beta"] for k in rows], float), family, ranges),
            "theta": np.array([truths[k]["theta"] for k in rows], float),
            **{key: codes[key][rows].numpy() for key in ("x_c", "mu_E", "mu_I", "x_p", "x_b") if codes.get(key) is not None},
        }
    return {"canonical": canonical, "families": families}


def score(part: dict, z_e: np.ndarray, z_i: np.ndarray) -> str:
    result = disentanglement({"x_c": part["x_c"], "z_E": z_e, "z_I": z_i}, part["beta"], part["theta"])
    c = result["codes"]
    return (f"S {result['S']:.2f} (z_I shape {c['z_I']['s_hat_beta']:.2f}, pose {c['z_I']['s_hat_theta']:.2f}; "
            f"z_E pose {c['z_E']['s_hat_theta']:.2f}, shape {c['z_E']['s_hat_beta']:.2f})")


def oracle(args, ae, vae) -> None:
    for family, part in split_codes(ae, vae, args.split)["families"].items():
        print(f"{family} ({len(part['rows'])} meshes)")
        print(f"  the run's codes           {score(part, part['mu_E'], part['mu_I'])}")
        print(f"  z_E = theta               {score(part, part['theta'], part['mu_I'])}")
        print(f"  z_I = beta                {score(part, part['mu_E'], part['beta'])}")
        print(f"  z_E = theta, z_I = beta   {score(part, part['theta'], part['beta'])}")
        if "x_p" in part:  # the pose encoder's own code in place of z_E (what z_E's encoder could keep)
            print(f"  z_E = x_p                 {score(part, part['x_p'], part['mu_I'])}")
        if "x_b" in part:
            print(f"  z_I = x_b                 {score(part, part['mu_E'], part['x_b'])}")
        if "x_p" in part and "x_b" in part:
            print(f"  z_E = x_p, z_I = x_b      {score(part, part['x_p'], part['x_b'])}")


def standardised(values: np.ndarray) -> np.ndarray:
    spread = values.std(0)
    return np.where(spread > 0, (values - values.mean(0)) / np.maximum(spread, 1e-12), 0.0)


def targets_of(truths: list[dict], root, target: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per training mesh: its family's target columns (padded to WIDTH), their mask, the family."""
    ranges = beta_ranges(root)
    rows = np.zeros((len(truths), WIDTH), np.float32)
    mask = np.zeros_like(rows)
    family = np.array([FAMILIES.index(t["family"]) for t in truths])
    for f, name in enumerate(FAMILIES):
        members = np.nonzero(family == f)[0]
        if len(members) < 2:
            raise SystemExit(f"{root}: fewer than 2 training meshes of family {name!r}")
        raw = np.array([truths[i][target] for i in members], float)
        if target == "beta":
            raw = normalised_beta(raw, name, ranges)
        rows[members, : raw.shape[1]] = standardised(raw)
        mask[members, : raw.shape[1]] = raw.std(0) > 0
    return torch.from_numpy(rows), torch.from_numpy(mask), torch.from_numpy(family)


def taught(args, ae, vae) -> None:
    torch.set_num_threads(2)
    training = []
    for root in args.train.split(","):
        dataset = load_dataset(root)
        indices = dataset.indices("train")
        rows, mask, family = targets_of([dataset.items[i].truth for i in indices], dataset.root, args.target)
        training.append((PointSampler(dataset, indices, ae.config.points, 5), rows, mask, family))
    held = split_codes(ae, vae, args.split)
    encoder, heads = PointNet((32, 64, 128), 64), nn.Linear(64, WIDTH * len(FAMILIES))
    optimizer = torch.optim.Adam([*encoder.parameters(), *heads.parameters()], 5e-4)
    generator = torch.Generator().manual_seed(0)

    def report(step: int) -> None:
        encoder.eval()
        with torch.no_grad():
            predicted = heads(encoder(held["canonical"])).view(-1, len(FAMILIES), WIDTH)
        for f, (name, part) in enumerate(held["families"].items()):
            truth = part[args.target]
            mine = predicted[part["rows"], f, : truth.shape[1]].numpy()
            live = truth.std(0) > 0
            r2 = 1 - ((mine - standardised(truth))[:, live] ** 2).mean()
            z_e, z_i = (mine, part["mu_I"]) if args.target == "theta" else (part["mu_E"], mine)
            print(f"step {step} {name}: held-out R2 {r2:.2f}; in place of the run's "
                  f"{'z_E' if args.target == 'theta' else 'z_I'}: {score(part, z_e, z_i)}; "
                  f"the run's own: {score(part, part['mu_E'], part['mu_I'])}", flush=True)
        encoder.train()

    started, step, next_report = time.monotonic(), 0, 0.0
    while True:
        elapsed = time.monotonic() - started
        if elapsed >= next_report:
            report(step)
            next_report += 120.0
        if elapsed > args.seconds:
            break
        sampler, rows, mask, family = training[int(torch.randint(len(training), (1,), generator=generator))]
        meshes = torch.randint(0, len(sampler), (32,), generator=generator)
        with torch.no_grad():
            clouds = rotate(sampler.views(meshes, 1, 0.0), random_rotation_matrices(32, generator))
            clouds = rotate(clouds, quaternion_to_matrix(ae.encode_rotation(clouds)).transpose(-1, -2))
        predicted = heads(encoder(clouds)).view(32, len(FAMILIES), WIDTH)[torch.arange(32), family[meshes]]
        weights = mask[meshes]
        loss = ((predicted - rows[meshes]).pow(2) * weights).sum() / weights.sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
    report(step)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("oracle", "taught"):
        command = commands.add_parser(name)
        command.add_argument("run", help="a trained run folder (or an imported bundle's)")
        command.add_argument("split", help="an evaluation split: one pose per fresh subject (make eval-split)")
        if name == "taught":
            command.add_argument("--train", required=True, help="comma-separated sim datasets to teach on")
            command.add_argument("--target", choices=("beta", "theta"), required=True)
            command.add_argument("--seconds", type=float, default=720.0)
    args = parser.parse_args()
    _, ae, vae, _ = load_run(args.run)
    if vae is None:
        raise SystemExit(f"{args.run}: no trained VAE")
    ae.eval()
    vae.eval()
    (oracle if args.command == "oracle" else taught)(args, ae, vae)


if __name__ == "__main__":
    main()
