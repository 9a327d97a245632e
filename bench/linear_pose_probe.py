"""Would ten numbers read linearly from the pose encoder's code x_p keep the pose that z_E loses?
(models/EXPERIMENTS.md, "mu_E taught the pose".) On a run's code bank, a ridge from x_p to each
family's theta (standardised per joint angle, or in radians with `raw`), then the prediction's top
K principal directions: x_p projected on them takes z_E's place in S on an evaluation split, beside
the run's own z_E (one draw of points and rotations, as `bench/s_probe.py`).

    .venv/bin/python bench/linear_pose_probe.py RUN BANK_DATASET SPLIT [K] [raw]
    .venv/bin/python bench/linear_pose_probe.py /work/runs/s16-zE /work/data/sim-grid-pose /work/data/sim-eval-tune 10
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "models"))
from s_probe import score, split_codes  # noqa: E402
from gdvae.data import load_dataset  # noqa: E402
from gdvae.train import load_run  # noqa: E402


def main() -> None:
    if len(sys.argv) < 4:
        raise SystemExit(__doc__)
    run, data, split = sys.argv[1:4]
    k = int(sys.argv[4]) if len(sys.argv) > 4 else 10
    raw = len(sys.argv) > 5 and sys.argv[5] == "raw"
    _, ae, vae, state = load_run(run)
    if vae is None or "x_p" not in state.get("bank", {}):
        raise SystemExit(f"{run}: needs a trained VAE and a code bank with the pose code x_p")
    ae.eval()
    vae.eval()
    bank = state["bank"]
    copies = bank.get("copies", 8)
    dataset = load_dataset(data)
    truths = [dataset.items[i].truth for i in dataset.indices("train")]  # the bank's meshes, in its order
    x_p = bank["x_p"].numpy()
    if len(truths) * copies != len(x_p):
        raise SystemExit(f"{data}: {len(truths)} training meshes, but the bank of {run} holds {len(x_p) // copies}")
    held = split_codes(ae, vae, split)
    for family, part in held["families"].items():
        rows = [m for m, t in enumerate(truths) if t["family"] == family]
        inputs = np.concatenate([x_p[m * copies:(m + 1) * copies] for m in rows])
        theta = np.repeat(np.array([truths[m]["theta"] for m in rows]), copies, 0)
        mean, spread = theta.mean(0), np.ones(theta.shape[1]) if raw else theta.std(0) + 1e-9
        centre = inputs.mean(0)
        centred = inputs - centre
        weights = np.linalg.solve(centred.T @ centred + 0.1 * len(centred) * np.eye(centred.shape[1]),
                                  centred.T @ ((theta - mean) / spread))
        predicted = centred @ weights
        _, _, axes = np.linalg.svd(predicted - predicted.mean(0), full_matrices=False)
        z_e = (part["x_p"] - centre) @ weights @ axes[:k].T
        print(f"{family}: z_E = {k} linear numbers of x_p {score(part, z_e, part['mu_I'])} | "
              f"the run's {score(part, part['mu_E'], part['mu_I'])}")


if __name__ == "__main__":
    main()
