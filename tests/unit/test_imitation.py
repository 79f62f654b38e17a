"""The imitation path `mea bench imitation` measures, end to end on two real Block Pull demos: the
run's demos and copies in the learner's replay, batches from its sampler, the learner's BC loss, and
the clone acting through the evaluator's policy runtime; plus the demonstration split of batches."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from mea_tools.bench.imitation import (
    ImitationBenchConfig,
    clone,
    clone_blob,
    demo_replay,
    record_demos,
    run_config,
)
from services.actor.config import ActorConfig
from services.actor.rollout import RolloutActor
from services.algorithms.batch import to_batch
from services.algorithms.policy import PolicyRuntime
from services.algorithms.replay import SequenceReplay
from services.algorithms.sac.losses import bc_loss
from services.augmenter.core.pipeline import augment_episode, with_images
from services.common.config import ServiceConfig
from services.episodes.rollout import policy_input
from services.episodes.scores import EpisodeResult
from services.evaluator.config import EvaluatorConfig
from services.plan import augmenter_config, learner_config
from services.tasks import make_env

RESULT = EpisodeResult(success=False, length=10, ret=0.0)
ROTATIONS = 4  # rotated copies per demo: enough to exercise the copies, cheap to augment


@pytest.fixture(scope="module")
def setting():
    """The run `mea bench imitation --demos 2 --rotations 4` clones: its 2 demos, learner, replay."""
    torch.set_num_threads(1)
    rc = run_config(ImitationBenchConfig(demos=(2,), rotations=ROTATIONS))
    learner = learner_config(rc, Path("unused"), ServiceConfig())
    demos = record_demos(rc, 2)
    replay, counts = demo_replay(demos, rc, learner)
    return rc, learner, demos, replay, counts


@pytest.mark.slow
def test_the_run_s_two_demos_and_their_copies_fill_the_replay(setting):
    rc, learner, demos, replay, counts = setting
    seeds = [int(d.seed) for d in demos]
    assert seeds == sorted(set(seeds)) and seeds[-1] < 8  # actor 0's stream under run seed 0, as `mea run`
    assert [d.policy_kind for d in demos] == ["expert_probe", "expert_direct"]
    assert all(d.is_demo and d.succeeded for d in demos)
    assert counts["episodes"] == 2 * (1 + ROTATIONS)
    assert counts["transitions"] == (1 + ROTATIONS) * sum(d.num_steps for d in demos)
    algo = learner.algorithm
    assert algo.net.group == "c4" and algo.observation == "voxel" and algo.net.image_size == 84


@pytest.mark.slow
def test_mea_copies_per_demo_are_the_bench_s_to_set(setting):
    _, learner, demos, _, _ = setting
    rc = run_config(ImitationBenchConfig(variant="mea", demos=(2,), rotations=ROTATIONS))
    none = demo_replay(demos, rc, learner, mea_copies=0)[1]
    assert none["episodes"] == 2 * (1 + ROTATIONS)
    three, nine = (demo_replay(demos, rc, learner, mea_copies=k)[1]["episodes"] for k in (3, 9))
    # MEA drops a copy it cannot make valid, so at most k more per demo, and more copies give more
    assert none["episodes"] < three <= none["episodes"] + 2 * 3 < nine <= none["episodes"] + 2 * 9


@pytest.mark.slow
def test_cloning_two_demos_fits_them_and_the_clone_replays_their_actions_on_their_seeds(setting):
    rc, learner, demos, replay, _ = setting
    algo = learner.algorithm
    fast = dataclasses.replace(
        learner, algorithm=dataclasses.replace(algo, sac=dataclasses.replace(algo.sac, lr=1e-3))
    )
    actor, before, after, _ = clone(replay, fast, seed=0, updates=400, batch=8, tag="test")
    assert before > 1.0, before  # an untrained actor is far from the demos
    assert after < before / 20, (before, after)

    # the clone through the evaluator's runtime (deterministic: tanh of the mean), in the evaluator's
    # env on each demo's own seed, fed the demo's actions: its actions are the demo's
    blob = clone_blob(actor, fast, "imitation-test")
    env = make_env(rc.task, EvaluatorConfig(task=rc.task).env_settings())
    projection = augmenter_config(rc, ServiceConfig()).augment.projection
    try:
        for demo in demos:
            stored = with_images(demo, projection).images  # what the replay holds
            runtime = PolicyRuntime(deterministic=True)
            runtime.load(blob)
            runtime.reset()
            obs = env.reset(int(demo.seed))
            errors = []
            for t in range(5):
                image = policy_input(obs, algo.observation)
                assert np.array_equal(image, stored[t])  # the same input the clone trained on
                errors.append(float(np.abs(runtime.act(image) - demo.actions[t]).max()))
                obs, *_ = env.step(demo.actions[t])
            assert max(errors) < 0.3 and np.mean(errors) < 0.12, (demo.seed, errors)
    finally:
        env.close()


@pytest.mark.slow
def test_batches_drawn_with_demo_fraction_hold_the_demos_and_the_bc_term_sees_only_them(setting):
    rc, learner, demos, _, _ = setting
    settings = augmenter_config(rc, ServiceConfig()).augment
    actor = RolloutActor(ActorConfig(task=rc.task, policy="random", seed_base=500), "actor-0")
    randoms = []
    for _ in range(3):
        b = actor.random_episode()
        randoms.append(b.finish(actor.episode_id(b)))
    actor.env.close()
    replay = SequenceReplay(
        20_000, image_size=84, seq_len=learner.seq_len, channels=learner.algorithm.net.in_channels, seed=0
    )
    family = {}  # stored episode id -> the raw episode it was made from
    for ep in [*demos, *randoms]:
        for out in augment_episode(ep, settings)[0]:
            replay.insert(out)
            family[out.episode_id] = ep.episode_id
    demo_ids = {d.episode_id for d in demos}

    rng = np.random.default_rng(3)
    seen = set()
    for _ in range(40):
        sample = replay.sample(8, rng, demo_fraction=0.5, trim=True)
        assert int(sample.from_demo_set.sum()) == 4
        assert np.array_equal(sample.from_demo_set, sample.is_demo)
        sources = [family[replay.episode_info(int(i))["episode_id"]] for i in sample.episode_index]
        assert [s in demo_ids for s in sources] == list(sample.from_demo_set)
        seen |= set(sources)
        batch = to_batch(sample)
        assert torch.equal(batch.demo, torch.from_numpy(sample.from_demo_set).float())
    assert seen == demo_ids | {r.episode_id for r in randoms}  # every demo and every other episode drawn

    # the BC term reads the demonstration rows only: the other episodes' actions do not move it
    batch = to_batch(replay.sample(8, np.random.default_rng(4), demo_fraction=0.5, trim=True))
    mean = torch.randn(batch.actions.shape[0], batch.actions.shape[1] + 1, batch.actions.shape[2])
    other = (1 - batch.demo)[:, None, None]
    scrambled = dataclasses.replace(batch, actions=batch.actions * (1 - other) + 0.9 * other)
    assert torch.allclose(bc_loss(mean, batch), bc_loss(mean, scrambled))
    assert not torch.allclose(
        bc_loss(mean, batch), bc_loss(mean, dataclasses.replace(batch, demo=1 - batch.demo))
    )


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--variant", "gasv2"], "--variant must be one of"),
        (["--task", "surgical_grasp_any"], "--task must be one of"),
        (["--demos", "0"], "--demos must be one or more counts >= 1"),
        (["--learner-preset", "gasv2"], "--learner-preset must be one of"),
        (["--expert", "oracle"], "--expert must be one of"),
        (["--mea-copies", "3"], "--mea-copies must be >= 0 and needs --variant mea"),
        (["--variant", "mea", "--mea-copies", "-1"], "--mea-copies must be >= 0"),
        (["--gripper-start", "centre"], "gripper_start must be one of ('random', 'fixed')"),
    ],
)
def test_bad_options_are_refused_in_one_line_and_nothing_is_written(argv, message, tmp_path, capsys):
    from services.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["bench", "imitation", *argv, "--out", str(tmp_path / "out")])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())
    assert exit_.value.code == 2 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("start", ["random", "fixed"])
def test_the_gripper_start_reaches_the_demos_and_the_evaluation(start, monkeypatch):
    import mea_tools.bench.imitation as imitation
    from services.plan import actor_config

    rc = run_config(ImitationBenchConfig(gripper_start=start))
    assert actor_config(rc, 0, ServiceConfig()).env_settings().gripper_start == start  # record_demos' actor

    class BuiltError(Exception):
        pass

    def make_env_(task, settings):
        raise BuiltError(settings)

    monkeypatch.setattr(imitation, "make_env", make_env_)
    with pytest.raises(BuiltError) as built:
        imitation.evaluate(None, "block_pull", False, 5, start)
    assert built.value.args[0].gripper_start == start


def test_the_clone_is_evaluated_as_the_evaluator_acts_it_and_as_actors_sample_it(monkeypatch):
    import mea_tools.bench.imitation as imitation

    acted = []

    class Runner:  # the evaluator's runner, reduced to what it was handed
        def __init__(self, env, *args) -> None:
            pass

        def episodes(self, runtime, seeds):
            acted.append(runtime.deterministic)
            return [dataclasses.replace(RESULT, success=runtime.deterministic) for _ in seeds]

    monkeypatch.setattr(imitation, "EpisodeRunner", Runner)
    monkeypatch.setattr(imitation, "record_demos", lambda rc, n, expert=None: [])
    monkeypatch.setattr(imitation, "demo_replay", lambda *a: (None, {"episodes": 0, "transitions": 0}))
    monkeypatch.setattr(imitation, "clone", lambda *a: (torch.nn.Linear(1, 1), 0.0, 0.0, 0.0))
    monkeypatch.setattr(imitation, "clone_blob", lambda *a: None)
    monkeypatch.setattr(PolicyRuntime, "load", lambda self, blob: None)
    result = imitation.run(ImitationBenchConfig(demos=(2,), train_seeds=(0,), eval_episodes=3, json=True))
    assert acted == [True, False]  # the evaluator's deterministic policy, then the sampled one
    (row,) = result["results"]["clones"]
    assert (row["success"], row["sampled_success"]) == (1.0, 0.0)
    assert (
        result["results"]["per demo count (mean ± std over training seeds)"][0]["sampled_success_mean"] == 0.0
    )
