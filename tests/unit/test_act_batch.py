"""Several envs' policy steps as one batch (``PolicyRuntime.act_batch``, SAC's ``act_many``): each
runtime acts as it would alone, to float rounding, with its own recurrent state and noise stream."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from proto.weights import WeightsBlob
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors


def _blob(version: int = 3, preset: str = "cpu-small") -> WeightsBlob:
    torch.manual_seed(0)
    spec = PolicySpec(PRESETS[preset])
    return WeightsBlob.create(
        version, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json()
    )


def _codes(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    return [rng.integers(0, 256, (2, 84, 84), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("deterministic", [False, True])
def test_a_batch_acts_as_each_runtime_alone_across_episode_starts(deterministic):
    blob, rng = _blob(), np.random.default_rng(0)
    source = PolicyRuntime(deterministic, seed=99)
    source.load(blob)
    batched = [PolicyRuntime(deterministic, seed=s) for s in (11, 12, 13)]
    for p in batched:
        p.follow(source)
    alone = [PolicyRuntime(deterministic, seed=s) for s in (11, 12, 13)]
    for p in alone:
        p.load(blob)
    for tick in range(5):
        if tick == 2:  # one env starts its next episode while the others go on
            batched[1].reset()
            alone[1].reset()
        codes = _codes(rng, 3)
        got = PolicyRuntime.act_batch(batched, codes)
        want = [p.act(c) for p, c in zip(alone, codes, strict=True)]
        for g, w in zip(got, want, strict=True):
            assert g.shape == (5,) and g.dtype == np.float32
            np.testing.assert_allclose(g, w, atol=1e-5)
    for b, a in zip(batched, alone, strict=True):  # the same draws from the same streams
        assert torch.equal(b.generator.get_state(), a.generator.get_state())
    if not deterministic:  # the streams differ: three envs do not act alike on the same image
        same = _codes(rng, 1) * 3
        acts = PolicyRuntime.act_batch(batched, same)
        assert not np.allclose(acts[0], acts[1])


def test_followers_share_the_weights_keep_their_state_and_restart_it_on_a_new_spec():
    blob, rng = _blob(), np.random.default_rng(1)
    source = PolicyRuntime(False, seed=0)
    source.load(blob)
    follower = PolicyRuntime(False, seed=5)
    follower.follow(source)
    assert follower.version == 3 and follower.runtime.actor is source.runtime.actor
    follower.act(_codes(rng, 1)[0])
    state = follower.runtime._state
    newer = _blob(4)
    source.load(newer)  # same spec: loaded in place, the follower sees it at once
    follower.follow(source)
    assert follower.version == 4 and follower.runtime._state is state
    source.load(_blob(5, "paper"))  # another spec: a new module, the follower starts afresh on it
    follower.follow(source)
    assert follower.runtime.actor is source.runtime.actor and follower.runtime._state is None
    assert follower.generator is not source.generator


def test_a_batch_needs_loaded_runtimes_of_one_actor():
    blob = _blob()
    a, b = PolicyRuntime(False, 1), PolicyRuntime(False, 2)
    with pytest.raises(RuntimeError, match="no weights"):
        PolicyRuntime.act_batch([a, b], _codes(np.random.default_rng(0), 2))
    a.load(blob)
    b.load(blob)  # each its own module: not one actor
    with pytest.raises(ValueError, match="one loaded actor"):
        PolicyRuntime.act_batch([a, b], _codes(np.random.default_rng(0), 2))


def test_a_runtime_over_a_built_actor_acts_as_one_loaded_from_its_blob():
    from services.algorithms.sac.policy import ActorRuntime

    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    actor = build_actor(spec.net)
    loaded = PolicyRuntime(deterministic=True)
    loaded.load(WeightsBlob.create(1, "equi_rsac", "run-1", actor_tensors(actor), spec.to_json()))
    direct = ActorRuntime.of(actor, spec)
    rng = np.random.default_rng(1)
    for tick, codes in enumerate(_codes(rng, 4)):
        got, want = direct.act(codes), loaded.act(codes)
        np.testing.assert_allclose(got, want, atol=1e-6)
        told = np.full(5, 0.25 * tick, np.float32)  # the previous action both are told
        direct.executed(told)
        loaded.executed(told)
