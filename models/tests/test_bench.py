"""`python -m gdvae bench`: the training path's throughput figures are measured, not made up."""

import json

import pytest

from gdvae.cli import main


def test_bench_times_the_batch_maker_and_both_steps(tiny_dataset, capsys):
    assert main(["bench", str(tiny_dataset), "--recipe", "smoke", "--partial-views", "0.5", "--seconds", "0.3",
                 "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    for part in ("batch_maker", "ae_step", "vae_step"):
        assert figures[part]["clouds_per_s"] > 0, part
    maker = figures["batch_maker"]
    # A batch is the recipe's canonical clouds and every copy's view of them.
    assert maker["clouds_per_batch"] == figures["ae_step"]["batch"] * (1 + figures["copies"])
    assert maker["clouds_per_s"] == pytest.approx(maker["batches_per_s"] * maker["clouds_per_batch"])
    assert figures["command"].startswith("python -m gdvae bench")
    assert figures["ae_step"]["with_batches_it_per_s"] > 0
    assert all(figures[part]["operators"] > 10 for part in ("batch_maker", "ae_step", "vae_step"))
    assert figures["dataset"]["meshes"] > 0 and figures["dataset"]["load_seconds"] > 0
    assert figures["batch_maker"]["cache_mb"] > 0
    # The process's peak holds at least the meshes' tensors.
    assert figures["peak_resident_mb"] > figures["batch_maker"]["cache_mb"]


def test_bench_prints_a_readable_report(tiny_dataset, capsys):
    assert main(["bench", str(tiny_dataset), "--recipe", "smoke", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "batch maker:" in out and "AE step:" in out and "VAE step:" in out and "command: python -m gdvae" in out
    assert "GB at the process's peak" in out
