"""The disc-shaped (dx, dy) range (``NetConfig.xy_range = "disc"``) as math: the radial tanh maps
onto the open unit disc and commutes with every rotation, its log-density is the Gaussian's less the
log-determinant of its Jacobian (checked against autograd's Jacobian), the log-density of a given
action inverts the sampler, and rotated copies of the policy's episodes take uniform angles (a box
policy's saturated actions fit only quarter turns)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from proto.weights import WeightsBlob
from services.algorithms.networks import NetConfig, build_actor, disc_xy
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.algorithms.sac.losses import (
    bc_loss,
    squash,
    squash_log_det,
    tanh_gaussian_log_prob,
    tanh_gaussian_sample,
    unsquash,
)
from services.augmenter.core.isometric import QUARTER, draw_rotation
from tests.helpers.learner import SIZE, TINY_NET

pytestmark = pytest.mark.unit

DISC_NET = dataclasses.replace(TINY_NET, xy_range="disc")


def turn_xy(a: torch.Tensor, phi: float) -> torch.Tensor:
    c, s = math.cos(phi), math.sin(phi)
    x, y = a[..., 1], a[..., 2]
    return torch.stack([a[..., 0], c * x - s * y, s * x + c * y, a[..., 3], a[..., 4]], -1)


def test_disc_squash_lands_inside_the_disc_and_commutes_with_every_rotation():
    g = torch.Generator().manual_seed(0)
    u = torch.randn(2000, 5, generator=g, dtype=torch.float64) * 3.0
    a = squash(u, disc=True)
    assert float(a[:, 1:3].norm(dim=-1).max()) < 1.0
    # the box reaches its corners: norms up to sqrt(2)
    assert float(squash(u)[:, 1:3].norm(dim=-1).max()) > 1.3
    torch.testing.assert_close(a[:, [0, 3, 4]], torch.tanh(u[:, [0, 3, 4]]))
    for phi in (0.3, 1.0, QUARTER, 2.5):
        torch.testing.assert_close(squash(turn_xy(u, phi), disc=True), turn_xy(a, phi))
    # a box squash commutes with quarter turns only
    assert not torch.allclose(squash(turn_xy(u, 0.3)), turn_xy(squash(u), 0.3))


@pytest.mark.parametrize("disc", [False, True])
def test_log_det_equals_autograds_jacobian(disc: bool):
    g = torch.Generator().manual_seed(1)
    for scale in (0.01, 1.0, 3.0):
        for u in torch.randn(6, 5, generator=g, dtype=torch.float64) * scale:
            jac = torch.autograd.functional.jacobian(lambda x: squash(x, disc), u)
            torch.testing.assert_close(
                squash_log_det(u, disc), torch.linalg.slogdet(jac)[1], rtol=1e-6, atol=1e-6
            )


def test_the_disc_density_integrates_to_one():
    """Monte Carlo over the disc's (dx, dy) with the other dimensions marginalised: the mean of
    pi(a) / uniform(a) over uniform points of the disc is pi's mass there, 1."""
    g = torch.Generator().manual_seed(2)
    n = 400_000
    r, t = (
        torch.rand(n, generator=g, dtype=torch.float64).sqrt() * 0.9999,
        torch.rand(n, generator=g) * 2 * math.pi,
    )
    a = torch.zeros(n, 5, dtype=torch.float64)
    a[:, 1], a[:, 2] = r * torch.cos(t), r * torch.sin(t)
    mean = torch.tensor([0.0, 0.4, -0.3, 0.0, 0.0], dtype=torch.float64)
    log_std = torch.tensor([0.0, -0.2, 0.1, 0.0, 0.0], dtype=torch.float64)
    # the other dimensions at 0 contribute their own density there; divide it out
    full = tanh_gaussian_log_prob(mean, log_std, a, bound=1 - 1e-9, disc=True)
    rest = tanh_gaussian_log_prob(mean[[0, 3, 4]], log_std[[0, 3, 4]], a[:, [0, 3, 4]], bound=1 - 1e-9)
    mass = float((full - rest).exp().mean() * math.pi)
    assert mass == pytest.approx(1.0, abs=0.01)


