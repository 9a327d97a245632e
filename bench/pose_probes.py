"""Does a trained run's code carry the body's pose in a form that holds for animals and poses it has
not seen? Three probes on the sim's depth-camera views (issue 32, models/EXPERIMENTS.md "Does any
z_E name the pose?"), each trained or measured on one dataset and tested on another whose subjects
and poses are fresh (e.g. `sim dataset --subjects 8 --poses 40 --seed 11 --gait-fraction 0.5
--split 0,0,1`):

- `retrieval RUN TEST`: per family, the median over meshes of the true-pose distance to the mesh of
  another subject whose mu_E is nearest, over the median true-pose distance (`gdvae-node
  evaluate`'s pose retrieval; 1: mu_E says nothing of the pose), on walking and prior poses apart;
- `probe RUN FIT TEST`: theta from mu_E and from x_c by ridge regression, and the gait phase
  (sin, cos) of the walking poses by a small MLP, fitted on FIT's training meshes (two views each),
  R2 on TEST's;
- `encoder RUN FIT TEST --seconds S`: fine-tunes the AE's shape encoder with a linear head per
  family onto the top 10 principal components of theta (standardised) for S seconds, printing the
  held-out R2 and the retrieval by the head's output every 500 steps: whether the point encoder
  itself can learn a pose code, and how fast on this machine (`--checkpoint FILE` saves it every
  2,000 steps and resumes a run cut short).

    .venv/bin/python bench/pose_probes.py retrieval RUN TEST
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "models"))
from gdvae.data import DepthCamera, load_dataset  # noqa: E402
from gdvae.evaluate import encode_all  # noqa: E402
from gdvae.geometry import quaternion_to_matrix, random_rotation_matrices, rotate  # noqa: E402
from gdvae.surface import PointSampler, view_directions  # noqa: E402
from gdvae.train import load_run, use_model_units  # noqa: E402

FAMILIES = ("quadruped", "biped")
CPU = torch.device("cpu")


class Views:
    """Depth-camera views of a dataset split's meshes in a run's units, `copies` per mesh (a random
    direction and yaw each), with each view's ground truth."""

    def __init__(self, run: str, points: int, data: str, split: str, copies: int, seed: int):
        dataset = load_dataset(data)
        use_model_units(dataset, json.loads((Path(run) / "dataset.json").read_text())["scale"])
        indices = dataset.indices(split)
        if not indices:
            raise SystemExit(f"{data}: no meshes in its {split!r} split")
        self.generator = torch.Generator().manual_seed(seed)
        self.sampler = PointSampler(dataset, indices, points, seed, DepthCamera(), "cpu")
        self.meshes = torch.arange(len(indices)).repeat(copies)
        self.truth = [dataset.items[indices[m]].truth for m in self.meshes.tolist()]
        self.family = np.array([FAMILIES.index(t["family"]) for t in self.truth])
        self.subject = np.array([t["subject"] for t in self.truth])

    def clouds(self, meshes: torch.Tensor, turned: bool = True) -> torch.Tensor:
        """Views of `meshes`, each turned by a random yaw (`turned`) or left in the mesh's canonical
        frame (the sim's meshes face +x)."""
        views = self.sampler.partial_views(meshes, view_directions(len(meshes), self.generator, CPU))
        turns = random_rotation_matrices(len(meshes), self.generator)
        return rotate(views, turns) if turned else views

    def codes(self, ae, vae) -> dict:
        parts = []
        with torch.no_grad():
            for chunk in self.meshes.split(512):
                parts.append(encode_all(ae, vae, self.clouds(chunk), torch.eye(3).expand(len(chunk), 3, 3), None))
        return {key: torch.cat([p[key] for p in parts]).numpy() for key in ("x_c", "mu_E", "mu_I")}

    def theta(self, family: int) -> np.ndarray:
        return np.array([t["theta"] for t, f in zip(self.truth, self.family) if f == family])


def retrieval_ratio(codes: np.ndarray, theta: np.ndarray, subjects: np.ndarray) -> float:
    """The median over rows of (true distance to the nearest code of another subject) / (median
    true distance to all other subjects' rows)."""
    ratios = []
    for i in range(len(codes)):
        others = np.nonzero(subjects != subjects[i])[0]
        truth = np.linalg.norm(theta[others] - theta[i], axis=1)
        if len(others) and np.median(truth) > 0:
            ratios.append(truth[np.argmin(np.linalg.norm(codes[others] - codes[i], axis=1))] / np.median(truth))
    return float(np.median(ratios)) if ratios else float("nan")


