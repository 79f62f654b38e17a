"""The inference server's core: the policy it holds, robot sessions, and one act() per observation.

Design notes: docs/architecture-notes.md, services/inference/core/sessions.py."""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from proto.actions import ACTION_DIM, JAW
from proto.episode import DSA_TASKS
from proto.inference import ActReply, ActRequest, ResetReply, ResetRequest
from proto.weights import WeightsBlob, tensors_digest
from services.algorithms.policy import PolicyRuntime, blob_observation
from services.inference.core.envelope import Envelope, Limits
from services.observation.projection import segment_policy_images

REFUSAL_REASONS = ("not_newer", "other_run", "digest", "load")
"""Why ``offer`` refused a blob (a metric label)."""
SESSION_HOLDS = ("no_session", "stale_episode", "bad_observation", "no_policy", "server_error")
"""Holds decided here rather than by the envelope (which has ``HOLD_REASONS``)."""
MAX_POINT_RADIUS = 2.0
"""Gripper-centric points farther than this (m) are not a manipulation scene: refused as out of space."""


def refused_reset(session: str, reason: str) -> ResetReply:
    """The answer to a reset that starts no episode."""
    return ResetReply(session=session, accepted=False, reason=reason[:256], episode=0, policy_version=-1,
                      run_id="", observation="")  # fmt: skip


def sessionless_hold(req: ActRequest, reason: str, episode: int, t0: float | None = None) -> ActReply:
    """A hold for a request no session answers (none open for its sender, the server starting or
    failing): no motion, the jaw commanded as the robot measures it."""
    hold = np.zeros(ACTION_DIM, np.float32)
    hold[JAW] = 1.0 if np.isfinite(req.state[4]) and req.state[4] >= 0.5 else -1.0
    seconds = 0.0 if t0 is None else time.perf_counter() - t0
    return ActReply(session=req.session, episode=episode, step=req.step, action=hold, policy_version=-1, held=True,
                    reasons=[reason], compute_seconds=seconds, nonce=req.nonce)  # fmt: skip


def episode_seed(session: str, episode: int) -> int:
    """The policy generator's seed for one episode of one session: a stochastic policy (GASv2's latent
    samples, or ``stochastic`` serving) replays exactly given the session's requests."""
    return zlib.crc32(f"{session}/{episode}".encode())


class SwapRefusedError(ValueError):
    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Loaded:
    """One weights version ready to serve: a runtime whose modules sessions share."""

    version: int
    run_id: str
    algorithm: str
    observation: str
    image_shape: tuple[int, int, int]
    runtime: PolicyRuntime


def load(blob: WeightsBlob, deterministic: bool = True) -> Loaded:
    """Build the policy of ``blob``; SwapRefusedError ("digest", "load") when it cannot serve."""
    if tensors_digest(blob.tensors) != blob.digest:
        raise SwapRefusedError("digest", f"weights v{blob.version}: digest does not match the tensors")
    runtime = PolicyRuntime(deterministic=deterministic)
    try:
        observation = blob_observation(blob)
        runtime.load(blob)
    except (ValueError, RuntimeError, KeyError) as exc:
        raise SwapRefusedError("load", f"weights v{blob.version} do not load: {str(exc)[:300]}") from None
    shape = runtime.spec.image_shape  # type: ignore[union-attr]  # loaded just above
    return Loaded(blob.version, blob.run_id, blob.algorithm, observation, shape, runtime)


@dataclass
class Session:
    id: str
    task: str
    envelope: Envelope
    episode: int = 0
    policy: Loaded | None = None
    runtime: PolicyRuntime | None = None
    last_seen: float = field(default_factory=time.monotonic)
    owner: str = ""
    """The sender (``<service>/<instance>``) that opened it; only it may drive the session."""


@dataclass(frozen=True)
class ServeSettings:
    max_observation_age: float = 0.5
    """An observation taken longer ago than this (s, by its stamp) is answered with a hold."""
    session_timeout: float = 600.0
    """A session not heard from for this long (s) is dropped; its robot must reset."""
    max_sessions: int = 64
    """More robots than this are refused at reset (each session holds a recurrent state)."""
    deterministic: bool = True
    """Serve the policy's mean action (the evaluator's choice) rather than a sample."""
    run_id: str = ""
    """Serve only weights of this training run (empty: the first one loaded)."""


