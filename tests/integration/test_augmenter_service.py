"""The augmenter service on the in-process bus: outputs, provenance, order, shards, bad input, audit."""

from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np
import pytest

from proto.control import Heartbeat
from proto.episode import Episode
from proto.topics import EPISODES_AUGMENTED, EPISODES_RAW, STATUS
from services.augmenter.audit_worker import Auditor
from services.augmenter.config import AugmenterConfig
from services.augmenter.core.mea import augment
from services.augmenter.core.pipeline import AugmentSettings, augment_episode, episode_seed
from services.augmenter.core.routing import output_kind, shard_of
from services.augmenter.main import run
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.common.metrics import ServiceMetrics
from services.observation.projection import (
    observation_channels,
    project_batch,
    quantize,
    segments_to_points,
)
from tests.helpers import BASE_TIME
from tests.helpers.synthetic import synthetic_episode

pytestmark = pytest.mark.integration
INSTANCE = "augmenter-t"


def demo(seed: int, actor_id: str = "actor-0", T: int = 20) -> Episode:
    """A successful scripted demonstration whose gripper follows its actions (MEA applies fully)."""
    ep, _ = synthetic_episode(seed, T=T)
    return dataclasses.replace(
        ep, episode_id=f"{actor_id}-{seed}-0", actor_id=actor_id, created_at=BASE_TIME + seed
    )


def random_episode(seed: int, actor_id: str = "actor-0") -> Episode:
    """A successful non-demo episode (random policy) with the same motion properties."""
    return dataclasses.replace(demo(seed, actor_id), is_demo=False, policy_kind="random")


def service_cfg(**kw) -> AugmenterConfig:
    svc = ServiceConfig(instance_id=INSTANCE, metrics_port=0, log_format="text", heartbeat_seconds=30.0)
    return AugmenterConfig(service=svc, **kw)


@dataclasses.dataclass
class Ran:
    outputs: list  # Deliveries on EPISODES_AUGMENTED, in arrival order
    heartbeat: Heartbeat  # the service's last heartbeat (published on exit)
    bus: InProcBus  # the service's own bus (its stats feed mea_bus_* metrics)


def run_service(cfg: AugmenterConfig, messages: list, audit=None, timeout: float = 60.0) -> Ran:
    """Run the service in a thread until it has received ``cfg.max_episodes`` valid episodes.

    ``messages`` are Episodes (published under their actor id) or raw bytes (published as-is,
    under source ``bad``). Publishing starts once the service holds its liveliness token, which it
    declares after subscribing."""
    assert cfg.max_episodes > 0
    hub = Hub()
    observer = InProcBus(hub)
    outputs = observer.subscribe(EPISODES_AUGMENTED, capacity=1024)
    status = observer.subscribe(STATUS, capacity=64, service="augmenter")
    watch = observer.watch_alive("augmenter")
    buses: list[InProcBus] = []
    result: dict = {}

    def factory(_c):
        buses.append(InProcBus(hub))
        return buses[-1]

    def target():
        try:
            result["rc"] = run(cfg, bus_factory=factory, audit=audit)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test thread
            result["error"] = exc

    thread = threading.Thread(target=target, name="augmenter", daemon=True)
    thread.start()
    try:
        assert watch.wait_for(lambda alive: ("augmenter", INSTANCE) in alive, timeout), result
        for msg in messages:
            if isinstance(msg, Episode):
                observer.publish(EPISODES_RAW, msg, source=msg.actor_id)
            else:
                observer.publish(EPISODES_RAW, msg, source="bad")
        thread.join(timeout)
        assert not thread.is_alive(), "the augmenter did not stop after max_episodes"
    finally:
        observer.close()  # unblocks a service stuck on a full queue, if the test failed
    if "error" in result:
        raise result["error"]
    assert result["rc"] == 0
    beats = [d.message for d in status.drain() if d.message.instance_id == INSTANCE]
    assert beats, "no heartbeat from the augmenter"
    return Ran(outputs.drain(), beats[-1], buses[0])


def by_source(outputs) -> dict[str, list[Episode]]:
    out: dict[str, list[Episode]] = {}
    for d in outputs:
        ep = d.message
        src = ep.episode_id if ep.augmentation is None else ep.augmentation.source_episode_id
        out.setdefault(src, []).append(ep)
    return out


