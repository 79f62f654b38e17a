"""The critic profile as math (a critic and actor whose values are known, against a loop over the
episodes) and `mea bench critic` on a saved learner checkpoint: its kinds, counts and one-line
refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from services.algorithms.batch import to_batch
from services.algorithms.sac.critic_profile import COLUMNS, TARGET_COLUMNS, step_profile
from services.common import config
from services.common.config import ServiceConfig
from services.learner import checkpoint
from tests.helpers.learner import learner_episode, tiny_learner_config, tiny_trainer
from tests.unit.test_sac_options import replay_with

pytestmark = pytest.mark.unit

W = torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0])  # Q = dx - dz: rates a descent and a move along +x


class KnownCritic(nn.Module):
    def features_of(self, batch) -> torch.Tensor:
        return torch.zeros(*batch.actions.shape[:1], batch.actions.shape[1] + 1, 1)

    def q(self, feats: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v = actions @ W
        return v, v + 1.0  # the min is the first


class KnownActor(nn.Module):
    """A pre-squash mean of atanh(0.5) on dx: the policy's mean action moves +x at half the range."""

    def forward(self, images, prev_actions, obs_mask=None, **_):
        mean = torch.zeros(*images.shape[:2], 5)
        mean[..., 1] = float(np.arctanh(0.5))
        return mean, None, None


def batches():
    replay = replay_with([4, 6, 3, 5], demos=2)
    slots = replay.slots()
    return [to_batch(replay.gather(slots[:2])), to_batch(replay.gather(slots[2:]))]


