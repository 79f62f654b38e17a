"""`mea serve` and `mea robot` wired on the in-process bus: the same episodes as the evaluator, swaps
under load, and the robot side's holds (watchdog, e-stop, lost server or operator)."""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import numpy as np
import pytest
import torch

from proto.actions import ACTION_DIM
from proto.inference import ActReply, ActRequest, EStop, ResetRequest
from proto.topics import ESTOP, WEIGHTS_ANNOUNCE
from proto.weights import WeightsBlob
from services.algorithms.networks import PRESETS, build_actor
from services.algorithms.policy import PolicyRuntime, PolicySpec, actor_tensors
from services.common import weights_file
from services.common.bus.base import Delivery
from services.common.bus.inproc import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.mcap_io import read_messages
from services.common.weights import WeightsServer
from services.evaluator.config import EvaluatorConfig
from services.evaluator.evaluation import EpisodeRunner
from services.inference import main as serve_main
from services.inference import robot as robot_main
from services.inference.adapter import RobotObservation, SimRobot, StepOutcome, sim_limits
from services.inference.config import ServeConfig
from services.inference.core.sessions import episode_seed
from services.inference.robot import RobotConfig, RobotLink
from services.tasks import make_env

SPEC = PolicySpec(PRESETS["cpu-small"])
# the server, the evaluator and the reference runtimes on one torch thread each, as deployed: actions
# are compared bit for bit
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def blob(version: int, seed: int = 0) -> WeightsBlob:
    torch.manual_seed(seed)
    return WeightsBlob.create(
        version, "equi_rsac", "run-a", actor_tensors(build_actor(SPEC.net)), SPEC.to_json()
    )


def svc(instance: str) -> ServiceConfig:
    return ServiceConfig(instance_id=instance, metrics_port=0, log_format="text")


def limits_file(tmp_path, env) -> str:
    lim = dataclasses.asdict(sim_limits(env))
    path = tmp_path / "limits.json"
    path.write_text(
        json.dumps({"default": {k: list(v) if isinstance(v, tuple) else v for k, v in lim.items()}})
    )
    return str(path)


def _until(pred, timeout: float) -> None:
    """Poll ``pred`` until it holds or ``timeout`` seconds pass (the caller asserts what it needs)."""
    deadline = time.monotonic() + timeout
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.01)


class Serving:
    """`mea serve` on a thread of this process, on the hub's bus."""

    def __init__(self, cfg: ServeConfig, hub: Hub) -> None:
        self.ready = threading.Event()
        self.server = None
        self.thread = threading.Thread(target=serve_main.run, args=(cfg, lambda c: InProcBus(hub), self._ready),
                                       daemon=True)  # fmt: skip
        self.thread.start()
        assert self.ready.wait(30), "mea serve did not come up"

    def _ready(self, server) -> None:
        self.server = server
        self.ready.set()

    def stop(self) -> None:
        self.server.ctx.shutdown.set()
        self.thread.join(10)


def serve_and_drive(
    tmp_path, robot: SimRobot, weights: WeightsBlob, episodes: int
) -> tuple[RobotConfig, dict]:
    """`mea serve` with ``weights`` (from a weights file) and `mea robot` driving ``robot`` through it
    for ``episodes`` episodes, recorded to ``robot.mcap``: the robot's config and run summary."""
    hub = Hub()
    path = weights_file.write(tmp_path / "weights", weights)
    serving = Serving(ServeConfig(weights=str(path), limits_file=limits_file(tmp_path, robot.env),
                                  service=svc("inference-0")), hub)  # fmt: skip
    try:
        cfg = RobotConfig(sim=True, task=robot.task, episodes=episodes, record=str(tmp_path / "robot.mcap"),
                          service=svc("robot-0"))  # fmt: skip
        return cfg, robot_main.run(cfg, lambda c: InProcBus(hub), robot)
    finally:
        serving.stop()


