"""C4 / D4 equivariant layers in plain PyTorch (weight-tied group convolutions, Cohen & Welling 2016).

Design notes: docs/architecture-notes.md, services/algorithms/equivariant.py."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from proto.actions import ACTION_DIM
from services.algorithms.groups import Group, action_matrix, inverse, transform_images

LSTMState = tuple[Tensor, Tensor]
"""(h, c), each (B, hidden channels)."""


def _spatial_index(group: Group, k: int) -> Tensor:
    """(|G|, k k) long: T_g(W).flatten() = W.flatten()[idx[g]] for every element g."""
    base = torch.arange(k * k).reshape(k, k)
    return torch.stack([transform_images(base, g).reshape(-1) for g in group.elements])


def _group_conv_index(group: Group, k: int) -> Tensor:
    """(|G| |G| k k,) long into a base kernel viewed (out, in, |G| k k): entry (g, h, p) selects
    W[..., g^-1 h, T_g-moved p] for output element g and input element h."""
    G, kk = group.order, k * k
    sp = _spatial_index(group, k)  # (G, kk)
    mul, inv = group.mul, group.inv
    gih = torch.tensor([[mul[inv[g]][h] for h in range(G)] for g in range(G)])  # (G, G): g^-1 h
    return (gih[:, :, None] * kk + sp[:, None, :]).reshape(-1)


def field_bias(bias: Tensor | None, group: Group) -> Tensor | None:
    """One bias per field -> one per channel (each field's value repeated over its |G| channels)."""
    return None if bias is None else bias.repeat_interleave(group.order)


def group_pool(x: Tensor, group: Group, dim: int = -1) -> Tensor:
    """Mean over the group axis of regular fields at ``dim``: (..., F |G|, ...) -> (..., F, ...)."""
    dim = dim % x.dim()
    G = group.order
    return x.unflatten(dim, (x.shape[dim] // G, G)).mean(dim + 1)


class GroupPool(nn.Module):
    """Invariant pooling of regular fields (channels at ``dim``)."""

    def __init__(self, group: Group, dim: int = -1) -> None:
        super().__init__()
        self.group, self.dim = group, dim

    def forward(self, x: Tensor) -> Tensor:
        return group_pool(x, self.group, self.dim)


class _TiedConv2d(nn.Module):
    """A conv2d whose kernel is gathered from a base weight (out_fields, in_size, taps) by the index
    ``kernel_index`` gives (|G| x taps entries), with one bias per output field."""

    def __init__(
        self,
        group: Group,
        in_size: int,
        out_fields: int,
        kernel_size: int,
        stride: int = 1,
        bias: bool = True,
    ) -> None:
        super().__init__()
        self.group, self.stride, self.k = group, stride, kernel_size
        self.in_size, self.out_fields = in_size, out_fields
        index = self.kernel_index(group, kernel_size)
        taps = index.numel() // group.order
        fan_in = in_size * taps
        self.weight = nn.Parameter(torch.randn(out_fields, in_size, taps) * math.sqrt(2.0 / fan_in))
        self.bias = nn.Parameter(torch.zeros(out_fields)) if bias else None
        self.register_buffer("index", index, persistent=False)

    @staticmethod
    def kernel_index(group: Group, k: int) -> Tensor:
        raise NotImplementedError

    def expanded_weight(self) -> Tensor:
        raise NotImplementedError

    def forward(self, x: Tensor) -> Tensor:
        return F.conv2d(x, self.expanded_weight(), field_bias(self.bias, self.group), self.stride)


class LiftConv2d(_TiedConv2d):
    """Trivial input channels (``in_size``) -> regular fields: output channel (f, g) correlates with
    T_g(W[f])."""

    @staticmethod
    def kernel_index(group: Group, k: int) -> Tensor:
        return _spatial_index(group, k).reshape(-1)

    def expanded_weight(self) -> Tensor:
        """(F |G|, C, k, k) conv2d kernel."""
        F_, C, kk = self.weight.shape
        G, k = self.group.order, self.k
        w = self.weight.index_select(2, self.index).view(F_, C, G, kk)
        return w.permute(0, 2, 1, 3).reshape(F_ * G, C, k, k)


class GroupConv2d(_TiedConv2d):
    """Regular fields (``in_size`` of them) -> regular fields with base kernel (out, in, |G|, k, k)."""

    @staticmethod
    def kernel_index(group: Group, k: int) -> Tensor:
        return _group_conv_index(group, k)

    def expanded_weight(self) -> Tensor:
        """(F_out |G|, F_in |G|, k, k) conv2d kernel."""
        Fo, Fi, _ = self.weight.shape
        G, k = self.group.order, self.k
        w = self.weight.index_select(2, self.index).view(Fo, Fi, G, G, k * k)
        return w.permute(0, 2, 1, 3, 4).reshape(Fo * G, Fi * G, k, k)


class GroupLinear(nn.Module):
    """Regular -> regular linear map on flat vectors (..., F_in |G|) -> (..., F_out |G|).

    Entry ((f, g), (f', h)) of the expanded matrix is W[f, f', g^-1 h]: the equivariant 1x1 conv."""

    def __init__(
        self, group: Group, in_fields: int, out_fields: int, bias: bool = True, gain: float = 2.0
    ) -> None:
        super().__init__()
        self.group, self.in_fields, self.out_fields = group, in_fields, out_fields
        G = group.order
        self.weight = nn.Parameter(torch.randn(out_fields, in_fields, G) * math.sqrt(gain / (in_fields * G)))
        self.bias = nn.Parameter(torch.zeros(out_fields)) if bias else None
        self.register_buffer("index", _group_conv_index(group, 1), persistent=False)

    def expanded_weight(self) -> Tensor:
        """(F_out |G|, F_in |G|) matrix."""
        Fo, Fi, G = self.weight.shape
        w = self.weight.index_select(2, self.index).view(Fo, Fi, G, G)
        return w.permute(0, 2, 1, 3).reshape(Fo * G, Fi * G)

    def forward(self, x: Tensor) -> Tensor:
        return F.linear(x, self.expanded_weight(), field_bias(self.bias, self.group))


class GroupLayerNorm(nn.Module):
    """LayerNorm over all channels of regular fields (..., F |G|), with one scale and bias per field.

    Mean and variance over every channel are invariant under the channel permutation by which g acts,
    so normalising commutes with it; a per-channel affine would not (the same reason as per-field
    biases), hence the scale and bias are tied over each field's |G| channels."""

    def __init__(self, group: Group, fields: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.group, self.eps = group, eps
        self.weight = nn.Parameter(torch.ones(fields))
        self.bias = nn.Parameter(torch.zeros(fields))

    def forward(self, x: Tensor) -> Tensor:
        G = self.group.order
        w, b = self.weight.repeat_interleave(G), self.bias.repeat_interleave(G)
        return F.layer_norm(x, x.shape[-1:], w, b, self.eps)


class ActionLift(nn.Module):
    """Action (..., 5) -> regular fields (..., F |G|): channel (f, g) = W[f] . (g^-1 a) + b[f].

    With A(g) the action representation (`groups.action_matrix`), the expanded matrix has rows
    W[f] A(g^-1); this spans every equivariant linear map from the action's type to regular fields.
    """

    def __init__(self, group: Group, out_fields: int, bias: bool = True) -> None:
        super().__init__()
        self.group, self.out_fields = group, out_fields
        self.weight = nn.Parameter(torch.randn(out_fields, ACTION_DIM) * math.sqrt(2.0 / ACTION_DIM))
        self.bias = nn.Parameter(torch.zeros(out_fields)) if bias else None
        mats = torch.stack([action_matrix(inverse(g)) for g in group.elements])  # (G, 5, 5)
        self.register_buffer("inv_action_matrices", mats, persistent=False)

    def expanded_weight(self) -> Tensor:
        """(F |G|, 5) matrix."""
        w = torch.einsum("fi,gij->fgj", self.weight, self.inv_action_matrices)
        return w.reshape(-1, ACTION_DIM)

    def forward(self, a: Tensor) -> Tensor:
        return F.linear(a, self.expanded_weight(), field_bias(self.bias, self.group))


class InvariantHead(nn.Module):
    """Regular fields (..., F |G|) -> n invariant outputs: mean over the group, then a linear map."""

    def __init__(self, group: Group, in_fields: int, out_features: int, bias: bool = True) -> None:
        super().__init__()
        self.group = group
        self.linear = nn.Linear(in_fields, out_features, bias=bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.linear(group_pool(x, self.group))


class ActionHead(nn.Module):
    """Regular fields (..., F |G|) -> action-typed outputs (..., 5) = (jaw, dx, dy, dz, dtheta).

    * jaw, dz (and dtheta for C4): trivial, mean over the group then weights and a bias;
    * (dx, dy): the frequency-1 irrep, v = sum_{f, g} f_{f,g} rho(g) e_f / |G| with a learned 2-vector
      e_f per field and no bias (a bias would not rotate);
    * dtheta for D4: the sign representation, s = sum_{f, g} w_f sign(g) f_{f,g} / |G|, no bias.

    One matrix (5, F |G|) is built per call and applied with a single linear.
    """

    def __init__(self, group: Group, in_fields: int) -> None:
        super().__init__()
        self.group = group
        self.signed = any(m for m, _ in group.elements)  # dtheta is the sign rep iff mirrors exist
        n_trivial = 2 if self.signed else 3
        bound = 1.0 / math.sqrt(in_fields)
        self.trivial = nn.Parameter(torch.empty(n_trivial, in_fields).uniform_(-bound, bound))
        self.trivial_bias = nn.Parameter(torch.zeros(n_trivial))
        self.irrep = nn.Parameter(torch.empty(in_fields, 2).uniform_(-bound, bound))
        self.sign_weight = (
            nn.Parameter(torch.empty(in_fields).uniform_(-bound, bound)) if self.signed else None
        )
        self.register_buffer("rho", group.matrices(), persistent=False)  # (G, 2, 2)
        self.register_buffer("sign", group.signs(), persistent=False)  # (G,)
        self.trivial_rows = [0, 3] if self.signed else [0, 3, 4]

    def expanded(self) -> tuple[Tensor, Tensor]:
        """The (5, F |G|) matrix and the (5,) bias (zero on the irrep and sign rows)."""
        G = self.group.order
        Fi = self.irrep.shape[0]
        rows = torch.zeros(ACTION_DIM, Fi, G, dtype=self.irrep.dtype, device=self.irrep.device)
        rows[self.trivial_rows] = self.trivial[:, :, None].expand(-1, -1, G)
        rows[1:3] = torch.einsum("gij,fj->ifg", self.rho, self.irrep)
        if self.sign_weight is not None:
            rows[4] = self.sign_weight[:, None] * self.sign[None, :]
        bias = torch.zeros(ACTION_DIM, dtype=self.trivial_bias.dtype, device=self.trivial_bias.device)
        bias[self.trivial_rows] = self.trivial_bias
        return rows.reshape(ACTION_DIM, Fi * G) / G, bias

    def forward(self, x: Tensor) -> Tensor:
        w, b = self.expanded()
        return F.linear(x, w, b)


class EquivariantLSTM(nn.Module):
    """LSTM over regular fields: (B, T, F_x |G|) -> (B, T, F_h |G|), state (h, c) of (B, F_h |G|).

    gates = GroupLinear_x(x_t) + GroupLinear_h(h_{t-1}) -> 4 F_h fields, gate-major (i, f, g, o), each a
    block of F_h regular fields; i, f, o = sigmoid, g = tanh, c_t = f c_{t-1} + i g, h_t = o tanh(c_t).
    Optional peepholes (i, f on c_{t-1}; o on c_t) have ONE scalar per field (P1). The input projection
    of all steps is one matmul; only the recurrent part loops over time.
    """

    def __init__(self, group: Group, input_fields: int, hidden_fields: int, peephole: bool = False) -> None:
        super().__init__()
        self.group, self.hidden_fields = group, hidden_fields
        self.hidden_channels = hidden_fields * group.order
        self.input_map = GroupLinear(group, input_fields, 4 * hidden_fields, bias=True, gain=1.0)
        self.hidden_map = GroupLinear(group, hidden_fields, 4 * hidden_fields, bias=False, gain=1.0)
        self.peephole = nn.Parameter(torch.zeros(3, hidden_fields)) if peephole else None

    def expanded_peepholes(self) -> Tensor | None:
        """(3, F_h |G|) per-channel peephole weights (i, f, o), tied within each field."""
        return None if self.peephole is None else self.peephole.repeat_interleave(self.group.order, dim=1)

    def initial_state(self, batch: int, like: Tensor) -> LSTMState:
        z = like.new_zeros(batch, self.hidden_channels)
        return z, z

    def forward(self, x: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        B, T, _ = x.shape
        h, c = self.initial_state(B, x) if state is None else state
        if self.peephole is None:
            # Without peepholes this is a plain LSTM whose weights are the expanded (equivariant)
            # matrices, gates in the same (i, f, g, o) order: aten's fused loop, about 4x faster
            # forward + backward than the Python loop below on a CPU (B 8, T 51, 64 channels).
            wi, wh = self.input_map.expanded_weight(), self.hidden_map.expanded_weight()
            bi = field_bias(self.input_map.bias, self.group)
            params = [wi, wh, bi, torch.zeros_like(bi)]
            out, h1, c1 = torch.lstm(x, (h[None], c[None]), params, True, 1, 0.0, self.training, False, True)
            return out, (h1[0], c1[0])
        xg = self.input_map(x).unbind(1)  # T x (B, 4 H); unbind: one stack in backward, not T scatters
        wh = self.hidden_map.expanded_weight()  # (4 H, H)
        peep = self.expanded_peepholes()
        outs = []
        for t in range(T):
            gates = torch.addmm(xg[t], h, wh.T)
            i, f, g, o = gates.chunk(4, dim=-1)
            if peep is not None:
                i = i + peep[0] * c
                f = f + peep[1] * c
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            if peep is not None:
                o = o + peep[2] * c
            h = torch.sigmoid(o) * torch.tanh(c)
            outs.append(h)
        return torch.stack(outs, dim=1), (h, c)
