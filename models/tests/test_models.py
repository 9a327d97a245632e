"""Contract tests of the networks and losses: shapes, gradients, invertibility, equivariance, and
the HFVAE estimator against a brute-force computation."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from gdvae.ae import AEConfig, Autoencoder, ae_loss, yaw_quaternion
from gdvae.flow import SpectralFlow
from gdvae.geometry import (chamfer, geodesic_distance, matrix_to_quaternion, quaternion_distance,
                            quaternion_to_matrix, random_rotation_matrices, rotate)
from gdvae.hfvae import gaussian_log_density, hfvae_terms
from gdvae.train import bank_batch
from gdvae.vae import LatentVAE, VAEConfig, correlation_penalty, covariance_penalty, vae_loss, view_consistency

SMALL_AE = dict(points=64, latent=24, rotation_hidden=(16, 32), shape_hidden=(16, 32), decoder_width=32, copies=2)


def small_vae(regime="gdvae++"):
    base = dict(latent=24, spectrum=6, n_extrinsic=3, width_scale=0.02, flow_layers=3, flow_hidden=32)
    return VAEConfig(**base) if regime == "gdvae++" else VAEConfig.flow_only(**base)


def only(config, **weights):
    """Every beta and omega of `config` at 0 but the given ones."""
    for name in vars(config):
        if name.startswith(("beta_", "omega_")):
            setattr(config, name, weights.get(name, 0.0))


def no_gradient(model):
    return [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]


@pytest.mark.parametrize("kind", ["ftl", "std"])
@pytest.mark.parametrize("supervised", [True, False])
def test_autoencoder_shapes_and_every_parameter_gets_a_gradient(kind, supervised):
    torch.manual_seed(0)
    model = Autoencoder(AEConfig(kind=kind, supervised=supervised, **SMALL_AE))
    clouds = torch.randn(3, 64, 3) * 0.3
    losses, output = ae_loss(model, clouds)
    assert output.x_c.shape == (6, 24) and output.canonical.shape == (6, 64, 3) and output.q.shape == (6, 4)
    losses.total.backward()
    assert no_gradient(model) == []
    assert math.isfinite(losses.parts["total"])
    model.eval()
    with torch.no_grad():
        out = model(torch.randn(5, 100, 3))  # any number of points at inference
    assert out.reconstruction.shape == (5, 64, 3)


def test_ftl_layer_is_equivariant():
    """With a rotation-covariant shape code, derotating by the true rotation gives the same x_c
    whatever the input rotation: U(x_c) = U(x~) R."""
    model = Autoencoder(AEConfig(kind="ftl", **SMALL_AE)).eval()

    class Covariant(torch.nn.Module):  # the first 8 points, flattened: rotates with the input
        def forward(self, points):
            return points[:, :8, :].reshape(len(points), -1)

    model.shape_encoder = Covariant()
    canonical = torch.randn(1, 64, 3)
    rotations = random_rotation_matrices(4, full=True)
    inputs = rotate(canonical.expand(4, -1, -1), rotations)
    x_c, pose_aware = model.encode_shape(inputs, rotations)
    torch.testing.assert_close(x_c, canonical[:, :8, :].reshape(1, -1).expand(4, -1), atol=1e-5, rtol=0)
    torch.testing.assert_close(pose_aware.view(4, 8, 3), inputs[:, :8, :])


def test_rotation_helpers():
    rotations = random_rotation_matrices(16, full=True)
    q = matrix_to_quaternion(rotations)
    torch.testing.assert_close(quaternion_to_matrix(q), rotations, atol=1e-5, rtol=0)
    assert geodesic_distance(rotations, rotations).max() < 1e-3
    assert quaternion_distance(q, -q).max() < 1e-6  # sign-invariant
    half_turn = torch.tensor([[[-1.0, 0, 0], [0, -1, 0], [0, 0, 1]]])
    assert geodesic_distance(half_turn, torch.eye(3)[None]).item() == pytest.approx(1.0, abs=1e-3)
    cloud = torch.randn(2, 50, 3)
    assert chamfer(cloud, cloud).max() < 1e-5
    assert chamfer(cloud, cloud + 1).min() > 1.0


def test_flow_inverse_and_log_determinant_against_autograd():
    torch.manual_seed(0)
    flow = SpectralFlow(6, layers=4, hidden=16).double()
    spectra = torch.rand(32, 6, dtype=torch.float64).cumsum(-1) + 0.5
    flow.input.fit(spectra)
    flow.train()
    flow(spectra)  # actnorm initialisation
    with torch.no_grad():
        for p in flow.parameters():
            p.add_(0.1 * torch.randn_like(p))
    flow.eval()
    latent, log_det = flow(spectra)
    torch.testing.assert_close(flow.inverse(latent), spectra, atol=1e-10, rtol=0)
    for row in range(3):
        jacobian = torch.autograd.functional.jacobian(lambda s: flow(s[None])[0][0], spectra[row])
        assert torch.linalg.slogdet(jacobian).logabsdet.item() == pytest.approx(log_det[row].item(), abs=1e-8)


def test_hfvae_terms_match_a_brute_force_computation():
    torch.manual_seed(1)
    batch, groups, dataset_size = 5, [2, 1, 3], 40
    mean, log_variance = torch.randn(batch, 6), torch.randn(batch, 6) * 0.3
    z = mean + torch.exp(0.5 * log_variance) * torch.randn(batch, 6)
    terms = hfvae_terms(z, mean, log_variance, groups, dataset_size)

    def log_q(i, dims):  # minibatch weighted sampling estimate of log q(z_i[dims])
        values = [sum(float(gaussian_log_density(z[i, d], mean[j, d], log_variance[j, d])) for d in dims)
                  for j in range(batch)]
        return math.log(sum(math.exp(v) for v in values)) - math.log(dataset_size * batch)

    blocks = [list(range(0, 2)), [2], list(range(3, 6))]
    mi = inter = intra = dim_kl = 0.0
    for i in range(batch):
        conditional = sum(float(gaussian_log_density(z[i, d], mean[i, d], log_variance[i, d])) for d in range(6))
        joint = log_q(i, range(6))
        group_terms = [log_q(i, block) for block in blocks]
        dims = [log_q(i, [d]) for d in range(6)]
        prior = [-0.5 * (math.log(2 * math.pi) + float(z[i, d]) ** 2) for d in range(6)]
        mi += conditional - joint
        inter += joint - sum(group_terms)
        intra += sum(g - sum(dims[d] for d in block) for g, block in zip(group_terms, blocks))
        dim_kl += sum(dims[d] - prior[d] for d in range(6))
    expected = {"mutual_information": mi, "inter_group_tc": inter, "intra_group_tc": intra, "dimension_kl": dim_kl}
    for key, value in expected.items():
        assert terms[key].item() == pytest.approx(value / batch, abs=1e-4), key


@pytest.mark.parametrize("regime", ["gdvae++", "fo"])
def test_vae_every_used_parameter_gets_a_gradient(regime):
    torch.manual_seed(0)
    model = LatentVAE(small_vae(regime))
    q = torch.nn.functional.normalize(torch.randn(16, 4), dim=-1)
    x_c, spectra = torch.randn(16, 24), torch.rand(16, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    losses = vae_loss(model, q, x_c, spectra, dataset_size=100)
    losses.total.backward()
    assert no_gradient(model) == []
    assert all(math.isfinite(v) for v in losses.parts.values())
    assert (model.spectral_variance is None) == (regime == "fo")


def test_view_consistency_is_zero_for_agreeing_views_and_about_one_for_unrelated_ones():
    torch.manual_seed(0)
    meshes = torch.randn(200, 6)
    assert view_consistency(torch.cat([meshes, meshes])).item() == pytest.approx(0.0, abs=1e-6)
    unrelated = view_consistency(torch.cat([meshes, torch.randn(200, 6)])).item()
    assert 0.8 < unrelated < 1.2
    # Scale-free: shrinking every code does not lower it.
    noisy = torch.cat([meshes, meshes + 0.3 * torch.randn(200, 6)])
    assert view_consistency(0.01 * noisy).item() == pytest.approx(view_consistency(noisy).item(), rel=1e-4)


def test_view_consistency_trains_the_intrinsic_encoder_only_when_weighted():
    q = torch.nn.functional.normalize(torch.randn(16, 4), dim=-1)
    x_c, spectra = torch.randn(16, 24), torch.rand(16, 6).cumsum(-1) + 1
    for weight in (0.0, 5.0):
        torch.manual_seed(0)
        model = LatentVAE(small_vae("fo"))
        only(model.config, omega_view=weight)
        model.flow.input.fit(spectra)
        losses = vae_loss(model, q, x_c, spectra, dataset_size=50, with_jacobian=False)
        assert losses.parts["view_consistency"] == (0.0 if weight == 0 else pytest.approx(losses.parts["total"] / weight))
        if weight:
            losses.total.backward()
            assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.intrinsic.mean.parameters())
    with pytest.raises(ValueError, match="omega_view"):
        VAEConfig(omega_view=-1.0).validate()


def test_paired_bank_batches_pair_two_copies_of_one_mesh():
    generator = torch.Generator().manual_seed(0)
    batch = bank_batch(size=80, batch=64, copies=8, paired=True, generator=generator)
    assert len(batch) == 64 and batch.max() < 80
    assert torch.equal(batch[:32] // 8, batch[32:] // 8)
    assert (batch[:32] != batch[32:]).any()
    plain = bank_batch(size=80, batch=64, copies=8, paired=False, generator=generator)
    assert len(plain) == 64 and not torch.equal(plain[:32] // 8, plain[32:] // 8)


def test_gdvaepp_cuts_the_intrinsic_consistency_gradient_through_the_flow():
    torch.manual_seed(0)
    model = LatentVAE(small_vae("gdvae++"))
    only(model.config, omega_intrinsic=1.0)
    q = torch.nn.functional.normalize(torch.randn(8, 4), dim=-1)
    spectra = torch.rand(8, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    vae_loss(model, q, torch.randn(8, 24), spectra, dataset_size=50, with_jacobian=False).total.backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.flow.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.intrinsic.mean.parameters())


def test_reconstruction_normalisation_per_dimension_or_relative():
    """The paper's L_R divides the relative x_c error by n = dim(x_c); `--relative-reconstruction` drops the 1/n."""
    q = torch.nn.functional.normalize(torch.randn(8, 4), dim=-1)
    x_c, spectra = torch.randn(8, 24), torch.rand(8, 6).cumsum(-1) + 1
    parts = {}
    for per_dimension in (True, False):
        torch.manual_seed(0)
        config = small_vae()
        config.reconstruction_per_dimension = per_dimension
        model = LatentVAE(config)
        model.flow.input.fit(spectra)
        model.code_norm.fill_(float(x_c.pow(2).sum(-1).mean()))
        torch.manual_seed(1)
        parts[per_dimension] = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False).parts
    assert parts[False]["reconstruction"] == pytest.approx(24 * parts[True]["reconstruction"], rel=1e-5)
    from gdvae.train import recipe
    assert recipe("cpu").vae.reconstruction_per_dimension is True
    assert recipe("paper").vae.reconstruction_per_dimension is True