def test_log_prob_of_a_sampled_disc_action_equals_the_samplers():
    g = torch.Generator().manual_seed(3)
    mean, log_std = torch.randn(4, 3, 5, generator=g), torch.randn(4, 3, 5, generator=g) * 0.3
    a, lp = tanh_gaussian_sample(mean, log_std, generator=g, disc=True)
    torch.testing.assert_close(
        tanh_gaussian_log_prob(mean, log_std, a, bound=1.0 - 1e-7, disc=True), lp, atol=1e-4, rtol=1e-4
    )
    torch.testing.assert_close(
        squash(unsquash(a, disc=True, bound=1.0 - 1e-7), disc=True), a, atol=1e-5, rtol=1e-5
    )


def test_a_recorded_action_outside_the_disc_has_a_finite_log_prob():
    corner = torch.tensor([[0.0, 1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]])
    lp = tanh_gaussian_log_prob(torch.zeros(2, 5), torch.zeros(2, 5), corner, disc=True)
    assert torch.isfinite(lp).all()
    # the corner is read as the edge (norm 0.999) in the same direction
    u = unsquash(corner, disc=True)
    assert float(u[0, 1]) == pytest.approx(float(u[0, 2])) and float(u[0, 1]) > 2.0


def test_bc_loss_reads_the_squashed_mean():
    """A demo action on the disc's edge at 45 degrees: the disc mean that reaches it has zero error,
    the box squash of the same mean does not."""
    from tests.unit.test_bc_filter import demo_batch

    batch = demo_batch()
    target = torch.tensor([0.0, 0.6, 0.6, 0.0, 0.0])
    batch = dataclasses.replace(batch, actions=target.expand_as(batch.actions).clone())
    mean = unsquash(target, disc=True).expand(*batch.actions.shape[:1], batch.actions.shape[1] + 1, 5)
    assert float(bc_loss(mean, batch, disc=True)) < 1e-8
    assert float(bc_loss(mean, batch)) > 1e-3


def test_the_setting_travels_with_the_weights_and_the_runtime_acts_on_the_disc():
    assert (
        NetConfig.from_dict({k: v for k, v in TINY_NET.to_dict().items() if k != "xy_range"}).xy_range
        == "box"
    )
    with pytest.raises(ValueError, match="xy_range"):
        dataclasses.replace(TINY_NET, xy_range="square")
    torch.manual_seed(0)
    actor = build_actor(DISC_NET)
    assert disc_xy(actor) and not disc_xy(build_actor(TINY_NET))
    spec = PolicySpec(DISC_NET)
    blob = WeightsBlob.decode(
        WeightsBlob.create(1, "equi_rsac", "r", actor_tensors(actor), spec.to_json()).encode()
    )
    with torch.no_grad():
        for p in actor.parameters():  # push the mean far out so that a box policy would saturate
            p.mul_(40.0)
    blob = WeightsBlob.decode(
        WeightsBlob.create(2, "equi_rsac", "r", actor_tensors(actor), spec.to_json()).encode()
    )
    rng = np.random.default_rng(0)
    for deterministic in (True, False):
        rt = PolicyRuntime(deterministic=deterministic, seed=1)
        rt.load(blob)
        for _ in range(20):
            a = rt.act(rng.integers(0, 256, (2, SIZE, SIZE), dtype=np.uint8))
            assert float(np.hypot(a[1], a[2])) < 1.0


def test_copies_of_disc_episodes_take_uniform_angles_where_saturated_box_ones_cannot():
    g = torch.Generator().manual_seed(4)
    u = torch.randn(8, 50, 5, generator=g) * 3.0  # a high-entropy policy: most tanh values near +-1
    rng = np.random.default_rng(0)
    box = [draw_rotation(rng, [squash(e).numpy()]) for e in u]
    disc = [draw_rotation(rng, [squash(e, disc=True).numpy()]) for e in u]
    quarter = lambda phi: abs(phi / QUARTER - round(phi / QUARTER)) < 1e-12  # noqa: E731
    assert all(quarter(p) for p in box)
    assert not any(quarter(p) for p in disc)
