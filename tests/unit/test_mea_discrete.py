"""Discrete MEA (Surgical Grasp Any) as math: phases, C4 draws, the transition prior, guards, provenance.

Synthetic surgical episodes obey the transition prior exactly (pivot moves by delta_xyz * a, the
object stays put), so a copy is valid when its pivot moves by delta_xyz * abar and its object world
points are the source's.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from proto.discrete_actions import TRIVIAL, index_of, rotate_c4, to_vector
from proto.episode import Episode
from services.augmenter.core.mea_discrete import (
    QUARTER_TURNS_PARAM,
    DiscreteCounts,
    MeaDiscreteSettings,
    copy_rng,
    draw_actions,
    draw_copy,
    free_motion_start,
    inside,
    mea_discrete_copies,
    mea_discrete_copy,
    offsets,
    phase_split,
)
from services.augmenter.core.pipeline import AugmentSettings, augment_episode, episode_seed, mea_copy_rng
from services.observation.dsa import decode_state_rows
from tests.helpers import build_episode
from tests.helpers.synthetic import SURGICAL_STEP, synthetic_surgical_episode

pytestmark = pytest.mark.unit
S = MeaDiscreteSettings()
FREE = MeaDiscreteSettings(pivot_low=(-9.0, -9.0, -9.0), pivot_high=(9.0, 9.0, 9.0), prior_tolerance=None)
"""No guard can refuse a draw: the plain distribution of the paper's draw."""
SEEDS = range(8)


def _copy(ep: Episode, k: int = 0, s: MeaDiscreteSettings = S, seed: int = 3) -> Episode:
    out = mea_discrete_copy(ep, s, copy_rng(seed, k), k, seed=seed)
    assert out is not None
    return out


def _kind(a: np.ndarray) -> tuple[str, int | None]:
    """("discrete", index) for one of the nine actions, else ("continuous", None)."""
    index = index_of(a, bool(a[0] > 0))
    return ("continuous", None) if index is None else ("discrete", index)


def test_settings_defaults_and_validation():
    assert (S.h_p, S.copies, S.p_rotate, S.delta_xyz) == (5, 200, 0.3, 0.015) and S.delta_xyz == SURGICAL_STEP
    assert np.allclose(np.subtract(S.pivot_high, S.pivot_low), [0.5, 0.5, 0.35]) and S.pivot_low[2] == 0.143
    for bad in ({"h_p": -1}, {"p_rotate": 1.5}, {"delta_xyz": 0.0}, {"pivot_low": (0.3, -0.25, 0.0)}):
        with pytest.raises(ValueError):
            MeaDiscreteSettings(**bad)


@pytest.mark.parametrize("h_p", [0, 1, 5, 200])
def test_phase_split_is_h_minus_h_p(h_p):
    ep = synthetic_surgical_episode(0)
    assert phase_split(ep, dataclasses.replace(S, h_p=h_p)) == max(0, ep.num_steps - h_p)


def test_no_copy_without_a_step_to_augment():
    ep = synthetic_surgical_episode(1)
    s = dataclasses.replace(S, h_p=ep.num_steps)
    assert mea_discrete_copy(ep, s, copy_rng(0, 0), 0, seed=0) is None
    counts = DiscreteCounts()
    assert mea_discrete_copies(ep, dataclasses.replace(s, copies=3), 0, counts=counts) == []
    assert (counts.made, counts.given_up) == (0, 3)


# --------------------------------------------------------------------------------------------
# the group draws
# --------------------------------------------------------------------------------------------


