"""`mea evaluator`: evaluate the learner's broadcast weights on held-out seeds, like Equi-RSAC's eval.
A service of its own so that evaluation never touches the training envs, runs the deterministic
policy and compares every version on the same episodes.

Design notes: docs/architecture-notes.md, services/evaluator/main.py."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

from proto.topics import EVAL_REPORTS, REPLAY_GATE
from proto.weights import WeightsBlob
from services.common import config, weights_file
from services.common.bus.base import Bus
from services.common.config import ServiceConfig
from services.common.replay_gate import GateTracker
from services.common.runtime import ServiceContext, subscribing_bus_factory, torch_threads
from services.common.scalars import ScalarLog
from services.common.weights import WeightsClient
from services.episodes.scores import EvalSummary
from services.evaluator.config import PRESETS, EvaluatorConfig
from services.evaluator.core.curves import run_improvement_timestep
from services.evaluator.core.schedule import last_evaluated_env_steps
from services.evaluator.evaluation import EpisodeRunner, Evaluation
from services.evaluator.history import HISTORY, append_history, read_history
from services.evaluator.metrics import evaluator_metrics
from services.evaluator.video import FPS, Film
from services.evaluator.video import missing_writer as missing_video_writer
from services.evaluator.video import write as write_video
from services.tasks import ManipulationEnv, make_env

log = logging.getLogger(__name__)


class _StopRequestedError(Exception):
    """Raised from inside a rollout when the service is asked to stop."""


class Evaluator:
    """The service's loop body, separate from the bus setup so it can be driven directly."""

    def __init__(self, cfg: EvaluatorConfig, ctx: ServiceContext, gate: GateTracker, weights: WeightsClient,
                 env: ManipulationEnv | None = None) -> None:  # fmt: skip
        self.cfg = cfg
        self.ctx = ctx
        self.gate = gate
        self.weights = weights
        self.env = env or make_env(cfg.task, cfg.env_settings())  # its own env: never a training one
        self.mx = evaluator_metrics(ctx.metrics)
        self.mx["version"].set(-1)
        self.mx["env_steps"].set(-1)
        self.mx["improvement"].set(-1)
        self.runner = EpisodeRunner(self.env, cfg.task, ctx.instance, self._keep_up,
                                    self.mx["episode_seconds"].observe)  # fmt: skip
        self.history_path = cfg.run_dir / HISTORY if cfg.run_dir is not None else None
        self.records: list[dict] = []
        if self.history_path is not None and self.history_path.exists():
            self.records = read_history(self.history_path)
            log.info(
                "eval history found", extra={"path": str(self.history_path), "records": len(self.records)}
            )
        self.improvement = run_improvement_timestep(self.records)
        if self.improvement is not None:
            self.mx["improvement"].set(self.improvement)
        self.schedule = cfg.schedule
        self.last_env_steps = last_evaluated_env_steps(self.records)  # the cadence survives a restart
        self.evaluations = 0  # by this process
        self.bad_weights = 0
        self.last: EvalSummary | None = None
        self.last_version = -1
        self.last_steps = -1
        self.started = time.monotonic()
        self.scalars = (
            None if cfg.tensorboard_dir is None else ScalarLog(cfg.tensorboard_dir, 1, ctx.instance)
        )
        self.videos_dir = None if cfg.run_dir is None or cfg.videos == 0 else cfg.run_dir / "eval" / "videos"
        why = None if self.videos_dir is None else missing_video_writer()
        if why is not None:  # said once; evaluating goes on without videos
            log.warning("evaluation videos off: no MP4 writer here (pip install imageio imageio-ffmpeg)",
                        extra={"reason": why})  # fmt: skip
            self.videos_dir = None

    def heartbeat_counters(self) -> dict[str, float]:
        """For the launcher table (the first four are shown); -1 means none yet / unknown."""
        out = {
            "evaluations": self.evaluations,
            "success_rate": -1.0 if self.last is None else self.last.success_rate,
            "env_steps": self.last_steps,
            "version": self.last_version,
            "grasp_score": -1.0 if self.last is None else self.last.grasp_score,
            "mean_return": -1.0 if self.last is None else self.last.mean_return,
            "learner_env_steps": self.gate.env_steps,
            "bad_weights": self.bad_weights,
        }
        if self.improvement is not None:
            out["improvement_env_steps"] = self.improvement
        return out

    def done(self) -> bool:
        return self.cfg.max_evaluations > 0 and self.evaluations >= self.cfg.max_evaluations

    def due(self) -> bool:
        """Is it time to pull (and evaluate) the newest version? (``core.schedule.Schedule.due``)"""
        return self.schedule.due(self.gate.env_steps, self.last_env_steps, time.monotonic() - self.started)

    def _bad(self, blob: WeightsBlob, reason: str, error: str) -> None:
        self.bad_weights += 1
        self.mx["bad_weights"].labels(reason).inc()
        log.error(
            "weights not evaluated", extra={"version": blob.version, "reason": reason, "error": error[:300]}
        )

    def pull(self):
        """The newest version in a fresh deterministic runtime, with its env steps; None if nothing new
        (or it could not be loaded)."""
        blob = self.weights.poll()
        if blob is None:
            return None
        env_steps = self.gate.env_steps
        # torch: imported once weights exist
        from services.algorithms.policy import ObservationUnavailableError, PolicyRuntime, check_observation

        runtime = PolicyRuntime(deterministic=True, seed=self.cfg.seed_base)
        try:  # a fresh runtime: a failed load cannot leave a half-overwritten network behind
            runtime.load(blob)
        except Exception as exc:  # noqa: BLE001 - a bad blob must not take the evaluator down
            self._bad(blob, "load", str(exc))
            return None
        try:
            depth_image = getattr(self.env.settings, "depth_image", False)  # the surgical env renders none
            check_observation(runtime.spec.observation, depth_image, "an evaluator", self.cfg.task)
        except ObservationUnavailableError as exc:
            self._bad(blob, "observation", str(exc))
            return None
        return blob, runtime, env_steps

    def _keep_up(self, _seconds: float = 0.0) -> None:
        """Between env steps: consume gates and announcements (bounded BLOCK queues); stop if asked."""
        self.gate.update()
        self.weights.absorb_announcements()
        if self.ctx.shutdown.is_set():
            raise _StopRequestedError

    def evaluate(self, blob: WeightsBlob, runtime, env_steps: int) -> dict | None:
        """Evaluate one version, report it and record it; returns the history record (None if aborted)."""
        seeds, at_budget = self.schedule.seeds_at(env_steps), self.schedule.at_budget(env_steps)
        log.info("evaluating", extra={"version": blob.version, "env_steps": env_steps, "episodes": len(seeds),
                                      "at_budget": at_budget})  # fmt: skip
        film = self._film(blob.version, env_steps, at_budget)
        try:
            ev = self.runner.evaluate(blob, runtime, env_steps, seeds, at_budget, film)
        except _StopRequestedError:
            log.info("evaluation abandoned at shutdown", extra={"version": blob.version})
            return None
        self.ctx.bus.publish(EVAL_REPORTS, ev.report(), source=self.ctx.instance)
        record = ev.record()
        self.records.append(record)
        if self.history_path is not None:
            try:
                append_history(self.history_path, record)
            except OSError:
                log.exception("could not append to the eval history", extra={"path": str(self.history_path)})
        self._keep_weights(blob)
        self._account(ev)
        self._tensorboard(ev, film)
        s = ev.summary
        log.info("evaluated", extra={"version": blob.version, "env_steps": env_steps,
                                     "success_rate": s.success_rate, "mean_return": s.mean_return,
                                     "grasp_score": s.grasp_score, "improvement_env_steps": self.improvement,
                                     "seconds": round(ev.wall_seconds, 2)})  # fmt: skip
        return record

    def _film(self, version: int, env_steps: int, at_budget: bool) -> Film | None:
        """A film of this evaluation's first episodes if it is a chosen one: the run's 1st evaluation,
        every ``video_every``-th after it (over the history, so a restart keeps the count) and the one
        at the budget."""
        if self.videos_dir is None or not (at_budget or len(self.records) % self.cfg.video_every == 0):
            return None
        steps = "?" if env_steps < 0 else f"{env_steps:,}"
        return Film(self.cfg.videos, self.cfg.video_size, title=f"v{version} at {steps} env steps")

    def _tensorboard(self, ev: Evaluation, film: Film | None) -> None:
        """The evaluation's scalars at the learner's env steps (none without a gate), and its video."""
        path = None
        if film is not None and film.frames and self.videos_dir is not None:
            t0 = time.perf_counter()
            path = self.videos_dir / f"v{ev.version:08d}_{max(ev.env_steps, 0)}steps.mp4"
            try:
                write_video(path, film.frames)
            except Exception:  # noqa: BLE001 - a video that cannot be written must not stop evaluating
                log.exception("could not write the evaluation video", extra={"path": str(path)})
                path = None
            else:
                log.info("evaluation video written", extra={"path": str(path), "frames": len(film.frames),
                                                            "seconds": round(time.perf_counter() - t0, 2)})  # fmt: skip
        if self.scalars is None or ev.env_steps < 0:
            return
        s, step = ev.summary, ev.env_steps
        self.scalars.add({"eval/success_rate": s.success_rate, "eval/return": s.mean_return,
                          "eval/length": s.mean_length, "eval/grasp_score": s.grasp_score}, step)  # fmt: skip
        if path is not None and film is not None:
            self.scalars.add_animation("eval/video", film.frames, step, FPS)
            self.scalars.add_text("eval/video_path", str(path), step)

    def _keep_weights(self, blob: WeightsBlob) -> None:
        """Keep the evaluated version beside its history line (the learner keeps only its newest), so
        `mea serve --weights RUN_DIR --version N` can serve any version the history scored."""
        if self.cfg.run_dir is None or self.cfg.keep_weights == 0:
            return
        creds = self.ctx.bus.credentials  # type: ignore[union-attr]
        try:
            weights_file.write(self.cfg.run_dir / weights_file.EVALUATED, blob, None if creds is None else creds.key,
                               self.ctx.instance, keep=self.cfg.keep_weights, service="evaluator")  # fmt: skip
        except OSError:
            log.exception("could not keep the evaluated weights", extra={"version": blob.version})

    def _account(self, ev: Evaluation) -> None:
        version, env_steps, s = ev.version, ev.env_steps, ev.summary
        self.evaluations += 1
        self.last, self.last_version, self.last_steps = s, version, env_steps
        self.last_env_steps = env_steps
        self.improvement = run_improvement_timestep(self.records)
        self.ctx.policy_version = version
        self.ctx.detail = f"v{version} at {env_steps} env steps: success {s.success_rate:.0%}"
        self.mx["evaluations"].inc()
        for name in ("success_rate", "mean_return", "mean_length", "grasp_score"):
            self.mx[name].set(getattr(s, name))
        self.mx["version"].set(version)
        self.mx["env_steps"].set(env_steps)
        self.mx["improvement"].set(-1 if self.improvement is None else self.improvement)

    def step(self) -> bool:
        """One cycle; True if a version was evaluated."""
        self.gate.update()
        if not self.due():
            return False
        pulled = self.pull()
        if pulled is None:
            return False
        return self.evaluate(*pulled) is not None

    def loop(self) -> None:
        while not self.ctx.shutdown.is_set() and not self.done():
            if not self.step():
                self.ctx.shutdown.wait(0.2)


