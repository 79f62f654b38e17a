"""`mea actor`: run one simulated task with a policy source and publish every finished episode.

Design notes: docs/architecture-notes.md, services/actor/main.py."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np

from proto.topics import EPISODE_ACKS, EPISODES_RAW
from services.actor import jump_start
from services.actor.config import PRESETS, ActorConfig, env_configs
from services.actor.outbox import Outbox
from services.actor.rollout import RolloutActor
from services.common import config
from services.common.replay_gate import GateFollower
from services.common.runtime import ServiceContext
from services.common.scalars import ScalarLog
from services.common.weights import WeightsClient
from services.episodes.builder import EpisodeBuilder
from services.episodes.rollout import EpisodeStepper, policy_input

log = logging.getLogger(__name__)


def _metrics(ctx: ServiceContext):
    m = ctx.metrics
    return {
        "steps": m.counter("mea_actor_env_steps", "Environment steps taken."),
        "episodes": m.counter(
            "mea_actor_episodes", "Episodes finished and published, by policy kind.", ["kind"]
        ),
        "successes": m.counter("mea_actor_successes", "Successful episodes, by policy kind.", ["kind"]),
        "step_seconds": m.histogram(
            "mea_actor_step_seconds",
            "Wall time of one env step (physics + observation).",
            (0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.2, 0.5, 1.0),
        ),  # fmt: skip
        "publish_seconds": m.histogram(
            "mea_actor_publish_seconds",
            "Time to encode and publish one episode.",
            (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.5),
        ),  # fmt: skip
        "failed_demos": m.counter(
            "mea_actor_failed_demos", "Expert attempts that failed (not published as demos)."
        ),
        "gate_wait": m.counter(
            "mea_actor_gate_wait_seconds", "Time spent waiting for the learner's replay gate to open."
        ),
        "bad_weights": m.counter("mea_actor_bad_weights", "Weights versions that could not be loaded."),
        "bad_actions": m.counter(
            "mea_actor_bad_actions",
            "Episodes dropped because the env refused the policy's action (non-finite).",
        ),
        "resent": m.counter(
            "mea_actor_resent_episodes",
            "Episodes published again (no ack yet when a consumer restarted or in time).",
        ),
        "evicted": m.counter(
            "mea_actor_evicted_episodes",
            "Unacknowledged episodes let go because the outbox was full and no learner was ever seen.",
        ),
        "unacked": m.gauge(
            "mea_actor_unacked_episodes", "Published episodes the learner has not acknowledged."
        ),
        "ack_wait": m.counter(
            "mea_actor_ack_wait_seconds", "Time spent waiting for acks with --unacked-limit episodes pending."
        ),
    }


CONSUMERS = ("augmenter", "learner")


class EpisodeSender:
    """The actor's side of at-least-once delivery (the learner's dedup makes it exactly-once)."""

    def __init__(self, ctx: ServiceContext, cfg: ActorConfig, mx: dict) -> None:
        self.ctx, self.mx = ctx, mx
        self.outbox: Outbox = Outbox(cfg.unacked_limit, cfg.resend_seconds)
        self.acks = ctx.bus.subscribe(EPISODE_ACKS, capacity=16)
        self.watch = ctx.bus.watch_alive()

    def publish(self, episode) -> None:
        self.ctx.bus.publish(EPISODES_RAW, episode, source=self.ctx.instance)
        evicted = self.outbox.evicted
        self.outbox.sent(episode.episode_id, episode, time.monotonic())
        if self.outbox.evicted > evicted:
            self.mx["evicted"].inc(self.outbox.evicted - evicted)
            log.warning("unacknowledged episodes let go: no learner has acknowledged them",
                        extra={"evicted_total": self.outbox.evicted})  # fmt: skip
        self.mx["unacked"].set(len(self.outbox))

    def learner_alive(self) -> bool:
        return any(svc == "learner" for svc, _ in self.watch.alive())

    def tend(self) -> None:
        """Take acks; publish again what a (re)started consumer or a late ack calls for."""
        for d in self.acks.drain():
            self.outbox.ack(d.message.episode_ids)
        for _, episode in self.outbox.due(time.monotonic(), self.watch.came_alive(CONSUMERS)):
            self.ctx.bus.publish(EPISODES_RAW, episode, source=self.ctx.instance)
            self.mx["resent"].inc()
        self.mx["unacked"].set(len(self.outbox))

    def learner_expected(self) -> bool:
        """A learner is alive, or was and is gone (crashed, restarting, or cut off by the network):
        its acks are expected, so nothing it has not acknowledged may be let go."""
        return self.learner_alive() or self.watch.came_alive(("learner",)) is not None

    def wait_for_room(self) -> None:
        """While a learner is expected, wait while the outbox is full (acks free it, resends go out).
        Only an actor that never saw a learner (collecting data alone) lets its oldest go, counted."""
        t0 = time.monotonic()
        self.tend()
        while self.outbox.full and self.learner_expected() and not self.ctx.shutdown.wait(0.1):
            self.tend()
        self.mx["ack_wait"].inc(time.monotonic() - t0)

    def flush(self, timeout: float) -> None:
        """Before a clean exit (episode limit reached): wait up to ``timeout`` s, while a learner is
        alive, until every published episode is acknowledged."""
        deadline = time.monotonic() + timeout
        self.tend()
        while len(self.outbox) and self.learner_alive() and time.monotonic() < deadline:
            if self.ctx.shutdown.wait(0.1):
                return
            self.tend()

    def close(self) -> None:
        self.acks.close()
        self.watch.close()


class EpisodeScalars:
    """The actor's TensorBoard points: means over ``tensorboard_every`` episodes of their return,
    success and weights lag, and the env steps per second over those episodes (waits included), at
    the learner's env steps (its gate's; an actor that does not follow the gate: its own). Episodes
    that end before a gate is seen are not counted: their env step is unknown (a resumed run's
    actors would otherwise write at steps before the run's). Without a ``tensorboard_dir`` it writes
    nothing."""

    def __init__(self, cfg: ActorConfig, instance: str, gate: GateFollower | None, env_steps: int) -> None:
        self.log = None
        if cfg.tensorboard_dir is not None:
            self.log = ScalarLog(cfg.tensorboard_dir, cfg.tensorboard_every, instance)
        self.gate = gate
        self.t0, self.steps0 = time.monotonic(), env_steps

    def episode(self, b: EpisodeBuilder, env_steps: int, lag: int | None) -> None:
        step = env_steps if self.gate is None else self.gate.tracker.env_steps
        if self.log is None or step < 0:
            return
        # a jump start's outcome is not the policy's from the reset: charted apart
        prefix = "charts/jump_start_" if b.meta["policy_kind"] == "jump_start" else "charts/"
        values = {f"{prefix}episodic_return": float(sum(b.rewards)), f"{prefix}success": float(b.success)}
        if b.jump_left is not None:  # by how much of the demonstration was left to the policy
            values[f"charts/jump_start_success_left_{jump_start.left_bin(b.jump_left)}"] = float(b.success)
        if lag is not None:
            values["charts/weights_lag"] = float(lag)
        if self.log.due:  # a rate over the whole window, added once
            now = time.monotonic()
            values["perf/env_steps_per_second"] = (env_steps - self.steps0) / max(now - self.t0, 1e-9)
            self.t0, self.steps0 = now, env_steps
        self.log.add(values, step)

    def close(self) -> None:
        if self.log is not None:
            self.log.close()


def _load_weights(
    weights: WeightsClient, policy, mx, counts: dict, depth_image: bool = False, task: str = ""
) -> None:
    """Pull a newer version if one was announced; a blob that does not fit, or that wants the depth
    image from an actor that does not render it, is counted and skipped (the old weights stay)."""
    blob = weights.poll()
    if blob is None:
        return
    try:
        # deferred: torch, for learned actors only (an expert or random actor starts without it)
        from services.algorithms.policy import blob_observation, check_observation

        check_observation(blob_observation(blob), depth_image, "an actor", task)
        policy.load(blob)  # only after the check: refused weights must not replace the ones acting
    except ValueError as exc:
        mx["bad_weights"].inc()
        log.error("weights not loaded", extra={"version": blob.version, "error": str(exc)[:300]})
        return
    # for `mea bench system`: which version, and when (wall clock) it became the acting policy
    counts["weights_version"], counts["weights_loaded_at"] = blob.version, time.time()


class EnvSlot:
    """One of the actor's envs: its rollouts (``RolloutActor``, as actor ``cfg.index`` alone), its
    policy state (a ``PolicyRuntime`` following the actor's weights, with its own noise) and the
    learned episode it is in."""

    def __init__(self, cfg: ActorConfig, instance: str) -> None:
        self.actor = RolloutActor(cfg, instance)
        self.policy = None
        if cfg.policy == "learned":
            from services.algorithms.policy import PolicyRuntime  # torch: only for learned actors

            self.policy = PolicyRuntime(deterministic=False, seed=cfg.first_seed())
        self.k = 0  # episodes after the demonstrations
        self.episode: EpisodeStepper | None = None


class ActorLoop:
    """The actor's episodes over its envs. With ``cfg.envs`` K > 1 the K envs step in lockstep: their
    learned episodes share one batched policy step per tick; an env whose episode ended starts its
    next one (the gate, the weights, and random or expert episodes handled as a single-env actor
    handles them before each episode), and a closed gate holds only the envs that would start one."""

    def __init__(self, cfg: ActorConfig, ctx: ServiceContext, counts: dict) -> None:
        self.cfg, self.ctx, self.counts = cfg, ctx, counts
        self.slots = [EnvSlot(c, ctx.instance) for c in env_configs(cfg)]
        self.mx = _metrics(ctx)
        self.weights = WeightsClient(ctx.bus) if cfg.policy == "learned" else None
        self.gate = GateFollower(ctx.bus, cfg.gate_timeout) if cfg.follow_gate else None
        self.sender = EpisodeSender(ctx, cfg, self.mx)
        self.policy = None  # loads each version once; every env's runtime follows it
        if cfg.policy == "learned":
            from services.algorithms.policy import PolicyRuntime  # torch: only for learned actors

            self.policy = PolicyRuntime(deterministic=False, seed=cfg.first_seed())
        self.finished, self.lag = 0, None
        self.scalars: EpisodeScalars | None = None
        self.jump_demos: list[jump_start.Demo] = []  # made again in ``run`` when cfg.jump_start > 0
        self.jump_rng = np.random.default_rng([cfg.first_seed(), 29])

    def on_step(self, seconds: float) -> None:
        self.counts["env_steps"] += 1
        self.mx["steps"].inc()
        self.mx["step_seconds"].observe(seconds)

    def publish(self, slot: EnvSlot, b: EpisodeBuilder) -> None:
        self.sender.wait_for_room()
        t0 = time.perf_counter()
        self.sender.publish(b.finish(slot.actor.episode_id(b)))
        self.mx["publish_seconds"].observe(time.perf_counter() - t0)
        kind = b.meta["policy_kind"]
        self.counts["episodes"] += 1
        self.mx["episodes"].labels(kind).inc()
        if b.success:
            self.counts["successes"] += 1
            self.mx["successes"].labels(kind).inc()

    def dropped(self, exc: ValueError) -> None:
        """A policy's action the env refused (non-finite): the episode is dropped, counted."""
        self.mx["bad_actions"].inc()
        log.error("episode dropped: the policy's action was refused",
                  extra={"version": self.ctx.policy_version, "error": str(exc)[:300]})  # fmt: skip

    def demos(self) -> None:
        """The demonstrations, whole expert episodes on env 0 (as on actor 0); failures counted."""
        cfg, first = self.cfg, self.slots[0]
        demos, max_attempts = 0, cfg.demos * cfg.max_demo_attempts
        for b in first.actor.demonstrations(cfg.demos, max_attempts, self.on_step, self.ctx.shutdown.is_set):
            if b.success:
                self.publish(first, b)
                demos += 1
            else:
                self.mx["failed_demos"].inc()
        if demos < cfg.demos:
            log.warning("fewer demonstrations than requested", extra={"demos": demos, "requested": cfg.demos})

    def done(self, slot: EnvSlot, b: EpisodeBuilder) -> None:
        self.publish(slot, b)
        self.scalars.episode(b, self.counts["env_steps"], self.lag)
        slot.k += 1
        self.finished += 1

    def starting(self) -> list[EnvSlot]:
        """The envs that start an episode now: idle ones within the episode limit, once the gate is
        open (waiting for it only when no env is in an episode)."""
        active = sum(s.episode is not None for s in self.slots)
        idle = [s for s in self.slots if s.episode is None]
        if self.cfg.episodes:
            idle = idle[: max(0, self.cfg.episodes - self.finished - active)]
        if not idle:
            return []
        self.sender.tend()
        if self.gate is not None and not active:
            self.mx["gate_wait"].inc(self.gate.wait(self.ctx.shutdown, self.sender.tend))
        elif self.gate is not None and self.gate.blocked():
            return []  # the envs in an episode step on
        return [] if self.ctx.shutdown.is_set() else idle

    def follow_weights(self) -> bool:
        """Load a newer version if one was announced, for every env; False while none has come."""
        acted = self.policy.version
        _load_weights(self.weights, self.policy, self.mx, self.counts, self.cfg.depth_image, self.cfg.task)
        if not self.policy.ready:
            return False
        self.ctx.policy_version = self.policy.version
        self.lag = None if acted < 0 else self.policy.version - acted
        for s in self.slots:
            s.policy.follow(self.policy)
        return True

    def prepare_jump_starts(self) -> None:
        """The run's demonstrations made again on env 0 (``jump_start.regenerate``), for jump starts."""
        if self.cfg.jump_start <= 0:
            return
        t0 = time.monotonic()
        self.jump_demos = jump_start.regenerate(self.cfg, self.slots[0].actor.env, self.ctx.instance)
        extra = {"demos": len(self.jump_demos), "requested": self.cfg.jump_start_demos,
                 "seconds": round(time.monotonic() - t0, 1)}  # fmt: skip
        if len(self.jump_demos) < self.cfg.jump_start_demos:
            log.warning("jump starts: fewer demonstrations made again than the run recorded", extra=extra)
        else:
            log.info("jump starts: the run's demonstrations made again", extra=extra)

    def start(self, slot: EnvSlot) -> None:
        """A learned episode begins (stepped by ``step``), jump-started from a demonstration with
        probability ``cfg.jump_start``; a random or expert one runs whole, here."""
        if slot.actor.next_is_learned():
            jump = jump_start.draw(self.jump_rng, self.jump_demos, self.cfg.jump_start)
            if jump is None:
                slot.episode = slot.actor.begin_learned(slot.policy, self.on_step)
                return
            try:
                slot.episode = slot.actor.begin_jump_start(slot.policy, jump, self.on_step)
            except ValueError as exc:
                slot.episode = None
                self.dropped(exc)
                return
            if slot.episode.done:  # the env ended it within the replayed steps
                b, slot.episode = slot.episode.builder, None
                self.done(slot, b)
            return
        try:
            b = slot.actor.policy_episode(slot.k, slot.policy, self.on_step)
        except ValueError as exc:
            self.dropped(exc)
            self.ctx.shutdown.wait(0.5)
            return
        self.done(slot, b)

    def step(self) -> None:
        """One batched policy step for every env in a learned episode, then one env step each."""
        active = [s for s in self.slots if s.episode is not None]
        if not active:
            return
        observation = self.policy.spec.observation
        inputs = [policy_input(s.episode.obs, observation) for s in active]
        actions = self.policy.act_batch([s.policy for s in active], inputs)
        for s, action in zip(active, actions, strict=True):
            try:
                ended = s.episode.step(action)
            except ValueError as exc:
                s.episode = None
                self.dropped(exc)
                continue
            if ended:
                b, s.episode = s.episode.builder, None
                self.done(s, b)

    def run(self) -> None:
        self.demos()
        self.prepare_jump_starts()
        self.scalars = EpisodeScalars(self.cfg, self.ctx.instance, self.gate, self.counts["env_steps"])
        shutdown = self.ctx.shutdown
        while (self.cfg.episodes == 0 or self.finished < self.cfg.episodes) and not shutdown.is_set():
            starting = self.starting()
            if starting and self.policy is not None and not self.follow_weights():
                shutdown.wait(0.2)  # no weights yet: wait for the learner's first version
                continue
            for s in starting:
                if not shutdown.is_set():
                    self.start(s)
            if not shutdown.is_set():
                self.step()

    def close(self) -> None:
        if self.scalars is not None:
            self.scalars.close()
        self.sender.flush(self.cfg.resend_seconds)  # a stop by SIGTERM returns at once
        if self.gate is not None:
            self.gate.close()
        self.sender.close()
        for s in self.slots:
            s.actor.env.close()


def run(cfg: ActorConfig, bus_factory=None) -> int:
    counts = {"env_steps": 0, "episodes": 0, "successes": 0}
    kwargs = {"bus_factory": bus_factory} if bus_factory else {}
    with ServiceContext("actor", cfg.service, counters=lambda: counts, index=cfg.index, **kwargs) as ctx:
        loop = ActorLoop(cfg, ctx, counts)
        loop.run()
        loop.close()
    return 0


def main(argv: Sequence[str]) -> int:
    return run(config.parse(ActorConfig, PRESETS, argv, "mea actor", ActorConfig.__doc__ or ""))


__all__ = ["main", "run"]
