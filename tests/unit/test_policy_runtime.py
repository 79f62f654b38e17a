"""Policy runtime: rebuilt from a weights blob alone, stepwise equal to the trained actor, state per episode."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from proto.weights import WeightsBlob
from services.algorithms.networks import build_actor
from services.algorithms.policy import (
    ObservationUnavailableError,
    PolicyRuntime,
    PolicySpec,
    actor_tensors,
    check_observation,
    images_from_codes,
)
from services.algorithms.sac.losses import deterministic_action
from tests.helpers.learner import SIZE, TINY_NET


def blob_for(actor, version: int = 3, spec: PolicySpec | None = None) -> WeightsBlob:
    spec = spec or PolicySpec(TINY_NET)
    return WeightsBlob.decode(
        WeightsBlob.create(version, "equi_rsac", "run-1", actor_tensors(actor), spec.to_json()).encode()
    )


def codes(rng, T: int) -> np.ndarray:
    return rng.integers(0, 256, (T, 2, SIZE, SIZE), dtype=np.uint8)


def test_deterministic_runtime_equals_the_actor_over_a_sequence():
    torch.manual_seed(0)
    actor = build_actor(TINY_NET)
    rt = PolicyRuntime(deterministic=True)
    rt.load(blob_for(actor))
    assert rt.version == 3
    rng = np.random.default_rng(1)
    obs = codes(rng, 6)
    got = []
    rt.reset()
    for o in obs:
        got.append(rt.act(o))
    # the same sequence through the trainer's forward: previous actions are the runtime's own
    prev = torch.zeros(1, 6, 5)
    prev[0, 1:] = torch.from_numpy(np.stack(got[:-1]))
    with torch.no_grad():
        mean, _, _ = actor(images_from_codes(torch.from_numpy(obs))[None], prev)
    np.testing.assert_allclose(np.stack(got), deterministic_action(mean)[0].numpy(), atol=1e-5)
    # reset starts a new episode: the first action repeats
    rt.reset()
    np.testing.assert_allclose(rt.act(obs[0]), got[0], atol=1e-6)


def test_state_is_carried_within_an_episode():
    torch.manual_seed(0)  # (tiny random nets can start with every ReLU dead; this one does not)
    rt = PolicyRuntime(deterministic=True)
    rt.load(blob_for(build_actor(TINY_NET)))
    o = codes(np.random.default_rng(3), 1)[0]
    first, second = rt.act(o), rt.act(o)
    assert np.abs(first).max() > 1e-3
    assert not np.allclose(first, second)  # same image, different history


def test_stochastic_actions_are_bounded_seeded_and_vary():
    torch.manual_seed(4)
    blob = blob_for(build_actor(TINY_NET))
    o = codes(np.random.default_rng(5), 1)[0]
    runs = []
    for _ in range(2):
        rt = PolicyRuntime(deterministic=False, seed=7)
        rt.load(blob)
        runs.append(np.stack([rt.act(o) for _ in range(5)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.all(np.abs(runs[0]) <= 1.0) and runs[0].std(0).min() > 0


def test_blobs_that_do_not_fit_are_refused_and_the_old_weights_kept():
    torch.manual_seed(6)
    rt = PolicyRuntime(deterministic=True)
    rt.load(blob_for(build_actor(TINY_NET), version=1))
    wider = dataclasses.replace(TINY_NET, lstm_hidden=16)
    good = blob_for(build_actor(wider), version=2, spec=PolicySpec(wider))
    wrong_spec = dataclasses.replace(
        good, config_json=PolicySpec(TINY_NET).to_json()
    )  # tensors of the wider net
    with pytest.raises(ValueError, match="do not fit"):
        rt.load(wrong_spec)
    with pytest.raises(ValueError, match="policy spec"):
        rt.load(dataclasses.replace(good, config_json="{}"))
    assert rt.version == 1
    rt.load(good)  # a new spec rebuilds the network
    assert rt.version == 2 and rt.runtime.actor.cfg.lstm_hidden == 16


def test_acting_without_weights_is_an_error():
    with pytest.raises(RuntimeError, match="no weights"):
        PolicyRuntime().act(np.zeros((2, SIZE, SIZE), np.uint8))


def test_a_blob_that_does_not_fit_leaves_the_running_policy_untouched():
    torch.manual_seed(8)
    rt = PolicyRuntime(deterministic=True)
    rt.load(blob_for(build_actor(TINY_NET), version=1))
    before = {k: v.clone() for k, v in rt.runtime.actor.state_dict().items()}
    bad = blob_for(build_actor(TINY_NET), version=2)
    name = next(iter(bad.tensors))
    tensors = {k: (np.zeros(3, np.float32) if k == name else v) for k, v in bad.tensors.items()}
    with pytest.raises(ValueError, match="do not fit"):
        rt.load(WeightsBlob.create(2, "equi_rsac", "run-1", tensors, bad.config_json))
    assert rt.version == 1
    for k, v in rt.runtime.actor.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_a_depth_policy_is_refused_where_no_depth_image_is_rendered():
    check_observation("voxel", depth_image=False, consumer="an actor")  # voxel: always buildable
    check_observation("voxel", depth_image=True, consumer="an actor")
    check_observation("depth", depth_image=True, consumer="an evaluator")
    for consumer in ("an actor", "an evaluator"):
        with pytest.raises(ObservationUnavailableError) as exc:
            check_observation("depth", depth_image=False, consumer=consumer)
        assert str(exc.value) == f"a depth-image policy needs {consumer} started with --depth-image"
    assert issubclass(ObservationUnavailableError, ValueError)  # refused like weights that do not fit
