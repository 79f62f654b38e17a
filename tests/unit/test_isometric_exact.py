"""Rotated copies are exact: no rotated (dx, dy) is ever clipped, the angle falls back to a multiple
of 90 degrees when no uniform draw fits, and the provenance regenerates every rotated copy.

The public code clips rotated actions to [-1, 1]; a diagonal (1, 1) move turned by 45 degrees
would be stored as (0, 1) while the observations show (0, 1.41): 2 cm of motion that the stored
action no longer produces.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from proto.episode import Episode
from services.augmenter.core.isometric import (
    QUARTER,
    compose_with_mea,
    cos_sin,
    draw_rotation,
    isometric_copy,
    rotate_actions,
    rotation_fits,
)
from services.augmenter.core.pipeline import (
    AugmentSettings,
    augment_episode,
    episode_seed,
    isometric_angle,
    mea_copies,
    shared_rotation,
)
from services.observation.depth_image import policy_images, rotate_images
from tests.helpers.synthetic import synthetic_episode

pytestmark = pytest.mark.unit

ALL = AugmentSettings(mea_on="all", reproject=False)
DIAGONALS = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], np.float32)


def exact_rotation(actions: np.ndarray, phi: float) -> np.ndarray:
    """(dx, dy) turned by phi in float64, no clipping: what the copy must store (to float32)."""
    a = np.asarray(actions, np.float64)
    c, s = math.cos(phi), math.sin(phi)
    return np.stack([c * a[:, 1] - s * a[:, 2], s * a[:, 1] + c * a[:, 2]], axis=1)


def with_actions(seed: int, kind: str) -> Episode:
    """A synthetic episode whose (dx, dy) are large: ``diagonal`` has full (+-1, +-1) moves, ``large``
    moves up to 1 per axis (most rotations would clip some), ``small`` moves inside the unit disc."""
    rng = np.random.default_rng([seed, 99])
    T = 20
    if kind == "small":
        r, t = rng.uniform(0, 0.99, T), rng.uniform(0, 2 * math.pi, T)
        xy = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    else:
        xy = rng.uniform(-0.3, 0.3, (T, 2))
        steps = rng.choice(T, 3, replace=False)
        xy[steps] = (
            DIAGONALS[rng.integers(4, size=3)] if kind == "diagonal" else rng.uniform(0.75, 1.0, (3, 2))
        )
        xy[steps] *= np.sign(rng.uniform(-1, 1, (3, 2)))
    return synthetic_episode(seed, T, xy=xy.astype(np.float32))[0]


def assert_exact(copy: Episode, source: Episode) -> float:
    phi = float(copy.augmentation.params["rotation"][0])
    assert np.abs(copy.actions[:, 1:3]).max() <= 1.0
    np.testing.assert_allclose(copy.actions[:, 1:3], exact_rotation(source.actions, phi), rtol=0, atol=2e-7)
    np.testing.assert_array_equal(copy.actions[:, [0, 3, 4]], source.actions[:, [0, 3, 4]])
    return phi


def is_quarter_turn(phi: float) -> bool:
    return abs(phi / QUARTER - round(phi / QUARTER)) < 1e-12


@pytest.mark.parametrize("kind", ["diagonal", "large", "small"])
def test_no_rotated_copy_is_clipped(kind):
    """Every stored rotated action is the exact rotation of its source's, over many episodes."""
    angles = []
    for seed in range(40):
        raw = with_actions(seed, kind)
        out, _ = augment_episode(raw, ALL)
        iso = [e for e in out if e.augmentation and e.augmentation.kind == "isometric"]
        both = [e for e in out if e.augmentation and e.augmentation.kind == "mea+isometric"]
        assert len(iso) == 4
        angles += [assert_exact(e, raw) for e in iso]
        # MEA∘isometric: the un-rotated MEA copies (regenerated) turned exactly by the shared angle
        seed_ = episode_seed(ALL.seed, raw.episode_id)
        made = {c.episode_id: c for c, _ in mea_copies(raw, ALL.mea, ALL.mea_copies, seed_) if c is not None}
        for e in both:
            angles.append(assert_exact(e, made[e.episode_id]))
    assert len(angles) > 4 * 40  # MEA∘isometric copies were checked too
    quarter = np.mean([is_quarter_turn(a) for a in angles])
    if kind == "diagonal":  # a (1, 1) move fits only the four quarter turns: every angle falls back
        assert quarter == 1.0
    elif kind == "small":  # every uniform draw fits: never a fallback
        assert quarter == 0.0
    else:  # some episodes find a uniform angle, some fall back
        assert 0.0 < quarter < 1.0


