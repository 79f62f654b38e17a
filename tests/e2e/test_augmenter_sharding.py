"""Two augmenter processes (shards 0 and 1 of 2) over real Zenoh on 127.0.0.1: every raw episode is
augmented exactly once, by the augmenter of its actor's shard, and per-actor order is kept."""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import time
from collections import Counter

import pytest

from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW
from services.augmenter.core.pipeline import AugmentSettings, augment_episode
from services.augmenter.core.routing import shard_of
from services.common.bus.zenoh_bus import ZenohBus
from tests.helpers import BASE_TIME
from tests.helpers.synthetic import synthetic_episode
from tests.helpers.zenoh_peer import peer_config

pytestmark = pytest.mark.e2e
CTX = mp.get_context("spawn")
SHARDS = 2
ACTORS = [f"actor-{i}" for i in range(6)]
PER_ACTOR = 3
STEP_TIMEOUT = 60.0


def augmenter_child(argv: list[str]) -> None:
    """Child entry (spawned): die with the test process, then run `mea augmenter argv`."""
    import sys

    from services.augmenter.main import main
    from services.common.runtime import die_with_parent

    die_with_parent()
    sys.exit(main(argv))


def raw_episode(actor_id: str, k: int) -> Episode:
    seed = 100 * ACTORS.index(actor_id) + k
    ep, _ = synthetic_episode(seed, T=12 + k)
    # odd k: a random-policy episode (no MEA with the default mea_on=demos)
    return dataclasses.replace(ep, episode_id=f"{actor_id}-{seed}-{k}", actor_id=actor_id,
                               created_at=BASE_TIME + seed, is_demo=k % 2 == 0,
                               policy_kind="expert_direct" if k % 2 == 0 else "random")  # fmt: skip


def source_of(ep: Episode) -> str:
    return ep.episode_id if ep.augmentation is None else ep.augmentation.source_episode_id


@pytest.mark.timeout(180)
def test_two_sharded_augmenters_process_every_raw_episode_exactly_once(zenoh_router):
    assert {shard_of(a, SHARDS) for a in ACTORS} == {0, 1}  # both augmenters get work
    raws = [raw_episode(a, k) for k in range(PER_ACTOR) for a in ACTORS]  # actors interleaved
    expected = {ep.episode_id: len(augment_episode(ep, AugmentSettings())[0]) for ep in raws}
    instances = [f"augmenter-{s}" for s in range(SHARDS)]
    procs = []
    bus = None
    try:
        bus = ZenohBus(peer_config(zenoh_router, "client"))
        outputs = bus.subscribe(EPISODES_AUGMENTED, capacity=1024)
        watch = bus.watch_alive("augmenter")
        for shard, instance in enumerate(instances):
            argv = ["--shard", str(shard), "--shards", str(SHARDS), "--max-episodes", str(len(raws)),
                    "--service.instance-id", instance, "--service.zenoh.mode", "client",
                    "--service.zenoh.connect", zenoh_router, "--service.metrics-port", "0",
                    "--service.log-format", "text"]  # fmt: skip
            p = CTX.Process(target=augmenter_child, args=(argv,), name=instance, daemon=True)
            p.start()
            procs.append(p)
        # each augmenter subscribes before declaring its token: once both tokens are seen, publish
        deadline = time.monotonic() + STEP_TIMEOUT
        while not watch.wait_for(lambda alive: all(("augmenter", i) in alive for i in instances), 1.0):
            assert all(p.is_alive() for p in procs), [p.exitcode for p in procs]
            assert time.monotonic() < deadline, "augmenters not alive in time"
        for ep in raws:
            bus.publish(EPISODES_RAW, ep, source=ep.actor_id)

        got: list[tuple[str, Episode]] = []
        while len(got) < sum(expected.values()):
            d = outputs.recv(timeout=STEP_TIMEOUT)
            assert d is not None, f"{len(got)} of {sum(expected.values())} outputs after {STEP_TIMEOUT} s"
            got.append((d.parts["source"], d.message))
        for p in procs:  # both stop by themselves after receiving every raw episode (--max-episodes)
            p.join(STEP_TIMEOUT)
            assert p.exitcode == 0, (p.name, p.exitcode)
        assert outputs.recv(timeout=1.0) is None  # nothing more (no duplicate) arrives afterwards
        assert bus.stats.bad["episodes_augmented"] == 0
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
            p.join(10.0)
        if bus is not None:
            bus.close()

    per_source = Counter(source_of(ep) for _, ep in got)
    assert per_source == Counter(expected)  # every raw episode, all its outputs, exactly once
    by_id = {ep.episode_id: ep for ep in raws}
    for instance, ep in got:
        actor = by_id[source_of(ep)].actor_id
        assert instance == f"augmenter-{shard_of(actor, SHARDS)}", (instance, ep.episode_id)
    assert {instance for instance, _ in got} == set(instances)
    # per actor, raw episodes come out in the order that actor published them, each before its copies
    for actor in ACTORS:
        order = [ep.episode_id for _, ep in got if ep.augmentation is None and ep.actor_id == actor]
        assert order == [ep.episode_id for ep in raws if ep.actor_id == actor]
    seen: set[str] = set()
    for _, ep in got:
        if ep.augmentation is None:
            seen.add(ep.episode_id)
        else:
            assert ep.augmentation.source_episode_id in seen  # raw first