def run(cfg: EvaluatorConfig, bus_factory: Callable[[ServiceConfig], Bus] | None = None,
        env: ManipulationEnv | None = None) -> int:  # fmt: skip
    """Run the evaluator until stopped (or ``max_evaluations``); ``env`` replaces its own env (tests)."""
    with torch_threads(cfg.torch_threads):
        return _run(cfg, bus_factory, env)


def _run(cfg: EvaluatorConfig, bus_factory: Callable[[ServiceConfig], Bus] | None,
         env: ManipulationEnv | None) -> int:  # fmt: skip
    holder: dict[str, object] = {}

    def declare(bus: Bus) -> None:
        holder["gate"] = GateTracker(bus.subscribe(REPLAY_GATE, capacity=64))
        holder["weights"] = WeightsClient(bus)

    def counters() -> dict[str, float]:
        core = holder.get("core")
        return core.heartbeat_counters() if isinstance(core, Evaluator) else {}

    make_bus = subscribing_bus_factory(bus_factory, declare)
    with ServiceContext("evaluator", cfg.service, bus_factory=make_bus, counters=counters) as ctx:
        gate, weights = holder["gate"], holder["weights"]
        core = Evaluator(cfg, ctx, gate, weights, env)  # type: ignore[arg-type]
        holder["core"] = core
        ctx.detail = f"{cfg.task}: {cfg.episodes} episodes every {cfg.every_env_steps} env steps"
        if cfg.final_env_steps:
            ctx.detail += f", {len(cfg.seeds_at(cfg.final_env_steps))} at {cfg.final_env_steps}"
        log.info("evaluating broadcast weights", extra={"task": cfg.task, "episodes": cfg.episodes,
                                                       "final_episodes": len(cfg.seeds_at(cfg.final_env_steps)),
                                                       "every_env_steps": cfg.every_env_steps,
                                                       "seed_base": cfg.seed_base,
                                                       "history": str(core.history_path)})  # fmt: skip
        try:
            core.loop()
        finally:
            weights.close()  # type: ignore[union-attr]
            gate.sub.close()  # type: ignore[union-attr]
            if env is None:
                core.env.close()
            if core.scalars is not None:
                core.scalars.close()
        log.info("evaluator done", extra={"evaluations": core.evaluations, "bad_weights": core.bad_weights,
                                          "improvement_env_steps": core.improvement})  # fmt: skip
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(EvaluatorConfig, PRESETS, argv, "mea evaluator", EvaluatorConfig.__doc__ or ""))


__all__ = ["Evaluator", "main", "run"]
