"""GASv2's learner configuration: DreamerV2's hyperparameters (reference section 6), the ones GASv2
inherits, as one frozen dataclass, plus narrower presets for CPU runs and tests.

``PRESETS["paper"]`` is the dataclass default. ``cpu-small`` narrows the networks only (every loss
and optimiser hyperparameter, and the 32 x 32 categorical latent, stay the paper's); ``smoke`` is a
tiny model for end-to-end tests. DreamerV2's ``min_std`` is not a field: it only applies to Gaussian
latents and this model's latents are categorical.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from services.algorithms.gasv2.action_features import FEATURE_DIM

ACTIVATIONS = ("elu", "relu", "silu", "tanh")
REWARD_TRANSFORMS = ("tanh", "identity")


def conv_out_size(size: int, kernels: tuple[int, ...]) -> int:
    """Side of the encoder's last feature map: each conv is stride 2, no padding (DreamerV2's VALID)."""
    for k in kernels:
        size = (size - k) // 2 + 1
    return size


def deconv_out_size(kernels: tuple[int, ...]) -> int:
    """Side of the decoder's output: transposed convs of stride 2 from a 1 x 1 map (DreamerV2)."""
    size = 1
    for k in kernels:
        size = (size - 1) * 2 + k
    return size


@dataclass(frozen=True)
class DreamerConfig:
    # observation and actions ---------------------------------------------------------------
    image_size: int = 64
    """Side of the square image observation (GASv2: 64)."""
    channels: int = 3
    """Image channels (GASv2's DSA image: 3)."""
    action_dim: int = FEATURE_DIM
    """Width of the world model's action input (5)."""
    num_actions: int = 9
    """The actor's discrete actions (9)."""
    # RSSM ----------------------------------------------------------------------------------
    deter: int = 1024
    """GRU state width."""
    hidden: int = 1024
    """Width of the RSSM's input and output layers."""
    stoch: int = 32
    """Number of categorical latent variables."""
    classes: int = 32
    """Classes of each categorical latent."""
    gru_norm: bool = True
    """Layer norm inside the GRU cell (DreamerV2's)."""
    # image encoder / decoder and MLPs ------------------------------------------------------
    cnn_depth: int = 48
    """Channels of the first encoder conv (doubling per layer)."""
    encoder_kernels: tuple[int, ...] = (4, 4, 4, 4)
    """Kernel of each stride-2 encoder conv."""
    decoder_kernels: tuple[int, ...] = (5, 5, 6, 6)
    """Kernel of each stride-2 decoder deconv."""
    mlp_layers: int = 4
    """Hidden layers of the head, actor and critic MLPs."""
    mlp_units: int = 400
    """Width of the hidden layers of those MLPs."""
    act: str = "elu"
    """Activation of the convs and MLPs."""
    # world-model loss ----------------------------------------------------------------------
    kl_balance: float = 0.8
    """Share of the KL term that trains the prior."""
    kl_free: float = 0.0
    """Free nats: KL below this is not penalised."""
    kl_free_avg: bool = True
    """Free nats on the batch-mean KL (else per step)."""
    kl_scale: float = 1.0
    """Weight of the KL term in the world-model loss."""
    pred_discount: bool = True
    """Learn a discount (continue) head."""
    reward_transform: str = "tanh"
    """Squashing of the learnt rewards (clip_rewards)."""
    # optimisers (DreamerV2: Adam, eps 1e-5, clip 100, decoupled weight decay 1e-6) -----------
    model_lr: float = 1e-4
    """Adam learning rate of the world model."""
    actor_lr: float = 8e-5
    """Adam learning rate of the actor."""
    critic_lr: float = 2e-4
    """Adam learning rate of the critic."""
    opt_eps: float = 1e-5
    """Adam epsilon of every optimiser."""
    grad_clip: float = 100.0
    """Gradient clipping by global norm, per optimiser."""
    weight_decay: float = 1e-6
    """Decoupled weight decay per step (not times lr)."""
    # behaviour -----------------------------------------------------------------------------
    discount: float = 0.99
    """Discount of the imagined returns."""
    lam: float = 0.95
    """Lambda of the lambda-returns."""
    horizon: int = 15
    """Imagination horizon."""
    actor_entropy: float = 2e-3
    """Entropy bonus scale of the actor loss."""
    slow_target_every: int = 100
    """Updates between slow-critic updates."""
    slow_target_fraction: float = 1.0
    """Step of the slow critic towards the critic (1: copy)."""

    def __post_init__(self) -> None:
        self._check_architecture()
        self._check_training()

    def _check_architecture(self) -> None:
        for name in (
            "image_size", "channels", "action_dim", "num_actions", "deter", "hidden", "stoch", "classes",
            "cnn_depth", "mlp_units", "horizon", "slow_target_every",
        ):  # fmt: skip
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not isinstance(self.mlp_layers, int) or self.mlp_layers < 0:
            raise ValueError(f"mlp_layers must be an int >= 0, got {self.mlp_layers!r}")
        for name in ("encoder_kernels", "decoder_kernels"):
            ks = getattr(self, name)
            if not isinstance(ks, tuple) or not ks or any(not isinstance(k, int) or k < 2 for k in ks):
                raise ValueError(f"{name} must be a non-empty tuple of ints >= 2, got {ks!r}")
        if conv_out_size(self.image_size, self.encoder_kernels) < 1:
            raise ValueError(
                f"encoder_kernels {self.encoder_kernels} shrink a {self.image_size}-pixel image to nothing"
            )
        if deconv_out_size(self.decoder_kernels) != self.image_size:
            raise ValueError(
                f"decoder_kernels {self.decoder_kernels} produce {deconv_out_size(self.decoder_kernels)}-pixel "
                f"images, not image_size {self.image_size}"
            )
        if self.act not in ACTIVATIONS:
            raise ValueError(f"act must be one of {ACTIVATIONS}, got {self.act!r}")

    def _check_training(self) -> None:
        if self.reward_transform not in REWARD_TRANSFORMS:
            raise ValueError(
                f"reward_transform must be one of {REWARD_TRANSFORMS}, got {self.reward_transform!r}"
            )
        if not 0.0 <= self.kl_balance <= 1.0:
            raise ValueError(f"kl_balance must be in [0, 1], got {self.kl_balance}")
        if self.kl_free < 0 or self.kl_scale < 0:
            raise ValueError(f"kl_free and kl_scale must be >= 0, got {self.kl_free}, {self.kl_scale}")
        for name in ("model_lr", "actor_lr", "critic_lr", "opt_eps", "grad_clip"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.weight_decay < 1.0:
            raise ValueError(f"weight_decay must be in [0, 1), got {self.weight_decay}")
        if not 0.0 <= self.discount <= 1.0 or not 0.0 <= self.lam <= 1.0:
            raise ValueError(f"discount and lam must be in [0, 1], got {self.discount}, {self.lam}")
        if self.actor_entropy < 0:
            raise ValueError(f"actor_entropy must be >= 0, got {self.actor_entropy}")
        if not 0.0 < self.slow_target_fraction <= 1.0:
            raise ValueError(f"slow_target_fraction must be in (0, 1], got {self.slow_target_fraction}")

    @property
    def stoch_dim(self) -> int:
        """Width of the flattened one-hot latent sample."""
        return self.stoch * self.classes

    @property
    def feat_dim(self) -> int:
        """Width of a model state's feature [stoch, deter] read by the heads, actor and critic."""
        return self.stoch_dim + self.deter

    def to_dict(self) -> dict[str, Any]:
        """JSON-able: tuples become lists."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DreamerConfig:
        """Inverse of ``to_dict``; missing keys keep their defaults, unknown keys are an error."""
        names = {f.name for f in fields(cls)}
        for key in d:
            if key not in names:
                raise ValueError(f"unknown DreamerConfig key {key!r}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


PAPER = DreamerConfig()

CPU_SMALL = replace(
    PAPER,
    deter=200,  # 1024 -> 200: the GRU (3 x 2048 x 1024 weights) dominated the RSSM's per-step cost
    hidden=200,  # 1024 -> 200: RSSM input/output layers, same reason
    cnn_depth=16,  # 48 -> 16: encoder and decoder convs cost ~9x less (channels enter squared)
    mlp_layers=2,  # 4 -> 2: reward, discount, actor and critic MLPs
    mlp_units=200,  # 400 -> 200
)
"""Narrower networks for a 2-core CPU (about 0.4 s per update at batch 16 x 6 on one thread, against
2.4 s for the paper's sizes); the 32 x 32 latent, kernels, losses and optimisers are the paper's."""

SMOKE = replace(PAPER, deter=32, hidden=32, stoch=8, classes=8, cnn_depth=8, mlp_layers=1, mlp_units=32)
"""A tiny model for end-to-end tests (every hyperparameter except the sizes as the paper's). The
latent stays 8 x 8 and the convs 8 deep: with 4 x 4 and 4 the toy worlds' posteriors collapsed
(KL -> 0, mean-image reconstructions) on some seeds."""

PRESETS: dict[str, DreamerConfig] = {"paper": PAPER, "cpu-small": CPU_SMALL, "smoke": SMOKE}
