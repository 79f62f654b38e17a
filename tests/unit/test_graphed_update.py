"""GraphedUpdate's bookkeeping, on the CPU: eager warm-up, one capture per key, replays counted as
updates, outputs copied out of the graph's memory, and the eager fallback. torch.cuda's graph and
stream calls are stood in for by fakes that record the update at capture and run it at replay (what
a CUDA graph does, without a GPU); tests/unit/test_learner_device.py runs the real one on CUDA."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
import torch

from services.algorithms.sac import graphed
from services.algorithms.sac.graphed import MAX_GRAPHS, GraphedUpdate
from services.algorithms.sac.losses import Batch


class FakeGraph:
    capturing: FakeGraph | None = None

    def __init__(self) -> None:
        self.recorded = None

    def replay(self) -> None:
        self.recorded()


@contextmanager
def fake_capture(graph: FakeGraph, capture_error_mode: str = "global"):
    assert capture_error_mode == "thread_local"
    FakeGraph.capturing = graph
    try:
        yield
    finally:
        FakeGraph.capturing = None


class FakeStream:
    def wait_stream(self, other) -> None:
        pass


@pytest.fixture(autouse=True)
def fake_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "Stream", lambda device=None: FakeStream())
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: FakeStream())
    monkeypatch.setattr(torch.cuda, "stream", lambda s: contextmanager(lambda: (yield))())
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: None)
    monkeypatch.setattr(torch.cuda, "CUDAGraph", FakeGraph)
    monkeypatch.setattr(torch.cuda, "graph", fake_capture)


class Learner:
    """A stand-in update: adds the batch's reward sum to a weight, reports it; ``fail_capture`` makes
    a capture raise as a host read inside it would."""

    def __init__(self, fail_capture: bool = False) -> None:
        self.weight = torch.zeros(())
        self.updates = 0
        self.setting = 0
        self.fail_capture = fail_capture
        self.param = torch.zeros(2, requires_grad=True)

    def update(self, batch: Batch) -> dict:
        def apply() -> dict:
            self.weight += batch.rewards.sum()
            self.out["weight"].copy_(self.weight)
            return self.out

        if FakeGraph.capturing is not None:
            if self.fail_capture:
                raise RuntimeError("operation not permitted when stream is capturing\nmore")
            self.out = {"weight": torch.zeros(()), "constant": 2.0}
            FakeGraph.capturing.recorded = apply  # recorded: nothing is computed now
            self.param.grad = torch.ones(2)  # gradients allocated inside the capture
            return self.out
        self.weight += batch.rewards.sum()
        return {"weight": self.weight.clone(), "constant": 2.0}

    def count(self) -> None:
        self.updates += 1

    def graphed(self) -> GraphedUpdate:
        return GraphedUpdate(
            self.update, lambda: (self.setting,), [self.param], torch.device("cuda"), self.count, warmup=2
        )


def batch(reward: float, steps: int = 4) -> Batch:
    z = torch.zeros(1, steps)
    return Batch(
        images=torch.zeros(1, steps + 1, 1, 2, 2), actions=torch.zeros(1, steps, 5), rewards=z + reward,
        terminated=z, mask=z + 1,
    )  # fmt: skip


def test_warm_up_then_one_capture_replayed_and_counted_with_outputs_copied_out():
    learner = Learner()
    update = learner.graphed()
    seen = [float(update(batch(r))["weight"]) for r in (1.0, 2.0)]  # eager warm-up
    assert update.captures == 0 and learner.updates == 2
    outs = [update(batch(r)) for r in (3.0, 4.0, 5.0)]  # capture, then replays of the one graph
    assert update.captures == 1 and update.enabled and learner.updates == 5
    # every update applied once (the capture computed nothing), with this call's batch
    assert float(learner.weight) == 4 * (1 + 2 + 3 + 4 + 5)
    assert seen + [float(o["weight"]) for o in outs] == [4.0, 12.0, 24.0, 40.0, 60.0]  # not overwritten
    assert outs[0]["constant"] == 2.0


def test_a_new_shape_or_host_setting_is_captured_once_more_and_too_many_fall_back_to_eager():
    learner = Learner()
    update = learner.graphed()
    for _ in range(3):
        update(batch(1.0))
    update(batch(1.0, steps=6))  # another shape
    learner.setting = 1
    update(batch(1.0, steps=6))  # another host setting
    update(batch(1.0, steps=6))  # replayed
    assert update.captures == 3 and learner.updates == 6
    for k in range(2, 2 + MAX_GRAPHS - 3):  # new settings up to MAX_GRAPHS graphs
        learner.setting = k
        update(batch(1.0))
    assert update.captures == MAX_GRAPHS and update.enabled
    learner.setting = 99  # one key too many: a setting that changes every update
    update(batch(1.0))
    assert not update.enabled and update.captures == MAX_GRAPHS
    update(batch(1.0))
    assert learner.updates == 6 + MAX_GRAPHS - 3 + 2
    assert (
        float(learner.weight) == 4 * (learner.updates - 3) + 6 * 3
    )  # three 6-step batches, each applied once


def test_a_capture_the_update_does_not_allow_leaves_it_eager_with_one_warning(caplog):
    learner = Learner(fail_capture=True)
    update = learner.graphed()
    with caplog.at_level("WARNING", logger=graphed.__name__):
        for r in (1.0, 1.0, 1.0, 1.0):
            update(batch(r))
    assert not update.enabled and update.captures == 0
    assert learner.updates == 4 and float(learner.weight) == 16.0  # the failed capture's update ran eagerly
    assert learner.param.grad is None
    (record,) = caplog.records
    assert record.reason == "operation not permitted when stream is capturing"


def test_graphs_are_refused_off_cuda():
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device, not cpu"):
        GraphedUpdate(lambda b: {}, lambda: (), [], torch.device("cpu"), lambda: None)