def test_beta_warmup_scales_only_the_hfvae_terms():
    torch.manual_seed(0)
    model = LatentVAE(small_vae())
    q = torch.nn.functional.normalize(torch.randn(8, 4), dim=-1)
    x_c, spectra = torch.randn(8, 24), torch.rand(8, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    totals, parts = {}, {}
    for scale in (0.0, 0.5, 1.0):
        torch.manual_seed(1)
        losses = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False, beta_scale=scale)
        totals[scale], parts[scale] = float(losses.total), losses.parts
    c = model.config
    p = parts[1.0]
    hf = (c.beta_intra_tc * p["intra_group_tc"] + c.beta_dimension_kl * p["dimension_kl"]
          + c.beta_mutual_information * p["mutual_information"] + c.beta_inter_tc * p["inter_group_tc"])
    terms = lambda scale: {k: v for k, v in parts[scale].items() if k != "total"}  # noqa: E731
    assert terms(0.0) == terms(1.0)  # the same sample: only the weighting changes
    assert totals[1.0] - totals[0.0] == pytest.approx(hf, rel=1e-4)
    assert totals[0.5] - totals[0.0] == pytest.approx(hf / 2, rel=1e-4)


def test_partial_views_train_against_the_whole_cloud():
    import trimesh

    from gdvae.data import Mesh
    from gdvae.surface import MeshCache, view_directions

    sphere = trimesh.creation.icosphere(subdivisions=3)
    mesh = Mesh(np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64))
    cache = MeshCache([mesh], scale=1.0)
    generator = torch.Generator().manual_seed(0)
    directions = view_directions(6, generator, cache.device)
    clouds = cache.sample(torch.zeros(3, dtype=torch.long), 64, generator)
    views = cache.sample_facing(torch.zeros(6, dtype=torch.long), 64, directions, generator)

    torch.manual_seed(0)
    model = Autoencoder(AEConfig(kind="ftl", points=64, latent=24, rotation_hidden=(8, 16), shape_hidden=(8, 16),
                                 decoder_width=16, copies=2))
    losses, output = ae_loss(model, clouds, views=views)
    losses.total.backward()
    assert no_gradient(model) == []
    assert output.canonical.shape == (6, 64, 3)
    with pytest.raises(ValueError, match="copies"):
        ae_loss(model, clouds, views=views[:4])
    model.config.supervised = False
    with pytest.raises(ValueError, match="supervised"):
        ae_loss(model, clouds, views=views)