def subject_auc(codes: np.ndarray, subjects: np.ndarray) -> float:
    """The probability that two views of one subject are nearer in `codes` than two views of two
    subjects (of the same family: the caller passes one family's rows)."""
    distances = np.linalg.norm(codes[:, None] - codes[None], axis=-1)
    upper = np.triu_indices(len(codes), 1)
    same = (subjects[:, None] == subjects[None])[upper]
    inside, between = np.sort(distances[upper][same]), distances[upper][~same]
    return float(np.searchsorted(inside, between, side="left").mean() / len(inside))


def identity(args) -> None:
    """Same-family subject AUC of mu_I and x_c on TEST's single views, as they are and whitened by
    their within-subject covariance per family, fitted on FIT's training meshes (`--fit`, three
    views each): how much a fixed metric that ignores what the view and the pose move would give."""
    _, ae, vae, _ = load_run(args.run)
    views = Views(args.run, ae.config.points, args.test, "test", 1, args.seed + 1)
    codes = views.codes(ae, vae)
    fit = Views(args.run, ae.config.points, args.fit, "train", 3, args.seed) if args.fit else None
    fit_codes = fit.codes(ae, vae) if fit else None
    for f, family in enumerate(FAMILIES):
        rows = views.family == f
        figures = []
        for key in ("mu_I", "x_c"):
            figures.append(f"{key} {subject_auc(codes[key][rows], views.subject[rows]):.3f}")
            if fit is not None:
                mine = fit.family == f
                if args.fit_subjects:
                    mine &= np.isin(fit.subject, np.unique(fit.subject[mine])[:args.fit_subjects])
                x, subjects = fit_codes[key][mine], fit.subject[mine]
                names, of_subject = np.unique(subjects, return_inverse=True)
                subject_means = np.stack([x[of_subject == k].mean(0) for k in range(len(names))])[of_subject]
                centred = x - subject_means
                within = centred.T @ centred / len(x) + 1e-6 * np.eye(x.shape[1])
                values, vectors = np.linalg.eigh(within)
                whiten = vectors / np.sqrt(np.maximum(values, 1e-9 * values.max()))
                means = subject_means - x.mean(0)
                between = (means @ whiten).T @ (means @ whiten) / len(x)
                _, axes = np.linalg.eigh(between)
                for k in (4, 8, 16):
                    lda = whiten @ axes[:, ::-1][:, :k]
                    figures.append(f"LDA{k} {subject_auc(codes[key][rows] @ lda, views.subject[rows]):.3f}")
        print(f"{family:10s} same-family subject AUC, single views: " + ", ".join(figures))


def r2(predicted, target) -> float:
    return float(1 - ((target - predicted) ** 2).sum() / ((target - target.mean(0)) ** 2).sum())


def retrieval(args) -> None:
    _, ae, vae, _ = load_run(args.run)
    views = Views(args.run, ae.config.points, args.test, "test", 1, args.seed)
    mu_e = views.codes(ae, vae)["mu_E"]
    walking = np.array([t.get("gait_phase") is not None for t in views.truth])
    for f, family in enumerate(FAMILIES):
        for label, rows in (("all", views.family == f), ("walking", (views.family == f) & walking),
                            ("prior", (views.family == f) & ~walking)):
            if rows.sum() > 1:
                theta = np.array([t["theta"] for t, r in zip(views.truth, rows) if r])
                print(f"{family:10s} {label:8s} pose retrieval by mu_E {retrieval_ratio(mu_e[rows], theta, views.subject[rows]):.2f} "
                      f"(floor {retrieval_ratio(theta, theta, views.subject[rows]):.2f}, {rows.sum()} views)")


def run_and_views(args, fit_copies: int):
    """The run's autoencoder and VAE, FIT's training meshes (`fit_copies` views each) and TEST's test
    meshes (one view each)."""
    _, ae, vae, _ = load_run(args.run)
    points = ae.config.points
    return (ae, vae, Views(args.run, points, args.fit, "train", fit_copies, args.seed),
            Views(args.run, points, args.test, "test", 1, args.seed + 1))


def probe(args) -> None:
    ae, vae, fit, test = run_and_views(args, 2)
    fit_codes, test_codes = fit.codes(ae, vae), test.codes(ae, vae)
    for f, family in enumerate(FAMILIES):
        for key in ("mu_E", "x_c"):
            x, xt = fit_codes[key][fit.family == f], test_codes[key][test.family == f]
            mean, std = x.mean(0), x.std(0) + 1e-6
            a, at = (np.c_[(v - mean) / std, np.ones(len(v))] for v in (x, xt))
            weights = np.linalg.solve(a.T @ a + 10.0 * np.eye(a.shape[1]), a.T @ fit.theta(f))
            print(f"{family:10s} {key:5s} theta by ridge: R2 fit {r2(a @ weights, fit.theta(f)):.2f}, "
                  f"held-out {r2(at @ weights, test.theta(f)):.2f}")
            phase_probe(family, key, fit, test, fit_codes[key], test_codes[key], f)