@pytest.mark.slow
def test_the_sim_robot_through_serve_runs_the_evaluators_episodes_action_for_action(tmp_path):
    task = "block_pull"
    cfg, summary = serve_and_drive(tmp_path, SimRobot(task, EvaluatorConfig().env_settings()), blob(3), 2)
    assert summary["holds"] == {} and summary["versions"] == {
        "3": sum(e["length"] for e in summary["episodes"])
    }
    served = [m.action for _, m in read_messages(tmp_path / "robot.mcap", types={"ActReply"})]

    env = make_env(task, EvaluatorConfig().env_settings())
    runtime = PolicyRuntime(deterministic=True)
    runtime.load(blob(3))
    taken: list[np.ndarray] = []
    act = runtime.act
    runtime.act = lambda image: taken.append(act(image)) or taken[-1]  # type: ignore[method-assign]
    results = EpisodeRunner(env, task, "evaluator-0").episodes(runtime, cfg_seeds := summary["seeds"])
    assert [(r.seed, r.success, r.length, r.ret) for r in results] == [
        (e["seed"], e["success"], e["length"], e["return"]) for e in summary["episodes"]
    ]
    assert cfg_seeds == [cfg.seed_base, cfg.seed_base + 1]
    np.testing.assert_array_equal(np.stack(served), np.stack(taken))


def test_a_gasv2_policy_on_the_surgical_arm_follows_the_executed_actions(tmp_path):
    """The hybrid controller replaces the policy's action on the approach: the robot reports what was
    executed and the server's latent state follows it, as the evaluator's runtime does."""
    from services.algorithms.gasv2.agent import GasV2Agent
    from services.algorithms.gasv2.config import PRESETS as GASV2_PRESETS
    from services.algorithms.gasv2.policy import GasV2Spec

    task = "surgical_grasp_any"
    agent = GasV2Agent(GASV2_PRESETS["smoke"], seed=0)
    tensors = {k: v.numpy().copy() for k, v in agent.policy.state_dict().items()}
    gas = WeightsBlob.create(2, "gasv2", "run-g", tensors, GasV2Spec(agent.cfg).to_json())
    robot = SimRobot(task, EvaluatorConfig(task=task).env_settings())
    robot.max_steps = 25
    _, summary = serve_and_drive(tmp_path, robot, gas, 1)
    requests = [m for _, m in read_messages(tmp_path / "robot.mcap", types={"ActRequest"})]
    served = [m.action for _, m in read_messages(tmp_path / "robot.mcap", types={"ActReply"})]
    assert summary["holds"] == {} and requests[0].image.shape == (3, 64, 64)
    # the served actions are what the policy gives when it is told what was executed, step by step
    runtime = PolicyRuntime(deterministic=True, seed=episode_seed("sim-psm", 1))
    runtime.load(gas)
    replayed = []
    for req in requests:
        if req.executed is not None:
            runtime.executed(req.executed)
        replayed.append(runtime.act(np.array(req.image)))
    np.testing.assert_array_equal(np.stack(served), np.stack(replayed))
    executed = [m.executed for m in requests[1:]]
    assert any(
        not np.array_equal(e, a) for e, a in zip(executed, served, strict=False)
    )  # the controller acted


@pytest.mark.slow
def test_swaps_under_load_never_mix_versions_in_an_episode_nor_go_back(tmp_path):
    hub = Hub()
    learner_bus = InProcBus(hub)
    weights = WeightsServer(learner_bus, "learner-0")
    robot = SimRobot("block_pull")
    robot.max_steps = 12  # short episodes: many episode starts while versions change
    serving = Serving(
        ServeConfig(limits_file=limits_file(tmp_path, robot.env), service=svc("inference-0")), hub
    )
    weights.publish(blob(1))
    stop = threading.Event()

    def publish_more() -> None:
        v = 1
        while not stop.wait(0.03):
            v += 1
            if v % 4 == 0:  # a corrupt blob now and then: refused, the old version keeps serving
                bad = dataclasses.replace(blob(v, seed=v), digest="f" * 64)
                weights._version, weights._payload = v, bad.encode()  # what the learner would serve
                learner_bus.publish(WEIGHTS_ANNOUNCE, bad.announcement(1), source="learner-0")
            else:
                weights.publish(blob(v, seed=v))

    publisher = threading.Thread(target=publish_more, daemon=True)
    publisher.start()
    try:
        cfg = RobotConfig(sim=True, episodes=8, record=str(tmp_path / "swap.mcap"), service=svc("robot-0"))
        summary = robot_main.run(cfg, lambda c: InProcBus(hub), robot)
    finally:
        stop.set()
        publisher.join(5)
        refused = serving.server.counts["refused"]
        serving.stop()
    replies = [m for _, m in read_messages(tmp_path / "swap.mcap", types={"ActReply"})]
    by_episode: dict[int, set[int]] = {}
    for r in replies:
        by_episode.setdefault(r.episode, set()).add(r.policy_version)
    assert all(len(v) == 1 for v in by_episode.values()), by_episode  # one version per episode
    per_episode = [next(iter(by_episode[e])) for e in sorted(by_episode)]
    assert per_episode == sorted(per_episode) and len(set(per_episode)) > 1  # forward, and it did swap
    assert all(v % 4 != 0 for v in per_episode)  # never a corrupt one
    assert refused >= 1 and summary["holds"] == {}


