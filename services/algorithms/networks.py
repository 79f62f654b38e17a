"""Equi-RSAC actor and critic (C4 / D4 equivariant) and their non-equivariant RSAC twin.

Design notes: docs/architecture-notes.md, services/algorithms/networks.py."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from proto.actions import ACTION_DIM
from services.algorithms.equivariant import (
    ActionHead,
    ActionLift,
    EquivariantLSTM,
    GroupConv2d,
    GroupLayerNorm,
    GroupLinear,
    InvariantHead,
    LiftConv2d,
    LSTMState,
)
from services.algorithms.groups import Group, get_group
from services.algorithms.privileged import CANONICAL_ANGLE, STATE_DIM

__all__ = ["PRESETS", "Actor", "Critic", "NetConfig", "StateCritic", "build_actor", "build_critic"]

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
GROUP_NAMES = ("c4", "d4", "none")
CRITIC_INPUTS = ("image", "state")
XY_RANGES = ("box", "disc")
KERNEL_BASES = ("free", "steerable")
PLAIN_FIELD_CHANNELS = 4
"""Channels per 'field' of the non-equivariant twin (matches the C4 channel counts)."""


@dataclass(frozen=True)
class NetConfig:
    """Widths of the Equi-RSAC networks. Channel counts (embeddings, LSTM, MLP) include the group axis."""

    group: str = "c4"
    """c4, d4 or none (RSAC, not equivariant)."""
    image_size: int = 84
    """H = W of the input images."""
    in_channels: int = 2
    """Image channels (depth + jaw opening)."""
    encoder: tuple[tuple[int, int, int], ...] = ((8, 8, 4), (16, 4, 2), (16, 3, 1), (16, 3, 1), (16, 3, 1))
    """(fields, kernel, stride) per conv + ReLU layer."""
    final_kernel: int = 3
    """Final conv kernel (leaves a 1x1 map)."""
    image_embed: int = 128
    """Channels of the image embedding."""
    action_embed: int = 16
    """a_{t-1}'s embedding (LSTM input)."""
    q_action_embed: int = 144
    """Q's action embedding (public: 144)."""
    lstm_hidden: int = 128
    """Channels of h and c."""
    mlp_hidden: tuple[int, ...] = (128, 128)
    """Actor and Q MLP hidden channels."""
    actor_prev_action: bool = True
    """The actor's LSTM reads a_{t-1} (Equi-RSAC)."""
    critic_layer_norm: bool = False
    """LayerNorm in the Q MLPs (RLPD)."""
    critic_heads: int = 2
    """Q heads (2: twin)."""
    critic_input: str = "image"
    """Critic input: image or state (sim only)."""
    state_critic_hidden: tuple[int, ...] = (256, 256)
    """State critic's MLP widths."""
    xy_range: str = "box"
    """(dx, dy): box (tanh per axis) or disc (radial)."""
    kernel_basis: str = "free"
    """Encoder kernels: free or steerable (c4)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "encoder", tuple(tuple(int(v) for v in layer) for layer in self.encoder))
        object.__setattr__(self, "mlp_hidden", tuple(int(v) for v in self.mlp_hidden))
        object.__setattr__(self, "state_critic_hidden", tuple(int(v) for v in self.state_critic_hidden))
        if self.xy_range not in XY_RANGES:
            raise ValueError(f"xy_range must be one of {XY_RANGES}, got {self.xy_range!r}")
        self._check_kernel_basis()
        if self.critic_input not in CRITIC_INPUTS:
            raise ValueError(f"critic_input must be one of {CRITIC_INPUTS}, got {self.critic_input!r}")
        if not self.state_critic_hidden or min(self.state_critic_hidden) < 1:
            raise ValueError(f"state_critic_hidden must be positive widths, got {self.state_critic_hidden}")
        if self.group not in GROUP_NAMES:
            raise ValueError(f"group must be one of {GROUP_NAMES}, got {self.group!r}")
        for name in (
            "image_size",
            "in_channels",
            "final_kernel",
            "image_embed",
            "action_embed",
            "q_action_embed",
            "lstm_hidden",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.encoder or any(len(layer) != 3 or min(layer) < 1 for layer in self.encoder):
            raise ValueError(
                f"encoder must be a non-empty list of positive (fields, kernel, stride), got {self.encoder}"
            )
        if any(w < 1 for w in self.mlp_hidden):
            raise ValueError(f"mlp_hidden must be positive, got {self.mlp_hidden}")
        if self.critic_heads < 2:
            raise ValueError(f"critic_heads must be >= 2, got {self.critic_heads}")
        self.spatial_sizes()  # raises on a bad grid
        G = self.channels_per_field
        if self.group != "none":
            for name in ("image_embed", "action_embed", "q_action_embed", "lstm_hidden"):
                if getattr(self, name) % G:
                    raise ValueError(f"{name}={getattr(self, name)} is not divisible by |{self.group}| = {G}")
            if any(w % G for w in self.mlp_hidden):
                raise ValueError(
                    f"mlp_hidden={self.mlp_hidden} has a width not divisible by |{self.group}| = {G}"
                )

    def _check_kernel_basis(self) -> None:
        if self.kernel_basis not in KERNEL_BASES:
            raise ValueError(f"kernel_basis must be one of {KERNEL_BASES}, got {self.kernel_basis!r}")
        if self.kernel_basis == "free":
            return
        if self.group != "c4":
            raise ValueError(f"kernel_basis steerable is built for group c4, not {self.group!r}")
        if importlib.util.find_spec("e2cnn") is None:
            raise ValueError(
                "kernel_basis steerable needs e2cnn, which is not installed: pip install 'mea-rl[steerable]'"
            )

    @property
    def channels_per_field(self) -> int:
        """|G| for the equivariant nets, 4 for the twin."""
        return PLAIN_FIELD_CHANNELS if self.group == "none" else get_group(self.group).order

    def spatial_sizes(self) -> list[int]:
        """Map sizes after each encoder layer, the final 1x1 included.

        Every layer needs (N - k) divisible by its stride so that the sampling grid is symmetric
        under 90-degree rotations and mirrors (otherwise equivariance is only approximate)."""
        n, sizes = self.image_size, []
        for i, (_, k, s) in enumerate((*self.encoder, (0, self.final_kernel, 1))):
            if n < k:
                raise ValueError(f"encoder layer {i}: kernel {k} is larger than its {n}x{n} input")
            if (n - k) % s:
                raise ValueError(
                    f"encoder layer {i}: (N - k) = ({n} - {k}) is not divisible by stride {s}; "
                    "the grid would not be symmetric under 90-degree rotation"
                )
            n = (n - k) // s + 1
            sizes.append(n)
        if n != 1:
            raise ValueError(
                f"the final conv (kernel {self.final_kernel}) leaves a {n}x{n} map, not 1x1; "
                f"sizes after each layer: {sizes}"
            )
        return sizes

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (tuples as lists)."""
        d = dataclasses.asdict(self)
        d["encoder"] = [list(layer) for layer in self.encoder]
        d["mlp_hidden"] = list(self.mlp_hidden)
        d["state_critic_hidden"] = list(self.state_critic_hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NetConfig:
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown NetConfig keys: {sorted(unknown)}")
        return cls(**d)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> NetConfig:
        """A named preset ('paper' | 'cpu-small'), optionally with fields replaced (e.g. group='d4')."""
        try:
            base = PRESETS[name]
        except KeyError:
            raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}") from None
        return dataclasses.replace(base, **overrides)