def test_the_old_clipping_would_have_changed_these_actions():
    """The test above can fail: rotating a diagonal move by a generic angle leaves [-1, 1]."""
    raw = with_actions(0, "diagonal")
    assert not rotation_fits(raw.actions, 0.7)
    with pytest.raises(ValueError, match="clipped"):
        rotate_actions(raw.actions, 0.7)
    with pytest.raises(ValueError, match="clipped"):
        isometric_copy(raw, math.pi / 4, seed=0, copy_index=0, episode_id="x")
    assert np.abs(exact_rotation(raw.actions, math.pi / 4)).max() > 1.4


def test_quarter_turns_are_exact_permutations():
    assert [cos_sin(k * QUARTER) for k in range(5)] == [
        (1.0, 0.0),
        (0.0, 1.0),
        (-1.0, 0.0),
        (0.0, -1.0),
        (1.0, 0.0),
    ]
    a = np.zeros((4, 5), np.float32)
    a[:, 1:3] = DIAGONALS
    turned = rotate_actions(a, QUARTER)
    np.testing.assert_array_equal(turned[:, 1:3], np.stack([-a[:, 2], a[:, 1]], axis=1))
    np.testing.assert_array_equal(rotate_actions(a, 2 * QUARTER)[:, 1:3], -a[:, 1:3])


def test_the_fallback_draws_each_quarter_turn():
    diagonal = np.zeros((1, 5), np.float32)
    diagonal[0, 1:3] = (1.0, 1.0)
    rng = np.random.default_rng(3)
    got = [draw_rotation(rng, [diagonal]) for _ in range(400)]
    counts = np.bincount([round(p / QUARTER) for p in got], minlength=4)
    assert all(is_quarter_turn(p) for p in got) and counts.min() > 70  # about 100 each
    # a fitting angle is returned at once; the bound on draws is what forces the fallback
    small = np.full((1, 5), 0.1, np.float32)
    assert not is_quarter_turn(draw_rotation(np.random.default_rng(0), [small]))
    assert is_quarter_turn(draw_rotation(np.random.default_rng(0), [small], draws=0))
    # one angle for several episodes must fit all of them
    wide = np.zeros((1, 5), np.float32)
    wide[0, 1:3] = (0.0, 1.0)
    phis = [draw_rotation(np.random.default_rng(s), [small, wide]) for s in range(50)]
    assert all(rotation_fits(wide, p) and rotation_fits(small, p) for p in phis)


@pytest.mark.parametrize("kind", ["diagonal", "large"])
def test_provenance_regenerates_every_rotated_copy(kind):
    raw = with_actions(5, kind)
    out, _ = augment_episode(raw, ALL)
    seed = episode_seed(ALL.seed, raw.episode_id)
    made = [c for c, _ in mea_copies(raw, ALL.mea, ALL.mea_copies, seed) if c is not None]
    for e in out[1:]:
        prov = e.augmentation
        phi = float(prov.params["rotation"][0])
        assert prov.seed == seed
        if prov.kind == "isometric":
            assert isometric_angle(prov.seed, prov.copy_index, raw.actions) == phi
            again = isometric_copy(
                raw, phi, seed=prov.seed, copy_index=prov.copy_index, episode_id=e.episode_id
            )
        else:
            assert shared_rotation(prov.seed, made) == phi
            again = compose_with_mea(made[prov.copy_index], phi)
        assert again.encode() == e.encode()


def test_depth_copies_use_the_same_exact_angles():
    """``equirsac``: the rendered image is turned by the same (fallback) angle as the actions; a
    quarter turn of the image is ``np.rot90`` bit for bit."""
    raw = with_actions(2, "diagonal")
    rng = np.random.default_rng(2)
    depth = rng.uniform(0.2, 0.5, (raw.num_steps + 1, 1, 84, 84)).astype(np.float16)
    raw = dataclasses.replace(raw, images=depth)
    out, _ = augment_episode(raw, AugmentSettings(observation="depth", mea_on="none"))
    codes = policy_images(depth[:, 0].astype(np.float32), raw.jaw)
    for e in out[1:]:
        phi = assert_exact(e, raw)
        assert is_quarter_turn(phi)
        np.testing.assert_array_equal(
            e.images[:, 0], np.rot90(codes[:, 0], k=round(phi / QUARTER), axes=(1, 2))
        )
        np.testing.assert_array_equal(e.images, rotate_images(codes, phi))