class StallingArm:
    """An arm whose observations stop coming: ``execute`` blocks until released."""

    task, max_steps = "block_pull", 5

    def __init__(self) -> None:
        self.held = threading.Event()
        self.reasons: list[str] = []
        self.release = threading.Event()

    def reset(self, seed: int, observation: str) -> RobotObservation:
        return RobotObservation(np.zeros(5, np.float32), time.time(), image=np.zeros((2, 84, 84), np.uint8))

    def execute(self, action: np.ndarray) -> StepOutcome:
        self.release.wait(10)
        return StepOutcome(self.reset(0, ""), np.zeros(ACTION_DIM, np.float32))

    def hold(self, reason: str) -> None:
        self.reasons.append(reason)
        self.held.set()

    def close(self) -> None:
        pass


def _link(hub: Hub, arm, **kw) -> tuple[RobotLink, InProcBus]:
    bus = InProcBus(hub)
    cfg = RobotConfig(sim=True, server="inference-0", service=svc("robot-0"), **kw)
    return RobotLink(cfg, bus, arm), bus


def test_the_watchdog_holds_within_its_timeout_when_commands_stop():
    hub = Hub()
    server_token = InProcBus(hub).declare_alive("inference", "inference-0")
    arm = StallingArm()
    link, _ = _link(hub, arm, command_timeout=0.3)
    try:
        assert link.hold_reason() is None
        t0 = time.monotonic()
        link.safety.last_command = link.clock()  # commanding: then nothing more arrives
        assert arm.held.wait(2.0)
        assert arm.reasons == ["watchdog"] and 0.3 <= time.monotonic() - t0 < 0.3 + 0.5
    finally:
        link.close()
        server_token.close()


@pytest.mark.parametrize("cause", ["operator_lost", "server_lost", "estop"])
def test_liveliness_loss_and_estop_make_the_robot_hold(cause):
    hub = Hub()
    server_token = InProcBus(hub).declare_alive("inference", "inference-0")
    operator_bus = InProcBus(hub)
    operator_token = operator_bus.declare_alive("operator", "op-1")
    arm = StallingArm()
    link, _ = _link(hub, arm, require_operator=True)
    try:
        assert link.hold_reason() is None and not arm.held.is_set()
        t0 = time.monotonic()
        if cause == "operator_lost":
            operator_token.close()
        elif cause == "server_lost":
            server_token.close()
        else:
            operator_bus.publish(
                ESTOP, EStop(operator_id="op-1", engaged=True, created_at=time.time()), source="op-1"
            )
        assert arm.held.wait(2.0) and arm.reasons == [cause]
        assert time.monotonic() - t0 < 1.0
        if cause == "estop":  # latched until released
            operator_bus.publish(
                ESTOP, EStop(operator_id="op-1", engaged=False, created_at=time.time()), source="op-1"
            )
            _until(lambda: link.hold_reason() is None, 2)
            assert link.hold_reason() is None
    finally:
        link.close()
        operator_token.close()
        server_token.close()


