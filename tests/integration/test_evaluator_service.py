"""The evaluator service on the in-process bus: broadcast weights -> deterministic held-out rollouts ->
EvalReport + history line; cadence in learner env steps; a blob that does not fit is counted and skipped."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from proto.control import EvalReport, Heartbeat, ReplayGate
from proto.topics import EVAL_REPORTS, REPLAY_GATE, STATUS
from proto.weights import WeightsBlob
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.weights import WeightsServer
from services.evaluator.config import EvaluatorConfig
from services.evaluator.history import read_history
from services.evaluator.main import run

pytestmark = pytest.mark.integration
INSTANCE = "evaluator-t"


def gate(bus: InProcBus, inserted: int, version: int) -> None:
    bus.publish(REPLAY_GATE, ReplayGate(learner_id="learner-0", run_id="run-1", inserted_steps=inserted,
                                        allowed_steps=inserted + 100, updates=inserted, policy_version=version,
                                        replay_transitions=inserted * 5, created_at=time.time()),
                source="learner-0")  # fmt: skip


def latest_beat(status, beats: list) -> Heartbeat | None:
    beats += [d.message for d in status.drain() if d.message.instance_id == INSTANCE]
    return beats[-1] if beats else None


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_evaluator_reports_versions_on_held_out_seeds_at_the_env_step_cadence(tmp_path):
    import torch

    from services.algorithms.networks import PRESETS, build_actor
    from services.algorithms.policy import PolicySpec, actor_tensors

    hub = Hub()
    observer = InProcBus(hub)
    reports = observer.subscribe(EVAL_REPORTS, capacity=16)
    status = observer.subscribe(STATUS, capacity=1024, service="evaluator")
    watch = observer.watch_alive("evaluator")
    server = WeightsServer(observer, "learner-0")
    torch.manual_seed(0)
    spec = PolicySpec(PRESETS["cpu-small"])
    tensors = actor_tensors(build_actor(spec.net))

    def blob(version: int, t=tensors) -> WeightsBlob:
        return WeightsBlob.create(version, "equi_rsac", "run-1", t, spec.to_json())

    cfg = EvaluatorConfig(task="block_pull", episodes=2, max_evaluations=2, points_per_segment=64, run_dir=tmp_path,
                          service=ServiceConfig(instance_id=INSTANCE, metrics_port=0, log_format="text",
                                                heartbeat_seconds=0.1))  # fmt: skip
    assert cfg.every_env_steps == 250 and cfg.seed_base == 1_000_000_000
    result: dict = {}

    def target() -> None:
        try:
            result["rc"] = run(cfg, bus_factory=lambda _c: InProcBus(hub))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test thread
            result["error"] = exc

    thread = threading.Thread(target=target, name="evaluator", daemon=True)
    thread.start()
    beats: list[Heartbeat] = []
    try:
        assert watch.wait_for(lambda alive: ("evaluator", INSTANCE) in alive, 30), result
        # 1. the learner has inserted 1000 env steps and publishes its first version: evaluated at once
        gate(observer, 1000, 3)
        server.publish(blob(3))
        d = reports.recv(timeout=60)
        assert d is not None, f"no first report: {result}"
        assert d.parts == {"source": INSTANCE}
        r1 = d.message
        assert isinstance(r1, EvalReport)
        assert (r1.evaluator_id, r1.run_id, r1.task) == (INSTANCE, "run-1", "block_pull")
        assert (r1.policy_version, r1.env_steps, r1.episodes) == (3, 1000, 2)
        assert 0.0 <= r1.success_rate <= 1.0 and 1.0 <= r1.mean_length <= 50.0
        if r1.success_rate == 0.0:
            assert r1.grasp_score == 0.0 and r1.mean_return == 0.0 and r1.mean_length == 50.0
        else:
            assert 0.0 < r1.grasp_score <= r1.success_rate

        # 2. a version made after only 100 more env steps is not evaluated (nor even pulled)
        gate(observer, 1100, 4)
        server.publish(blob(4))
        assert reports.recv(timeout=1.5) is None
        # 3. a blob that does not fit arrives as the steps pass the cadence: counted, skipped, no crash
        server.publish(blob(5, {"not_a_layer.weight": np.zeros((3, 3), np.float32)}))
        gate(observer, 1250, 5)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            beat = latest_beat(status, beats)
            if beat is not None and beat.counters.get("bad_weights", 0) >= 1:
                break
            time.sleep(0.05)
        else:
            pytest.fail(f"bad weights were not counted: {latest_beat(status, beats)}")
        assert reports.recv(timeout=0.0) is None
        assert thread.is_alive(), result
        # 4. the next good version (same tensors as v3) is evaluated, at the gate's 1250 steps
        server.publish(blob(6))
        d = reports.recv(timeout=60)
        assert d is not None, f"no second report: {result}"
        r2 = d.message
        assert (r2.policy_version, r2.env_steps, r2.episodes) == (6, 1250, 2)
        # same weights, same held-out seeds, deterministic policy: the same episodes
        assert (r2.success_rate, r2.mean_return, r2.mean_length, r2.grasp_score) == (
            r1.success_rate, r1.mean_return, r1.mean_length, r1.grasp_score)  # fmt: skip
        thread.join(timeout=30)
        assert not thread.is_alive(), "the evaluator did not stop after max_evaluations"
    finally:
        server.close()
        observer.close()
    if "error" in result:
        raise result["error"]
    assert result["rc"] == 0

    history = read_history(tmp_path / "eval" / "history.jsonl")
    assert [(h["version"], h["env_steps"]) for h in history] == [(3, 1000), (6, 1250)]
    for h, r in zip(history, (r1, r2), strict=True):
        assert h["seeds"] == [1_000_000_000, 1_000_000_001]  # held out: at 1e9 and above, the same each time
        assert all(s >= 1_000_000_000 for s in h["seeds"])
        assert h["episodes"] == 2 and len(h["successes"]) == len(h["lengths"]) == 2
        for key in ("success_rate", "mean_return", "mean_length", "grasp_score"):
            assert h[key] == pytest.approx(getattr(r, key))
        assert h["wall_seconds"] > 0 and h["created_at"] > 0 and h["task"] == "block_pull"
        assert sum(h["successes"]) / 2 == h["success_rate"]
        assert np.mean(h["lengths"]) == h["mean_length"]
    json.loads((tmp_path / "eval" / "history.jsonl").read_text().splitlines()[0])  # one object per line
    # every evaluated version is kept beside the history, so it can be served later
    from services.common import weights_file

    assert [v for v, _ in weights_file.versions(tmp_path / "eval" / "weights")] == [3, 6]
    assert weights_file.read(weights_file.resolve(tmp_path, 3), None).digest == blob(3).digest

    last = latest_beat(status, beats)
    assert last is not None and last.policy_version == 6
    c = last.counters
    assert list(c)[:4] == ["evaluations", "success_rate", "env_steps", "version"]
    assert (c["evaluations"], c["env_steps"], c["version"], c["bad_weights"]) == (2, 1250, 6, 1)
    assert c["learner_env_steps"] == 1250


def test_the_run_plan_passes_the_task_the_run_dir_and_the_runs_eval_settings(tmp_path):
    from services.plan import config_for
    from services.run_config import RunConfig

    cfg = config_for(RunConfig(task="block_pick", variant="equirsac", eval_every=500, eval_episodes=4,
                               final_eval_episodes=7, env_steps=2000), tmp_path, "evaluator", 0)  # fmt: skip
    assert (cfg.task, cfg.run_dir, cfg.every_env_steps, cfg.episodes) == ("block_pick", tmp_path, 500, 4)
    assert cfg.final_env_steps == 2000 and cfg.final_episodes == 7 and cfg.depth_image
    # `mea run`'s defaults reach the evaluator: 20 episodes per evaluation, 50 at the budget
    defaults = config_for(RunConfig(task="drawer_open"), tmp_path, "evaluator", 0)
    assert (defaults.episodes, defaults.final_episodes, defaults.final_env_steps) == (20, 50, 40_000)
    assert defaults.every_env_steps == 1000 and defaults.task == "drawer_open" and not defaults.depth_image
    with pytest.raises(ValueError):
        EvaluatorConfig(task="stack")
    with pytest.raises(ValueError):
        EvaluatorConfig(episodes=0)
    with pytest.raises(ValueError):
        EvaluatorConfig(final_episodes=-1)


def test_held_out_seeds_at_the_budget_extend_the_same_sequence():
    cfg = EvaluatorConfig(episodes=3, final_episodes=5, final_env_steps=2000, seed_base=100)
    assert cfg.seeds == cfg.seeds_at(1999) == cfg.seeds_at(-1) == (100, 101, 102)
    assert cfg.seeds_at(2000) == cfg.seeds_at(2500) == (100, 101, 102, 103, 104)
    assert cfg.at_budget(2000) and not cfg.at_budget(1999)
    # no budget, or no final size: every evaluation has --episodes
    assert EvaluatorConfig(episodes=3, final_episodes=5).seeds_at(10**6) == (
        1_000_000_000,
        1_000_000_001,
        1_000_000_002,
    )
    assert EvaluatorConfig(episodes=3, final_env_steps=2000, seed_base=0).seeds_at(2000) == (0, 1, 2)


class _FakeEnv:
    """Enough of a ManipulationEnv for the cadence (no simulator)."""

    def __init__(self) -> None:
        from services.tasks import EnvSettings

        self.settings = EnvSettings()


def _cadence_evaluator(tmp_path, **kw):
    from types import SimpleNamespace

    from services.common.metrics import ServiceMetrics
    from services.common.replay_gate import GateTracker
    from services.common.runtime import Shutdown
    from services.evaluator.main import Evaluator

    # keep_weights 0: these tests drive the schedule with fake blobs
    cfg = EvaluatorConfig(run_dir=tmp_path, first_gate_wait=60.0, keep_weights=0, **kw)
    ctx = SimpleNamespace(metrics=ServiceMetrics("evaluator", "evaluator-u"), instance="evaluator-u",
                          shutdown=Shutdown(install_signals=False), bus=None, policy_version=-1, detail="")  # fmt: skip
    gate = GateTracker(SimpleNamespace(drain=list))
    return Evaluator(cfg, ctx, gate, weights=None, env=_FakeEnv()), gate  # type: ignore[arg-type]


def _at(gate, steps: int | None) -> None:
    gate.latest = None if steps is None else ReplayGate(
        learner_id="learner-0", run_id="run-1", inserted_steps=steps, allowed_steps=steps, updates=0,
        policy_version=0, replay_transitions=0, created_at=time.time())  # fmt: skip


def test_cadence_first_version_then_every_env_steps_then_the_budget(tmp_path):
    ev, gate = _cadence_evaluator(tmp_path, every_env_steps=250, final_env_steps=1200)
    assert not ev.due()  # nothing evaluated, no gate yet: wait (up to first_gate_wait) for the steps
    _at(gate, 40)
    assert ev.due()  # the first version as soon as it exists
    ev.last_env_steps = 1000  # evaluated at 1000
    for steps, due in ((1100, False), (1199, False), (1200, True), (1249, True)):
        _at(gate, steps)
        assert ev.due() is due, steps  # 1200: the budget, off the cadence
    ev.last_env_steps = 1200
    for steps, due in ((1200, False), (1449, False), (1450, True), (300, True), (None, False)):
        _at(gate, steps)  # 300: the learner went back (restart); None: steps unknown again -> wait for them
        assert ev.due() is due, steps


def test_a_restarted_evaluator_keeps_the_cadence_and_improvement_from_its_history(tmp_path):
    from services.evaluator.history import append_history

    for steps, success in ((0, 0.0), (250, 0.2), (500, 0.1)):
        append_history(
            tmp_path / "eval" / "history.jsonl", {"version": 1, "env_steps": steps, "success_rate": success}
        )
    ev, gate = _cadence_evaluator(tmp_path, every_env_steps=250)
    assert ev.last_env_steps == 500 and ev.improvement == 250
    assert ev.heartbeat_counters()["improvement_env_steps"] == 250
    assert ev.ctx.metrics.registry.get_sample_value("mea_evaluator_improvement_env_steps") == 250
    assert not ev.due()  # no gate yet (a resumed run's first seconds): no evaluation at env steps -1
    _at(gate, 600)
    assert not ev.due()
    _at(gate, 750)
    assert ev.due()


def test_the_evaluation_at_the_budget_runs_final_episodes_held_out_seeds(tmp_path, monkeypatch):
    """Driven cycle by cycle (gate -> due -> pull -> rollouts -> report + history) with a fake env,
    policy and rollout: before the budget M seeds, at the budget the first M_final of the same ones."""
    from types import SimpleNamespace

    import services.algorithms.policy as policy_module
    import services.evaluator.evaluation as evaluation

    rolled: list[int] = []

    def fake_run_episode(env, seed, act, builder, on_step=None, executed=None):
        rolled.append(seed)
        success = seed % 2 == 0  # even seeds succeed after 10 steps, odd ones time out at 50
        for t in range(10 if success else 50):
            builder.step(np.zeros(5, np.float32), float(success and t == 9), success and t == 9, t == 49)
        return builder

    class FakeRuntime:
        def __init__(self, deterministic: bool, seed: int) -> None:
            assert deterministic
            self.spec = SimpleNamespace(observation="policy_image")
            self.version = -1

        def load(self, blob) -> None:
            self.version = blob.version

        def reset(self) -> None:
            pass

    class FakeWeights:
        def __init__(self) -> None:
            self.pending: list = []

        def poll(self):
            return self.pending.pop(0) if self.pending else None

        def absorb_announcements(self) -> None:
            pass

    monkeypatch.setattr(evaluation, "run_episode", fake_run_episode)
    monkeypatch.setattr(policy_module, "PolicyRuntime", FakeRuntime)
    published: list = []  # videos 0: a fake env cannot be filmed
    ev, gate_tracker = _cadence_evaluator(tmp_path, episodes=3, final_episodes=6, every_env_steps=1000,
                                          final_env_steps=2500, videos=0)  # fmt: skip
    ev.ctx.bus = SimpleNamespace(publish=lambda topic, msg, source: published.append(msg))
    ev.env.segment_names = ("gripper", "object_a", "object_b")
    weights = FakeWeights()
    ev.weights = weights

    def blob(version: int) -> SimpleNamespace:
        return SimpleNamespace(version=version, run_id="run-1")

    for steps, version, evaluated in ((1000, 1, True), (1500, 2, False), (2000, 3, True), (2600, 4, True)):
        _at(gate_tracker, steps)
        weights.pending.append(blob(version))
        assert ev.step() is evaluated, steps
        if not evaluated:
            weights.pending.clear()

    base = 1_000_000_000
    regular, final = [base, base + 1, base + 2], [base + k for k in range(6)]
    assert rolled == regular + regular + final
    assert [(r.policy_version, r.env_steps, r.episodes) for r in published] == [(1, 1000, 3), (3, 2000, 3),
                                                                                 (4, 2600, 6)]  # fmt: skip
    assert published[-1].success_rate == pytest.approx(3 / 6) and published[0].success_rate == pytest.approx(
        2 / 3
    )
    history = read_history(tmp_path / "eval" / "history.jsonl")
    assert [(h["env_steps"], h["episodes"], h["at_budget"]) for h in history] == [(1000, 3, False), (2000, 3, False),
                                                                                   (2600, 6, True)]  # fmt: skip
    assert [h["seeds"] for h in history] == [regular, regular, final]
    assert history[-1]["successes"] == [True, False] * 3 and len(history[-1]["lengths"]) == 6


def test_a_depth_policy_is_refused_by_an_evaluator_without_the_depth_image(tmp_path, caplog):
    """The observation check shared with the actor: counted under reason "observation", not evaluated."""
    import logging
    from types import SimpleNamespace

    from services.algorithms.networks import build_actor
    from services.algorithms.policy import PolicySpec, actor_tensors
    from services.tasks import EnvSettings
    from tests.helpers.learner import TINY_NET

    spec = PolicySpec(TINY_NET, observation="depth")
    blob = WeightsBlob.create(4, "equi_rsac", "run-1", actor_tensors(build_actor(spec.net)), spec.to_json())
    ev, _ = _cadence_evaluator(tmp_path)
    ev.weights = SimpleNamespace(poll=lambda: blob)
    with caplog.at_level(logging.ERROR, logger="services.evaluator.main"):
        assert ev.pull() is None
    registry = ev.ctx.metrics.registry
    assert ev.bad_weights == 1
    assert registry.get_sample_value("mea_evaluator_bad_weights_total", {"reason": "observation"}) == 1
    assert [r.error for r in caplog.records if r.getMessage() == "weights not evaluated"] == [
        "a depth-image policy needs an evaluator started with --depth-image"
    ]
    ev.env.settings = EnvSettings(depth_image=True)  # rendered here: the same weights load
    blob_, runtime, _steps = ev.pull()
    assert blob_ is blob and runtime.spec.observation == "depth" and runtime.version == 4
    assert ev.bad_weights == 1
