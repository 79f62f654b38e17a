"""Generic test helpers: free ports and deterministic message factories.

Kept free of pytest so that spawned child processes can import them (``tests.helpers...``).
Everything here is deterministic in its ``seed``: two processes building the same message with
the same arguments get byte-identical encodings.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable

import numpy as np

from mea_tools.bench.harness import free_port
from proto.actions import ACTION_DIM
from proto.codec import Message
from proto.episode import Episode
from proto.msgpack_wire import pack
from proto.weights import WeightsBlob

SEGMENTS = ("gripper", "object_0", "object_1")
"""Segment names of every factory-made episode: the gripper, then two objects."""
BASE_TIME = 1_700_000_000.0
"""``created_at`` of factory-made episodes is ``BASE_TIME + seed`` (deterministic)."""

_issued_ports: set[int] = set()
_port_lock = threading.Lock()


def port_is_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def find_free_port_base(offsets: tuple[int, ...], avoid: set[int] = frozenset()) -> int:  # type: ignore[assignment]
    """A `mea run --metrics-port` base whose ports ``base + offset`` are all free (and not in ``avoid``)."""
    for _ in range(200):
        base = free_port()
        ports = {base + o for o in offsets}
        if base + max(offsets) < 65535 and not ports & avoid and all(port_is_free(p) for p in ports):
            return base
    raise RuntimeError("no free port base")


def find_free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, never the same one twice per process."""
    for _ in range(100):
        port = free_port()
        with _port_lock:
            if port not in _issued_ports:
                _issued_ports.add(port)
                return port
    raise RuntimeError("no free port found on 127.0.0.1")


def poll_until(predicate: Callable[[], object], seconds: float, every: float = 0.05) -> bool:
    """Whether ``predicate()`` came true within ``seconds``, asked every ``every`` s (a bounded poll)."""
    deadline = time.monotonic() + seconds
    while not predicate() and time.monotonic() < deadline:
        time.sleep(every)
    return bool(predicate())


def stop_process(proc: subprocess.Popen, timeout: float = 20.0) -> None:
    """SIGTERM a process started with ``start_new_session=True`` that still runs; SIGKILL its
    process group when it has not ended ``timeout`` seconds later."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def build_episode(
    T: int = 8,
    seed: int = 0,
    *,
    with_images: bool = False,
    P: int = 16,
    actor_id: str = "actor-0",
    task: str = "block_pull",
    truncated: bool = False,
    image_shape: tuple[int, int, int] = (3, 32, 32),
    validate: bool = True,
    **overrides: object,
) -> Episode:
    """A small valid raw Episode: segments gripper/object_0/object_1, ``P`` points each, ``T`` steps.

    Actions are float32 in [-1, 1]; only the last step ends the episode (terminated, or truncated
    when ``truncated=True``). ``overrides`` replace fields afterwards (pass ``validate=False`` to
    build a deliberately invalid episode).
    """
    if T < 1:
        raise ValueError("an episode needs T >= 1")
    rng = np.random.default_rng(seed)
    S = len(SEGMENTS)
    points = (rng.standard_normal((T + 1, S, P, 3)) * 0.05).astype(np.float32)
    point_counts = rng.integers(0, 4 * P, size=(T + 1, S)).astype(np.int32)
    jaw = rng.uniform(0.0, 1.0, T + 1).astype(np.float32)
    actions = np.clip(rng.uniform(-1.0, 1.0, (T, ACTION_DIM)), -1.0, 1.0).astype(np.float32)
    rewards = rng.standard_normal(T).astype(np.float32)
    ends = np.zeros(T, dtype=bool)
    ends[-1] = True
    gripper_pose = rng.uniform(-0.5, 0.5, (T + 1, 4)).astype(np.float32)
    quats = rng.standard_normal((T + 1, S - 1, 4))
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    positions = rng.uniform(-0.5, 0.5, (T + 1, S - 1, 3))
    object_poses = np.concatenate([positions, quats], axis=-1).astype(np.float32)
    contacts = rng.random((T + 1, S - 1)) < 0.2
    images = rng.integers(0, 256, (T + 1, *image_shape), dtype=np.uint8) if with_images else None
    ep = Episode(
        episode_id=f"{actor_id}-{seed}-0",
        task=task,
        seed=seed,
        actor_id=actor_id,
        policy_version=-1,
        policy_kind="random",
        is_demo=False,
        created_at=BASE_TIME + seed,
        segments=list(SEGMENTS),
        points=points,
        point_counts=point_counts,
        jaw=jaw,
        actions=actions,
        rewards=rewards,
        terminated=ends & (not truncated),
        truncated=ends & truncated,
        gripper_pose=gripper_pose,
        object_poses=object_poses,
        contacts=contacts,
        images=images,
    )
    if overrides:
        ep = dataclasses.replace(ep, **overrides)
    if validate:
        ep = Episode.from_wire(ep.to_wire())  # raises ProtocolError if the result is not a valid Episode
    return ep


def build_weights(
    version: int,
    *,
    nbytes: int = 64 * 1024,
    seed: int = 0,
    run_id: str = "run-0",
    algorithm: str = "rsac",
) -> WeightsBlob:
    """A WeightsBlob of about ``nbytes`` of tensors (float32 bulk plus a few small tensors)."""
    rng = np.random.default_rng(seed)
    n_bulk = max(1, nbytes // 4 - 64)
    tensors = {
        "actor.fc.weight": rng.standard_normal(n_bulk).astype(np.float32).reshape(-1, 1),
        "actor.fc.bias": rng.standard_normal(16).astype(np.float32),
        "critic.head.weight": rng.standard_normal((4, 8)).astype(np.float16),
        "log_alpha": np.array(0.1, dtype=np.float32),
        "num_updates": np.array([version], dtype=np.int64),
        "mask": rng.random(8) < 0.5,
    }
    return WeightsBlob.create(version, algorithm, run_id, tensors, config_json='{"hidden": 16}')


def message_diff(a: Message, b: Message) -> list[str]:
    """Names of the fields whose encodings differ (empty when the messages are equal)."""
    if type(a) is not type(b):
        return [f"<type {type(a).__name__} != {type(b).__name__}>"]
    wa, wb = a.to_wire(), b.to_wire()
    return [name for name in wa if pack(wa[name]) != pack(wb[name])]


def assert_messages_equal(a: Message, b: Message) -> None:
    """Equal type, equal fields (arrays by dtype, shape and bytes) and byte-identical encodings."""
    diff = message_diff(a, b)
    assert not diff, f"{type(a).__name__} differs in {diff}"
    assert a.encode() == b.encode()
