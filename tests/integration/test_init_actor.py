"""`--init-actor`: a fresh learner starts its actor (and the critic encoder it shares) from weights on
disk, read with their digest and seal checked; a file that does not fit, or one given with --resume,
is refused with one line, exit 2 and nothing written; a learner with a checkpoint keeps its own."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from proto.topics import EPISODES_AUGMENTED
from proto.weights import WeightsBlob
from services.algorithms.networks import build_actor
from services.algorithms.policy import PolicySpec, actor_tensors
from services.algorithms.sac.config import SacSettings
from services.cli import main as mea
from services.common import run_key, weights_file
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.learner import init_actor
from tests.helpers.learner import TINY_NET, learner_episode, start_learner, tiny_learner_config, tiny_trainer

pytestmark = pytest.mark.integration
SHARED = SacSettings(share_encoder=True)


def source_blob(
    seed: int = 7, net=TINY_NET, observation: str = "voxel", algorithm: str = "equi_rsac"
) -> WeightsBlob:
    """An actor's weights as `mea bench imitation` writes a clone (random weights of ``seed``)."""
    torch.manual_seed(seed)
    tensors = actor_tensors(build_actor(net))
    return WeightsBlob.create(0, algorithm, "clone-1", tensors, PolicySpec(net, observation).to_json())


def state(module: torch.nn.Module) -> dict[str, np.ndarray]:
    return {k: v.detach().numpy().copy() for k, v in module.state_dict().items()}


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_fresh_trainer_takes_the_actor_and_the_shared_encoder_and_keeps_its_target_in_step(tmp_path):
    blob = source_blob()
    weights_file.write(tmp_path / "clone" / "weights", blob)
    _, read = init_actor.read(tmp_path / "clone")  # a directory: its newest weights file
    trainer = tiny_trainer(sac=SHARED)
    cfg = tiny_learner_config(tmp_path, ServiceConfig(), sac=SHARED)
    assert not same(state(trainer.agent.actor), read.tensors)
    init_actor.load_into(trainer, init_actor.check_fits(read, cfg.algorithm))
    sac = trainer.agent
    assert same(state(sac.actor), blob.tensors)
    encoder = {k.removeprefix("encoder."): v for k, v in blob.tensors.items() if k.startswith("encoder.")}
    assert encoder and same(state(sac.critic.encoder), encoder)  # the critic reads the clone's encoder
    assert same(state(sac.critic_target), state(sac.critic))

    # without a shared encoder the critic keeps its own
    own = tiny_trainer()
    critic_before = state(own.agent.critic)
    init_actor.load_into(
        own, init_actor.check_fits(read, tiny_learner_config(tmp_path, ServiceConfig()).algorithm)
    )
    assert same(state(own.agent.actor), blob.tensors) and same(state(own.agent.critic), critic_before)


def test_weights_that_do_not_fit_or_do_not_verify_are_refused(tmp_path):
    cfg = tiny_learner_config(tmp_path, ServiceConfig())
    wider = dataclasses.replace(TINY_NET, lstm_hidden=16)
    with pytest.raises(ValueError, match="do not fit the network"):
        init_actor.check_fits(source_blob(net=wider), cfg.algorithm)
    with pytest.raises(ValueError, match="observes 'depth'"):
        init_actor.check_fits(source_blob(observation="depth"), cfg.algorithm)
    with pytest.raises(ValueError, match="rsac policy"):
        init_actor.check_fits(source_blob(algorithm="rsac"), cfg.algorithm)

    # a learner's sealed file is checked with its run's key (RUN/run.key beside RUN/learner/weights)
    run = tmp_path / "run"
    key = run_key.create(run / run_key.FILE_NAME)
    path = weights_file.write(run / weights_file.LEARNER, source_blob(), key, "learner-0")
    assert init_actor.read(run)[0] == path  # the run dir resolves to its learner's newest file
    assert same(init_actor.read(path)[1].tensors, source_blob().tensors)
    run_key.create(tmp_path / "other" / run_key.FILE_NAME)
    moved = tmp_path / "other" / "weights" / path.name
    moved.parent.mkdir(parents=True)
    moved.write_bytes(path.read_bytes())  # beside another run's key: the seal does not verify
    with pytest.raises(ValueError, match="refused"):
        init_actor.read(moved)
    data = bytearray(source_blob().encode())
    data[-1] ^= 1  # a tensor byte flipped: the digest does not match
    (tmp_path / "clone.blob").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="refused"):
        init_actor.read(tmp_path / "clone.blob")
    with pytest.raises(ValueError, match="no such file"):
        init_actor.read(tmp_path / "missing")


def _versions(run_dir) -> dict[int, WeightsBlob]:
    return {v: weights_file.read(p, None) for v, p in weights_file.versions(run_dir / weights_file.DIRECTORY)}


def test_the_learner_starts_from_the_file_and_a_resumed_learner_keeps_its_checkpoint(tmp_path):
    blob = source_blob()
    src = weights_file.write(tmp_path / "clone" / "weights", blob)
    svc = ServiceConfig(instance_id="learner-t", metrics_port=0, log_format="text", heartbeat_seconds=0.2)
    run_dir = tmp_path / "learner"
    cfg = tiny_learner_config(run_dir, svc, sac=SHARED, init_actor=src, samples_per_insert=0.5, min_steps=20,
                              error_buffer=5.0, max_updates=2)  # fmt: skip
    hub = Hub()
    observer = InProcBus(hub)
    thread, result = start_learner(cfg, hub, observer)
    for k in range(2):  # 20 env steps: 5 updates allowed, 2 run, then the learner exits
        observer.publish(EPISODES_AUGMENTED, learner_episode(k, T=10, demo=k == 0), source="augmenter-0")
    thread.join(timeout=60)
    assert not thread.is_alive() and result["rc"] == 0
    first = _versions(run_dir)
    assert same(first[0].tensors, blob.tensors)  # version 0 is the file's actor
    trained = first[max(first)]
    assert not same(trained.tensors, blob.tensors)  # and training moved it on

    resumed = dataclasses.replace(cfg, resume=True)  # a restarted learner: its checkpoint wins
    thread, result = start_learner(resumed, hub, observer)
    thread.join(timeout=60)
    assert result["rc"] == 0
    after = _versions(run_dir)
    assert same(after[max(after)].tensors, trained.tensors)


def test_mea_run_refuses_a_clone_that_does_not_fit_and_init_actor_with_resume(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    weights_file.write(tmp_path / "tiny" / "weights", source_blob())  # TINY_NET: not the cpu-small actor
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(SystemExit) as exit_:
        mea(["run", "--init-actor", str(tmp_path / "tiny"), "--run-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert err[0].startswith("mea run: --init-actor: weights v0 do not fit the network"), err
    with pytest.raises(SystemExit) as exit_:
        mea(["run", "--resume", str(tmp_path / "r"), "--init-actor", str(tmp_path / "tiny")])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())
    assert exit_.value.code == 2 and "--init-actor starts a fresh run" in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written