def test_squared_correlation_penalty_is_near_zero_for_independent_groups_and_scale_free():
    torch.manual_seed(0)
    batch = 4096
    a, b = torch.randn(batch, 3), torch.randn(batch, 10)
    independent = correlation_penalty([a, b])
    # 2 * 3 * 10 squared correlations, each about 1/batch for independent groups.
    assert independent.item() < 2 * 30 * 5 / batch
    dependent = correlation_penalty([a, torch.cat([a[:, :1] + 0.1 * torch.randn(batch, 1), b[:, 1:]], -1)])
    assert dependent.item() > 1.5
    # Shrinking a group does not lower it (the raw covariance form does).
    assert correlation_penalty([a, 0.01 * b]).item() == pytest.approx(independent.item(), rel=1e-3)
    assert covariance_penalty([a, 0.01 * b]).item() < 0.02 * covariance_penalty([a, b]).item()


@pytest.mark.parametrize("form", ["covariance", "correlation", "off"])
def test_every_covariance_form_trains_and_a_zero_jacobian_weight_skips_l_j(form):
    torch.manual_seed(0)
    config = small_vae()
    config.covariance_form = form
    config.omega_jacobian = 0.0
    model = LatentVAE(config)
    q = torch.nn.functional.normalize(torch.randn(16, 4), dim=-1)
    x_c, spectra = torch.randn(16, 24), torch.rand(16, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    losses = vae_loss(model, q, x_c, spectra, dataset_size=100)
    losses.total.backward()
    assert no_gradient(model) == []
    assert losses.parts["jacobian"] == 0.0
    assert (losses.parts["covariance"] == 0.0) == (form == "off")
    with pytest.raises(ValueError, match="covariance_form"):
        VAEConfig(covariance_form="l2").validate()


def test_the_yaw_head_round_trips_angles_across_plus_minus_pi_without_a_seam():
    psi = torch.cat([torch.linspace(-math.pi, math.pi, 2001, dtype=torch.float64),
                     torch.tensor([math.pi - 1e-4, -math.pi + 1e-4], dtype=torch.float64)])
    direction = torch.stack([psi.cos(), psi.sin()], -1) * 3.0  # any scale
    q = yaw_quaternion(direction)
    c, s = psi.cos(), psi.sin()
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    expected = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                            torch.stack([zero, zero, one], -1)], -2)
    assert torch.allclose(quaternion_to_matrix(q), expected, atol=1e-6)
    # Consecutive angles give nearby rotations all the way round, through +-pi.
    steps = geodesic_distance(quaternion_to_matrix(q[1:2001]), quaternion_to_matrix(q[:2000])) * 180
    assert steps.max().item() < 0.2
    # The yaw read back from q (as the node does: 2 atan2(z, w)) is psi.
    read = 2 * torch.atan2(q[:, 3], q[:, 0])
    assert torch.allclose(torch.remainder(read - psi + math.pi, 2 * math.pi) - math.pi, zero, atol=1e-6)
    # Finite gradients next to the seam.
    near = torch.tensor([[math.cos(math.pi - 1e-3), math.sin(math.pi - 1e-3)]], requires_grad=True)
    geodesic_distance(quaternion_to_matrix(yaw_quaternion(near)), torch.eye(3)[None]).sum().backward()
    assert torch.isfinite(near.grad).all()