def phase_probe(family, key, fit, test, fit_codes, test_codes, f) -> None:
    """An MLP (128 hidden units) from the code to the gait phase (sin, cos) of the walking poses."""
    def rows(views, codes):
        keep = [i for i, t in enumerate(views.truth) if views.family[i] == f and t.get("gait_phase") is not None]
        phase = np.array([views.truth[i]["gait_phase"] for i in keep]) * 2 * np.pi
        return torch.from_numpy(codes[keep]).float(), torch.from_numpy(np.c_[np.sin(phase), np.cos(phase)]).float()
    (x, y), (xt, yt) = rows(fit, fit_codes), rows(test, test_codes)
    if len(x) < 10 or len(xt) < 2:
        return
    mean, std = x.mean(0), x.std(0) + 1e-6
    x, xt = (x - mean) / std, (xt - mean) / std
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 128), torch.nn.ReLU(), torch.nn.Linear(128, 2))
    optimizer = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-3)
    for _ in range(1500):
        loss = (net(x) - y).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = net(xt)
        error = torch.rad2deg(torch.atan2(predicted[:, 0], predicted[:, 1]) - torch.atan2(yt[:, 0], yt[:, 1])).remainder(360)
        error = torch.minimum(error, 360 - error).median()
        print(f"{family:10s} {key:5s} gait phase by MLP: R2 fit {r2(net(x).numpy(), y.numpy()):.2f}, held-out "
              f"{r2(predicted.numpy(), yt.numpy()):.2f}, median phase error {error:.0f} deg (chance 90; "
              f"{len(x)} / {len(xt)} views)")


def pose_targets(fit, test):
    """Theta on its top 10 principal components per family (fitted on FIT), standardised, and the
    measure: held-out retrieval of the true pose by the head's output."""
    components = {}
    for f, family in enumerate(FAMILIES):
        theta = fit.theta(f)
        mean = theta.mean(0)
        _, values, axes = np.linalg.svd(theta - mean, full_matrices=False)
        std = ((theta - mean) @ axes[:10].T).std(0)
        components[f] = (mean, axes[:10], std)
        print(f"{family}: the top 10 principal components hold {100 * (values[:10] ** 2).sum() / (values ** 2).sum():.0f}% "
              "of theta's variance")

    def targets(views):
        return torch.tensor(np.array([((np.array(t["theta"]) - components[f][0]) @ components[f][1].T) / components[f][2]
                                      for t, f in zip(views.truth, views.family)]), dtype=torch.float32)

    def measure(predicted):
        return "retrieval " + " / ".join(
            f"{retrieval_ratio(predicted[test.family == f], test.theta(f), test.subject[test.family == f]):.2f}"
            for f in range(len(FAMILIES)))
    return targets(fit), targets(test), measure


def beta_targets(fit, test):
    """The sim's shape parameters (beta) per family, standardised on FIT (zero-padded to the widest
    family's), and the measure: same-family subject AUC of the head's output on single views."""
    width = max(len(t["beta"]) for t in fit.truth)
    stats = {}
    for f in range(len(FAMILIES)):
        beta = np.array([t["beta"] for t, g in zip(fit.truth, fit.family) if g == f])
        stats[f] = (beta.mean(0), beta.std(0) + 1e-9)

    def targets(views):
        rows = np.zeros((len(views.truth), width), np.float32)
        for i, (t, f) in enumerate(zip(views.truth, views.family)):
            rows[i, :len(t["beta"])] = (np.array(t["beta"]) - stats[f][0]) / stats[f][1]
        return torch.from_numpy(rows)

    def measure(predicted):
        return "subject AUC " + " / ".join(
            f"{subject_auc(predicted[test.family == f], test.subject[test.family == f]):.3f}" for f in range(len(FAMILIES)))
    return targets(fit), targets(test), measure


