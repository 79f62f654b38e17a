"""Equi-RSAC networks: the actor's mean transforms like an action and its log std is invariant, both Q
values are invariant and the critic's features are regular fields, at every step of whole sequences,
for C4 and D4 at paper and cpu-small widths with random weights and biases. The non-equivariant twin
has the same interface and fails the same check. Also: step == forward, causality, gradients reach
every parameter, and NetConfig validation / round trips."""

from __future__ import annotations

import copy
import dataclasses
import json

import pytest
import torch
from torch import Tensor, nn

from services.algorithms.groups import get_group, transform_actions, transform_images, transform_regular
from services.algorithms.networks import (
    PRESETS,
    Actor,
    Critic,
    NetConfig,
    build_actor,
    build_critic,
    encode_real,
)

pytestmark = pytest.mark.unit

EQUI = [(p, grp) for p in ("paper", "cpu-small") for grp in ("c4", "d4")]
EQUI_IDS = [f"{p}-{grp}" for p, grp in EQUI]
ATOL, RTOL = 1e-4, 1e-5


def nets(preset: str, group: str, seed: int = 0) -> tuple[Actor, Critic]:
    """Actor and critic with random weights and random (nonzero) biases."""
    cfg = NetConfig.preset(preset, group=group)
    torch.manual_seed(seed)
    actor, critic = build_actor(cfg), build_critic(cfg)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for module in (actor, critic):
            for name, p in module.named_parameters():
                if "bias" in name:
                    p.copy_(0.3 * torch.randn(p.shape, generator=gen))
    return actor, critic


def inputs(seed: int = 0, B: int = 2, T: int = 6, size: int = 84) -> tuple[Tensor, Tensor, Tensor]:
    """Images (B, T, 2, size, size), previous actions (zeros at t = 0) and current actions."""
    gen = torch.Generator().manual_seed(seed)
    images = torch.rand(B, T, 2, size, size, generator=gen)
    actions = torch.rand(B, T, 5, generator=gen) * 2 - 1
    prev = torch.cat([torch.zeros(B, 1, 5), actions[:, :-1]], dim=1)
    return images, prev, actions


def assert_close_tol(actual: Tensor, expected: Tensor) -> None:
    assert actual.shape == expected.shape
    err = (actual - expected).abs() - (ATOL + RTOL * expected.abs())
    assert float(err.max()) <= 0, f"max error {float((actual - expected).abs().max()):.3e}"


def max_diff(a: Tensor, b: Tensor) -> float:
    return float((a - b).abs().max())


# ------------------------------------------------------------------------------------------------
# equivariance of whole networks
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("preset", "group"), EQUI, ids=EQUI_IDS)
@torch.no_grad()
def test_actor_mean_transforms_like_an_action_and_log_std_is_invariant(preset: str, group: str) -> None:
    actor, _ = nets(preset, group)
    images, prev, _ = inputs(1)
    mean, log_std, (h, c) = actor(images, prev)
    assert mean.abs().max() > 1e-2 and log_std.std() > 1e-3  # not vacuous
    G = get_group(group)
    for g in G.elements:
        mean_g, log_std_g, (h_g, c_g) = actor(transform_images(images, g), transform_actions(prev, g))
        assert_close_tol(mean_g, transform_actions(mean, g))
        assert_close_tol(log_std_g, log_std)
        assert_close_tol(h_g, transform_regular(h, g, G))
        assert_close_tol(c_g, transform_regular(c, g, G))
    # (dx, dy) really turn: the mean itself is not invariant
    mean_r, _, _ = actor(transform_images(images, (0, 1)), transform_actions(prev, (0, 1)))
    assert max_diff(mean_r[..., 1:3], mean[..., 1:3]) > 1e-3


@pytest.mark.parametrize(("preset", "group"), EQUI, ids=EQUI_IDS)
@torch.no_grad()
def test_q_values_are_invariant_and_features_are_regular_fields(preset: str, group: str) -> None:
    _, critic = nets(preset, group, seed=3)
    images, prev, actions = inputs(2)
    feats, _ = critic.features(images, prev)
    q1, q2 = critic.q(feats, actions)
    assert q1.shape == q2.shape == actions.shape[:2]
    assert q1.std() > 1e-3 and max_diff(q1, q2) > 1e-3
    G = get_group(group)
    for g in G.elements:
        feats_g, _ = critic.features(transform_images(images, g), transform_actions(prev, g))
        assert_close_tol(feats_g, transform_regular(feats, g, G))
        q1_g, q2_g = critic.q(feats_g, transform_actions(actions, g))
        assert_close_tol(q1_g, q1)
        assert_close_tol(q2_g, q2)