class InferenceCore:
    """The policy held, the sessions, and the answers to reset and act requests."""

    def __init__(self, settings: ServeSettings, limits_for=lambda session: Limits()) -> None:
        self.settings = settings
        self.limits_for = limits_for
        self.current: Loaded | None = None
        self.sessions: dict[str, Session] = {}
        self.estop = False

    # weights ---------------------------------------------------------------------------------
    def offer(self, blob: WeightsBlob) -> Loaded:
        """Make ``blob`` the current policy if it passes every check (SwapRefusedError otherwise)."""
        cur = self.current
        lineage = self.settings.run_id or (cur.run_id if cur is not None else "")
        if lineage and blob.run_id != lineage:
            raise SwapRefusedError("other_run", f"weights of run {blob.run_id}, serving run {lineage}")
        if cur is not None and blob.version <= cur.version:
            raise SwapRefusedError("not_newer", f"weights v{blob.version} are not newer than v{cur.version}")
        loaded = load(blob, self.settings.deterministic)
        self.current = loaded  # one assignment: the next reset takes it
        return loaded

    # sessions --------------------------------------------------------------------------------
    def expire(self, now: float) -> list[str]:
        gone = [s for s, v in self.sessions.items() if now - v.last_seen > self.settings.session_timeout]
        for s in gone:
            del self.sessions[s]
        return gone

    def reset(self, req: ResetRequest, now: float, sender: str = "") -> ResetReply:
        def refuse(reason: str) -> ResetReply:
            return refused_reset(req.session, reason)

        self.expire(now)
        cur = self.current
        if cur is None:
            return refuse("no weights loaded yet")
        if (cur.observation == "dsa") != (req.task in DSA_TASKS):
            return refuse(f"the {cur.observation!r} policy cannot observe {req.task}")
        s = self.sessions.get(req.session)
        if s is not None and s.owner != sender:
            return refuse(f"session {req.session} belongs to {s.owner or 'an unauthenticated robot'}")
        if s is None:
            if len(self.sessions) >= self.settings.max_sessions:
                return refuse(f"{self.settings.max_sessions} sessions open (max_sessions)")
            limits = self.limits_for(req.session)
            s = self.sessions[req.session] = Session(req.session, req.task, Envelope(limits), owner=sender)
        s.task, s.episode, s.last_seen = req.task, s.episode + 1, now
        s.policy, s.runtime = cur, cur.runtime.fresh(seed=episode_seed(s.id, s.episode))
        s.runtime.reset()
        s.envelope.jaw, s.envelope.last_command_at = 1.0, None
        return ResetReply(session=s.id, accepted=True, reason="", episode=s.episode, policy_version=cur.version,
                          run_id=cur.run_id, observation=cur.observation)  # fmt: skip

    # act -------------------------------------------------------------------------------------
    def act(self, req: ActRequest, now: float, wall: float, sender: str = "") -> ActReply:
        """The command for one observation (``now``: monotonic s, ``wall``: UNIX time s) from
        ``sender`` (the session's owner, or it is treated as no session)."""
        t0 = time.perf_counter()
        s = self.sessions.get(req.session)
        if s is None or s.owner != sender:
            return sessionless_hold(req, "no_session", 0, t0)
        s.last_seen = now
        version = s.policy.version if s.policy is not None else -1

        def held(reason: str) -> ActReply:
            return self._reply(req, s.episode, s.envelope.hold(reason).action, version, True, (reason,), t0)

        if req.episode != s.episode:
            return held("stale_episode")
        if self.estop:
            return held("estop")
        if wall - req.stamp > self.settings.max_observation_age:
            return held("watchdog")
        pivot = req.state[:3].astype(np.float64)
        bad = s.envelope.check_observation(pivot)
        if bad is not None or not np.isfinite(req.state).all():
            return held(bad or "non_finite_observation")
        if s.runtime is None or s.policy is None:
            return held("no_policy")
        try:
            image = self._policy_input(req, s.policy)
        except ValueError as exc:
            return held(str(exc))
        if req.executed is not None and req.step > 0:
            if not np.isfinite(req.executed).all() or np.abs(req.executed).max() > 1.0:
                return held("bad_observation")
            s.runtime.executed(req.executed)
        action = s.runtime.act(image)
        decision = s.envelope.command(action, pivot, now)
        return self._reply(req, s.episode, decision.action, version, decision.hold, decision.reasons, t0)

    @staticmethod
    def _policy_input(req: ActRequest, policy: Loaded) -> np.ndarray:
        """uint8 (C, H, W) codes for ``policy``; ValueError with a hold reason when it cannot be built."""
        if req.image is not None:
            if tuple(req.image.shape) != policy.image_shape:
                raise ValueError("bad_observation")
            return np.array(req.image)  # decoded arrays are read-only views of the payload
        if policy.observation != "voxel":  # only the voxel projection is rendered here
            raise ValueError("bad_observation")
        points, counts = req.points, req.point_counts
        if not np.isfinite(points).all():
            raise ValueError("non_finite_observation")
        if np.abs(points).max(initial=0.0) > MAX_POINT_RADIUS:
            raise ValueError("out_of_workspace")
        if (counts < 0).any():
            raise ValueError("bad_observation")
        jaw = np.array([np.clip(req.state[4], 0.0, 1.0)], np.float32)
        return segment_policy_images(points[None], counts[None], jaw)[0]

    @staticmethod
    def _reply(req: ActRequest, episode: int, action: np.ndarray, version: int, held: bool,
               reasons: tuple[str, ...], t0: float) -> ActReply:  # fmt: skip
        return ActReply(session=req.session, episode=episode, step=req.step,
                        action=np.asarray(action, np.float32), policy_version=version, held=held,
                        reasons=list(reasons), compute_seconds=time.perf_counter() - t0,
                        nonce=req.nonce)  # fmt: skip