def test_trivial_actions_never_change_and_the_rest_only_to_their_c4_images():
    seen_continuous = seen_discrete = 0
    for seed in SEEDS:
        ep = synthetic_surgical_episode(seed)
        hp = phase_split(ep, FREE)
        for k in range(40):
            abar, turns = draw_actions(ep.actions, hp, copy_rng(seed, k), FREE)
            assert turns.shape == (hp,) and turns.dtype == np.int64 and set(turns.tolist()) <= {0, 1, 2, 3}
            assert np.array_equal(abar[hp:], ep.actions[hp:])  # trivial phase: the source's, bit for bit
            for t in range(hp):
                a, b = ep.actions[t], abar[t]
                kind, index = _kind(a)
                if kind == "discrete":
                    seen_discrete += 1
                    if index in TRIVIAL:
                        assert turns[t] == 0 and a.tobytes() == b.tobytes()
                    else:
                        assert np.array_equal(b, to_vector(rotate_c4(index, int(turns[t])), bool(a[0] > 0)))
                    continue
                seen_continuous += 1
                x, y = float(a[1]), float(a[2])
                images = [(x, y), (-y, x), (-x, -y), (y, -x)]
                assert (float(b[1]), float(b[2])) == images[int(turns[t])]
                assert np.array_equal(b[[0, 3, 4]], a[[0, 3, 4]])  # jaw, dz and dtheta unchanged
                if x == 0.0 and y == 0.0:
                    assert turns[t] == 0
    assert seen_continuous > 100 and seen_discrete > 100


def test_continuous_turns_agree_with_rotate_c4_on_the_discrete_actions():
    # the (dx, dy) turn used for the P-controller's steps is rotate_c4 on +-x, +-y
    ep = synthetic_surgical_episode(0)
    for index in set(range(8)) - TRIVIAL:
        for jaw_open in (True, False):
            a = to_vector(index, jaw_open)
            nudged = ep.actions.copy()
            nudged[0] = a
            nudged[1] = a * np.array([1, 0.5, 0.5, 1, 1], np.float32)  # continuous, same direction
            seen = set()
            for k in range(200):
                abar, turns = draw_actions(nudged, 2, np.random.default_rng(k), FREE)
                assert np.array_equal(abar[0], to_vector(rotate_c4(index, int(turns[0])), jaw_open))
                assert np.array_equal(abar[1, 1:3], 0.5 * abar[0, 1:3]) or turns[0] != turns[1]
                seen.add(int(turns[0]))
            assert seen == {0, 1, 2, 3}


def test_non_trivial_actions_change_at_the_rate_p_rotate():
    changed = total = 0
    for seed in SEEDS:
        ep = synthetic_surgical_episode(seed)
        hp = phase_split(ep, FREE)
        mask = np.array([np.any(ep.actions[t, 1:3] != 0) for t in range(hp)])
        for k in range(60):
            abar, turns = draw_actions(ep.actions, hp, copy_rng(seed, k), FREE)
            diff = np.any(abar[:hp] != ep.actions[:hp], axis=1)
            assert np.array_equal(diff, turns != 0)  # a drawn turn always changes the action
            changed += int(diff[mask].sum())
            total += int(mask.sum())
    p = FREE.p_rotate
    assert total > 5000
    assert abs(changed / total - p) < 4 * math.sqrt(p * (1 - p) / total), changed / total


def test_turns_are_uniform_over_the_three_non_identity_elements():
    ep = synthetic_surgical_episode(2)
    hp = phase_split(ep, FREE)
    turns = np.concatenate([draw_actions(ep.actions, hp, copy_rng(2, k), FREE)[1] for k in range(400)])
    counts = np.bincount(turns[turns > 0], minlength=4)[1:]
    n = counts.sum()
    assert n > 1000 and np.all(np.abs(counts / n - 1 / 3) < 4 * math.sqrt(2 / 9 / n))


# --------------------------------------------------------------------------------------------
# the copy: phases, the transition prior, the object fixed in the world
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_the_trivial_and_termination_phases_equal_the_source(seed):
    ep = synthetic_surgical_episode(seed)
    out = _copy(ep, seed)
    hp = phase_split(ep, S)
    assert out.augmentation.phase_split == hp and out.num_steps == ep.num_steps  # no prior-guard cut here
    for name in ("actions", "rewards", "terminated", "truncated"):
        assert getattr(out, name)[hp:].tobytes() == getattr(ep, name)[hp:].tobytes(), name
    for name in ("points", "point_counts", "jaw", "gripper_pose", "object_poses", "contacts"):
        assert getattr(out, name)[hp:].tobytes() == getattr(ep, name)[hp:].tobytes(), name
    for name in ("rewards", "terminated", "truncated", "jaw", "object_poses", "point_counts"):
        assert np.array_equal(getattr(out, name), getattr(ep, name)), name
    assert np.array_equal(out.actions[:, 0], ep.actions[:, 0])  # the jaw command is never changed
    assert out.task == ep.task and out.segments == ep.segments and out.images is None