def encoder(args) -> None:
    ae, _, fit, test = run_and_views(args, 1)
    fit_targets, test_targets, held_out = (beta_targets if args.target == "beta" else pose_targets)(fit, test)
    width = fit_targets.shape[1]

    def framed(views, meshes):
        """The encoder's input: a view turned by a random yaw (`any`), left facing the way the mesh
        faces (`true`: the heading known), or turned and turned back by the autoencoder's own
        rotation estimate (`estimated`: what a bundle can do)."""
        if args.frame == "true":
            return views.clouds(meshes, turned=False)
        clouds = views.clouds(meshes)
        if args.frame == "estimated":
            with torch.no_grad():
                clouds = rotate(clouds, quaternion_to_matrix(ae.encode_rotation(clouds)).transpose(-1, -2))
        return clouds
    ae.rotation_encoder.eval()
    test_clouds = framed(test, test.meshes)
    heads = torch.nn.Linear(ae.config.latent, width * len(FAMILIES))
    optimizer = torch.optim.Adam([*ae.shape_encoder.parameters(), *heads.parameters()], args.learning_rate)

    def code(clouds, family):
        return heads(ae.shape_encoder(clouds)).view(len(clouds), len(FAMILIES), width)[torch.arange(len(clouds)), family]

    def measure() -> str:
        ae.shape_encoder.eval()
        with torch.no_grad():
            predicted = code(test_clouds, torch.from_numpy(test.family))
        ae.shape_encoder.train()
        return f"held-out R2 {r2(predicted.numpy(), test_targets.numpy()):.2f}, {held_out(predicted.numpy())}"

    step, spent = 0, 0.0
    checkpoint = Path(args.checkpoint) if args.checkpoint else None
    if checkpoint and checkpoint.exists():
        state = torch.load(checkpoint, weights_only=False)
        ae.shape_encoder.load_state_dict(state["encoder"])
        heads.load_state_dict(state["heads"])
        optimizer.load_state_dict(state["optimizer"])
        fit.generator.set_state(state["generator"])
        step, spent = state["step"], state["seconds"]
        print(f"resumed from {checkpoint}: step {step}, {spent:.0f} s trained")
    else:
        print(f"before: {measure()} (head untrained)")

    def save() -> None:
        if checkpoint:
            state = {"encoder": ae.shape_encoder.state_dict(), "heads": heads.state_dict(),
                     "optimizer": optimizer.state_dict(), "generator": fit.generator.get_state(),
                     "step": step, "seconds": spent + time.monotonic() - started}
            torch.save(state, checkpoint.with_suffix(".tmp"))
            checkpoint.with_suffix(".tmp").replace(checkpoint)

    started = time.monotonic()
    while spent + time.monotonic() - started < args.seconds:
        chosen = torch.randint(0, len(fit.meshes), (32,), generator=fit.generator)
        loss = (code(framed(fit, fit.meshes[chosen]), torch.from_numpy(fit.family[chosen.numpy()]))
                - fit_targets[chosen]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
        if step % 500 == 0:
            print(f"step {step} ({spent + time.monotonic() - started:.0f} s): batch loss {loss.item():.3f}; {measure()}",
                  flush=True)
        if step % 2000 == 0:
            save()
    save()
    print(f"after {step} steps: {measure()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    commands = parser.add_subparsers(dest="command", required=True)
    one = commands.add_parser("retrieval")
    one.add_argument("run")
    one.add_argument("test", help="a sim dataset of fresh subjects and poses (its test split)")
    one.set_defaults(handler=retrieval)
    one = commands.add_parser("identity")
    one.add_argument("run")
    one.add_argument("test", help="a sim dataset of fresh subjects in several poses (its test split)")
    one.add_argument("--fit", help="a sim dataset whose training meshes fit the linear discriminant")
    one.add_argument("--fit-subjects", type=int, help="fit on this many of its subjects per family (default: all)")
    one.set_defaults(handler=identity)
    for name, handler in (("probe", probe), ("encoder", encoder)):
        command = commands.add_parser(name)
        command.add_argument("run")
        command.add_argument("fit", help="the sim dataset the probe is fitted on (its training split)")
        command.add_argument("test", help="a sim dataset of fresh subjects and poses (its test split)")
        if name == "encoder":
            command.add_argument("--seconds", type=float, default=600.0)
            command.add_argument("--learning-rate", type=float, default=1e-4)
            command.add_argument("--target", choices=("theta", "beta"), default="theta",
                                 help="what the head predicts: the pose (theta's top 10 components) or the "
                                 "subject's shape (beta), measured by pose retrieval or same-family subject AUC")
            command.add_argument("--frame", choices=("any", "true", "estimated"), default="any",
                                 help="the views' heading: any yaw (the encoder must ignore it), the mesh's own "
                                 "(known), or turned back by the autoencoder's rotation estimate")
            command.add_argument("--checkpoint", help="saves the encoder, heads and optimizer there every 2,000 "
                                 "steps and resumes from it when it exists (--seconds counts the whole run)")
        command.set_defaults(handler=handler)
    args = parser.parse_args()
    args.handler(args)


if __name__ == "__main__":
    main()