def test_an_autoencoder_with_the_yaw_head_trains_and_exports_its_quaternion(tmp_path):
    import onnxruntime
    torch.manual_seed(0)
    config = AEConfig(points=32, latent=12, rotation_hidden=(8, 16), shape_hidden=(8, 16), decoder_width=8,
                      copies=2, rotation_head="yaw")
    model = Autoencoder(config)
    losses, _ = ae_loss(model, torch.randn(3, 32, 3))
    losses.total.backward()
    assert all(p.grad is not None for p in model.rotation_encoder.parameters())
    model.eval()
    points = torch.randn(2, 32, 3)
    torch.onnx.export(_RotationGraph(model).eval(), (points,), tmp_path / "rotation.onnx", dynamo=False,
                      input_names=["points"], output_names=["q"])
    session = onnxruntime.InferenceSession(str(tmp_path / "rotation.onnx"), providers=["CPUExecutionProvider"])
    (exported,) = session.run(None, {"points": points.numpy()})
    q = model.encode_rotation(points).detach().numpy()
    assert np.abs(exported - q).max() < 1e-5
    assert np.allclose(q[:, 1:3], 0) and (q[:, 0] >= 0).all()
    with pytest.raises(ValueError, match="up axis"):
        AEConfig(rotation_head="yaw", full_rotations=True).validate()