PRESETS: dict[str, NetConfig] = {
    # Equi-RSAC widths (tasks-and-baselines.md section 2).
    "paper": NetConfig(),
    # For 2 CPU cores: the same 84x84 geometry and depth; encoder fields halved (C4: 16-32 channels,
    # D4: 32-64), image embedding, LSTM and MLPs 128 -> 64, action embeddings 16 -> 8 (the critic's 144 -> 8). Every width is
    # divisible by 8, so the preset works for C4 and D4 alike.
    "cpu-small": NetConfig(
        encoder=((4, 8, 4), (8, 4, 2), (8, 3, 1), (8, 3, 1), (8, 3, 1)),
        image_embed=64,
        action_embed=8,
        q_action_embed=8,
        lstm_hidden=64,
        mlp_hidden=(64, 64),
    ),
}


# ------------------------------------------------------------------------------------------------
# building blocks: one factory per kind of layer, equivariant or plain
# ------------------------------------------------------------------------------------------------


def _plain_init(module: nn.Module, gain: float) -> nn.Module:
    """Orthogonal weights, zero biases (the RSAC twin)."""
    for name, p in module.named_parameters():
        if "weight" in name:
            nn.init.orthogonal_(p, gain=gain)
        else:
            nn.init.zeros_(p)
    return module


