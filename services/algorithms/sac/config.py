"""Recurrent SAC's hyperparameters (``SacSettings``): the paper's values as defaults, and the options
the CPU recipes add (BC term, Q filter, n-step and bounded targets, a shared encoder)."""

from __future__ import annotations

from dataclasses import dataclass

ACTOR_OBJECTIVES = ("sac", "crr")
ALPHA_LOSSES = ("alpha", "log_alpha")


@dataclass(frozen=True)
class SacSettings:
    gamma: float = 0.9
    """Discount (Equi-RSAC: 0.9)."""
    tau: float = 0.005
    """Target critic's soft-update rate."""
    lr: float = 3e-4
    """Critic's (and actor's) Adam rate."""
    # Adam steps at its rate whatever the size of the critic's action gradient, so an actor started
    # from a clone moves as fast along a critic that barely ranks actions as along one that does
    actor_lr: float | None = None
    """Actor's Adam rate; None: lr."""
    alpha_lr: float = 1e-3
    """Adam learning rate of log alpha."""
    init_alpha: float = 0.1
    """Initial entropy temperature."""
    target_entropy: float = -5.0
    """Target entropy (-action_dim)."""
    autotune_alpha: bool = True
    """Tune alpha to the target entropy."""
    # the same fixed point, different speeds under Adam: "alpha" (the public Equi-RSAC code, CleanRL)
    # scales log alpha's gradient by alpha, so alpha falls about 2.5x slower per update than with
    # "log_alpha" (Stable-Baselines3), whose gradient does not depend on alpha
    alpha_loss: str = "alpha"
    """Temperature loss: alpha or log_alpha."""
    bc_weight: float = 0.0
    """BC term's weight (0: off)."""
    n_step: int = 1
    """n of n-step critic targets (1: Equi-RSAC)."""
    return_bound: bool = False
    """Targets >= the observed return-to-go."""
    # with a task that ends on success, the soft value's entropy bonus (about alpha H / (1 - gamma) for
    # going on) can outweigh the success reward while alpha is high, and the policy first learns to
    # avoid the goal; SERL's pixel agents leave it out of the targets for that reason
    backup_entropy: bool = True
    """Entropy bonus in the critic targets."""
    share_encoder: bool = False
    """Actor reads the critic's encoder."""
    bc_filter: bool = False
    """Clone only demo actions the critic prefers."""
    bc_decay_updates: int = 0
    """Updates to decay bc_weight to 0 (0: off)."""
    # CQL's term (Kumar et al. 2020) in the critic loss: an actor released from a clone climbs the
    # critic into actions near the clone's that it overrates
    conservative_weight: float = 0.0
    """CQL term's weight (0: off)."""
    # Cal-QL (Nakamoto et al. 2023): CQL's push-down stops at the data's return-to-go, so a
    # released clone's actions are not rated below what its own episodes earned
    conservative_calibrated: bool = False
    """CQL: policy Q floored at return-to-go."""
    # crr (Wang et al. 2020): the weighted likelihood of replayed actions the critic rates above the
    # policy's own mean action, so the actor never follows the critic's gradient into actions that
    # no episode tried; crr_beta 0 keeps an action where its advantage is > 0, else weighs exp(A / beta)
    actor_objective: str = "sac"
    """Actor loss: sac or crr."""
    crr_beta: float = 0.0
    """crr: 0 keeps A > 0, else exp(A/beta) <= 20."""
    # REDQ (Chen et al. 2021) draws 2 of many heads per update for the target's min; None takes the
    # min over every head (the twin's rule; SAC-N's, An et al. 2021, with more heads)
    target_heads: int | None = None
    """Heads in the target's min; None: all."""
    # critic warm-up: BC (where on) still trains the actor meanwhile
    actor_warmup_updates: int = 0
    """Updates before actor and alpha move."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {self.tau}")
        if self.lr <= 0 or self.alpha_lr <= 0 or self.init_alpha <= 0 or self.actor_rate <= 0:
            raise ValueError("lr, actor_lr, alpha_lr and init_alpha must be positive")
        if self.bc_weight < 0:
            raise ValueError(f"bc_weight must be >= 0, got {self.bc_weight}")
        if self.n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {self.n_step}")
        if self.bc_decay_updates < 0:
            raise ValueError(f"bc_decay_updates must be >= 0, got {self.bc_decay_updates}")
        if self.actor_objective not in ACTOR_OBJECTIVES:
            raise ValueError(
                f"actor_objective must be one of {ACTOR_OBJECTIVES}, not {self.actor_objective!r}"
            )
        if self.alpha_loss not in ALPHA_LOSSES:
            raise ValueError(f"alpha_loss must be one of {ALPHA_LOSSES}, not {self.alpha_loss!r}")
        if self.conservative_weight < 0:
            raise ValueError(f"conservative_weight must be >= 0, got {self.conservative_weight}")
        if self.conservative_calibrated and self.conservative_weight == 0:
            raise ValueError("conservative_calibrated calibrates the CQL term: set conservative_weight > 0")
        if self.crr_beta < 0:
            raise ValueError(f"crr_beta must be >= 0, got {self.crr_beta}")
        if self.target_heads is not None and self.target_heads < 1:
            raise ValueError(f"target_heads must be >= 1, got {self.target_heads}")
        if self.actor_warmup_updates < 0:
            raise ValueError(f"actor_warmup_updates must be >= 0, got {self.actor_warmup_updates}")

    @property
    def actor_rate(self) -> float:
        """The actor's Adam learning rate: ``actor_lr`` where set, else ``lr``."""
        return self.lr if self.actor_lr is None else self.actor_lr

    def bc_weight_at(self, updates: int) -> float:
        """The BC weight after ``updates`` updates (``bc_decay_updates``' linear decay)."""
        if self.bc_decay_updates == 0:
            return self.bc_weight
        return self.bc_weight * max(0.0, 1.0 - updates / self.bc_decay_updates)
