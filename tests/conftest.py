"""Shared fixtures: free ports, a Zenoh router on 127.0.0.1, message factories, a seeded RNG.

The factories themselves live in :mod:`tests.helpers` so that spawned child processes can build
the very same (deterministic) messages.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `tests.helpers` must import here and in spawned children
    sys.path.insert(0, str(ROOT))

# detailed failures from the shared assertions
pytest.register_assert_rewrite(
    "tests.helpers.wire_asserts", "tests.helpers.env_asserts", "tests.helpers.tiny_nets", "tests.helpers.cli"
)

from proto.episode import Episode  # noqa: E402
from proto.weights import WeightsBlob  # noqa: E402
from tests.helpers import build_episode, build_weights, find_free_port  # noqa: E402

SEED = 20240611
"""Seed of the ``seeded_rng`` fixture."""


@pytest.fixture
def free_port() -> Callable[[], int]:
    """A function returning a free TCP port on 127.0.0.1 (a different one on each call)."""
    return find_free_port


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """Torch on one thread for a module's tests (``pytest.mark.usefixtures("one_torch_thread")``):
    as the services run, and another thread count sums in another order (bit-for-bit comparisons)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def zenoh_router() -> Iterator[str]:
    """A Zenoh router (ZenohBus in router mode) on ``tcp/127.0.0.1:<free port>``; yields the endpoint.

    Multicast scouting is off and the router connects nowhere: peers and clients reach it with
    ``ZenohConfig(mode=..., connect=(endpoint,))`` (see ``tests.helpers.zenoh_peer.peer_config``).
    """
    import zenoh

    from services.common.bus.zenoh_bus import ZenohBus
    from tests.helpers.zenoh_peer import endpoint_for, router_config

    last_error: Exception | None = None
    for _ in range(3):  # the port can be taken between probing and binding; try another
        endpoint = endpoint_for(find_free_port())
        try:
            router = ZenohBus(router_config(endpoint))
        except zenoh.ZError as exc:
            last_error = exc
            continue
        try:
            yield endpoint
        finally:
            router.close()
        return
    raise RuntimeError(f"could not start a Zenoh router on 127.0.0.1: {last_error}")


@pytest.fixture
def make_episode() -> Callable[..., Episode]:
    """Factory: ``make_episode(T=8, seed=0, with_images=False, P=16, actor_id=..., **overrides)``.

    A valid raw Episode with segments gripper/object_0/object_1, float32 actions in [-1, 1] and
    only the last step terminated (``truncated=True`` truncates it instead). Deterministic in
    ``seed``; see :func:`tests.helpers.build_episode`.
    """
    return build_episode


@pytest.fixture
def make_weights() -> Callable[..., WeightsBlob]:
    """Factory: ``make_weights(version, nbytes=64 KiB, seed=0, run_id="run-0", algorithm="rsac")``."""
    return build_weights


@pytest.fixture
def seeded_rng() -> np.random.Generator:
    """A fresh numpy Generator seeded with :data:`SEED` (the same stream in every test)."""
    return np.random.default_rng(SEED)