@pytest.mark.timeout(120)
def test_demo_gives_raw_then_four_isometric_then_six_mea_copies_with_provenance_and_images():
    raw = demo(1)
    settings = AugmentSettings()
    ran = run_service(service_cfg(augment=settings, max_episodes=1), [raw])
    assert all(d.parts == {"source": INSTANCE} for d in ran.outputs)
    eps = [d.message for d in ran.outputs]
    assert [output_kind(e) for e in eps] == ["raw"] + ["isometric"] * 4 + ["mea"] * 6  # raw first
    seed = episode_seed(settings.seed, raw.episode_id)

    first = eps[0]
    assert first.augmentation is None and first.episode_id == raw.episode_id
    assert np.array_equal(first.actions, raw.actions) and np.array_equal(first.points, raw.points)
    for k, e in enumerate(eps[1:5]):
        a = e.augmentation
        assert (a.kind, a.source_episode_id, a.seed, a.copy_index) == ("isometric", raw.episode_id, seed, k)
        assert e.episode_id == f"{raw.episode_id}.iso{k}" and e.num_steps == raw.num_steps
    phis = set()
    for k, e in enumerate(eps[5:]):
        a = e.augmentation
        assert (a.kind, a.source_episode_id, a.seed, a.copy_index) == (
            "mea+isometric",
            raw.episode_id,
            seed,
            k,
        )
        assert e.episode_id == f"{raw.episode_id}.mea{k}" and 1 <= a.phase_split <= e.num_steps
        phis.add(float(a.params["rotation"][0]))
    assert len(phis) == 1  # G_t x G: one shared isometric rotation for the episode's MEA copies

    # every output carries its uint8 policy images: exactly the reference projection of its clouds
    spec = settings.projection
    for e in eps:
        assert e.images is not None and e.images.dtype == np.uint8
        assert e.images.shape == (e.num_steps + 1, 2, spec.size, spec.size)
        pts, valid = segments_to_points(e.points, e.point_counts)
        ref = quantize(observation_channels(project_batch(pts, spec, valid), e.jaw, spec), spec)
        assert np.array_equal(e.images, ref), e.episode_id

    # what went over the bus is what the pipeline makes locally, byte for byte
    local, _ = augment_episode(raw, settings)
    assert [e.encode() for e in eps] == [e.encode() for e in local]
    c = ran.heartbeat.counters
    assert (c["episodes_in"], c["episodes_out"], c["skipped_shard"], c["failed"]) == (1, 11, 0, 0)
    assert c["transitions_out"] == sum(e.num_steps for e in eps)


@pytest.mark.timeout(120)
def test_mea_applies_to_demos_only_by_default_and_to_every_episode_with_mea_on_all():
    episodes = [random_episode(2), demo(3)]
    ran = run_service(service_cfg(max_episodes=2), episodes)
    got = by_source(ran.outputs)
    assert [output_kind(e) for e in got[episodes[0].episode_id]] == ["raw"] + ["isometric"] * 4
    assert [output_kind(e) for e in got[episodes[1].episode_id]] == ["raw"] + ["isometric"] * 4 + ["mea"] * 6

    ran = run_service(service_cfg(augment=AugmentSettings(mea_on="all"), max_episodes=1), episodes[:1])
    kinds = [output_kind(d.message) for d in ran.outputs]
    assert kinds == ["raw"] + ["isometric"] * 4 + ["mea"] * 6

    ran = run_service(service_cfg(augment=AugmentSettings(mea_on="none"), max_episodes=1), [demo(3)])
    assert [output_kind(d.message) for d in ran.outputs] == ["raw"] + ["isometric"] * 4


@pytest.mark.timeout(120)
def test_invalid_payloads_are_counted_and_skipped_and_the_service_goes_on():
    hb = Heartbeat(service="actor", instance_id="actor-0", pid=1, state="running", started_at=1.0,
                   created_at=1.0, policy_version=-1, counters={})  # fmt: skip
    good = demo(4)
    messages = [b"\x00not msgpack", hb.encode(), good.encode()[:-7], good]
    ran = run_service(service_cfg(max_episodes=1), messages)
    assert ran.bus.stats.bad["episodes_raw"] == 3  # exported as mea_bus_rejected_messages_total
    assert ran.bus.stats.received["episodes_raw"] == 1
    assert list(by_source(ran.outputs)) == [good.episode_id]
    assert len(ran.outputs) == 11 and ran.heartbeat.counters["failed"] == 0