class _RotationGraph(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, points):
        return self.model.encode_rotation(points)


@pytest.mark.parametrize("true_rotation", [True, False])
def test_the_code_bank_of_a_supervised_model_uses_the_true_rotation(true_rotation):
    from dataclasses import replace
    from gdvae.train import encode_bank, recipe
    torch.manual_seed(0)
    chosen = recipe("smoke")
    chosen = replace(chosen, bank_true_rotation=true_rotation)
    ae = Autoencoder(chosen.ae)
    cloud = torch.randn(chosen.bank_copies, chosen.ae.points, 3)

    class Sampler:
        def __len__(self):
            return 1

        def views(self, chosen, copies, partial):
            return cloud[:len(chosen) * copies]

    torch.manual_seed(7)
    bank = encode_bank(ae, Sampler(), np.ones((1, 6)), chosen)
    torch.manual_seed(7)
    rotations = random_rotation_matrices(chosen.bank_copies, full=chosen.ae.full_rotations)
    ae.eval()
    with torch.no_grad():
        predicted = ae.encode_rotation(rotate(cloud, rotations))
    expected_q = matrix_to_quaternion(rotations) if true_rotation else predicted
    assert torch.allclose(bank["q"], expected_q, atol=1e-6)
    with torch.no_grad():
        expected_x, _ = ae.encode_shape(rotate(cloud, rotations), quaternion_to_matrix(expected_q))
    assert torch.allclose(bank["x_c"], expected_x, atol=1e-5)


