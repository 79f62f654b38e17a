"""f(g x) = g f(x) for every equivariant layer and every element of C4 and D4, with random weights and
random (nonzero) biases; negative controls (an untied per-channel perturbation) show the checks fail
when equivariance is broken."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from services.algorithms.equivariant import (
    ActionHead,
    ActionLift,
    EquivariantLSTM,
    GroupConv2d,
    GroupLinear,
    GroupPool,
    InvariantHead,
    LiftConv2d,
    group_pool,
)
from services.algorithms.groups import C4, D4, Group, transform_actions, transform_images, transform_regular

pytestmark = pytest.mark.unit

GROUPS = [C4, D4]
CASES = [(grp, g) for grp in GROUPS for g in grp.elements]
CASE_IDS = [f"{grp.name}-m{g[0]}r{g[1]}" for grp, g in CASES]
RTOL, ATOL = 1e-5, 1e-4


def randomize_biases(module: nn.Module, seed: int = 0) -> nn.Module:
    """Random biases (and peepholes) everywhere: zero-initialised terms would hide untied biases."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if "bias" in name or "peephole" in name:
                p.copy_(torch.randn(p.shape, generator=gen) * 0.5)
    return module


def max_violation(actual: Tensor, expected: Tensor) -> float:
    """max |a - e| - (atol + rtol |e|): <= 0 iff within tolerance everywhere."""
    return float(((actual - expected).abs() - (ATOL + RTOL * expected.abs())).max().detach())


def assert_equivariant(actual: Tensor, expected: Tensor) -> None:
    assert actual.shape == expected.shape
    assert expected.abs().max() > 1e-2  # not vacuous
    assert max_violation(actual, expected) <= 0, f"max error {(actual - expected).abs().max():.3e}"


def images(seed: int, *shape: int) -> Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------------------------
# convolutions
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
@pytest.mark.parametrize(("size", "k", "stride"), [(84, 8, 4), (20, 4, 2), (9, 3, 1), (10, 3, 1)])
def test_lift_conv(group: Group, g, size: int, k: int, stride: int) -> None:
    torch.manual_seed(0)
    layer = randomize_biases(LiftConv2d(group, 2, 3, k, stride))
    x = images(1, 2, 2, size, size)
    expected = transform_regular(layer(x), g, group, spatial=True)
    assert_equivariant(layer(transform_images(x, g)), expected)


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
@pytest.mark.parametrize(("size", "k", "stride"), [(20, 4, 2), (7, 3, 1), (3, 3, 1), (6, 1, 1)])
def test_group_conv(group: Group, g, size: int, k: int, stride: int) -> None:
    torch.manual_seed(0)
    layer = randomize_biases(GroupConv2d(group, 3, 2, k, stride))
    x = images(2, 2, 3 * group.order, size, size)
    expected = transform_regular(layer(x), g, group, spatial=True)
    assert_equivariant(layer(transform_regular(x, g, group, spatial=True)), expected)


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
def test_conv_stack_with_relu(group: Group, g) -> None:
    """The paper's first two layers with ReLU, at full 84 x 84 size."""
    torch.manual_seed(0)
    net = randomize_biases(
        nn.Sequential(LiftConv2d(group, 2, 4, 8, 4), nn.ReLU(), GroupConv2d(group, 4, 3, 4, 2), nn.ReLU())
    )
    x = images(3, 2, 2, 84, 84)
    expected = transform_regular(net(x), g, group, spatial=True)
    assert_equivariant(net(transform_images(x, g)), expected)


def test_c4_group_conv_kernel_is_a_cyclic_roll_of_rotated_kernels() -> None:
    """Output element r sees input element h through W[..., (h - r) mod 4] turned r times."""
    torch.manual_seed(0)
    layer = GroupConv2d(C4, 1, 1, 3)
    base = layer.weight.detach().view(4, 3, 3)
    w = layer.expanded_weight().detach()
    for r in range(4):
        for h in range(4):
            torch.testing.assert_close(w[r, h], torch.rot90(base[(h - r) % 4], r, dims=(0, 1)))


def test_one_bias_per_field() -> None:
    layer = GroupConv2d(D4, 3, 5, 3)
    assert layer.bias.shape == (5,) and layer.expanded_weight().shape == (40, 24, 3, 3)
    assert LiftConv2d(D4, 2, 5, 3).bias.shape == (5,)
    assert GroupLinear(C4, 2, 6).bias.shape == (6,)