_RELU_GAIN = math.sqrt(2.0)


class ImageEncoder(nn.Module):
    """(N, C, H, W) -> (N, image_embed): conv + ReLU layers down to a 1x1 map, flattened.

    Runs in channels_last memory format: with oneDNN on the 2-core CPU, forward + backward of the
    paper-width C4 encoder on 1632 images took 0.76 s against 1.23 s in NCHW (D4: 2.35 s vs 2.96 s)."""

    def __init__(self, cfg: NetConfig, group: Group | None) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        specs = [*cfg.encoder, (None, cfg.final_kernel, 1)]
        c_in, fields_in = cfg.in_channels, None
        for fields, k, s in specs:
            if group is None:
                c_out = cfg.image_embed if fields is None else fields * PLAIN_FIELD_CHANNELS
                layers.append(_plain_init(nn.Conv2d(c_in, c_out, k, s), _RELU_GAIN))
                c_in = c_out
            else:
                f_out = cfg.image_embed // group.order if fields is None else fields
                if cfg.kernel_basis == "steerable":
                    layers.append(SteerableConv2d(cfg.in_channels, fields_in, f_out, k, s))
                elif fields_in is None:
                    layers.append(LiftConv2d(group, cfg.in_channels, f_out, k, s))
                else:
                    layers.append(GroupConv2d(group, fields_in, f_out, k, s))
                fields_in = f_out
            layers.append(nn.ReLU(inplace=True))
        self.net = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        x = x.contiguous(memory_format=torch.channels_last)
        return self.net(x).flatten(1)


class SteerableConv2d(nn.Module):
    """A C4 conv whose kernel lies in e2cnn's steerable basis (the public Equi-RSAC encoder's escnn
    R2Conv: rings with Gaussian radial profiles, band-limited angular frequencies), expanded once per
    forward and run as one conv2d. Input: ``in_channels`` trivial channels, or ``fields_in`` regular
    fields where given; output ``fields_out`` regular fields, in this module's channel order
    (field-major, group minor, the same roll under a quarter turn). e2cnn builds the basis only,
    imported here lazily; its module is kept out of the state dict (its buffer names are not weights
    keys), and only the basis coefficients and field biases are this module's parameters."""

    def __init__(self, in_channels: int, fields_in: int | None, fields_out: int, k: int, stride: int) -> None:
        super().__init__()
        from e2cnn import gspaces
        from e2cnn import nn as enn

        space = gspaces.Rot2dOnR2(4)
        reprs = in_channels * [space.trivial_repr] if fields_in is None else fields_in * [space.regular_repr]
        conv = enn.R2Conv(enn.FieldType(space, reprs), enn.FieldType(space, fields_out * [space.regular_repr]),
                          k, stride=stride)  # fmt: skip
        object.__setattr__(self, "_conv", conv)  # not a submodule
        self.weight, self.bias = conv.weights, conv.bias
        self.stride = stride

    def _apply(self, fn, recurse: bool = True):
        super()._apply(fn, recurse)
        self._conv._apply(fn)
        self._conv.weights, self._conv.bias = self.weight, self.bias
        return self

    def __deepcopy__(self, memo):
        import copy

        clone = type(self).__new__(type(self))
        memo[id(self)] = clone
        for key, value in self.__dict__.items():
            object.__setattr__(clone, key, copy.deepcopy(value, memo))
        clone._conv.weights, clone._conv.bias = clone.weight, clone.bias
        return clone

    def forward(self, x: Tensor) -> Tensor:
        weight, bias = self._conv.expand_parameters()
        return F.conv2d(x, weight, bias, self.stride)


