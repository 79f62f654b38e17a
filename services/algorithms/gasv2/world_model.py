"""DreamerV2's world model: CNN encoder, RSSM, CNN decoder, reward and discount heads, and its loss
over a ``ChunkBatch``.

    L_model = kl_scale KL_balanced + E[-log p(x_t | s_t)] + E[-log p(r_t | s_t)] + E[-log p(c_t | s_t)]

every expectation a mean over the batch's real observations (``mask``): padding contributes nothing.
Image and reward are unit-variance Gaussians, written without their constant (0.5 x squared
error, summed over pixels for the image); the image target is the image in [0, 1] centred by -0.5
(DreamerV2's preprocessing), the reward target the transformed reward (``reward_transform``); the
discount head is a Bernoulli on "observation t is not terminal" (the batch's ``discounts``).
Imagination multiplies its probability by ``cfg.discount``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from services.algorithms.gasv2.chunks import ChunkBatch
from services.algorithms.gasv2.config import DreamerConfig, conv_out_size
from services.algorithms.gasv2.rssm import (
    RSSM,
    RSSMState,
    activation,
    features,
    init_weights,
    kl_loss,
    masked_mean,
)


def mlp(inp: int, out: int, layers: int, units: int, act: str) -> nn.Sequential:
    """``layers`` dense + activation layers of ``units``, then a linear output (DreamerV2's MLP)."""
    mods: list[nn.Module] = []
    for _ in range(layers):
        mods += [nn.Linear(inp, units), activation(act)]
        inp = units
    mods.append(nn.Linear(inp, out))
    net = nn.Sequential(*mods)
    init_weights(net)
    return net


def transform_reward(reward: Tensor, kind: str) -> Tensor:
    """DreamerV2's ``clip_rewards``: the reward head learns tanh(r) (or r)."""
    return torch.tanh(reward) if kind == "tanh" else reward


class Encoder(nn.Module):
    """Images (..., C, H, W) in [0, 1] -> embeddings (..., embed_dim): stride-2 convs without padding,
    depth doubling from ``cnn_depth``, each followed by the activation."""

    def __init__(self, cfg: DreamerConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        inp = cfg.channels
        for i, k in enumerate(cfg.encoder_kernels):
            depth = 2**i * cfg.cnn_depth
            layers += [nn.Conv2d(inp, depth, k, stride=2), activation(cfg.act)]
            inp = depth
        self.convs = nn.Sequential(*layers)
        self.embed_dim = inp * conv_out_size(cfg.image_size, cfg.encoder_kernels) ** 2
        self.image_shape = (cfg.channels, cfg.image_size, cfg.image_size)
        init_weights(self)

    def forward(self, images: Tensor) -> Tensor:
        lead = images.shape[:-3]
        if tuple(images.shape[-3:]) != self.image_shape:
            raise ValueError(f"images must end in {self.image_shape}, got {tuple(images.shape)}")
        x = self.convs(images.reshape(-1, *self.image_shape) - 0.5)
        return x.reshape(*lead, self.embed_dim)


class Decoder(nn.Module):
    """Features (N, F) -> mean image (N, C, H, W) in the centred space [-0.5, 0.5]: a dense layer to
    a 1 x 1 map of 32 x cnn_depth channels, then stride-2 transposed convs (the last without
    activation)."""

    def __init__(self, cfg: DreamerConfig) -> None:
        super().__init__()
        n = len(cfg.decoder_kernels)
        self.dense = nn.Linear(cfg.feat_dim, 32 * cfg.cnn_depth)
        layers: list[nn.Module] = []
        inp = 32 * cfg.cnn_depth
        for i, k in enumerate(cfg.decoder_kernels):
            last = i == n - 1
            depth = cfg.channels if last else int(2 ** (n - i - 2) * cfg.cnn_depth)
            layers.append(nn.ConvTranspose2d(inp, depth, k, stride=2))
            if not last:
                layers.append(activation(cfg.act))
            inp = depth
        self.deconvs = nn.Sequential(*layers)
        init_weights(self)

    def forward(self, feat: Tensor) -> Tensor:
        return self.deconvs(self.dense(feat)[:, :, None, None])


class WorldModel(nn.Module):
    def __init__(self, cfg: DreamerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.rssm = RSSM(cfg, self.encoder.embed_dim)
        self.decoder = Decoder(cfg)
        self.reward_head = mlp(cfg.feat_dim, 1, cfg.mlp_layers, cfg.mlp_units, cfg.act)
        self.discount_head = (
            mlp(cfg.feat_dim, 1, cfg.mlp_layers, cfg.mlp_units, cfg.act) if cfg.pred_discount else None
        )

    def reward(self, feat: Tensor) -> Tensor:
        """Predicted (transformed) reward arriving with the state of ``feat`` (...)."""
        return self.reward_head(feat).squeeze(-1)

    def discount(self, feat: Tensor) -> Tensor:
        """cfg.discount x P(the state of ``feat`` is not terminal) (...); cfg.discount without the head."""
        if self.discount_head is None:
            return torch.full(feat.shape[:-1], self.cfg.discount, dtype=feat.dtype, device=feat.device)
        return self.cfg.discount * torch.sigmoid(self.discount_head(feat).squeeze(-1))

    def loss(
        self, batch: ChunkBatch, generator: torch.Generator | None = None
    ) -> tuple[Tensor, RSSMState, dict[str, Tensor]]:
        """(model loss, posterior states (B, L, ...), detached metrics) of one batch."""
        cfg = self.cfg
        mask = batch.mask.bool()
        embeds = self.encoder(batch.images)
        posts, priors = self.rssm.observe(embeds, batch.actions, batch.is_first, generator=generator)
        kl, kl_value = kl_loss(
            posts.logits, priors.logits, cfg.kl_balance, cfg.kl_free, cfg.kl_free_avg, mask
        )
        feat = features(posts)
        # decode the real observations only: padding costs no decoder time and cannot enter the mean
        real = feat[mask]
        target = batch.images[mask] - 0.5
        image_nll = 0.5 * (self.decoder(real) - target).pow(2).sum((1, 2, 3))
        image_loss = image_nll.sum() / max(real.shape[0], 1)
        reward_target = transform_reward(batch.rewards, cfg.reward_transform)
        reward_loss = masked_mean(0.5 * (self.reward(feat) - reward_target).pow(2), mask)
        if self.discount_head is not None:
            logits = self.discount_head(feat).squeeze(-1)
            bce = F.binary_cross_entropy_with_logits(logits, batch.discounts, reduction="none")
            discount_loss = masked_mean(bce, mask)
        else:
            discount_loss = feat.new_zeros(())
        model_loss = cfg.kl_scale * kl + image_loss + reward_loss + discount_loss
        metrics = {
            "model_loss": model_loss,
            "image_loss": image_loss,
            "reward_loss": reward_loss,
            "discount_loss": discount_loss,
            "kl": masked_mean(kl_value, mask),
            "prior_entropy": masked_mean(_entropy(priors.logits), mask),
            "post_entropy": masked_mean(_entropy(posts.logits), mask),
        }
        return model_loss, posts, {k: v.detach() for k, v in metrics.items()}


def _entropy(logits: Tensor) -> Tensor:
    """Entropy of the categorical latents (..., stoch, classes), summed over them: (...)."""
    log_p = logits.log_softmax(-1)
    return -(log_p.exp() * log_p).sum((-2, -1))