@pytest.mark.parametrize("group", ["c4", "d4"])
@torch.no_grad()
def test_mirror_negates_the_mean_dtheta_under_d4_only(group: str) -> None:
    actor, _ = nets("cpu-small", group, seed=5)
    images, prev, _ = inputs(3)
    mean, _, _ = actor(images, prev)
    mirrored = transform_images(images, (1, 0))
    prev_m = transform_actions(prev, (1, 0))
    if group == "d4":
        mean_m, _, _ = actor(mirrored, prev_m)
        assert_close_tol(mean_m[..., 4], -mean[..., 4])
        assert_close_tol(mean_m[..., 2], -mean[..., 2])
        assert_close_tol(mean_m[..., [0, 1, 3]], mean[..., [0, 1, 3]])
    else:  # C4 has no mirror: dtheta is invariant under rotations and carries a bias
        mean_r, _, _ = actor(transform_images(images, (0, 2)), transform_actions(prev, (0, 2)))
        assert_close_tol(mean_r[..., 4], mean[..., 4])


@pytest.mark.parametrize("preset", ["paper", "cpu-small"])
@torch.no_grad()
def test_non_equivariant_twin_has_the_same_interface_but_is_not_equivariant(preset: str) -> None:
    actor, critic = nets(preset, "none")
    ref_actor, ref_critic = nets(preset, "c4")
    images, prev, actions = inputs(4)
    mean, log_std, (h, c) = actor(images, prev)
    ref_mean, ref_log_std, (ref_h, _) = ref_actor(images, prev)
    assert mean.shape == ref_mean.shape and log_std.shape == ref_log_std.shape and h.shape == ref_h.shape
    feats, _ = critic.features(images, prev)
    assert feats.shape == ref_critic.features(images, prev)[0].shape
    g = (0, 1)
    mean_g, _, _ = actor(transform_images(images, g), transform_actions(prev, g))
    assert max_diff(mean_g, transform_actions(mean, g)) > 1e-3
    q1, _ = critic.q(feats, actions)
    q1_g, _ = critic.q(critic.features(transform_images(images, g), transform_actions(prev, g))[0],
                       transform_actions(actions, g))  # fmt: skip
    assert max_diff(q1_g, q1) > 1e-4


def test_twin_channel_counts_match_c4() -> None:
    """A layer of F fields has 4 F channels in the twin: the same conv shapes as the C4 expanded kernels."""
    twin, equi = build_actor(NetConfig(group="none")), build_actor(NetConfig(group="c4"))
    twin_convs = [m.weight.shape for m in twin.encoder.modules() if isinstance(m, nn.Conv2d)]
    equi_convs = [m.expanded_weight().shape for m in equi.encoder.net if hasattr(m, "expanded_weight")]
    assert twin_convs == equi_convs
    assert [s[0] for s in twin_convs] == [32, 64, 64, 64, 64, 128]


