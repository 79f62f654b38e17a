"""The augmenter's pure pipeline: what each raw episode becomes, with provenance and images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from proto.episode import Episode
from services.augmenter.core.mea import augment
from services.augmenter.core.pipeline import AugmentSettings, augment_episode, episode_seed
from tests.helpers.synthetic import synthetic_episode

pytestmark = pytest.mark.unit


def _kinds(out):
    return [e.augmentation.kind if e.augmentation else "raw" for e in out]


def test_a_demo_gets_raw_then_isometric_then_mea_copies_with_images():
    ep, _ = synthetic_episode(1)
    out, stats = augment_episode(ep, AugmentSettings())
    assert _kinds(out) == ["raw"] + ["isometric"] * 4 + ["mea+isometric"] * 6
    assert stats.outputs == 11 and stats.mea_made == 6 and stats.transitions == sum(e.num_steps for e in out)
    for e in out:
        assert e.images.shape == (e.num_steps + 1, 2, 84, 84) and e.images.dtype == np.uint8
        Episode.decode(e.encode())  # every output is a valid wire message
    for e in out[1:]:
        assert e.augmentation.source_episode_id == ep.episode_id
    # all MEA copies of one episode share one isometric rotation; the plain copies each have their own
    mea_phis = {float(e.augmentation.params["rotation"][0]) for e in out[5:]}
    iso_phis = {float(e.augmentation.params["rotation"][0]) for e in out[1:5]}
    assert len(mea_phis) == 1 and len(iso_phis) == 4


def _with_outcome(ep: Episode, demo: bool, success: bool) -> Episode:
    T = ep.num_steps
    rewards = np.zeros(T, np.float32)
    terminated, truncated = np.zeros(T, bool), np.zeros(T, bool)
    if success:
        rewards[-1], terminated[-1] = 1.0, True
    else:
        truncated[-1] = True
    return dataclasses.replace(ep, is_demo=demo, rewards=rewards, terminated=terminated, truncated=truncated)


@pytest.mark.parametrize(
    ("mea_on", "demo", "success", "gets_mea"),
    [
        ("demos", True, True, True),
        ("demos", True, False, False),  # failed expert attempts are not demonstrations
        ("demos", False, True, False),
        ("successes", False, True, True),
        ("successes", False, False, False),
        ("all", False, False, True),
        ("none", True, True, False),
    ],
)
def test_which_episodes_get_mea(mea_on, demo, success, gets_mea):
    ep = _with_outcome(synthetic_episode(2)[0], demo, success)
    out, _ = augment_episode(ep, AugmentSettings(mea_on=mea_on, reproject=False))
    assert ("mea+isometric" in _kinds(out)) == gets_mea
    assert _kinds(out).count("isometric") == 4  # the isometric copies apply to every stored episode


@pytest.mark.parametrize(
    ("demo", "success", "rotated"), [(True, True, 9), (False, True, 9), (False, False, 4)]
)
def test_successes_get_their_own_count_of_rotated_copies(demo, success, rotated):
    ep = _with_outcome(synthetic_episode(4)[0], demo, success)
    s = AugmentSettings(success_isometric_copies=9, mea_on="none", reproject=False)
    out, _ = augment_episode(ep, s)
    assert _kinds(out) == ["raw"] + ["isometric"] * rotated
    angles = {float(e.augmentation.params["rotation"][0]) for e in out[1:]}
    assert len(angles) == rotated  # each copy its own angle
    # and the first copies are the ones the paper's count makes: the extra count only adds copies
    paper, _ = augment_episode(ep, dataclasses.replace(s, success_isometric_copies=0))
    for a, b in zip(paper[1:], out[1:5], strict=True):
        assert np.array_equal(a.actions, b.actions) and np.array_equal(a.points, b.points)


def test_a_copy_regenerates_from_its_provenance():
    ep, _ = synthetic_episode(3)
    s = AugmentSettings(isometric_on_mea=False, reproject=False)
    out, _ = augment_episode(ep, s)
    copy = out[-1]
    prov = copy.augmentation
    assert prov.seed == episode_seed(s.seed, ep.episode_id)
    again, _ = augment(ep, s.mea, np.random.default_rng([prov.seed, 1_000_001 + prov.copy_index]), seed=prov.seed,
                       copy_index=prov.copy_index, episode_id=copy.episode_id)  # fmt: skip
    assert np.array_equal(again.actions, copy.actions) and np.array_equal(again.points, copy.points)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="mea_on"):
        AugmentSettings(mea_on="sometimes")
    with pytest.raises(ValueError, match="copy counts"):
        AugmentSettings(mea_copies=-1)