def test_an_engaged_estop_holds_at_the_server_too(tmp_path):
    hub = Hub()
    path = weights_file.write(tmp_path / "weights", blob(1))
    serving = Serving(ServeConfig(weights=str(path), service=svc("inference-0")), hub)
    operator = InProcBus(hub)
    try:
        operator.publish(
            ESTOP, EStop(operator_id="op-1", engaged=True, created_at=time.time()), source="op-1"
        )
        _until(lambda: serving.server.core.estop, 5)
        core = serving.server.core
        r = core.reset(
            ResetRequest(session="arm-1", task="block_pull", created_at=time.time()), time.monotonic()
        )
        req = ActRequest(session="arm-1", episode=r.episode, step=0, stamp=time.time(),
                         state=np.array([0, 0, 0.1, 0, 1], np.float32), image=np.zeros((2, 84, 84), np.uint8))  # fmt: skip
        reply: ActReply = serving.server.on_act(Delivery("k", {}, req, 0))
        assert reply.held and reply.reasons == ["estop"]
        assert serving.server.mx["holds"].labels("estop")._value.get() == 1
    finally:
        serving.stop()


def test_an_unsigned_blob_is_refused_and_the_signed_version_keeps_serving(tmp_path):
    """With the run's key, the server takes weights only from the run's learner: an unsealed
    announcement and blob from another process are refused (counted) and v1 keeps serving."""
    from services.common import run_key
    from services.common.bus.base import Credentials

    key_file = tmp_path / "run.key"
    key = run_key.create(key_file)
    hub = Hub()
    learner_bus = InProcBus(hub)
    learner_bus.authenticate(Credentials(key, "learner", "learner-0"))
    WeightsServer(learner_bus, "learner-0").publish(blob(1))
    cfg = ServeConfig(service=dataclasses.replace(svc("inference-0"), run_key_file=str(key_file)))
    serving = Serving(cfg, hub)
    try:
        _until(lambda: serving.server.core.current is not None, 10)
        assert serving.server.core.current.version == 1
        rogue = WeightsServer(InProcBus(hub), "learner-9")  # no key: nothing it sends is sealed
        rogue.publish(blob(2, seed=4))
        _until(lambda: serving.server.counts["refused"] > 0, 10)
        assert serving.server.counts["refused"] >= 1
        assert serving.server.mx["refused"].labels("invalid")._value.get() >= 1
        robot = InProcBus(hub)
        robot.authenticate(Credentials(key, "robot", "robot-0"))
        from proto.topics import SERVE_ACT, SERVE_RESET

        r = robot.call(SERVE_RESET, ResetRequest(session="arm", task="block_pull", created_at=time.time()),
                       source="inference-0").message  # fmt: skip
        req = ActRequest(session="arm", episode=r.episode, step=0, stamp=time.time(),
                         state=np.array([0.5, 0, 0.2, 0, 1], np.float32), image=np.zeros((2, 84, 84), np.uint8))  # fmt: skip
        reply = robot.call(SERVE_ACT, req, source="inference-0").message
        assert (
            r.policy_version == 1 and reply.policy_version == 1 and serving.server.core.current.version == 1
        )
    finally:
        serving.stop()


def test_a_failing_handler_answers_with_a_reason_not_silence(tmp_path, monkeypatch):
    hub = Hub()
    path = weights_file.write(tmp_path / "weights", blob(1))
    serving = Serving(ServeConfig(weights=str(path), service=svc("inference-0")), hub)
    try:
        robot = InProcBus(hub)
        from proto.topics import SERVE_ACT, SERVE_RESET

        def boom(*a, **k):
            raise RuntimeError("policy exploded")

        monkeypatch.setattr(serving.server.core, "reset", boom)
        r = robot.call(SERVE_RESET, ResetRequest(session="arm", task="block_pull", created_at=time.time()),
                       source="inference-0").message  # fmt: skip
        assert not r.accepted and "policy exploded" in r.reason
        monkeypatch.setattr(serving.server.core, "act", boom)
        req = ActRequest(session="arm", episode=1, step=0, stamp=time.time(), nonce=9,
                         state=np.array([0.5, 0, 0.2, 0, 1], np.float32), image=np.zeros((2, 84, 84), np.uint8))  # fmt: skip
        reply = robot.call(SERVE_ACT, req, source="inference-0").message
        assert reply.held and reply.reasons == ["server_error"] and reply.nonce == 9
        assert serving.server.mx["holds"].labels("server_error")._value.get() == 1
    finally:
        serving.stop()