@pytest.mark.parametrize("from_end", [True, False])
def test_each_column_is_the_mean_of_its_known_values_per_step(from_end):
    bs = batches()
    p = step_profile(KnownActor(), KnownCritic(), bs, steps=5, from_end=from_end, random_actions=4)
    expect = {c: [[] for _ in range(5)] for c in ("recorded", "turned", "reversed", "reward")}
    for b in bs:
        for e, length in enumerate(b.mask.sum(1).tolist()):
            for i in range(min(5, int(length))):
                t = int(length) - 1 - i if from_end else i
                dx, dy, dz = (float(b.actions[e, t, j]) for j in (1, 2, 3))
                expect["recorded"][i].append(dx - dz)
                expect["turned"][i].append(-dy - dz)  # (dx, dy) -> (-dy, dx)
                expect["reversed"][i].append(-dx + dz)
                expect["reward"][i].append(float(b.rewards[e, t]))
    assert p.steps == ((1, 2, 3, 4, 5) if from_end else (0, 1, 2, 3, 4))
    assert p.counts.tolist() == [len(v) for v in expect["recorded"]] == [4, 4, 4, 3, 2]
    for c in ("recorded", "turned", "reversed"):
        np.testing.assert_allclose(p.values[c], [np.mean(v) for v in expect[c]], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(p.rewards, [np.mean(v) for v in expect["reward"]])
    np.testing.assert_allclose(p.values["policy_mean"], 0.5, rtol=1e-5)  # dx = tanh(atanh 0.5), dz = 0
    assert (np.abs(p.values["random"]) < 2).all()  # dx - dz of actions in the box


def test_the_random_column_is_seeded_and_past_the_longest_episode_nothing_is_counted():
    bs = batches()
    a = step_profile(KnownActor(), KnownCritic(), bs, steps=8, from_end=True, seed=3)
    b = step_profile(KnownActor(), KnownCritic(), bs, steps=8, from_end=True, seed=3)
    c = step_profile(KnownActor(), KnownCritic(), bs, steps=8, from_end=True, seed=4)
    np.testing.assert_array_equal(a.values["random"], b.values["random"])
    assert not np.allclose(a.values["random"][:6], c.values["random"][:6])
    assert a.counts.tolist() == [4, 4, 4, 3, 2, 1, 0, 0]
    assert np.isnan(a.values["recorded"][6:]).all() and np.isnan(a.rewards[6:]).all()
    with pytest.raises(ValueError, match="steps and random_actions must be >= 1"):
        step_profile(KnownActor(), KnownCritic(), bs, steps=0, from_end=True)


class LiveCritic(KnownCritic):
    """The critic the target copy trails: a quarter above it everywhere."""

    def q(self, feats: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v = actions @ W + 0.25
        return v + 1.0, v  # the min is the second


def test_the_live_critic_and_the_targets_are_columns_beside_the_target_critics():
    bs = batches()
    plain = step_profile(KnownActor(), KnownCritic(), bs, steps=5, from_end=True)
    assert set(plain.values) == set(COLUMNS)
    p = step_profile(KnownActor(), KnownCritic(), bs, steps=5, from_end=True, live=LiveCritic(),
                     targets=lambda b: 2 * b.rewards + 1)  # fmt: skip
    assert set(p.values) == set(COLUMNS) | set(TARGET_COLUMNS)
    np.testing.assert_allclose(p.values["live"], p.values["recorded"] + 0.25, rtol=1e-5)
    np.testing.assert_allclose(p.values["target"], 2 * p.rewards + 1, rtol=1e-5)
    for c in COLUMNS:
        np.testing.assert_array_equal(p.values[c], plain.values[c])


def saved_run(tmp_path: Path) -> Path:
    """A run directory holding a tiny learner's settings and one checkpoint of its trainer."""
    run = tmp_path / "run"
    cfg = tiny_learner_config(run, ServiceConfig(), min_steps=10)
    trainer = tiny_trainer(min_steps=10)
    for k in range(7):
        trainer.insert(learner_episode(k, T=6 + k % 3, demo=k < 2))
    assert trainer.step() is not None
    checkpoint.save_trainer(run / "learner" / "checkpoints", trainer, checkpoint.Lineage(1, "run-x", {}), {})
    config.save(cfg, run / "learner" / "learner.json")
    return run


def test_the_bench_profiles_each_kind_of_stored_episode(tmp_path, capsys):
    from mea_tools.bench.critic import CriticBenchConfig, run

    path = saved_run(tmp_path)
    out = run(CriticBenchConfig(run=path, steps=3, json=True))
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(json.dumps(out))
    kinds = out["kinds"]
    assert kinds["demos"]["episodes"] == 2
    assert kinds["successes"]["episodes"] + kinds["failures"]["episodes"] == 5
    demos = kinds["demos"]["from_end"]
    assert demos["steps"] == [1, 2, 3] and demos["counts"] == [2, 2, 2]
    assert set(COLUMNS) <= set(demos) and all(isinstance(v, float) for v in demos["recorded"])
    assert (out["updates"], out["checkpoint"]) == (1, "learner-000001.pt")


def test_the_benchs_targets_end_at_the_reward_of_a_terminal_step_and_repeat(tmp_path, capsys):
    from mea_tools.bench.critic import CriticBenchConfig, run

    path = saved_run(tmp_path)
    cfg = CriticBenchConfig(run=path, steps=3, targets=True, json=True)
    first, again = run(cfg), run(cfg)
    capsys.readouterr()
    assert first["kinds"] == again["kinds"]  # the targets' sampled next actions are seeded
    for kind in first["kinds"].values():
        if not kind["episodes"]:
            continue
        end = kind["from_end"]
        assert set(TARGET_COLUMNS) <= set(end) and all(isinstance(v, float) for v in end["live"])
        # every stored episode ends terminated: its last target is its reward, with no bootstrap
        assert end["target"][0] == pytest.approx(end["reward"][0], abs=1e-5)
        assert end["target"][1] != pytest.approx(end["reward"][1], abs=1e-5)  # bootstrapped
    run(CriticBenchConfig(run=path, steps=2, targets=True))
    printed = capsys.readouterr().out
    assert "| live | target | target-live |" in printed and "target: its TD target" in printed


def test_the_bench_refuses_in_one_line_and_writes_nothing(tmp_path, capsys):
    from mea_tools.bench.critic import CriticBenchConfig, run

    with pytest.raises(ValueError, match="--run is required"):
        CriticBenchConfig()
    with pytest.raises(SystemExit):
        run(CriticBenchConfig(run=tmp_path / "absent"))
    assert "learner.json: no such file" in capsys.readouterr().err
    path = saved_run(tmp_path)
    settings = path / "learner" / "learner.json"
    saved = json.loads(settings.read_text())
    settings.write_text(json.dumps({**saved, "algorithm": {"name": "gasv2"}}))
    files = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit):
        run(CriticBenchConfig(run=path))
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the learner is 'gasv2'" in err
    assert {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} == files
    settings.write_text(json.dumps(saved))
    for p in (path / "learner" / "checkpoints").iterdir():
        p.unlink()
    files = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit):
        run(CriticBenchConfig(run=path))
    err = capsys.readouterr().err
    assert err.startswith("mea bench critic: ") and err.count("\n") == 1
    assert {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} == files


