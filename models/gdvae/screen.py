"""The 2^k screen of the VAE objective (issue 11): which of the paper's loss terms collapse z_E.

Each suspected cause is a two-level factor (the paper's literal form against the alternative), and
every combination is a VAE trained on the same autoencoder and code bank (`train --init-from`),
then measured by `evaluate --retrieval-only` (S over five draws, the posterior's active units, pose
transfer against both baselines). One run folder per cell under the screen's folder, so an
interrupted screen resumes where it stopped; the table and the factors' main effects are written
to `screen.md` and `screen.json`.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Factor:
    name: str  # short label, used in cell names
    meaning: str
    field: str  # the VAEConfig field, as `--set` names it
    paper: str  # the paper's literal value (level 0)
    alternative: str  # level 1


FACTORS = (
    Factor("R", "L_R normalisation: 1/dim(x_c) (paper) or relative error only", "vae.reconstruction_per_dimension",
           "true", "false"),
    Factor("B", "beta_4 (inter-group TC): 80 (paper, HA) or 8", "vae.beta_inter_tc", "80", "8"),
    Factor("C", "L_Sigma: raw covariances (paper) or squared correlations", "vae.covariance_form",
           "covariance", "correlation"),
    Factor("J", "L_J: omega_J = 200 (paper) or off", "vae.omega_jacobian", "200", "0"),
    Factor("K", "beta_2 (dimension-wise KL): 20 (paper, HA) or 2", "vae.beta_dimension_kl", "20", "2"),
)


def cells(factors: list[Factor]) -> list[dict[str, int]]:
    """The full factorial: every combination of levels, the paper's cell first."""
    return [dict(zip((f.name for f in factors), levels)) for levels in itertools.product((0, 1), repeat=len(factors))]


def cell_name(levels: dict[str, int]) -> str:
    return "-".join(f"{name}{level}" for name, level in levels.items())


def run_cell(levels: dict[str, int], factors: list[Factor], fixed: list[str], ae_run: str, dataset: str,
             folder: Path, recipe: str, iterations: int, threads: int, sim: str | None) -> dict:
    """Trains (or resumes) and evaluates one cell; returns its metrics."""
    run = folder / cell_name(levels)
    metrics_file = run / "metrics.json"
    if metrics_file.exists():
        return json.loads(metrics_file.read_text())
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    settings = [f"--set={assignment}" for assignment in fixed]
    settings += [f"--set={f.field}={f.alternative if levels[f.name] else f.paper}" for f in factors]
    python = [sys.executable, "-m", "gdvae"]
    started = time.monotonic()
    with open(run.with_suffix(".log"), "a") as output:
        subprocess.run([*python, "train", dataset, "--out", str(run), "--init-from", ae_run, "--recipe", recipe,
                        "--vae-iterations", str(iterations), *settings],
                       check=True, env=environment, stdout=output, stderr=subprocess.STDOUT)
        evaluation = [*python, "evaluate", str(run), dataset, "--retrieval-only", "--out", str(metrics_file)]
        if sim:
            evaluation += ["--sim", sim]
        subprocess.run(evaluation, check=True, env=environment, stdout=subprocess.DEVNULL, stderr=output)
    log.info("cell %s done in %.1f min", run.name, (time.monotonic() - started) / 60)
    return json.loads(metrics_file.read_text())


def summarise(levels: dict[str, int], metrics: dict) -> dict:
    """The screen's figures of one cell."""
    retrieval = metrics.get("retrieval", {})
    transfer = metrics.get("pose_transfer", {})
    return {
        "cell": cell_name(levels),
        "levels": levels,
        "S": metrics.get("S"),
        "S_std": metrics.get("S_std"),
        "S_by_family": {family: values.get("S") for family, values in retrieval.items() if isinstance(values, dict)},
        "z_E_active": metrics["posterior"]["z_E"]["active_units"],
        "z_I_active": metrics["posterior"]["z_I"]["active_units"],
        "transfer_d_C": transfer.get("transfer_d_C"),
        "pose_source_d_C": transfer.get("baseline_pose_source_d_C"),
        "shape_source_d_C": transfer.get("baseline_shape_source_d_C"),
    }