@pytest.mark.timeout(120)
def test_only_the_shard_s_actors_are_processed_in_per_actor_order_and_a_full_queue_drops_nothing():
    actors = [f"actor-{i}" for i in range(8)]
    shards = {a: shard_of(a, 2) for a in actors}
    assert set(shards.values()) == {0, 1}  # both shards have actors
    episodes = [demo(10 * i + k, actor_id=a) for k in range(2) for i, a in enumerate(actors)]
    # queue=1: the publisher waits on the full queue (backpressure); every episode still arrives
    ran = run_service(service_cfg(shard=1, shards=2, queue=1, max_episodes=len(episodes)), episodes)
    mine = [e for e in episodes if shards[e.actor_id] == 1]
    raws = [d.message for d in ran.outputs if d.message.augmentation is None]
    assert [e.episode_id for e in raws] == [e.episode_id for e in mine]  # publication order kept
    got = by_source(ran.outputs)
    assert set(got) == {e.episode_id for e in mine}
    assert all(len(v) == 11 for v in got.values())
    c = ran.heartbeat.counters
    assert c["episodes_in"] == len(mine) and c["skipped_shard"] == len(episodes) - len(mine)
    assert c["episodes_out"] == 11 * len(mine)


def test_config_refuses_a_shard_outside_the_shards_and_bad_fractions():
    with pytest.raises(ValueError, match="shard"):
        AugmenterConfig(shard=2, shards=2)
    with pytest.raises(ValueError, match="audit_fraction"):
        AugmenterConfig(audit_fraction=1.5)
    assert shard_of("actor-3", 1) == 0 and shard_of("actor-3", 5) == shard_of("actor-3", 5)


class StubAudit:
    """Records what it audits; every transition valid except the first of each copy."""

    def __init__(self, fail_on: str = "") -> None:
        self.calls: list[tuple[Episode, Episode]] = []
        self.fail_on = fail_on

    def __call__(self, copy: Episode, source: Episode) -> np.ndarray:
        self.calls.append((copy, source))
        if copy.episode_id == self.fail_on:
            raise RuntimeError("physics exploded")
        valid = np.ones(copy.num_steps, bool)
        valid[0] = False
        return valid


@pytest.mark.timeout(120)
def test_audit_hook_sees_every_mea_copy_unrotated_and_reports_the_valid_fraction():
    raw = demo(5)
    stub = StubAudit()
    ran = run_service(service_cfg(audit_fraction=1.0, audit_queue=16, max_episodes=1), [raw], audit=stub)
    assert len(stub.calls) == 6
    seed = episode_seed(0, raw.episode_id)
    for k, (copy, source) in enumerate(sorted(stub.calls, key=lambda c: c[0].augmentation.copy_index)):
        assert source.episode_id == raw.episode_id
        assert copy.augmentation.kind == "mea" and copy.augmentation.copy_index == k
        # the copy before the shared isometric rotation, as the pipeline draws it
        expected, _ = augment(raw, AugmentSettings().mea, np.random.default_rng([seed, 1_000_001 + k]),
                              seed=seed, copy_index=k, episode_id=f"{raw.episode_id}.mea{k}")  # fmt: skip
        assert copy.encode() == expected.encode()
    steps = sum(c.num_steps for c, _ in stub.calls)
    c = ran.heartbeat.counters
    assert c["audited_copies"] == 6
    assert c["audit_valid_fraction"] == pytest.approx((steps - 6) / steps)


def test_auditor_picks_a_stable_fraction_counts_errors_and_never_blocks():
    raw = demo(6)
    outputs, _ = augment_episode(raw, AugmentSettings(reproject=False))
    metrics = ServiceMetrics("augmenter", "t")
    gauge = "mea_augmenter_audit_valid_ratio"
    stub = StubAudit(fail_on=f"{raw.episode_id}.mea0")
    auditor = Auditor(1.0, AugmentSettings(), metrics, audit=stub, capacity=2)
    assert math.isnan(metrics.registry.get_sample_value(gauge))
    # not started: the queue fills at 2 copies and the rest are skipped, without blocking
    assert auditor.offer(raw, outputs) == 2 and auditor.skipped == 4
    auditor.start()
    try:
        assert auditor.wait_idle(30.0)
    finally:
        auditor.close()
    assert auditor.errors == 1 and auditor.copies == 1
    assert metrics.registry.get_sample_value("mea_augmenter_audited_copies_total", {"result": "error"}) == 1
    assert metrics.registry.get_sample_value(gauge) == pytest.approx(auditor.valid_fraction)
    assert 0 < auditor.valid_fraction < 1

    off = Auditor(0.0, AugmentSettings(), ServiceMetrics("augmenter", "t"), audit=stub)
    assert off.offer(raw, outputs) == 0
    half = Auditor(0.5, AugmentSettings(), ServiceMetrics("augmenter", "t"), audit=stub)
    ids = [f"actor-{i}-{i}-0.mea{k}" for i in range(400) for k in range(6)]
    picked = [half.chosen(i) for i in ids]
    assert 0.45 < np.mean(picked) < 0.55 and picked == [half.chosen(i) for i in ids]