def encode_real(
    encoder: nn.Module,
    images: Tensor,
    obs_mask: Tensor | None,
    skip_padding: bool,
    real_images: Tensor | None = None,
) -> Tensor:
    """``encoder`` over (B, T, C, H, W) images -> (B, T, E), zeros at the steps ``obs_mask`` marks as
    padding. ``skip_padding`` leaves padded images out of the encoder (the CPU: less work); otherwise
    every image goes through it and padding is zeroed after (a GPU: no host synchronisation to read
    the mask and fixed shapes, the same values; padded images never reach a loss either way).
    ``real_images``: ``images[obs_mask]`` already gathered (``Batch.real_images``), so that the
    update's two or three encoders do not each copy the batch's images again."""
    B, T = images.shape[:2]
    if not skip_padding or obs_mask is None:
        emb = encoder(images.flatten(0, 1)).unflatten(0, (B, T))
        return emb if obs_mask is None else emb * obs_mask.unsqueeze(-1).to(emb.dtype)
    if real_images is not None and real_images.shape[0] != int(obs_mask.sum()):
        raise ValueError(
            f"{real_images.shape[0]} gathered images for {int(obs_mask.sum())} real observations"
        )
    if bool(obs_mask.all()):  # every step real: the gather is the flattening
        flat = images.flatten(0, 1) if real_images is None else real_images
        return encoder(flat).unflatten(0, (B, T))
    real = encoder(images[obs_mask] if real_images is None else real_images)
    emb = real.new_zeros(B, T, real.shape[-1])
    emb[obs_mask] = real
    return emb