@pytest.mark.parametrize("seed", SEEDS)
def test_the_pivot_follows_the_transition_prior_and_the_object_stays_put(seed):
    ep = synthetic_surgical_episode(seed)
    for k in range(5):
        out = _copy(ep, k, seed=seed)
        hp = out.augmentation.phase_split
        pbar = out.gripper_pose[:, :3].astype(np.float64)
        steps = np.diff(pbar, axis=0)[:hp]
        np.testing.assert_allclose(steps, S.delta_xyz * out.actions[:hp, 1:4].astype(np.float64), atol=2e-7)
        assert np.array_equal(out.gripper_pose[hp], ep.gripper_pose[hp])  # pbar_{H_p} = p_{H_p}
        assert np.array_equal(out.gripper_pose[:, 2:], ep.gripper_pose[:, 2:])  # z and yaw never move
        world = out.points[:, 1:].astype(np.float64) + pbar[:, None, None, :]
        source = ep.points[:, 1:].astype(np.float64) + ep.gripper_pose[:, None, None, :3].astype(np.float64)
        np.testing.assert_allclose(world, source, atol=2e-7)  # object world points unchanged
        assert np.array_equal(out.points[:, 0], ep.points[:, 0])  # the gripper cloud in its own frame
        assert np.all(inside(pbar, S))


def test_contacts_are_dropped_only_where_the_gripper_moved():
    ep = build_episode(T=24, seed=5, task="surgical_grasp_any")
    ep = dataclasses.replace(ep, contacts=np.ones_like(ep.contacts))
    for k in range(10):
        out = _copy(ep, k, s=FREE)
        hp = out.augmentation.phase_split
        moved = np.any(out.gripper_pose[:, :3] != ep.gripper_pose[:, :3], axis=1)
        assert not moved[hp:].any()
        assert np.array_equal(out.contacts, np.repeat(~moved[:, None], ep.contacts.shape[1], axis=1))


def _loop_reference(ep: Episode, abar: np.ndarray, hp: int, delta: float) -> dict[str, np.ndarray]:
    """The copy written out step by step, straight from the paper's sums."""
    T, S_ = ep.num_steps, ep.points.shape[1]
    points = ep.points.astype(np.float64).copy()
    pose = ep.gripper_pose.astype(np.float64).copy()
    contacts = ep.contacts.copy()
    for t in range(T + 1):
        D = np.zeros(3)
        for j in range(t, hp):
            for c in range(3):
                D[c] += float(ep.actions[j, 1 + c]) - float(abar[j, 1 + c])
        D *= delta
        for i in range(1, S_):
            for p in range(points.shape[2]):
                points[t, i, p] -= D
        pose[t, :3] += D
        if t < hp and np.any(D != 0):
            contacts[t] = False
    return {"points": points, "gripper_pose": pose, "contacts": contacts}


@pytest.mark.parametrize("seed", range(4))
def test_vectorised_copy_equals_a_plain_loop_on_a_random_episode(seed):
    ep = build_episode(T=30, seed=seed, task="surgical_grasp_any")  # two objects, random everything
    sub, draw = draw_copy(ep, FREE, copy_rng(seed, 0))
    assert draw.start == 0 and draw.hp == 25 and draw.abar is not None
    out = mea_discrete_copy(ep, FREE, copy_rng(seed, 0), 0, seed=seed)
    assert np.array_equal(out.actions, draw.abar)
    ref = _loop_reference(ep, draw.abar, draw.hp, FREE.delta_xyz)
    np.testing.assert_allclose(out.points, ref["points"], atol=1e-6)
    np.testing.assert_allclose(out.gripper_pose, ref["gripper_pose"], atol=1e-6)
    assert np.array_equal(out.contacts, ref["contacts"])
    D = offsets(ep.actions, draw.abar, draw.hp, FREE.delta_xyz)
    assert D.shape == (ep.num_steps + 1, 3) and not D[draw.hp :].any()


# --------------------------------------------------------------------------------------------
# guards
# --------------------------------------------------------------------------------------------


