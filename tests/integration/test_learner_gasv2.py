"""The learner service with a gasv2 preset on the in-process bus: the same contract as Equi-RSAC
(version 0 at start, versioned weights every publish_every updates, the limiter, refused input
counted, a checkpoint on exit and a resume that continues the lineage), with GASv2's published
policy (encoder, RSSM, actor) acting through the consumers' PolicyRuntime."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mea_tools.bench.learner import random_dsa_episode
from proto.discrete_actions import NAMES, to_vector
from proto.topics import EPISODES_AUGMENTED, STATUS, WEIGHTS_ANNOUNCE
from services.algorithms.policy import PolicyRuntime
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.weights import WeightsClient
from services.learner import checkpoint
from services.learner.config import PRESETS
from tests.helpers.learner import learner_episode, start_learner

pytestmark = pytest.mark.integration
DISCRETE = {tuple(to_vector(i, jaw)) for i in range(len(NAMES)) for jaw in (True, False)}


def svc() -> ServiceConfig:
    return ServiceConfig(instance_id="learner-g", metrics_port=0, log_format="text", heartbeat_seconds=0.2)


def config(tmp_path, **kw):
    return dataclasses.replace(PRESETS["gasv2-smoke"], run_dir=tmp_path, threads=1, gate_seconds=0.1,
                               checkpoint_minutes=0.0, service=svc(), **kw)  # fmt: skip


def test_gasv2_learner_trains_publishes_a_latent_policy_and_resumes_its_lineage(tmp_path):
    rng = np.random.default_rng(0)
    cfg = config(tmp_path, min_steps=40, samples_per_insert=0.25, error_buffer=2.0, max_updates=6)
    hub = Hub()
    observer = InProcBus(hub)
    announces = observer.subscribe(WEIGHTS_ANNOUNCE, capacity=256)
    status = observer.subscribe(STATUS, capacity=1024, service="learner")
    thread, result = start_learner(cfg, hub, observer)

    v0 = announces.recv(timeout=30)
    assert v0 is not None and v0.message.version == 0 and v0.message.algorithm == "gasv2"
    client = WeightsClient(observer, timeout=10.0)
    blob = client.poll()
    policy = PolicyRuntime(deterministic=False, seed=1)
    policy.load(blob)
    assert policy.spec.observation == "dsa"
    image = random_dsa_episode(rng, 0).images[0]
    actions = [tuple(policy.act(image)) for _ in range(20)]
    assert set(actions) <= DISCRETE  # one of the nine discrete actions, as the env takes them

    # refused: an Equi-RSAC episode (no DSA images); counted, the learner goes on
    observer.publish(EPISODES_AUGMENTED, learner_episode(90), source="augmenter-0")
    # 3 raw episodes of 40 steps -> 120 env steps -> 0.25 x 120 - (0.25 x 40 - 2) = 22 updates allowed
    for k in range(3):
        observer.publish(EPISODES_AUGMENTED, random_dsa_episode(rng, k, is_demo=k == 0), source="augmenter-0")
    thread.join(timeout=300)
    assert not thread.is_alive() and result["rc"] == 0
    beats = [d.message.counters for d in status.drain()]
    last = beats[-1]
    assert last["updates"] == 6 and last["rejected"] == 1 and last["env_steps"] == 120
    for key in ("model_loss", "image_loss", "reward_loss", "critic_loss", "actor_loss"):
        assert np.isfinite(last[key]), key
    versions = [d.message.version for d in announces.drain()]
    assert versions == sorted(set(versions)) and max(versions) >= 3  # publish_every 2
    assert checkpoint.exists(tmp_path / "checkpoints")

    # resume: the replay, the updates and the version lineage continue
    cfg2 = dataclasses.replace(cfg, resume=True, max_updates=8)
    hub2 = Hub()
    observer2 = InProcBus(hub2)
    announces2 = observer2.subscribe(WEIGHTS_ANNOUNCE, capacity=256)
    status2 = observer2.subscribe(STATUS, capacity=1024, service="learner")
    thread2, result2 = start_learner(cfg2, hub2, observer2)
    thread2.join(timeout=300)
    assert not thread2.is_alive() and result2["rc"] == 0
    after = [d.message.counters for d in status2.drain()][-1]
    assert after["updates"] == 8 and after["env_steps"] == 120 and after["replay_transitions"] == 120
    resumed = [d.message for d in announces2.drain()]
    assert resumed and min(a.version for a in resumed) > max(versions)
    assert {a.algorithm for a in resumed} == {"gasv2"} and len({a.run_id for a in resumed}) == 1


def test_gasv2_presets_observe_dsa_and_train_on_the_configured_device():
    from services.algorithms.gasv2.algorithm import GasV2Config
    from services.algorithms.sac.algorithm import SacConfig
    from services.learner.config import LearnerConfig, build_trainer

    with pytest.raises(ValueError, match="device must be cpu, cuda or cuda:N"):
        LearnerConfig(device="gpu")  # every learner may leave the CPU (tests/unit/test_learner_device.py)
    with pytest.raises(ValueError, match="starts from a gasv2 preset"):
        SacConfig(name="gasv2")  # the SAC presets' config does not fit its windows
    with pytest.raises(ValueError, match="gasv2 learner's only"):
        SacConfig(observation="dsa")
    with pytest.raises(ValueError, match="observes dsa"):
        GasV2Config(observation="voxel")
    trainer = build_trainer(dataclasses.replace(PRESETS["gasv2-smoke"], device="cpu"))
    assert str(trainer.agent.device) == "cpu" and set(trainer.policy_tensors()) == set(
        trainer.agent.policy.state_dict()
    )
