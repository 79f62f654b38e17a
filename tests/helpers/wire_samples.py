"""Seeded valid messages of every wire type, and their wire maps, for the codec contract tests.

One generator per message type (``rng -> message``: many shapes and dtypes, including empty and
edge values); ``test_every_registered_type_has_generators`` fails when a message type is added to
the registry without one. Deterministic in the seed; free of pytest.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from collections.abc import Callable
from typing import Any

import numpy as np

import proto
from proto.actions import ACTION_DIM
from proto.codec import Message
from proto.control import ACK_WINDOW, SERVICES, STATES, EpisodeAck, EvalReport, Heartbeat, ReplayGate
from proto.episode import AUGMENTATION_KINDS, POLICY_KINDS, TASKS, Augmentation, Episode
from proto.inference import OBSERVATIONS, STATE_DIM, ActReply, ActRequest, EStop, ResetReply, ResetRequest
from proto.weights import ALGORITHMS, WeightsAnnouncement, WeightsBlob

# make sure every proto module has registered its messages before the registry is inspected
for _mod in pkgutil.iter_modules(proto.__path__):
    importlib.import_module(f"proto.{_mod.name}")

SEED = 20240611
ID_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"


def rand_id(rng: np.random.Generator, max_len: int = 24) -> str:
    n = int(rng.integers(1, max_len + 1))
    return "".join(ID_CHARS[i] for i in rng.integers(0, len(ID_CHARS), n))


def rand_time(rng: np.random.Generator) -> float:
    return float(rng.choice([0.0, 1_700_000_000.0 + rng.random() * 1e6, rng.random()]))


def rand_finite(rng: np.random.Generator, shape: tuple[int, ...], dtype: Any = np.float32) -> np.ndarray:
    return (rng.standard_normal(shape) * rng.choice([1e-3, 1.0, 1e3])).astype(dtype)


def gen_augmentation(rng: np.random.Generator, max_phase: int = 50) -> Augmentation:
    phase = int(rng.integers(0, max_phase + 1))
    params = {"rotation": rand_finite(rng, (1,)), "delta_r": rand_finite(rng, (phase,), np.float64)}
    if rng.random() < 0.5:
        params["flip:index"] = rng.integers(-(2**40), 2**40, size=int(rng.integers(0, 4)), dtype=np.int64)
    return Augmentation(
        source_episode_id=rand_id(rng),
        kind=str(rng.choice(AUGMENTATION_KINDS)),
        seed=int(rng.integers(0, 2**63 - 1, dtype=np.int64)),
        copy_index=int(rng.integers(0, 1_000_001)),
        phase_split=phase,
        params=params,
    )


def gen_episode(
    rng: np.random.Generator, *, images: bool | None = None, augmented: bool | None = None
) -> Episode:
    T = int(rng.integers(1, 7))
    S = int(rng.integers(1, 5))
    P = int(rng.integers(0, 6))
    images = bool(rng.random() < 0.5) if images is None else images
    augmented = bool(rng.random() < 0.5) if augmented is None else augmented
    ends = np.zeros(T, dtype=bool)
    ends[-1] = True
    truncated = bool(rng.random() < 0.5)
    actions = rng.uniform(-1.0, 1.0, (T, ACTION_DIM)).astype(np.float32)
    actions[0, 0] = rng.choice([-1.0, 1.0, 0.0])  # the bounds themselves are valid
    img = None
    if images:
        C, H, W = int(rng.choice([1, 3])), int(rng.integers(1, 9)), int(rng.integers(1, 9))
        dtype = rng.choice(["uint8", "uint16", "float16", "float32"])
        if dtype in ("uint8", "uint16"):
            img = rng.integers(0, np.iinfo(dtype).max + 1, (T + 1, C, H, W)).astype(dtype)
        else:
            img = rng.random((T + 1, C, H, W)).astype(dtype)
    return Episode(
        episode_id=rand_id(rng),
        task=str(rng.choice(TASKS)),
        seed=int(rng.integers(0, 2**63 - 1, dtype=np.int64)),
        actor_id=rand_id(rng),
        policy_version=int(rng.integers(-1, 1000)),
        policy_kind=str(rng.choice(POLICY_KINDS)),
        is_demo=bool(rng.random() < 0.5),
        created_at=rand_time(rng),
        segments=["gripper"] + [f"object_{i}" for i in range(S - 1)],
        points=rand_finite(rng, (T + 1, S, P, 3)),
        point_counts=rng.integers(0, 1000, (T + 1, S)).astype(np.int32),
        jaw=rng.uniform(0.0, 1.0, T + 1).astype(np.float32),
        actions=actions,
        rewards=rand_finite(rng, (T,)),
        terminated=ends & (not truncated),
        truncated=ends & truncated,
        gripper_pose=rand_finite(rng, (T + 1, 4)),
        object_poses=rand_finite(rng, (T + 1, S - 1, 7)),
        contacts=rng.random((T + 1, S - 1)) < 0.3,
        images=img,
        augmentation=gen_augmentation(rng, max_phase=T) if augmented else None,
    )


def gen_weights_announcement(rng: np.random.Generator) -> WeightsAnnouncement:
    return WeightsAnnouncement(
        version=int(rng.integers(0, 2**62, dtype=np.int64)),
        algorithm=str(rng.choice(ALGORITHMS)),
        digest=rng.bytes(32).hex(),
        byte_size=int(rng.integers(0, 2**40)),
        created_at=rand_time(rng),
        run_id=rand_id(rng),
    )


def gen_tensors(rng: np.random.Generator) -> dict[str, np.ndarray]:
    tensors: dict[str, np.ndarray] = {}
    for i in range(int(rng.integers(0, 6))):
        ndim = int(rng.integers(0, 5))
        shape = tuple(int(d) for d in rng.integers(0, 5, ndim))
        kind = rng.choice(["float32", "float16", "int64", "bool"])
        if kind == "bool":
            arr = rng.random(shape) < 0.5
        elif kind == "int64":
            arr = rng.integers(-(2**62), 2**62, shape, dtype=np.int64)
        else:
            arr = rand_finite(rng, shape, kind)
        tensors[f"layer{i}.{rand_id(rng, 8)}"] = np.asarray(arr, dtype=kind)
    return tensors


def gen_weights_blob(rng: np.random.Generator) -> WeightsBlob:
    tensors = gen_tensors(rng)
    blob = WeightsBlob.create(
        int(rng.integers(0, 2**62, dtype=np.int64)),
        str(rng.choice(ALGORITHMS)),
        rand_id(rng),
        tensors,
        config_json='{"hidden": [256, 256], "note": "ünïcödé ✓"}',
    )
    return dataclasses.replace(blob, created_at=rand_time(rng))


def gen_heartbeat(rng: np.random.Generator) -> Heartbeat:
    counters = {
        f"c{i}_{rand_id(rng, 6)}": float(rng.standard_normal() * 1e6) for i in range(int(rng.integers(0, 6)))
    }
    kwargs: dict[str, Any] = {}
    if rng.random() < 0.5:
        kwargs["detail"] = "last error: ✗ " + rand_id(rng, 40)
    return Heartbeat(
        service=str(rng.choice(SERVICES)),
        instance_id=rand_id(rng),
        pid=int(rng.integers(0, 2**31)),
        state=str(rng.choice(STATES)),
        started_at=rand_time(rng),
        created_at=rand_time(rng),
        policy_version=int(rng.integers(-1, 2**40)),
        counters=counters,
        **kwargs,
    )


def fixed_heartbeat(**changes: Any) -> Heartbeat:
    """A hand-written valid heartbeat (a learner's), with ``changes`` to its fields."""
    beat = Heartbeat(
        service="learner",
        instance_id="learner-0",
        pid=4242,
        state="running",
        started_at=1_700_000_000.0,
        created_at=1_700_000_001.5,
        policy_version=7,
        counters={"updates": 10.0, "replay.size": 1e6, "loss/critic": -0.25},
    )
    return dataclasses.replace(beat, **changes)


def fixed_eval_report(**changes: Any) -> EvalReport:
    """A hand-written valid evaluation report, with ``changes`` to its fields."""
    report = EvalReport(
        evaluator_id="evaluator-0",
        run_id="run-0",
        task="drawer_open",
        policy_version=3,
        env_steps=-1,
        episodes=20,
        success_rate=0.35,
        mean_return=-1.5,
        mean_length=47,  # ints are valid numbers (decoded as floats: not canonical bytes)
        grasp_score=0.0,
        created_at=1_700_000_000.0,
    )
    return dataclasses.replace(report, **changes)


def fixed_replay_gate() -> ReplayGate:
    """A hand-written valid replay gate."""
    return ReplayGate(
        learner_id="learner-0",
        run_id="run-0",
        inserted_steps=100,
        allowed_steps=150,
        updates=90,
        policy_version=-1,
        replay_transitions=1100,
        created_at=1_700_000_000.0,
    )


def gen_eval_report(rng: np.random.Generator) -> EvalReport:
    return EvalReport(
        evaluator_id=rand_id(rng),
        run_id=rand_id(rng),
        task=str(rng.choice(TASKS)),
        policy_version=int(rng.integers(0, 2**40)),
        env_steps=int(rng.integers(-1, 2**40)),
        episodes=int(rng.integers(1, 1_000_001)),
        success_rate=float(rng.random()),
        mean_return=float(rng.standard_normal() * 100),
        mean_length=float(rng.random() * 500),
        grasp_score=float(rng.random()),
        created_at=rand_time(rng),
    )


def gen_replay_gate(rng: np.random.Generator) -> ReplayGate:
    inserted = int(rng.integers(0, 2**40))
    return ReplayGate(
        learner_id=rand_id(rng),
        run_id=rand_id(rng),
        inserted_steps=inserted,
        allowed_steps=inserted + int(rng.integers(0, 1000)),
        updates=int(rng.integers(0, 2**40)),
        policy_version=int(rng.integers(-1, 2**40)),
        replay_transitions=int(rng.integers(0, 2**40)),
        created_at=rand_time(rng),
    )


def gen_episode_ack(rng: np.random.Generator) -> EpisodeAck:
    return EpisodeAck(
        learner_id=rand_id(rng),
        run_id=rand_id(rng),
        episode_ids=[rand_id(rng) for _ in range(int(rng.integers(0, ACK_WINDOW + 1)))],
        created_at=rand_time(rng),
    )


def special_floats32() -> np.ndarray:
    """float32 values a robot may put on the wire where nothing is range-checked: NaN (quiet, negative,
    signalling, with a payload), infinities, signed zero, a subnormal and the extremes."""
    nans = np.array([0x7FC00000, 0xFFC00000, 0x7F800001, 0x7FC0BEEF], np.uint32).view(np.float32)
    finite = np.array([-0.0, np.finfo(np.float32).max, -np.finfo(np.float32).max, 1e-45], np.float32)
    return np.concatenate([nans, np.array([np.inf, -np.inf], np.float32), finite])


def rand_any_float32(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Mostly finite float32, sometimes with special values (NaN payloads included) mixed in."""
    flat = rand_finite(rng, shape).reshape(-1)
    if flat.size and rng.random() < 0.5:
        special = special_floats32()
        for i in rng.integers(0, flat.size, int(rng.integers(1, flat.size + 1))):
            flat[i] = special[int(rng.integers(0, len(special)))]
    return flat.reshape(shape)


HOLD_REASONS = (
    "no_session",
    "stale_episode",
    "estop",
    "watchdog",
    "non_finite_observation",
    "out_of_workspace",
)
CLAMP_REASONS = ("workspace_x", "workspace_z", "step_xyz", "yaw_limit", "jaw")
"""Examples of ``ActReply.reasons`` (the wire only fixes the pattern ``[a-z_]{1,32}``)."""


def gen_reset_request(rng: np.random.Generator) -> ResetRequest:
    return ResetRequest(session=rand_id(rng), task=str(rng.choice(TASKS)), created_at=rand_time(rng))


def gen_reset_reply(rng: np.random.Generator) -> ResetReply:
    if rng.random() < 0.5:  # refused
        return ResetReply(session=rand_id(rng), accepted=False, reason="no weights yet ✗ " + rand_id(rng, 40),
                          episode=0, policy_version=-1, run_id="", observation="")  # fmt: skip
    return ResetReply(
        session=rand_id(rng),
        accepted=True,
        reason="",
        episode=int(rng.choice([1, int(rng.integers(1, 2**62, dtype=np.int64)), 2**62])),
        policy_version=int(rng.integers(0, 2**62, dtype=np.int64)),
        run_id=rand_id(rng),
        observation=str(rng.choice(OBSERVATIONS)),
    )


def gen_act_request(rng: np.random.Generator, *, points: bool | None = None) -> ActRequest:
    """One observation: points (with point_counts) or an image, never both (``ActRequest.validate``);
    ``state`` and ``executed`` may hold any float32, NaN and inf included."""
    points = bool(rng.random() < 0.5) if points is None else points
    step = int(rng.choice([0, int(rng.integers(1, 1_000_001)), 1_000_000]))
    obs: dict[str, Any] = {}
    if points:
        S, P = int(rng.integers(1, 5)), int(rng.integers(0, 7))
        obs["points"] = rand_any_float32(rng, (S, P, 3))
        obs["point_counts"] = rng.integers(0, 2**31 - 1, S).astype(np.int32)
    else:
        C, H, W = int(rng.choice([1, 2, 3])), int(rng.integers(1, 9)), int(rng.integers(1, 9))
        obs["image"] = rng.integers(0, 256, (C, H, W)).astype(np.uint8)
    executed = None if step == 0 or rng.random() < 0.2 else rand_any_float32(rng, (ACTION_DIM,))
    return ActRequest(
        session=rand_id(rng),
        episode=int(rng.integers(1, 2**62, dtype=np.int64)),
        step=step,
        stamp=rand_time(rng),
        state=rand_any_float32(rng, (STATE_DIM,)),
        executed=executed,
        **obs,
    )


def gen_act_reply(rng: np.random.Generator) -> ActReply:
    held = bool(rng.random() < 0.5)
    if held:
        action = np.array([rng.choice([-1.0, 1.0, rng.uniform(-1, 1)]), 0, 0, 0, 0], np.float32)
    else:
        action = rng.uniform(-1.0, 1.0, ACTION_DIM).astype(np.float32)
        action[int(rng.integers(0, ACTION_DIM))] = rng.choice([-1.0, 1.0, -0.0])  # the bounds are valid
    n_reasons = int(rng.integers(1 if held else 0, 17))
    reasons = HOLD_REASONS + CLAMP_REASONS if held else CLAMP_REASONS
    return ActReply(
        session=rand_id(rng),
        episode=int(rng.integers(0, 2**62, dtype=np.int64)),
        step=int(rng.integers(0, 1_000_001)),
        action=action,
        policy_version=int(rng.integers(-1, 2**40)),
        held=held,
        reasons=[str(rng.choice(reasons)) for _ in range(n_reasons)],
        compute_seconds=float(rng.choice([0.0, rng.random() * 0.05, rng.random() * 10])),
    )


def gen_estop(rng: np.random.Generator) -> EStop:
    kwargs: dict[str, Any] = {}
    if rng.random() < 0.5:
        kwargs["reason"] = "operator pressed the button ✋ " + rand_id(rng, 40)
    return EStop(
        operator_id=rand_id(rng), engaged=bool(rng.random() < 0.5), created_at=rand_time(rng), **kwargs
    )


GENERATORS: dict[str, Callable[[np.random.Generator], Message]] = {
    "Augmentation": gen_augmentation,
    "Episode": gen_episode,
    "WeightsAnnouncement": gen_weights_announcement,
    "WeightsBlob": gen_weights_blob,
    "Heartbeat": gen_heartbeat,
    "EvalReport": gen_eval_report,
    "ReplayGate": gen_replay_gate,
    "EpisodeAck": gen_episode_ack,
    "ResetRequest": gen_reset_request,
    "ResetReply": gen_reset_reply,
    "ActRequest": gen_act_request,
    "ActReply": gen_act_reply,
    "EStop": gen_estop,
}


def real_message_types() -> list[str]:
    """Registered top-level types, except throwaway ones that test modules may define.

    Nested-only types (Augmentation) are covered inside the messages that carry them."""
    return sorted(
        name
        for name, cls in Message._REGISTRY.items()
        if "test" not in cls.__module__.split(".")[0] and not cls.NESTED_ONLY
    )


def wire_of(msg: Message) -> dict[str, Any]:
    return {"_type": msg.TYPE, "_v": msg.VERSION, **msg.to_wire()}


def sample(type_name: str, seed: int = SEED) -> Message:
    return GENERATORS[type_name](np.random.default_rng(seed))


def episode(
    *, images: bool = False, augmented: bool = False, min_T: int = 1, min_S: int = 1, min_P: int = 1
) -> Episode:
    """A valid episode with at least the given sizes (deterministic)."""
    rng = np.random.default_rng(SEED)
    while True:
        ep = gen_episode(rng, images=images, augmented=augmented)
        _, S, P, _ = ep.points.shape
        if ep.num_steps >= min_T and min_S <= S and min_P <= P:
            return ep


def episode_wire(**kw: Any) -> dict[str, Any]:
    wire = wire_of(episode(**kw))
    for k, v in wire.items():
        if isinstance(v, np.ndarray):
            wire[k] = v.copy()
    return wire