def _leaves(ep: Episode, s: MeaDiscreteSettings, rng: np.random.Generator) -> bool:
    """Whether the first draw from ``rng`` takes the pivot out of the workspace."""
    hp = phase_split(ep, s)
    abar, _ = draw_actions(ep.actions, hp, rng, s)
    D = offsets(ep.actions, abar, hp, s.delta_xyz)[:hp]
    pos = ep.gripper_pose[:hp, :3].astype(np.float64) + D
    return bool(np.any(~inside(pos, s) & np.any(D != 0, axis=1)))


def test_a_copy_that_would_leave_the_workspace_is_redrawn_or_dropped_never_emitted():
    ep = synthetic_surgical_episode(4)
    lo = ep.gripper_pose[:, :3].min(0) - 0.005  # a workspace hugging the source's path
    hi = ep.gripper_pose[:, :3].max(0) + 0.005
    tight = dataclasses.replace(S, pivot_low=tuple(lo.tolist()), pivot_high=tuple(hi.tolist()), max_redraws=0)
    leaving = [k for k in range(60) if _leaves(ep, tight, copy_rng(9, k))]
    assert 5 < len(leaving) < 55
    for k in range(60):  # no redraws: exactly the draws that leave are dropped
        out = mea_discrete_copy(ep, tight, copy_rng(9, k), k, seed=9)
        assert (out is None) == (k in leaving)
        assert out is None or np.all(inside(out.gripper_pose[:, :3].astype(np.float64), tight))
    redraw = dataclasses.replace(tight, max_redraws=30)
    counts = DiscreteCounts()
    out = mea_discrete_copies(ep, dataclasses.replace(redraw, copies=60), 9, counts=counts)
    assert counts.redraws >= len(leaving) and counts.made + counts.given_up == 60 and len(out) == counts.made
    assert counts.made > 60 - len(leaving)  # redrawn copies were kept
    for copy in out:
        assert np.all(inside(copy.gripper_pose[:, :3].astype(np.float64), redraw))


def test_a_step_that_broke_the_prior_cuts_the_copy_after_it():
    ep = synthetic_surgical_episode(5)
    pose = ep.gripper_pose.copy()
    pose[4:, 0] -= 0.01  # step 3 was clipped by 1 cm
    clipped = dataclasses.replace(ep, gripper_pose=pose)
    hp = phase_split(clipped, S)
    assert free_motion_start(ep, hp, S) == 0 and free_motion_start(clipped, hp, S) == 4
    assert free_motion_start(clipped, hp, dataclasses.replace(S, prior_tolerance=None)) == 0
    out = _copy(clipped, 1)
    assert out.augmentation.params["start"].tolist() == [4] and out.augmentation.phase_split == hp - 4
    assert out.num_steps == ep.num_steps - 4
    assert np.array_equal(out.rewards, ep.rewards[4:]) and np.array_equal(out.gripper_pose[hp - 4], pose[hp])
    counts = DiscreteCounts()
    mea_discrete_copies(clipped, dataclasses.replace(S, copies=3), 1, counts=counts)
    assert counts.cut == 3


# --------------------------------------------------------------------------------------------
# copies, seeds and provenance
# --------------------------------------------------------------------------------------------


def test_k_copies_are_deterministic_for_a_seed_and_distinct():
    ep = synthetic_surgical_episode(6)
    s = dataclasses.replace(S, copies=40)
    a, b = mea_discrete_copies(ep, s, 11), mea_discrete_copies(ep, s, 11)
    assert len(a) == 40 and [e.encode() for e in a] == [e.encode() for e in b]
    assert len({e.actions.tobytes() for e in a}) == 40  # pairwise distinct
    assert [e.episode_id for e in a] == [f"{ep.episode_id}.mea{k}" for k in range(40)]
    other = mea_discrete_copies(ep, s, 12)
    assert [e.actions.tobytes() for e in other] != [e.actions.tobytes() for e in a]


def test_copies_follow_the_pipeline_seeding_convention():
    ep = synthetic_surgical_episode(7)
    seed = episode_seed(0, ep.episode_id)
    copies = mea_discrete_copies(ep, dataclasses.replace(S, copies=4), seed)
    for k, c in enumerate(copies):
        again = mea_discrete_copy(ep, S, mea_copy_rng(seed, k), k, seed=seed)
        assert again.encode() == c.encode()