def test_the_code_bank_shows_partial_views_in_the_chosen_share():
    from dataclasses import replace
    from gdvae.train import encode_bank, recipe
    chosen = recipe("smoke")
    ae = Autoencoder(chosen.ae)
    asked = []

    class Sampler:
        def __len__(self):
            return 2

        def views(self, chosen_meshes, copies, partial):
            asked.append((torch.as_tensor(chosen_meshes).tolist(), copies, partial))
            return torch.randn(len(chosen_meshes) * copies, chosen.ae.points, 3)

    spectra = np.ones((2, 6))
    # None follows the AE's partial views; an explicit share overrides it.
    for partial_views, bank_partial, expected in ((0.75, None, 0.75), (0.75, 0.0, 0.0), (0.0, 1.0, 1.0)):
        asked.clear()
        bank = encode_bank(ae, Sampler(), spectra, replace(chosen, partial_views=partial_views,
                                                           bank_partial_views=bank_partial))
        # Both meshes' copies in one batch, mesh-major (the bank's layout: entry // copies = mesh).
        assert asked == [([0] * chosen.bank_copies + [1] * chosen.bank_copies, 1, expected)]
        assert bank["x_c"].shape[0] == 2 * chosen.bank_copies and torch.equal(bank["spectrum"], torch.ones(4, 6))
    with pytest.raises(ValueError, match="bank_partial_views"):
        encode_bank(ae, Sampler(), spectra, replace(chosen, bank_partial_views=1.5))


@pytest.mark.parametrize("name", ["body", "pose"])
def test_a_taught_term_is_zero_for_codes_that_name_the_truth_and_positive_otherwise(name):
    """vae.omega_body teaches mu_I beta through a linear head per family; omega_pose teaches mu_E
    itself theta's principal coordinates (no head: its targets are n_E wide for every family)."""
    torch.manual_seed(0)
    config = replace(small_vae("fo"), omega_body=1.0, body_heads=2 * 3) if name == "body" else \
        replace(small_vae("fo"), omega_pose=1.0)
    model = LatentVAE(config)
    q = torch.nn.functional.normalize(torch.randn(8, 4), dim=-1)
    x_c, spectra = torch.randn(8, 24), torch.rand(8, 6).cumsum(-1) + 1
    model.flow.input.fit(spectra)
    family = torch.tensor([0, 1] * 4)
    with pytest.raises(ValueError, match=f"no {name} targets"):
        vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False)
    with torch.no_grad():
        (_, (mu_e, _), (mu_i, _)) = model.encode(q, x_c)
        exact = model.body_heads(mu_i).view(8, 2, 3)[torch.arange(8), family] if name == "body" else mu_e.clone()
    mask = torch.ones_like(exact)
    mask[family == 0, 2] = 0  # family 0 has fewer columns: its padding is not scored
    exact[family == 0, 2] = 5.0
    targets = {"rows": exact, "mask": mask, "family": family}
    parts = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False, taught={name: targets}).parts
    assert parts[name] == pytest.approx(0.0, abs=1e-10)
    targets["rows"] = exact + 0.5 * mask
    parts = vae_loss(model, q, x_c, spectra, dataset_size=100, with_jacobian=False, taught={name: targets}).parts
    assert parts[name] == pytest.approx(0.25, rel=1e-5)
    # A term that teaches a code whose encoder is held fixed is refused.
    kept = "keep_intrinsic" if name == "body" else "keep_extrinsic"
    with pytest.raises(ValueError, match=kept):
        replace(small_vae("fo"), **{f"omega_{name}": 1.0, kept: True}).validate()
