"""GDVAE++ training kit: data, spectra, the autoencoder and latent VAE of the paper, its metrics,
and the ONNX bundles the node loads. See models/README.md."""

__version__ = "0.1.0"