# ------------------------------------------------------------------------------------------------
# recurrence: step == forward, causality, gradients
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("group", ["c4", "d4", "none"])
@torch.no_grad()
def test_step_loop_equals_forward(group: str) -> None:
    actor, _ = nets("cpu-small", group)
    images, prev, _ = inputs(5, B=3, T=5)
    mean, log_std, (h, c) = actor(images, prev)
    state = None
    for t in range(images.shape[1]):
        m_t, s_t, state = actor.step(images[:, t], prev[:, t], state)
        torch.testing.assert_close(m_t, mean[:, t], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(s_t, log_std[:, t], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(state[0], h, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(state[1], c, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("group", ["c4", "d4", "none"])
@torch.no_grad()
def test_outputs_before_t_ignore_inputs_from_t_on(group: str) -> None:
    """Padding independence: changing steps >= t0 leaves every output at steps < t0 unchanged."""
    actor, critic = nets("cpu-small", group)
    images, prev, actions = inputs(6, T=6)
    images2, prev2, actions2 = inputs(7, T=6)
    t0 = 3
    images2[:, :t0], prev2[:, :t0], actions2[:, :t0] = images[:, :t0], prev[:, :t0], actions[:, :t0]
    mean, log_std, _ = actor(images, prev)
    mean2, log_std2, _ = actor(images2, prev2)
    torch.testing.assert_close(mean2[:, :t0], mean[:, :t0], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(log_std2[:, :t0], log_std[:, :t0], atol=1e-6, rtol=1e-6)
    assert max_diff(mean2[:, t0:], mean[:, t0:]) > 1e-4  # the later inputs do matter
    feats, _ = critic.features(images, prev)
    feats2, _ = critic.features(images2, prev2)
    torch.testing.assert_close(feats2[:, :t0], feats[:, :t0], atol=1e-6, rtol=1e-6)
    q, q2 = critic.q(feats, actions)[0], critic.q(feats2, actions2)[0]
    torch.testing.assert_close(q2[:, :t0], q[:, :t0], atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("group", ["c4", "d4", "none"])
def test_every_parameter_gets_a_gradient(group: str) -> None:
    actor, critic = nets("cpu-small", group)
    images, prev, actions = inputs(8, T=3)
    mean, log_std, _ = actor(images, prev)
    (mean.square().sum() + log_std.sum()).backward()
    feats, _ = critic.features(images, prev)
    q1, q2 = critic.q(feats, actions)
    (q1.sum() + q2.sum()).backward()
    for module in (actor, critic):
        for name, p in module.named_parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_state_dict_holds_only_weights() -> None:
    """Index tables are rebuilt on construction, so checkpoints and broadcast weights carry only parameters."""
    actor = build_actor(NetConfig.preset("cpu-small", group="d4"))
    assert set(actor.state_dict()) == {n for n, _ in actor.named_parameters()}
    copy = build_actor(NetConfig.preset("cpu-small", group="d4"))
    copy.load_state_dict(actor.state_dict())
    images, prev, _ = inputs(9, B=1, T=2)
    with torch.no_grad():
        torch.testing.assert_close(copy(images, prev)[0], actor(images, prev)[0])


# ------------------------------------------------------------------------------------------------
# NetConfig
# ------------------------------------------------------------------------------------------------


def test_paper_preset_is_the_reference_geometry() -> None:
    cfg = NetConfig.preset("paper")
    assert cfg == NetConfig()
    assert cfg.spatial_sizes() == [20, 9, 7, 5, 3, 1]
    assert (cfg.image_embed, cfg.action_embed, cfg.lstm_hidden, cfg.mlp_hidden) == (128, 16, 128, (128, 128))
    # the public critic embeds the action it rates into 144 channels (tasks-and-baselines.md section 2)
    assert cfg.q_action_embed == 144 and build_critic(cfg).q1[0][0].in_fields * 4 == 128 + 128 + 144


@pytest.mark.parametrize("name", sorted(PRESETS))
@pytest.mark.parametrize("group", ["c4", "d4", "none"])
def test_presets_round_trip_through_json(name: str, group: str) -> None:
    cfg = NetConfig.preset(name, group=group)
    back = NetConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg and isinstance(back.encoder[0], tuple) and isinstance(back.mlp_hidden, tuple)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"group": "c8"}, "group must be"),
        ({"encoder": ((8, 8, 4), (16, 4, 3))}, "not divisible by stride"),
        ({"encoder": ((8, 8, 4), (16, 4, 2), (16, 3, 1))}, "not 1x1"),
        ({"image_size": 80}, "not divisible by stride"),
        ({"image_embed": 102}, "image_embed=102 is not divisible"),
        ({"group": "d4", "action_embed": 12}, "action_embed=12 is not divisible"),
        ({"q_action_embed": 18}, "q_action_embed=18 is not divisible"),
        ({"q_action_embed": 0}, "q_action_embed must be positive"),
        ({"group": "d4", "mlp_hidden": (128, 100)}, "mlp_hidden"),
        ({"lstm_hidden": 0}, "lstm_hidden must be positive"),
        ({"final_kernel": 30}, "larger than"),
    ],
)
def test_invalid_configs_are_rejected_with_the_reason(overrides: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(NetConfig(), **overrides)


def test_unknown_names_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown preset"):
        NetConfig.preset("huge")
    with pytest.raises(ValueError, match="unknown NetConfig keys"):
        NetConfig.from_dict({"width": 3})


def test_bad_input_shapes_are_rejected() -> None:
    actor = build_actor(NetConfig.preset("cpu-small"))
    with pytest.raises(ValueError, match="prev_actions"):
        actor(torch.zeros(1, 2, 2, 84, 84), torch.zeros(1, 3, 5))


# ------------------------------------------------------------------------------------------------
# padded steps: skipped by the encoder (CPU) or encoded and zeroed (a GPU), the same numbers
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["cpu-small", "paper"])
def test_encoding_padding_and_zeroing_it_equals_leaving_it_out_values_and_gradients(preset):
    actor, _ = nets(preset, "c4")
    images, _, _ = inputs(seed=3, B=3, T=5)
    lengths = torch.tensor([5, 2, 4])
    obs_mask = torch.arange(5)[None] < lengths[:, None]  # episodes of 5, 2 and 4 observations
    images = images * obs_mask[:, :, None, None, None]  # padding is zeros, as the replay pads
    target = torch.randn(3, 5, actor.cfg.image_embed, generator=torch.Generator().manual_seed(4))

    def run(skip_padding: bool) -> tuple[Tensor, list[Tensor]]:
        actor.zero_grad(set_to_none=True)
        emb = encode_real(actor.encoder, images, obs_mask, skip_padding=skip_padding)
        (emb * target).sum().backward()
        return emb.detach(), [p.grad.clone() for p in actor.encoder.parameters()]

    skipped, skipped_grads = run(True)
    dense, dense_grads = run(False)
    assert float(skipped[~obs_mask].abs().max()) == 0.0 and float(dense[~obs_mask].abs().max()) == 0.0
    assert float(skipped[obs_mask].abs().amax(-1).min()) > 0  # every real step is encoded, not zeroed
    assert_close_tol(dense, skipped)
    assert len(dense_grads) == len(skipped_grads) > 0
    for got, want in zip(dense_grads, skipped_grads, strict=True):
        assert_close_tol(got, want)
    # without padding both paths are the plain encoder
    full = torch.ones_like(obs_mask)
    plain = encode_real(actor.encoder, images, None, skip_padding=True)
    assert torch.equal(encode_real(actor.encoder, images, full, skip_padding=True), plain)
    assert_close_tol(encode_real(actor.encoder, images, full, skip_padding=False), plain)


# ------------------------------------------------------------------------------------------------
# the steerable kernel basis (the public encoder's escnn R2Conv basis, built by e2cnn)
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["paper", "cpu-small"])
@torch.no_grad()
def test_steerable_encoders_are_c4_equivariant_with_the_public_parameter_count(preset: str) -> None:
    cfg = NetConfig.preset(preset, kernel_basis="steerable")
    torch.manual_seed(0)
    actor, critic = build_actor(cfg), build_critic(cfg)
    free = NetConfig.preset(preset)
    n = sum(p.numel() for p in actor.encoder.parameters())
    # tasks-and-baselines.md section 9: the public C4 encoder (escnn) has 33,784 parameters where
    # unconstrained k x k kernels have 55,400
    if preset == "paper":
        assert n == 33_784
        assert sum(p.numel() for p in build_actor(free).encoder.parameters()) == 55_400
    images, prev, actions = inputs(4)
    mean, _, (h, _) = actor(images, prev)
    feats, _ = critic.features(images, prev)
    q1, _ = critic.q(feats, actions)
    G = get_group("c4")
    for g in G.elements:
        mean_g, _, (h_g, _) = actor(transform_images(images, g), transform_actions(prev, g))
        assert_close_tol(mean_g, transform_actions(mean, g))
        assert_close_tol(h_g, transform_regular(h, g, G))
        feats_g, _ = critic.features(transform_images(images, g), transform_actions(prev, g))
        assert_close_tol(critic.q(feats_g, transform_actions(actions, g))[0], q1)


def test_steerable_weights_are_plain_state_dicts_that_load_copy_and_train() -> None:
    cfg = NetConfig.preset("cpu-small", kernel_basis="steerable")
    torch.manual_seed(1)
    actor, other = build_actor(cfg), build_actor(cfg)
    # only parameters, under ordinary names (the weights message refuses e2cnn's buffer names)
    assert set(actor.state_dict()) == {n for n, _ in actor.named_parameters()}
    assert all(name.replace(".", "").replace("_", "").isalnum() for name in actor.state_dict())
    images, prev, _ = inputs(5, B=1, T=2)
    with torch.no_grad():
        assert max_diff(other(images, prev)[0], actor(images, prev)[0]) > 1e-4
        other.load_state_dict(actor.state_dict())
        torch.testing.assert_close(other(images, prev)[0], actor(images, prev)[0])
        twin = copy.deepcopy(actor)
        for p in actor.parameters():
            p.add_(0.05)
        torch.testing.assert_close(twin(images, prev)[0], other(images, prev)[0])  # the copy kept its own
        assert max_diff(twin(images, prev)[0], actor(images, prev)[0]) > 1e-4
    actor.eval()
    assert set(actor.state_dict()) == set(other.state_dict())
    actor.train()
    before = [p.detach().clone() for p in actor.encoder.parameters()]
    actor(images, prev)[0].sum().backward()
    torch.optim.SGD(actor.parameters(), lr=0.1).step()
    assert all(max_diff(b, p) > 0 for b, p in zip(before, actor.encoder.parameters(), strict=True))


@pytest.mark.parametrize("group", ["d4", "none"])
def test_steerable_basis_is_refused_outside_c4(group: str) -> None:
    with pytest.raises(ValueError, match="steerable is built for group c4"):
        NetConfig.preset("cpu-small", group=group, kernel_basis="steerable")
    with pytest.raises(ValueError, match="kernel_basis must be one of"):
        NetConfig.preset("cpu-small", kernel_basis="smooth")