def main_effects(rows: list[dict], factors: list[Factor], measures=("S", "z_E_active", "transfer_d_C")) -> dict:
    """Per factor and measure: mean over the cells at the alternative level minus the mean at the
    paper's level (the factorial's main effect)."""
    effects = {}
    for factor in factors:
        effects[factor.name] = {}
        for measure in measures:
            high = [r[measure] for r in rows if r["levels"][factor.name] == 1 and r[measure] is not None]
            low = [r[measure] for r in rows if r["levels"][factor.name] == 0 and r[measure] is not None]
            effects[factor.name][measure] = (sum(high) / len(high) - sum(low) / len(low)) if high and low else None
    return effects


def number(value, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def table(rows: list[dict], effects: dict, factors: list[Factor], command: str) -> str:
    lines = [f"# VAE objective screen\n\n`{command}`\n", "Factors (level 0 = the paper's form, 1 = the alternative):\n"]
    lines += [f"- **{f.name}**: {f.meaning} (`{f.field}` = {f.paper} / {f.alternative})" for f in factors]
    names = [f.name for f in factors]
    lines += ["", "| " + " | ".join(names) + " | S ± sd (biped / quadruped) | z_E active | z_I active "
              "| transfer d_C | pose-source d_C | shape-source d_C |",
              "|" + "---|" * (len(names) + 6)]
    for r in rows:
        families = " / ".join(number(v, 2) for v in r["S_by_family"].values())
        lines.append("| " + " | ".join(str(r["levels"][n]) for n in names)
                     + f" | {number(r['S'], 2)} ± {number(r['S_std'], 2)} ({families}) | {r['z_E_active']} "
                     f"| {r['z_I_active']} | {number(r['transfer_d_C'], 4)} | {number(r['pose_source_d_C'], 4)} "
                     f"| {number(r['shape_source_d_C'], 4)} |")
    lines += ["", "Main effects (mean at level 1 minus mean at level 0):", "",
              "| factor | S | z_E active units | transfer d_C |", "|---|---|---|---|"]
    for name, values in effects.items():
        lines.append(f"| {name} | {number(values['S'], 2)} | {number(values['z_E_active'], 1)} "
                     f"| {number(values['transfer_d_C'], 4)} |")
    return "\n".join(lines) + "\n"


def screen(ae_run: str, dataset: str, out: str, recipe: str, iterations: int, factor_names: str, jobs: int,
           sim: str | None, command: str, fixed: list[str] = ()) -> str:
    """Trains and measures every cell (resuming finished ones), writes screen.md and screen.json.
    `fixed`: `--set` assignments applied to every cell (e.g. a factor left out of the design held at
    its alternative level)."""
    known = {f.name: f for f in FACTORS}
    unknown = [name for name in factor_names if name not in known]
    if unknown:
        raise ValueError(f"unknown factor(s) {', '.join(unknown)} (known: {', '.join(known)})")
    if not (Path(ae_run) / "checkpoint.pt").exists():
        raise FileNotFoundError(f"{ae_run}: no checkpoint.pt (train it with --stop-after bank first)")
    factors = [known[name] for name in factor_names]
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    design = cells(factors)
    threads = max(1, (os.cpu_count() or 1) // jobs)
    log.info("screen: %d cells x %d VAE iterations, %d at a time, into %s", len(design), iterations, jobs, folder)
    with ThreadPoolExecutor(jobs) as pool:
        results = list(pool.map(lambda levels: run_cell(levels, factors, list(fixed), ae_run, dataset, folder,
                                                        recipe, iterations, threads, sim), design))
    rows = [summarise(levels, metrics) for levels, metrics in zip(design, results)]
    effects = main_effects(rows, factors)
    text = table(rows, effects, factors, command)
    (folder / "screen.json").write_text(json.dumps({"command": command, "iterations": iterations,
                                                    "fixed": list(fixed), "cells": rows,
                                                    "main_effects": effects}, indent=2) + "\n")
    (folder / "screen.md").write_text(text)
    return text
