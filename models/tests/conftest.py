"""Shared fixtures for the kit's tests: small meshes, a tiny sim-format dataset, and a tiny paired
dataset written by the sim itself."""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest
import trimesh

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


@pytest.fixture(scope="session")
def paired_dataset(tmp_path_factory):
    """A tiny dataset written by the sim with shared poses (two families, 4 subjects x 3 poses)."""
    sim = pathlib.Path(__file__).resolve().parents[2] / "target" / "release" / "sim"
    if not sim.exists():
        pytest.skip("target/release/sim is not built (make binaries)")
    out = tmp_path_factory.mktemp("paired")
    subprocess.run([str(sim), "dataset", "--out", str(out), "--subjects", "4", "--poses", "3", "--shared-poses",
                    "--split", "0.5,0,0.5", "--vertices", "800", "--seed", "3"], check=True, capture_output=True)
    return out


@pytest.fixture
def inspect_with_node():
    """`gdvae-node inspect-model BUNDLE --load`'s output (the test is skipped without the binary;
    ONNX Runtime comes from the project's .venv beside the binary's ancestors, runtime.rs)."""
    node = pathlib.Path(__file__).resolve().parents[2] / "target" / "release" / "gdvae-node"
    if not node.exists():
        pytest.skip("target/release/gdvae-node is not built (make binaries)")

    def inspect(bundle) -> str:
        shown = subprocess.run([str(node), "inspect-model", str(bundle), "--load"], capture_output=True, text=True,
                               timeout=120)
        assert shown.returncode == 0, shown.stderr
        return shown.stdout
    return inspect


def write_mesh(path: pathlib.Path, mesh: trimesh.Trimesh) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Two 'families' of ellipsoid-with-bump subjects in a few poses, in the sim's layout
    (meshes/*.ply, ground_truth.jsonl, splits.json). Shapes differ by axis lengths (beta) and by
    where the bump sits (theta), so retrieval has something to find."""
    root = tmp_path_factory.mktemp("tiny")
    rng = np.random.default_rng(0)
    lines, splits = [], {"train": [], "validation": [], "test": []}
    for family in ("blobA", "blobB"):
        for subject in range(6):
            beta = rng.uniform(0.6, 1.4, size=3)
            name = f"{family}-{subject:04d}"
            split = "train" if subject < 4 else "test"
            splits[split].append(name)
            for pose in range(3):
                theta = rng.normal(0, 0.3, size=6)
                sphere = trimesh.creation.icosphere(subdivisions=3)
                vertices = sphere.vertices * beta * (0.3 if family == "blobA" else 0.4)
                direction = np.array([np.cos(theta[0]), np.sin(theta[0]), 0.3 * theta[1]])
                bump = np.exp(-8 * np.sum((sphere.vertices - direction / np.linalg.norm(direction)) ** 2, 1))
                vertices = vertices * (1 + 0.25 * bump[:, None])
                file = f"meshes/{name}-{pose:03d}.ply"
                write_mesh(root / file, trimesh.Trimesh(vertices, sphere.faces, process=False))
                lines.append(json.dumps({"file": file, "family": family, "subject": name, "split": split,
                                         "beta": beta.tolist(), "theta": theta.tolist(), "yaw": 0.0}))
    (root / "ground_truth.jsonl").write_text("\n".join(lines) + "\n")
    (root / "splits.json").write_text(json.dumps(splits))
    return root
