"""How good is the learning signal? Spectral distances within and between subjects.

GDVAE++ separates intrinsic shape from pose because the Laplace-Beltrami spectrum barely changes
when a subject articulates (near-isometric motion) but changes when its proportions change. This
report measures exactly that on a dataset with ground truth: the paper's d_lambda between meshes of
the same subject (same beta, different theta) versus different subjects of the same family, and
how often a mesh's nearest spectrum belongs to the same subject.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .data import MeshDataset, normalize
from .spectrum import SpectrumCache, spectral_distance

log = logging.getLogger(__name__)


def _spectrum_job(job):
    folder, mesh, count = job
    return SpectrumCache(folder).mesh_spectrum(mesh, count)


def dataset_spectra(dataset: MeshDataset, count: int, cache: SpectrumCache, progress=True,
                    workers: int | None = None) -> np.ndarray:
    """Spectra of every mesh of `dataset` in model units (the dataset-wide scale), cached, computed
    by `workers` processes (default: one per core)."""
    import multiprocessing
    import os

    spectra = np.zeros((len(dataset.meshes), count))
    started = time.monotonic()
    last = started
    jobs = [(cache.folder, normalize(mesh, dataset.scale), count) for mesh in dataset.meshes]
    workers = workers or os.cpu_count() or 1
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        results = pool.imap(_spectrum_job, jobs, chunksize=8)
        for index, values in enumerate(results):
            spectra[index] = values
            now = time.monotonic()
            if progress and (now - last > 5.0 or index + 1 == len(dataset.meshes)):
                rate = (index + 1) / max(now - started, 1e-9)
                log.info("spectra %d/%d (%.1f/s, ETA %.0f s)", index + 1, len(spectra), rate,
                         (len(spectra) - index - 1) / rate)
                last = now
    return spectra


def spectral_report(dataset: MeshDataset, spectra: np.ndarray) -> dict:
    """Per family (from ground truth) and overall: mean d_lambda within and between subjects,
    their ratio, and the 1-nearest-neighbour subject accuracy by spectrum."""
    if not dataset.has_ground_truth:
        raise ValueError("the spectral report needs ground truth (subject ids): ground_truth.jsonl is missing")
    subjects = np.array([item.subject for item in dataset.items])
    families = np.array([(item.truth or {}).get("family", "all") for item in dataset.items])
    report = {}
    for family in sorted(set(families)) + ["all"]:
        mask = np.ones(len(subjects), bool) if family == "all" else families == family
        if mask.sum() < 2:
            continue
        s = subjects[mask]
        distance = spectral_distance(spectra[mask][:, None, :], spectra[mask][None, :, :])
        same = s[:, None] == s[None, :]
        off_diagonal = ~np.eye(len(s), dtype=bool)
        within = distance[same & off_diagonal]
        between = distance[~same]
        np.fill_diagonal(distance, np.inf)
        nearest = distance.argmin(axis=1)
        report[family] = {
            "meshes": int(mask.sum()),
            "subjects": int(len(set(s))),
            "within_subject_mean": float(within.mean()) if len(within) else None,
            "between_subject_mean": float(between.mean()) if len(between) else None,
            "ratio_between_to_within": float(between.mean() / within.mean()) if len(within) and len(between) else None,
            "nearest_spectrum_same_subject": float((s[nearest] == s).mean()),
        }
    return report
