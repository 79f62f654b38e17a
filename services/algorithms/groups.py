"""The C4 / D4 symmetry groups and how they act on images, actions and regular fields.

Design notes: docs/architecture-notes.md, services/algorithms/groups.py."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from proto.actions import ACTION_DIM

Element = tuple[int, int]
"""(m, r): mirror bit and number of quarter turns."""


_ROT = ((1, 0, 0, 1), (0, -1, 1, 0), (-1, 0, 0, -1), (0, 1, -1, 0))
"""R(r 90 deg) as (a, b, c, d) = [[a, b], [c, d]], r = 0..3."""


def compose(g: Element, h: Element) -> Element:
    """g h: apply h first, then g."""
    m1, r1 = g
    m2, r2 = h
    return (m1 ^ m2, (r1 + (-r2 if m1 else r2)) % 4)


def inverse(g: Element) -> Element:
    m, r = g
    return (m, (r if m else -r) % 4)


def sign(g: Element) -> int:
    """Sign representation (-1)^m: how dtheta transforms."""
    return -1 if g[0] else 1


def matrix(g: Element) -> tuple[tuple[int, int], tuple[int, int]]:
    """2x2 integer matrix R(r 90 deg) F^m acting on (x, y) (and on (dx, dy))."""
    m, r = g
    a, b, c, d = _ROT[r % 4]
    s = -1 if m else 1  # F^m negates the second column
    return ((a, b * s), (c, d * s))


def action_matrix(g: Element, dtype: torch.dtype = torch.float32) -> Tensor:
    """5x5 matrix A(g) with transform_actions(a, g) = A(g) a; a homomorphism g -> A(g)."""
    A = torch.eye(ACTION_DIM, dtype=dtype)
    A[1:3, 1:3] = torch.tensor(matrix(g), dtype=dtype)
    A[4, 4] = float(sign(g))
    return A


@dataclass(frozen=True)
class Group:
    """A finite group of plane symmetries with its multiplication and inverse tables (by index)."""

    name: str
    elements: tuple[Element, ...]

    @property
    def order(self) -> int:
        return len(self.elements)

    def index(self, g: Element) -> int:
        return self.elements.index((int(g[0]), int(g[1]) % 4))

    @cached_property
    def mul(self) -> tuple[tuple[int, ...], ...]:
        """mul[i][j] = index of elements[i] elements[j]."""
        return tuple(tuple(self.index(compose(g, h)) for h in self.elements) for g in self.elements)

    @cached_property
    def inv(self) -> tuple[int, ...]:
        return tuple(self.index(inverse(g)) for g in self.elements)

    def matrices(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """(|G|, 2, 2): the matrix of every element, in index order."""
        return torch.tensor([matrix(g) for g in self.elements], dtype=dtype)

    def signs(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """(|G|,): the sign of every element."""
        return torch.tensor([sign(g) for g in self.elements], dtype=dtype)

    def regular_permutation(self, g: Element) -> list[int]:
        """perm with (g f)_h = f_{perm[h]}, i.e. perm[h] = index(g^-1 h)."""
        gi = inverse(g)
        return [self.index(compose(gi, h)) for h in self.elements]


C4 = Group("c4", tuple((0, r) for r in range(4)))
D4 = Group("d4", tuple((m, r) for m in range(2) for r in range(4)))
_GROUPS = {"c4": C4, "d4": D4}


def get_group(name: str) -> Group:
    try:
        return _GROUPS[name]
    except KeyError:
        raise ValueError(f"unknown group {name!r}; expected one of {sorted(_GROUPS)}") from None


def transform_images(x: Tensor, g: Element) -> Tensor:
    """g acting on images (..., H, W): flip columns if m, then rot90 r times (exact for even sizes)."""
    m, r = g
    if m:
        x = torch.flip(x, dims=(-1,))
    return torch.rot90(x, k=r % 4, dims=(-2, -1)) if r % 4 else x


def transform_actions(a: Tensor, g: Element) -> Tensor:
    """g acting on actions (..., 5): rotate/reflect (dx, dy), sign-flip dtheta under a mirror."""
    if a.shape[-1] != ACTION_DIM:
        raise ValueError(f"actions must end with {ACTION_DIM} entries, got shape {tuple(a.shape)}")
    return a @ action_matrix(g, a.dtype).to(a.device).T


def transform_regular(x: Tensor, g: Element, group: Group, spatial: bool = False) -> Tensor:
    """g acting on regular fields: channels at dim -3 with spatial (H, W) at the end if ``spatial``,
    else channels at dim -1. Permutes the channels of each field and, if spatial, moves space."""
    G = group.order
    cdim = -3 if spatial else -1
    C = x.shape[cdim]
    if C % G:
        raise ValueError(f"{C} channels is not a whole number of {group.name} regular fields")
    perm = torch.tensor(group.regular_permutation(g), device=x.device)
    idx = (torch.arange(C // G, device=x.device)[:, None] * G + perm[None, :]).reshape(-1)
    y = x.index_select(x.dim() + cdim, idx)
    return transform_images(y, g) if spatial else y