def test_untied_per_channel_kernel_breaks_equivariance() -> None:
    """Negative control: perturbing one output channel's kernel (not its whole field) is detected."""
    torch.manual_seed(0)
    layer = GroupConv2d(C4, 2, 2, 3)
    x = images(4, 1, 8, 7, 7)
    w = layer.expanded_weight().detach().clone()
    w[1] += 0.3 * torch.randn_like(w[1])
    f = lambda t: torch.nn.functional.conv2d(t, w)  # noqa: E731
    g = (0, 1)
    expected = transform_regular(f(x), g, C4, spatial=True)
    assert max_violation(f(transform_regular(x, g, C4, spatial=True)), expected) > 1e-2


def test_asymmetric_stride_grid_breaks_equivariance() -> None:
    """(N - k) not divisible by the stride: the sampling grid is not symmetric and the check fails."""
    torch.manual_seed(0)
    layer = LiftConv2d(C4, 1, 2, 3, stride=2)
    x = images(5, 1, 1, 10, 10)  # (10 - 3) % 2 == 1
    g = (0, 1)
    expected = transform_regular(layer(x), g, C4, spatial=True)
    assert max_violation(layer(transform_images(x, g)), expected) > 1e-2


# ------------------------------------------------------------------------------------------------
# 1x1 layers, lifting of actions, pooling and heads
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
def test_group_linear_and_mlp(group: Group, g) -> None:
    torch.manual_seed(0)
    mlp = randomize_biases(nn.Sequential(GroupLinear(group, 3, 4), nn.ReLU(), GroupLinear(group, 4, 2)))
    x = images(6, 5, 3 * group.order)
    assert_equivariant(mlp(transform_regular(x, g, group)), transform_regular(mlp(x), g, group))


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
def test_action_lift(group: Group, g) -> None:
    torch.manual_seed(0)
    lift = randomize_biases(ActionLift(group, 3))
    a = images(7, 6, 5)
    assert_equivariant(lift(transform_actions(a, g)), transform_regular(lift(a), g, group))


def test_action_lift_for_d4_sees_dtheta_as_a_pseudo_scalar() -> None:
    """Under D4 a mirror negates dtheta; treating it as trivial (pitfall P2) would fail the check."""
    torch.manual_seed(0)
    lift = ActionLift(D4, 2)
    a = torch.zeros(1, 5)
    a[0, 4] = 1.0
    out = lift(a).view(2, 8)
    torch.testing.assert_close(out[:, 4:], -out[:, :4])  # mirrored elements see -dtheta


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
def test_invariant_pooling_and_head(group: Group, g) -> None:
    torch.manual_seed(0)
    head = randomize_biases(InvariantHead(group, 3, 4))
    x = images(8, 5, 3 * group.order)
    xg = transform_regular(x, g, group)
    assert_equivariant(head(xg), head(x))
    assert_equivariant(GroupPool(group)(xg), group_pool(x, group))
    maps = images(9, 2, 3 * group.order, 4, 4)
    pooled = group_pool(transform_regular(maps, g, group, spatial=True), group, dim=1)
    assert_equivariant(pooled, transform_images(group_pool(maps, group, dim=1), g))


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
def test_action_head(group: Group, g) -> None:
    """(dx, dy) rotate / reflect with g, dtheta flips sign under a mirror (D4), jaw and dz are invariant."""
    torch.manual_seed(0)
    head = randomize_biases(ActionHead(group, 3))
    x = images(10, 5, 3 * group.order)
    assert_equivariant(head(transform_regular(x, g, group)), transform_actions(head(x), g))


def test_action_head_bias_only_on_trivial_outputs() -> None:
    for group, rows in ((C4, [0, 3, 4]), (D4, [0, 3])):
        head = randomize_biases(ActionHead(group, 2))
        out = head(torch.zeros(1, 2 * group.order))[0]
        assert torch.all(out[rows] != 0)
        assert torch.all(out[[r for r in range(5) if r not in rows]] == 0)


# ------------------------------------------------------------------------------------------------
# LSTM
# ------------------------------------------------------------------------------------------------


def _lstm_case(group: Group, peephole: bool, cls=EquivariantLSTM):
    torch.manual_seed(0)
    lstm = randomize_biases(cls(group, 3, 2, peephole=peephole))
    x = images(11, 3, 6, 3 * group.order)
    h0, c0 = images(12, 3, 2 * group.order), images(13, 3, 2 * group.order)
    return lstm, x, (h0, c0)


def _lstm_violation(lstm, x, state, group: Group, g) -> float:
    out, (h, c) = lstm(x, state)
    tx = transform_regular(x, g, group)
    ts = tuple(transform_regular(s, g, group) for s in state)
    out_g, (h_g, c_g) = lstm(tx, ts)
    pairs = [(out_g, transform_regular(out, g, group)), (h_g, transform_regular(h, g, group))]
    pairs.append((c_g, transform_regular(c, g, group)))
    return max(max_violation(a, e) for a, e in pairs)