def test_provenance_round_trips_through_the_wire():
    ep = synthetic_surgical_episode(3)
    out = _copy(ep, 2)
    back = Episode.decode(out.encode())
    aug = back.augmentation
    assert (aug.kind, aug.source_episode_id, aug.seed, aug.copy_index) == ("mea", ep.episode_id, 3, 2)
    assert set(aug.params) == {QUARTER_TURNS_PARAM, "start"}
    turns = aug.params[QUARTER_TURNS_PARAM]
    assert (
        turns.dtype == np.int64 and turns.shape == (aug.phase_split,) and aug.params["start"].tolist() == [0]
    )
    assert np.array_equal(turns, out.augmentation.params[QUARTER_TURNS_PARAM])
    # the recorded turns rebuild the copy's actions
    hp = aug.phase_split
    assert np.any(turns != 0)
    for t in range(hp):
        x, y = float(ep.actions[t, 1]), float(ep.actions[t, 2])
        assert (float(back.actions[t, 1]), float(back.actions[t, 2])) == [(x, y), (-y, x), (-x, -y), (y, -x)][
            int(turns[t])
        ]


# --------------------------------------------------------------------------------------------
# re-projection and the pipeline
# --------------------------------------------------------------------------------------------


def test_each_copy_is_re_rendered_by_the_injected_reprojection():
    ep = synthetic_surgical_episode(1)
    seen = []

    def render(copy: Episode) -> Episode:
        seen.append(copy)
        assert copy.images is not None and np.array_equal(copy.images, ep.images)  # the state rows to read
        world = copy.points + copy.gripper_pose[:, None, None, :3]
        images = np.zeros((copy.num_steps + 1, 3, 64, 64), np.uint8)
        images[:, 0, 0, :3] = np.clip(np.rint(world[:, 0].mean(1) * 100 + 100), 0, 255)
        return dataclasses.replace(copy, images=images)

    s = dataclasses.replace(S, copies=5)
    out = mea_discrete_copies(ep, s, 2, render)
    assert len(seen) == 5 and all(
        e.images is not None and e.images.shape == (e.num_steps + 1, 3, 64, 64) for e in out
    )
    plain = mea_discrete_copies(ep, s, 2)
    assert all(e.images is None for e in plain)
    assert [e.actions.tobytes() for e in plain] == [e.actions.tobytes() for e in out]
    with pytest.raises(ValueError, match="reproject"):
        mea_discrete_copies(
            ep, s, 2, lambda c: c if c.images is None else dataclasses.replace(c, images=None)
        )


def test_the_pipeline_gives_the_surgical_task_discrete_mea_and_no_isometric_copies():
    ep = synthetic_surgical_episode(2)
    settings = AugmentSettings(mea_discrete=dataclasses.replace(S, copies=7))
    out, stats = augment_episode(ep, settings)
    assert out[0] is ep and out[0].images is not None  # the raw episode keeps the env's own images
    assert [e.augmentation.kind for e in out[1:]] == ["mea"] * 7
    assert stats.mea_made == 7 and stats.outputs == 8 and stats.transitions == sum(e.num_steps for e in out)
    assert all(QUARTER_TURNS_PARAM in e.augmentation.params for e in out[1:])
    for e in out[1:]:  # re-rendered (discrete_reprojector), with the source's state rows
        assert e.images.shape == (e.num_steps + 1, 3, 64, 64) and e.images.dtype == np.uint8
        start = int(e.augmentation.params["start"][0])
        src = ep.images[start:]
        assert [decode_state_rows(i) for i in e.images] == [decode_state_rows(i) for i in src]
    assert augment_episode(ep, dataclasses.replace(settings, reproject=False))[0][1].images is None
    seed = episode_seed(settings.seed, ep.episode_id)
    again = mea_discrete_copy(ep, S, copy_rng(seed, 2), 2, seed=seed)
    assert dataclasses.replace(out[3], images=None).encode() == again.encode()
    assert augment_episode(ep, dataclasses.replace(settings, mea_on="none"))[0] == [ep]
    failed = dataclasses.replace(ep, terminated=np.zeros(ep.num_steps, bool), truncated=ep.terminated)
    assert len(augment_episode(failed, settings)[0]) == 1  # demos only (the default)
    assert AugmentSettings().mea_count(ep) == 200
