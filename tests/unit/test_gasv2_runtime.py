"""GASv2 on the consumers' side: the world model's action features, the weights' spec, and the
runtime that steps the published latent policy one observation at a time, which must see exactly
what the learner trains on (the replay's windows of the same episode)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mea_tools.bench.learner import APPROACH_STEPS, random_dsa_episode
from proto.actions import JAW
from proto.discrete_actions import NAMES, TOGGLE, to_vector
from proto.weights import WeightsBlob
from services.algorithms.gasv2.action_features import DISCRETE_FEATURES, features
from services.algorithms.gasv2.agent import GasV2Agent
from services.algorithms.gasv2.chunk_replay import ChunkReplay, to_chunk_batch
from services.algorithms.gasv2.config import PRESETS
from services.algorithms.gasv2.policy import GasV2Spec, LatentRuntime
from services.algorithms.networks import PRESETS as NET_PRESETS
from services.algorithms.policy import PolicyRuntime, PolicySpec, blob_observation, check_observation

CFG = PRESETS["smoke"]


def test_features_mark_toggles_and_keep_motion():
    # open, close (toggle), +x while closed, open (toggle), a controller step (continuous, jaw open)
    acts = np.array([[1, 0, 0, 1, 0], [-1, 0, 0, 0, 0], [-1, 1, 0, 0, 0], [1, 0, 0, 0, 0], [1, 0.3, -0.2, 0.5, 0]],
                    np.float32)  # fmt: skip
    f = features(acts)
    assert f[:, JAW].tolist() == [0, 1, 0, 1, 0]
    np.testing.assert_array_equal(f[:, 1:], acts[:, 1:])
    # the jaw closed before the episode: an open command is a toggle
    assert features(acts[:1], jaw_open_at_start=False)[0, JAW] == 1


@pytest.mark.parametrize("jaw_open", [True, False])
def test_discrete_features_do_not_depend_on_the_jaw(jaw_open):
    for i in range(len(NAMES)):
        a = to_vector(i, jaw_open)[None]
        np.testing.assert_array_equal(features(a, jaw_open_at_start=jaw_open)[0], DISCRETE_FEATURES[i])
    assert DISCRETE_FEATURES[TOGGLE].tolist() == [1, 0, 0, 0, 0]


def episode_with_toggles(seed: int):
    """A surgical-like episode whose policy phase closes the jaw, moves, opens it again."""
    rng = np.random.default_rng(seed)
    ep = random_dsa_episode(rng, seed)
    acts, jaw_open = ep.actions.copy(), True
    for t in range(APPROACH_STEPS, ep.num_steps):
        index = TOGGLE if t in (APPROACH_STEPS + 3, APPROACH_STEPS + 9) else int(rng.integers(0, 8))
        acts[t] = to_vector(index, jaw_open)
        jaw_open = acts[t, JAW] >= 0
    return dataclasses.replace(ep, actions=acts)


def blob_of(agent: GasV2Agent, version: int = 0) -> WeightsBlob:
    tensors = {k: v.numpy().copy() for k, v in agent.policy.state_dict().items()}
    return WeightsBlob.create(version, "gasv2", "run-1", tensors, GasV2Spec(agent.cfg).to_json())


@pytest.mark.slow
def test_runtime_sees_what_the_learner_trains_on():
    """Stepping the runtime through an episode, told each executed action (the controller's during
    the approach), gives the same logits as the published policy over the replay's window of it."""
    torch.manual_seed(0)
    agent = GasV2Agent(CFG, seed=0)
    ep = episode_with_toggles(3)
    replay = ChunkReplay(1_000, seed=0)
    replay.insert_episode(ep)
    T = ep.num_steps
    window = to_chunk_batch(replay.sample_chunks(1, T + 1, np.random.default_rng(0)))
    assert window.is_first[0, 0] and window.mask.all()

    gen = torch.Generator().manual_seed(7)
    reference, state = [], agent.policy.initial_state(1)
    with torch.no_grad():
        for t in range(T + 1):
            logits, state = agent.policy.step(state, window.actions[:, t], window.images[:, t],
                                              window.is_first[:, t], generator=gen)  # fmt: skip
            reference.append(logits[0])
    runtime = LatentRuntime(deterministic=True, generator=torch.Generator().manual_seed(7))
    runtime.load(blob_of(agent))
    runtime.reset()
    for t in range(T + 1):
        action = runtime.act(ep.images[t])
        torch.testing.assert_close(runtime.logits, reference[t], rtol=1e-5, atol=1e-6)
        jaw_open_before = t == 0 or bool(ep.actions[t - 1, JAW] >= 0)  # as executed, not as chosen
        np.testing.assert_array_equal(action, to_vector(int(reference[t].argmax()), jaw_open_before))
        if t < T:
            runtime.executed(ep.actions[t])


@pytest.mark.slow
def test_runtime_tracks_the_jaw_of_its_own_actions():
    agent = GasV2Agent(CFG, seed=1)
    runtime = LatentRuntime(deterministic=False, generator=torch.Generator().manual_seed(0))
    runtime.load(blob_of(agent))
    image = random_dsa_episode(np.random.default_rng(0), 0).images[-1]
    jaw_open, toggles = True, 0
    for _ in range(200):  # no executed() reports: the runtime's own choices were executed
        a = runtime.act(image)
        toggled = (a[JAW] >= 0) != jaw_open
        moves = np.flatnonzero(a[1:])
        assert (toggled and moves.size == 0) or (not toggled and moves.size == 1)
        jaw_open, toggles = bool(a[JAW] >= 0), toggles + toggled
    assert toggles >= 5  # the walk closed and opened the jaw
    runtime.reset()  # an episode starts with the jaw open: a toggle closes it
    while (a := runtime.act(image))[1:].any():
        pass
    assert a[JAW] == -1.0


def test_policy_runtime_dispatches_on_the_algorithm_and_refuses_what_does_not_fit():
    agent = GasV2Agent(CFG, seed=0)
    runtime = PolicyRuntime(deterministic=True, seed=0)
    blob = blob_of(agent, version=4)
    runtime.load(blob)
    assert runtime.ready and runtime.version == 4 and runtime.spec.observation == "dsa"
    assert blob_observation(blob) == "dsa"
    a = runtime.act(random_dsa_episode(np.random.default_rng(0), 0).images[0])
    assert a.shape == (5,) and abs(a[JAW]) == 1.0
    # a blob whose tensors do not fit: refused, the loaded policy keeps acting
    bad = {k: np.zeros(1, np.float32) for k in blob.tensors}
    with pytest.raises(ValueError, match="do not fit"):
        runtime.load(WeightsBlob.create(5, "gasv2", "run-1", bad, blob.config_json))
    assert runtime.version == 4
    with pytest.raises(ValueError, match="GASv2 policy spec"):
        GasV2Spec.from_json(PolicySpec(net=NET_PRESETS["cpu-small"]).to_json())
    # observations: a dsa policy only where the env renders the DSA image, and only it there
    check_observation("dsa", False, "an actor", "surgical_grasp_any")
    for obs, task in (("dsa", "block_pull"), ("voxel", "surgical_grasp_any")):
        with pytest.raises(ValueError, match="cannot run on"):
            check_observation(obs, False, "an actor", task)