def test_the_handover_refuses_a_run_without_recorded_demonstrations(tmp_path, capsys):
    from mea_tools.bench.critic import CriticBenchConfig, run

    with pytest.raises(ValueError, match="--handover-steps"):
        CriticBenchConfig(run=tmp_path, handover=2, handover_steps=(0, 4))
    with pytest.raises(ValueError, match="--handover must be >= 0"):
        CriticBenchConfig(run=tmp_path, handover=-1)
    with pytest.raises(ValueError, match="--handover-moves .* --handover N"):
        CriticBenchConfig(run=tmp_path, handover_moves=True)
    path = saved_run(tmp_path)
    files = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit):
        run(CriticBenchConfig(run=path, steps=2, handover=2))
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no recorded demonstrations" in err
    assert {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} == files


class ReplayOnlyEnv:
    """Succeeds only when a stored demonstration's own actions are executed to its last one: a
    whole replay reproduces it, and a policy that takes over before the end does not finish."""

    def __init__(self, demos: dict[int, np.ndarray], size: int) -> None:
        self.demos, self.size = demos, size
        self.settings = type("Settings", (), {"max_steps": 12})()

    def reset(self, seed: int) -> np.ndarray:
        self.actions, self.t = self.demos[seed], 0
        return np.zeros((2, self.size, self.size), np.uint8)

    def step(self, action):
        on_script = self.t < len(self.actions) and np.allclose(action, self.actions[self.t])
        self.t += 1
        done = on_script and self.t == len(self.actions)
        self.actions = self.actions if on_script else np.zeros((0, 5), np.float32)
        return np.zeros((2, self.size, self.size), np.uint8), float(done), done, False, {}

    def close(self) -> None:
        pass


def test_the_handover_plays_each_recorded_demonstration_beside_its_critic(tmp_path, capsys, monkeypatch):
    import services.episodes.rollout
    import services.tasks
    from mea_tools.bench.critic import CriticBenchConfig, run
    from services.common.mcap_io.recorder import McapRecorder
    from tests.helpers.learner import SIZE

    path = saved_run(tmp_path)
    (path / "config.json").write_text(json.dumps({"task": "block_pull", "gripper_start": "fixed"}))
    demos = [learner_episode(k, T=6 + k % 3, demo=True) for k in range(2)]  # the replay's two demos
    (path / "episodes").mkdir()
    with McapRecorder(path / "episodes" / "raw-0-0000.mcap") as rec:
        for ep in [learner_episode(5), *demos]:
            rec.write(ep, topic="/mea/episodes/raw")
    env = ReplayOnlyEnv({ep.seed: np.asarray(ep.actions, np.float32) for ep in demos}, SIZE)
    monkeypatch.setattr(services.tasks, "make_env", lambda task, settings: env)
    monkeypatch.setattr(services.episodes.rollout, "policy_input", lambda obs, observation: obs)
    cfg = CriticBenchConfig(
        run=path, steps=2, handover=5, handover_steps=(1, 3), handover_moves=True, json=True
    )
    out = run(cfg)
    capsys.readouterr()
    h = out["handover"]
    assert (h["demos"], h["in_replay"], h["reproduced"], h["steps"]) == (2, 2, 2, [1, 3])
    for k in ("1", "3"):  # the policy never plays the demo's own last action: no success, return 0
        assert h["plays"][k] == {"episodes": 2, "successes": 0, "mean_policy_steps": None, "mean_return": 0.0}
    assert all(isinstance(q, float) for q in h["critic_policy_mean"])
    # the demo's own last move succeeds at once (return 1) and its reverse never does; 3 steps back
    # the policy takes over after either move and does not finish
    last, earlier = h["moves"]
    assert (last["k"], last["episodes"], last["successes_recorded"], last["successes_reversed"]) == (
        1,
        2,
        2,
        0,
    )
    assert (last["return_recorded"], last["return_reversed"], last["return_gap"]) == (1.0, 0.0, 1.0)
    assert (earlier["k"], earlier["successes_recorded"], earlier["return_gap"]) == (3, 0, 0.0)
    assert last["critic_gap"] == pytest.approx(last["critic_recorded"] - last["critic_reversed"])


def test_the_climb_options_are_refused_in_one_line(tmp_path, capsys):
    from mea_tools.bench.critic import CriticBenchConfig, _algorithm, _climb_actor

    for bad, says in (({"climb": -1}, "--climb must be >= 0"), ({"climb": 5, "climb_every": 0}, "--climb-every"),
                      ({"climb_actor": tmp_path}, "give --climb N too")):  # fmt: skip
        with pytest.raises(ValueError, match=says):
            CriticBenchConfig(run=tmp_path, **bad)
    algo = _algorithm(saved_run(tmp_path))
    with pytest.raises(SystemExit):
        _climb_actor(tmp_path / "absent", algo)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--climb-actor {tmp_path / 'absent'}:" in err