@pytest.mark.parametrize(("group", "g"), CASES, ids=CASE_IDS)
@pytest.mark.parametrize("peephole", [False, True])
def test_lstm_sequence_and_state(group: Group, g, peephole: bool) -> None:
    """Whole sequences (T = 6) from a carried, non-zero state: outputs and final (h, c) transform."""
    lstm, x, state = _lstm_case(group, peephole)
    out, _ = lstm(x, state)
    assert out.abs().max() > 1e-2
    assert _lstm_violation(lstm, x, state, group, g) <= 0


class PerChannelPeepholeLSTM(EquivariantLSTM):
    """The public code's bug (P1): peephole weights that differ between the channels of one field."""

    def expanded_peepholes(self) -> Tensor | None:
        tied = super().expanded_peepholes()
        gen = torch.Generator().manual_seed(99)
        return tied + 0.5 * torch.randn(tied.shape, generator=gen)


@pytest.mark.parametrize("group", GROUPS, ids=lambda g: g.name)
def test_lstm_with_per_channel_peepholes_fails_the_check(group: Group) -> None:
    lstm, x, state = _lstm_case(group, True, PerChannelPeepholeLSTM)
    worst = max(_lstm_violation(lstm, x, state, group, g) for g in group.elements[1:])
    assert worst > 1e-3


def test_lstm_matches_torch_lstm_with_the_expanded_weights() -> None:
    """Without peepholes the recurrence is torch's LSTM (gate order i, f, g, o) on the expanded matrices."""
    lstm, x, (h0, c0) = _lstm_case(D4, False)
    ref = nn.LSTM(x.shape[-1], lstm.hidden_channels, batch_first=True)
    with torch.no_grad():
        ref.weight_ih_l0.copy_(lstm.input_map.expanded_weight())
        ref.weight_hh_l0.copy_(lstm.hidden_map.expanded_weight())
        ref.bias_ih_l0.copy_(lstm.input_map.bias.repeat_interleave(D4.order))
        ref.bias_hh_l0.zero_()
    out, (h, c) = lstm(x, (h0, c0))
    ref_out, (ref_h, ref_c) = ref(x, (h0[None], c0[None]))
    torch.testing.assert_close(out, ref_out)
    torch.testing.assert_close(h, ref_h[0])
    torch.testing.assert_close(c, ref_c[0])


def test_lstm_zero_state_default_and_split_sequences() -> None:
    """state=None means zeros, and running two halves with the carried state equals one pass."""
    lstm, x, _ = _lstm_case(C4, True)
    out, state = lstm(x)
    zeros = torch.zeros(x.shape[0], lstm.hidden_channels)
    torch.testing.assert_close(lstm(x, (zeros, zeros))[0], out)
    first, mid = lstm(x[:, :3])
    second, end = lstm(x[:, 3:], mid)
    torch.testing.assert_close(torch.cat([first, second], dim=1), out)
    torch.testing.assert_close(end[0], state[0])
    torch.testing.assert_close(end[1], state[1])


@pytest.mark.parametrize("group", GROUPS, ids=lambda g: g.name)
def test_fused_lstm_equals_the_step_loop_in_values_and_gradients(group: Group) -> None:
    """The peephole-free LSTM runs aten's fused recurrence; with zero peepholes the same weights take
    the Python step loop. Outputs, final state and every parameter's and input's gradient agree."""
    fused, x, (h0, c0) = _lstm_case(group, False)
    looped = EquivariantLSTM(group, 3, 2, peephole=True)
    looped.load_state_dict({**fused.state_dict(), "peephole": torch.zeros(3, 2)})
    grads = []
    for lstm in (fused, looped):
        xi, hi, ci = (t.clone().requires_grad_(True) for t in (x, h0, c0))
        out, (h, c) = lstm(xi, (hi, ci))
        (out.sin().sum() + h.square().sum() + c.cos().sum()).backward()
        named = {n: p.grad for n, p in lstm.named_parameters() if n != "peephole"}
        grads.append((out, h, c, xi.grad, hi.grad, ci.grad, named))
    for a, b in zip(grads[0][:6], grads[1][:6], strict=True):
        torch.testing.assert_close(a, b)
    assert grads[0][6].keys() == grads[1][6].keys() and grads[0][6]
    for name, g in grads[0][6].items():
        assert g.abs().max() > 0
        torch.testing.assert_close(g, grads[1][6][name])