class PlainLSTM(nn.Module):
    """nn.LSTM (batch first, orthogonal weights, zero biases) with the (B, H) state convention."""

    def __init__(self, input_size: int, hidden: int) -> None:
        super().__init__()
        self.hidden_channels = hidden
        self.lstm = _plain_init(nn.LSTM(input_size, hidden, batch_first=True), 1.0)

    def forward(self, x: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        hx = None if state is None else (state[0][None].contiguous(), state[1][None].contiguous())
        out, (h, c) = self.lstm(x, hx)
        return out, (h[0], c[0])


def _action_embed(cfg: NetConfig, group: Group | None, channels: int | None = None) -> nn.Module:
    """Linear (equivariant: lift to regular fields) + ReLU of an action into ``channels``
    (``cfg.action_embed`` unless given)."""
    channels = cfg.action_embed if channels is None else channels
    if group is None:
        return nn.Sequential(_plain_init(nn.Linear(ACTION_DIM, channels), _RELU_GAIN), nn.ReLU())
    return nn.Sequential(ActionLift(group, channels // group.order), nn.ReLU())


def _lstm(cfg: NetConfig, group: Group | None) -> nn.Module:
    if group is None:
        return PlainLSTM(cfg.image_embed + cfg.action_embed, cfg.lstm_hidden)
    G = group.order
    return EquivariantLSTM(group, (cfg.image_embed + cfg.action_embed) // G, cfg.lstm_hidden // G)


def _mlp(cfg: NetConfig, group: Group | None, in_channels: int, layer_norm: bool = False) -> nn.Sequential:
    """Hidden layers (linear [+ LayerNorm] + ReLU) of width cfg.mlp_hidden."""
    layers: list[nn.Module] = []
    for width in cfg.mlp_hidden:
        if group is None:
            layers.append(_plain_init(nn.Linear(in_channels, width), _RELU_GAIN))
            if layer_norm:
                layers.append(nn.LayerNorm(width))
        else:
            layers.append(GroupLinear(group, in_channels // group.order, width // group.order))
            if layer_norm:
                layers.append(GroupLayerNorm(group, width // group.order))
        layers.append(nn.ReLU())
        in_channels = width
    return nn.Sequential(*layers)


def _invariant_head(cfg: NetConfig, group: Group | None, in_channels: int, n: int) -> nn.Module:
    if group is None:
        return _plain_init(nn.Linear(in_channels, n), 1.0)
    return InvariantHead(group, in_channels // group.order, n)


def _mlp_out(cfg: NetConfig, width_in: int) -> int:
    return cfg.mlp_hidden[-1] if cfg.mlp_hidden else width_in


class _Recurrent(nn.Module):
    """Encoder + previous-action embedding + LSTM, shared structure of actor and critic."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.group = None if cfg.group == "none" else get_group(cfg.group)
        self.encoder = ImageEncoder(cfg, self.group)
        self.action_embed = _action_embed(cfg, self.group)
        self.lstm = _lstm(cfg, self.group)

    def initial_state(self, batch: int) -> LSTMState:
        p = next(self.parameters())
        z = p.new_zeros(batch, self.cfg.lstm_hidden)
        return z, z

    def encode(
        self, images: Tensor, obs_mask: Tensor | None = None, real_images: Tensor | None = None
    ) -> Tensor:
        """e(o_t) (B, T, image_embed). With ``obs_mask`` (B, T) bool, only the real observations go
        through the encoder and padded steps get zeros: padding comes after an episode's last step,
        so with a causal LSTM and masked losses nothing real depends on it. ``real_images``: see
        ``encode_real``."""
        cpu = images.device.type == "cpu"
        return encode_real(self.encoder, images, obs_mask, skip_padding=cpu, real_images=real_images)

    def recurrent(
        self,
        images: Tensor,
        prev_actions: Tensor,
        state: LSTMState | None,
        embedding: Tensor | None = None,
        obs_mask: Tensor | None = None,
        real_images: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, LSTMState]:
        """(h_t (B, T, lstm_hidden), e(o_t) (B, T, image_embed), final state). ``embedding``, if given,
        is e(o_t) already computed (an encoder shared with the critic) and the encoder is skipped;
        ``obs_mask``, ``real_images``: see ``encode``."""
        if (
            images.dim() != 5
            or prev_actions.shape[:2] != images.shape[:2]
            or prev_actions.shape[-1] != ACTION_DIM
        ):
            raise ValueError(
                f"expected images (B, T, C, H, W) and prev_actions (B, T, {ACTION_DIM}), "
                f"got {tuple(images.shape)} and {tuple(prev_actions.shape)}"
            )
        emb = self.encode(images, obs_mask, real_images) if embedding is None else embedding
        h, state = self.lstm(torch.cat([emb, self.action_embed(prev_actions)], dim=-1), state)
        return h, emb, state


def disc_xy(actor: nn.Module) -> bool:
    """Whether ``actor`` squashes (dx, dy) onto the disc (``NetConfig.xy_range``); a module without a
    NetConfig (the tests' small nets) keeps the box."""
    cfg = getattr(actor, "cfg", None)
    return isinstance(cfg, NetConfig) and cfg.xy_range == "disc"


class Actor(_Recurrent):
    """Gaussian policy before the squashing (``sac.losses.squash``): mean and log std per step."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__(cfg)
        width_in = cfg.lstm_hidden + cfg.image_embed
        self.mlp = _mlp(cfg, self.group, width_in)
        out = _mlp_out(cfg, width_in)
        if self.group is None:
            self.mean_head: nn.Module = _plain_init(nn.Linear(out, ACTION_DIM), 1.0)
        else:
            self.mean_head = ActionHead(self.group, out // self.group.order)
        self.log_std_head = _invariant_head(cfg, self.group, out, ACTION_DIM)

    def forward(
        self,
        images: Tensor,
        prev_actions: Tensor,
        state: LSTMState | None = None,
        embedding: Tensor | None = None,
        obs_mask: Tensor | None = None,
        real_images: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, LSTMState]:
        """images (B, T, C, H, W), prev_actions (B, T, 5) -> mean (B, T, 5) (pre-tanh), log_std
        (B, T, 5) in [-20, 2], final (h, c). ``embedding``, ``obs_mask``, ``real_images``: see
        ``recurrent``."""
        if not self.cfg.actor_prev_action:
            prev_actions = torch.zeros_like(prev_actions)  # invariant under every g: still equivariant
        h, emb, state = self.recurrent(images, prev_actions, state, embedding, obs_mask, real_images)
        z = self.mlp(torch.cat([h, emb], dim=-1))
        log_std = self.log_std_head(z).clamp(LOG_STD_MIN, LOG_STD_MAX)
        return self.mean_head(z), log_std, state

    def step(
        self, image: Tensor, prev_action: Tensor, state: LSTMState | None = None
    ) -> tuple[Tensor, Tensor, LSTMState]:
        """One step for acting: image (B, C, H, W), prev_action (B, 5) -> mean (B, 5), log_std (B, 5), state."""
        mean, log_std, state = self.forward(image[:, None], prev_action[:, None], state)
        return mean[:, 0], log_std[:, 0], state


class Critic(_Recurrent):
    """``cfg.critic_heads`` Q heads (twin by default) over shared recurrent features; every Q value
    is an invariant scalar."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__(cfg)
        self.feature_dim = cfg.lstm_hidden + cfg.image_embed
        # the action Q rates gets its own, wide embedding: with a few ReLU features of it, Q can
        # barely tell one move from another (the public critic's 144 channels; docs/results.md)
        self.q_action_embed = _action_embed(cfg, self.group, cfg.q_action_embed)
        width_in = self.feature_dim + cfg.q_action_embed
        out = _mlp_out(cfg, width_in)
        ln = cfg.critic_layer_norm

        def head() -> nn.Sequential:
            return nn.Sequential(
                _mlp(cfg, self.group, width_in, ln), _invariant_head(cfg, self.group, out, 1)
            )

        # q1, q2 and then the rest: a twin's parameter names and initial draws are the same as before
        # heads could be added, so its checkpoints load and its updates keep their bits
        self.q1, self.q2 = head(), head()
        self.more_q = nn.ModuleList(head() for _ in range(cfg.critic_heads - 2))

    def features(
        self,
        images: Tensor,
        prev_actions: Tensor,
        state: LSTMState | None = None,
        obs_mask: Tensor | None = None,
        real_images: Tensor | None = None,
    ) -> tuple[Tensor, LSTMState]:
        """images (B, T, C, H, W), prev_actions (B, T, 5) -> [h_t, e(o_t)] (B, T, feature_dim), final
        state. ``obs_mask``, ``real_images``: see ``recurrent``."""
        h, emb, state = self.recurrent(
            images, prev_actions, state, obs_mask=obs_mask, real_images=real_images
        )
        return torch.cat([h, emb], dim=-1), state

    def features_of(self, batch: Any) -> Tensor:
        """``features`` of a SAC batch's sequences (B, L+1, feature_dim)."""
        return self.features(
            batch.images, batch.prev_actions, obs_mask=batch.obs_mask, real_images=batch.real_images
        )[0]

    def q(self, features: Tensor, actions: Tensor) -> tuple[Tensor, ...]:
        """features (..., feature_dim), actions (..., 5) -> (Q1, Q2, ...), one per head, each (...)."""
        x = torch.cat([features, self.q_action_embed(actions)], dim=-1)
        return tuple(h(x).squeeze(-1) for h in (self.q1, self.q2, *self.more_q))


class StateCritic(nn.Module):
    """``cfg.critic_heads`` Q heads (twin by default) on the privileged state
    (``privileged.critic_state`` rows) and the action: plain MLPs with LayerNorm. The rows are in a
    frame turned by their angle (column 0), so the action's (dx, dy) is turned into it too: Q is then
    invariant under any rotation about z and horizontal translation of scene and action together
    (the symmetry the equivariant critic has for C4 only)."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.feature_dim = STATE_DIM

        def mlp() -> nn.Sequential:
            layers: list[nn.Module] = []
            width = STATE_DIM - 1 + ACTION_DIM
            for hidden in cfg.state_critic_hidden:
                layers += [_plain_init(nn.Linear(width, hidden), _RELU_GAIN), nn.LayerNorm(hidden), nn.ReLU()]
                width = hidden
            return nn.Sequential(*layers, _plain_init(nn.Linear(width, 1), 1.0))

        self.q1, self.q2 = mlp(), mlp()
        self.more_q = nn.ModuleList(mlp() for _ in range(cfg.critic_heads - 2))

    def features_of(self, batch: Any) -> Tensor:
        """The batch's privileged rows (B, L+1, STATE_DIM); ValueError if it carries none."""
        if batch.state is None or batch.state.shape[-1] != STATE_DIM:
            got = None if batch.state is None else tuple(batch.state.shape)
            raise ValueError(
                f"state: the state critic needs (B, L+1, {STATE_DIM}) privileged rows, got {got}"
            )
        return batch.state

    def q(self, features: Tensor, actions: Tensor) -> tuple[Tensor, ...]:
        """features (..., STATE_DIM), actions (..., 5) -> (Q1, Q2, ...), one per head, each (...)."""
        phi = features[..., CANONICAL_ANGLE]
        c, s = torch.cos(phi), torch.sin(phi)
        dx, dy = actions[..., 1], actions[..., 2]
        turned = torch.stack(
            [actions[..., 0], c * dx + s * dy, -s * dx + c * dy, actions[..., 3], actions[..., 4]], -1
        )
        x = torch.cat([features[..., CANONICAL_ANGLE + 1 :], turned], dim=-1)
        return tuple(h(x).squeeze(-1) for h in (self.q1, self.q2, *self.more_q))


def build_actor(cfg: NetConfig) -> Actor:
    return Actor(cfg)


def build_critic(cfg: NetConfig) -> Critic | StateCritic:
    return StateCritic(cfg) if cfg.critic_input == "state" else Critic(cfg)
