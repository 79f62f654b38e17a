"""The Equi-RSAC learner on a torch device (`--device`, `--learner-device`): device names checked in one
line, batches copied to the device, statistics left there and read every N updates as means (the same
numbers), published weights and checkpoints on the CPU so a run resumes across devices.

Everything runs on the CPU here; the tests marked ``cuda`` need a GPU and skip, saying so, where
there is none (``tools/gpu-check.sh`` runs them on one)."""

from __future__ import annotations

import dataclasses
import json
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

from proto.topics import EPISODES_AUGMENTED, STATUS, WEIGHTS_ANNOUNCE
from services.algorithms.batch import to_batch
from services.algorithms.networks import build_actor, build_critic
from services.algorithms.policy import PolicyRuntime
from services.algorithms.sac.agent import RecurrentSAC
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.config import SacSettings
from services.algorithms.trainer import MetricsWindow, Trainer
from services.common import config
from services.common.bus import Hub, InProcBus
from services.common.config import ServiceConfig
from services.learner import checkpoint, init_actor
from services.learner.config import LearnerConfig, build_trainer, check_device
from services.plan import config_for
from services.run_config import RunConfig, read_resume
from tests.helpers.learner import SIZE, TINY_NET, learner_episode, start_learner, tiny_learner_config

pytestmark = pytest.mark.unit
CUDA = torch.cuda.is_available()
needs_cuda = [
    pytest.mark.cuda,
    pytest.mark.skipif(
        not CUDA,
        reason=f"CUDA is absent here (torch {torch.__version__}); tools/gpu-check.sh runs it on a GPU",
    ),
]
DEVICES = ["cpu", pytest.param("cuda", marks=needs_cuda)]
OWN_FILES = ("agent.py", "losses.py", "algorithm.py", "trainer.py", "batch.py", "tensors.py")
"""The update loop's own modules: none of them may wait for the device between metric reads."""


def filled_trainer(device: str = "cpu", episodes: int = 6, **kw) -> Trainer:
    trainer = build_trainer(tiny_learner_config(Path("unused"), ServiceConfig(), device=device, **kw))
    for k in range(episodes):
        trainer.insert(learner_episode(k, T=10 + k % 3, demo=k == 0))
    return trainer


READS = ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__", "__index__")
"""Tensor methods that bring a value to the host: on a GPU each one waits for the queued work."""


@contextmanager
def reads_back(monkeypatch: pytest.MonkeyPatch, device: str) -> Iterator[list[str]]:
    """Every value read from a ``device`` tensor by the update loop's own modules (``OWN_FILES``) while
    inside, as "file:line method"."""
    seen: list[str] = []

    def spy(name: str, original):
        def read(self, *args, **kwargs):
            caller = sys._getframe(1)
            where = Path(caller.f_code.co_filename).name
            if self.device.type == device and where in OWN_FILES:
                seen.append(f"{where}:{caller.f_lineno} {name}")
            return original(self, *args, **kwargs)

        return read

    with monkeypatch.context() as m:
        for name in READS:
            m.setattr(torch.Tensor, name, spy(name, getattr(torch.Tensor, name)))
        yield seen


@pytest.fixture(autouse=True)
def _restore_precision() -> Iterator[None]:
    """A CUDA trainer allows TF32 for the process (``prepare_device``): put it back for later tests."""
    matmul, cudnn = torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32
    yield
    torch.set_float32_matmul_precision(matmul)
    torch.backends.cudnn.allow_tf32 = cudnn


@contextmanager
def full_fp32() -> Iterator[None]:
    """fp32 matmuls, convolutions and cuDNN LSTMs in full precision inside (a CUDA learner allows
    TF32 for its process), restored after."""
    matmul, cudnn = torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32
    torch.set_float32_matmul_precision("highest")
    torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(matmul)
        torch.backends.cudnn.allow_tf32 = cudnn


def actor_output(actor: torch.nn.Module, seed: int = 3) -> torch.Tensor:
    """The actor's mean and log std (CPU) on a fixed random sequence, computed on the actor's device."""
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(2, 5, 2, SIZE, SIZE, generator=g)
    prev = torch.rand(2, 5, 5, generator=g) * 2 - 1
    device = next(actor.parameters()).device
    with torch.no_grad():
        mean, log_std, _ = actor(images.to(device), prev.to(device))
    return torch.cat([mean, log_std], -1).cpu()


# ------------------------------------------------------------------------------------------------
# device names
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", ["gpu", "cuda0", "cpu:1", "CUDA", "", "mps", "cuda:x"])
def test_a_device_name_that_is_not_cpu_or_cuda_is_refused_in_one_line(bad):
    with pytest.raises(ValueError, match=r"^--device must be cpu, cuda or cuda:N, not ") as err:
        LearnerConfig(device=bad)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"^--learner-device must be cpu, cuda or cuda:N"):
        RunConfig(learner_device=bad)


@pytest.mark.skipif(CUDA, reason="checks the refusal on a machine without CUDA; this one has it")
@pytest.mark.parametrize("name", ["cuda", "cuda:1"])
def test_cuda_where_there_is_none_is_refused_naming_the_option(name):
    with pytest.raises(ValueError, match=rf"^--learner-device '{name}': CUDA is unavailable here .*use cpu$"):
        RunConfig(learner_device=name)
    with pytest.raises(ValueError, match=rf"^--device '{name}': CUDA is unavailable here"):
        LearnerConfig(device=name)


@pytest.mark.parametrize("algorithm", ["equi_rsac", "rsac"])
def test_every_sac_learner_accepts_the_cpu_and_names_its_device(algorithm):
    group = "c4" if algorithm == "equi_rsac" else "none"
    cfg = LearnerConfig(SacConfig(algorithm, net=dataclasses.replace(TINY_NET, group=group)), device="cpu")
    assert cfg.metrics_every == 1  # the CPU reads each update's numbers, as before
    check_device("cpu", "--device")  # no exception


@pytest.mark.parametrize("name", ["cuda", "cuda:0"])
@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=f"CUDA is absent here (torch {torch.__version__})")
def test_cuda_is_accepted_where_it_is_and_reads_metrics_every_tensorboard_point(name):
    cfg = LearnerConfig(device=name, tensorboard_every=7)
    assert cfg.metrics_every == 7
    assert RunConfig(learner_device=name).learner_device == name
    with pytest.raises(ValueError, match=r"CUDA device\(s\), cuda:0"):
        LearnerConfig(device=f"cuda:{torch.cuda.device_count()}")


def test_a_resumed_run_takes_the_learner_device_from_the_command_line(tmp_path):
    # a run started on a GPU (saved "cuda") continues on this machine's --learner-device
    saved = config.to_jsonable(RunConfig(run_dir=tmp_path))
    saved["learner_device"] = "cuda:0"
    (tmp_path / "config.json").write_text(json.dumps(saved))
    resumed = read_resume(RunConfig(resume=tmp_path, learner_device="cpu"), given={"learner_device"})
    assert resumed.config.learner_device == "cpu" and resumed.config.resumes == 1
    # so are its torch threads, whatever the run was started with (a config.json from before the
    # setting existed included)
    del saved["learner_threads"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    two = read_resume(RunConfig(resume=tmp_path, learner_threads=2), given={"learner_threads"})
    assert two.config.learner_threads == 2 and config_for(two.config, tmp_path, "learner", 0).threads == 2
    assert config_for(RunConfig(), tmp_path, "learner", 0).threads == 1  # by default one: it shares the cores
    with pytest.raises(ValueError, match=r"^--learner-threads must be >= 0"):
        RunConfig(learner_threads=-1)
    with pytest.raises(ValueError, match="--task cannot change on --resume"):
        read_resume(RunConfig(resume=tmp_path, task="block_pick"), given={"task", "learner_device"})


# ------------------------------------------------------------------------------------------------
# batches, statistics
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_a_batch_on_the_device_holds_the_cpu_batch_bit_for_bit(device):
    trainer = filled_trainer()
    sample = trainer.replay.sample(4, np.random.default_rng(0), trim=True)
    ref, got = to_batch(sample), to_batch(sample, device)
    assert torch.equal(ref.actions, torch.from_numpy(sample.actions))  # the CPU shares the sample's arrays
    for name in ("images", "actions", "rewards", "terminated", "mask", "demo", "obs_mask"):
        a, b = getattr(ref, name), getattr(got, name)
        assert b.device.type == device and b.dtype == a.dtype, name
        assert torch.equal(b.cpu(), a), name
    assert ref.images.dtype == torch.float32 and float(ref.images.max()) <= 1.0


def test_update_is_update_tensors_read_as_floats_bit_for_bit():
    def sac() -> RecurrentSAC:
        torch.manual_seed(0)
        return RecurrentSAC(build_actor(TINY_NET), build_critic(TINY_NET), SacSettings(bc_weight=1.0))

    a, b = sac(), sac()
    sample = filled_trainer().replay.sample(4, np.random.default_rng(1), trim=True)
    for _ in range(2):
        torch.manual_seed(5)
        floats = a.update(to_batch(sample))
        torch.manual_seed(5)
        tensors = b.update_tensors(to_batch(sample))
        assert list(floats) == list(tensors) and "bc_loss" in floats
        assert all(isinstance(v, float) for v in floats.values())
        assert floats == {k: float(v) for k, v in tensors.items()}
    for p, q in zip(a.actor.parameters(), b.actor.parameters(), strict=True):
        assert torch.equal(p, q)


def test_the_metrics_window_gives_the_means_of_what_it_was_given_and_starts_again():
    w = MetricsWindow()
    w.add({"loss": torch.tensor(1.0), "bc_weight": 2.0})
    w.add({"loss": torch.tensor(4.0)})
    assert w.read() == {"loss": 2.5, "bc_weight": 2.0}
    assert w.read() == {}


def test_reading_every_n_updates_trains_the_same_and_reports_the_means():
    every, steps = 3, 6
    eager, lazy = filled_trainer(), filled_trainer()
    lazy.metrics_every = every
    per_update, reads = [], []
    for i in range(steps):
        torch.manual_seed(100 + i)
        per_update.append(eager.step())
        torch.manual_seed(100 + i)
        info = lazy.step()
        assert info is not None and info["batch_demo_share"] == per_update[-1]["batch_demo_share"]
        if (i + 1) % every:
            assert set(info) == {"batch_demo_share", "batch_reward_transitions"}
        else:
            reads.append(info)
    assert len(reads) == steps // every
    for r, window in zip(reads, (per_update[:every], per_update[every:]), strict=True):
        for key in ("critic_loss", "actor_loss", "alpha", "q1", "entropy", "actor_grad_norm"):
            assert r[key] == pytest.approx(np.mean([u[key] for u in window]), rel=1e-5, abs=1e-7), key
    for p, q in zip(eager.agent.actor.parameters(), lazy.agent.actor.parameters(), strict=True):
        assert torch.equal(p, q)  # the same training, bit for bit: only the reading differs


# ------------------------------------------------------------------------------------------------
# checkpoints and published weights cross devices
# ------------------------------------------------------------------------------------------------


def test_on_cpu_keeps_cpu_tensors_and_the_containers():
    t = torch.ones(2)
    state = {"a": t, "b": [t, (1, 2.0)], "c": {"d": "x"}}
    out = checkpoint.on_cpu(state)
    assert out["a"] is t and out["b"][0] is t and out["b"][1] == (1, 2.0) and type(out["b"][1]) is tuple
    assert out["c"] == {"d": "x"}


@pytest.mark.parametrize("trained_on", DEVICES)
@pytest.mark.parametrize("resumed_on", DEVICES)
def test_a_checkpoint_resumes_on_another_device_with_the_same_actor(tmp_path, trained_on, resumed_on):
    trainer = filled_trainer(trained_on)
    for _ in range(3):
        assert trainer.step() is not None
    lineage = checkpoint.Lineage(version=2, run_id="run", last={})
    path, _ = checkpoint.save_trainer(tmp_path, trainer, lineage, {"device": trained_on})
    # written from the CPU whatever the training device: loads anywhere without map_location
    raw = torch.load(path, weights_only=True)
    tensors = [v for v in _leaves(raw["learner"]) if isinstance(v, torch.Tensor)]
    assert tensors and {t.device.type for t in tensors} == {"cpu"}

    resumed = filled_trainer(resumed_on, episodes=0)
    assert checkpoint.restore_trainer(tmp_path, resumed)[0].version == 2
    assert resumed.updates == 3 and len(resumed.replay) == len(trainer.replay)
    # the same weights bit for bit; outputs as close as fp32 kernels of two devices get (cuDNN's may differ)
    with full_fp32():
        assert torch.allclose(
            actor_output(resumed.agent.actor), actor_output(trainer.agent.actor), rtol=1e-4, atol=1e-4
        )
    state, ref = resumed.agent.actor.state_dict(), trainer.agent.actor.state_dict()
    assert all(torch.equal(state[k].cpu(), ref[k].cpu()) for k in ref)
    assert resumed.agent.log_alpha.device.type == resumed_on
    opt_state = next(iter(resumed.agent.critic_opt.state.values()))
    assert opt_state["exp_avg"].device.type == resumed_on  # the optimiser's moments moved with it
    # torch's default Adam on either device, whichever wrote the optimiser's state (the fused one
    # refuses the transposed gradient einsum gives the mean head's irrep)
    assert not any(o.defaults.get("fused")
                   for o in (resumed.agent.actor_opt, resumed.agent.critic_opt, resumed.agent.alpha_opt))  # fmt: skip
    assert resumed.step() is not None and resumed.updates == 4  # and it trains on


def test_a_loaded_optimiser_state_keeps_this_learners_adam_not_its_writers():
    trainer = filled_trainer("cpu")
    assert trainer.step() is not None
    state = trainer.agent.state_dict()
    for name in ("actor_opt", "critic_opt", "alpha_opt"):  # as a fused, graphed CUDA learner wrote it
        for group in state[name]["param_groups"]:
            group.update(fused=True, capturable=True, foreach=False)
    resumed = filled_trainer("cpu")
    resumed.agent.load_state_dict(state)
    for opt in (resumed.agent.actor_opt, resumed.agent.critic_opt, resumed.agent.alpha_opt):
        for group in opt.param_groups:
            assert (group["fused"], group["capturable"], group["foreach"]) == (None, False, None)
        assert opt.state  # the moments came with it
    assert resumed.step() is not None and resumed.agent.updates == 2


@pytest.mark.parametrize("device", DEVICES)
def test_published_weights_are_numpy_on_the_cpu_and_act_like_the_trained_actor(device):
    trainer = filled_trainer(device)
    trainer.step()
    tensors = trainer.policy_tensors()
    assert all(isinstance(v, np.ndarray) for v in tensors.values())
    actor = build_actor(TINY_NET)
    actor.load_state_dict({k: torch.from_numpy(v) for k, v in tensors.items()})
    with full_fp32():
        assert torch.allclose(actor_output(actor), actor_output(trainer.agent.actor), rtol=1e-4, atol=1e-4)


def _leaves(x):
    if isinstance(x, dict):
        for v in x.values():
            yield from _leaves(v)
    elif isinstance(x, (list, tuple)):
        for v in x:
            yield from _leaves(v)
    else:
        yield x


# ------------------------------------------------------------------------------------------------
# the service: a run on the device, resumed on another
# ------------------------------------------------------------------------------------------------


def _run_learner(tmp_path: Path, device: str, resume: bool, max_updates: int) -> dict[str, float]:
    svc = ServiceConfig(instance_id="learner-d", metrics_port=0, log_format="text", heartbeat_seconds=0.2)
    cfg = tiny_learner_config(tmp_path, svc, device=device, resume=resume, max_updates=max_updates,
                              samples_per_insert=1.0, min_steps=20, error_buffer=30.0,
                              tensorboard_dir=tmp_path / "tb", tensorboard_every=3)  # fmt: skip
    hub = Hub()
    observer = InProcBus(hub)
    status = observer.subscribe(STATUS, capacity=1024, service="learner")
    announces = observer.subscribe(WEIGHTS_ANNOUNCE, capacity=256)
    thread, result = start_learner(cfg, hub, observer)
    for k in range(4):
        observer.publish(
            EPISODES_AUGMENTED, learner_episode(10 * max_updates + k, T=10), source="augmenter-0"
        )
    thread.join(timeout=120)
    assert not thread.is_alive() and result["rc"] == 0
    assert announces.drain()
    policy = PolicyRuntime(deterministic=True)
    policy.load(init_actor.read(tmp_path)[1])  # the newest version the run wrote, acting on this CPU
    assert np.all(np.abs(policy.act(np.zeros((2, SIZE, SIZE), np.uint8))) <= 1)
    return [d.message.counters for d in status.drain()][-1]


def test_the_learner_reading_metrics_every_n_updates_reports_them_and_resumes(tmp_path, monkeypatch):
    # on the CPU the learner reads each update; force the GPU's every-N reading to run its path here
    monkeypatch.setattr(LearnerConfig, "metrics_every", property(lambda self: 3))
    first = _run_learner(tmp_path, "cpu", resume=False, max_updates=7)
    assert first["updates"] == 7 and np.isfinite(first["critic_loss"])  # read at update 6, kept after
    assert list((tmp_path / "tb").rglob("events.out.tfevents.*"))
    second = _run_learner(tmp_path, "cpu", resume=True, max_updates=10)
    assert second["updates"] == 10 and np.isfinite(second["critic_loss"])


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=f"CUDA is absent here (torch {torch.__version__})")
def test_a_gpu_run_resumes_on_the_cpu_and_back(tmp_path):
    legs = [("cuda", 5), ("cpu", 8), ("cuda", 11)]
    for i, (device, updates) in enumerate(legs):
        counters = _run_learner(tmp_path, device, resume=i > 0, max_updates=updates)
        assert counters["updates"] == updates, device
        assert np.isfinite(counters["critic_loss"]), device


# ------------------------------------------------------------------------------------------------
# no waiting for the device inside the update loop
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_updates_between_metric_reads_read_nothing_back_from_the_device(device, monkeypatch):
    eager = filled_trainer(device)
    eager.metrics_every = 1  # a GPU's default reads every N
    with reads_back(monkeypatch, device) as reads:
        assert eager.step() is not None
    assert any(r.startswith("agent.py:") for r in reads)  # each update's floats: what a GPU must not do

    lazy = filled_trainer(device)
    lazy.metrics_every = 3
    lazy.step()  # update 1
    with reads_back(monkeypatch, device) as reads:
        unread = lazy.step()  # update 2
    assert reads == [] and set(unread) == {"batch_demo_share", "batch_reward_transitions"}
    with reads_back(monkeypatch, device) as reads:
        info = lazy.step()  # update 3 reads the means of 1 to 3: the window's read is the only one
    assert reads and {r.split(":")[0] for r in reads} == {"trainer.py"} and "critic_loss" in info


def test_prepare_device_leaves_the_cpu_precision_alone():
    before = torch.get_float32_matmul_precision()
    filled_trainer("cpu", episodes=0)
    assert torch.get_float32_matmul_precision() == before


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=f"CUDA is absent here (torch {torch.__version__})")
def test_cuda_updates_between_metric_reads_never_synchronise_in_the_loops_own_code():
    # unequal lengths: padded batches, which a GPU's encoders take whole (no mask read back)
    trainer = filled_trainer("cuda", tensorboard_every=4)
    assert trainer.metrics_every == 4 and trainer.agent.device.type == "cuda"
    assert torch.get_float32_matmul_precision() == "high" and torch.backends.cudnn.allow_tf32  # TF32
    assert trainer.step() is not None  # update 1 warms up cuDNN, cuBLAS and the allocators
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            unread = [trainer.step(), trainer.step()]  # updates 2 and 3: nothing read back
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert all(set(info) == {"batch_demo_share", "batch_reward_transitions"} for info in unread)
    syncs = [(Path(w.filename).name, w.lineno) for w in caught if "synchronizing" in str(w.message)]
    print("host synchronisations in two updates (file, line):", sorted(set(syncs)))  # pytest -rP shows it
    # agent.py's lines also carry what its network calls and backward passes do; these call nothing
    assert not [s for s in syncs if s[0] in ("trainer.py", "batch.py", "tensors.py", "networks.py")]
    info = trainer.step()  # update 4 reads the means of updates 1 to 4
    assert np.isfinite(info["critic_loss"]) and "alpha" in info


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=f"CUDA is absent here (torch {torch.__version__})")
def test_the_update_benchmark_times_cuda_with_percentiles():
    from mea_tools.bench.learner import LearnerBenchConfig, bench_updates

    rows = bench_updates(LearnerBenchConfig(variants=("cpu-small:c4",), updates=3, episodes=8, device="cuda"))
    (row,) = rows
    assert row["device"].startswith("cuda") and 0 < row["ms/update p50"] <= row["ms/update p99"]


# ------------------------------------------------------------------------------------------------
# CUDA graphs (--cuda-graphs)
# ------------------------------------------------------------------------------------------------


def test_cuda_graphs_are_refused_off_a_gpu_in_one_line_and_pad_every_batch_to_seq_len():
    with pytest.raises(
        ValueError, match=r"^--cuda-graphs needs a CUDA learner \(--device cuda\), not --device cpu$"
    ):
        tiny_learner_config(
            Path("unused"), ServiceConfig(), algorithm=SacConfig(net=TINY_NET, cuda_graphs=True)
        )
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device"):
        RecurrentSAC(build_actor(TINY_NET), build_critic(TINY_NET), SacSettings(), "cpu", cuda_graphs=True)
    trainer = filled_trainer("cpu")  # episodes of 10-12 steps in a seq_len-20 replay
    for graphs, want in ((False, 12), (True, trainer.replay.seq_len)):
        algo = dataclasses.replace(trainer.config, cuda_graphs=graphs)
        sample = algo.sample(trainer.replay, 4, np.random.default_rng(0), 0.0, False)
        assert sample.seq_len == want, graphs


def _twin_sacs(
    device: str, heads: int = 2, target_heads: int | None = None
) -> tuple[RecurrentSAC, RecurrentSAC]:
    net = dataclasses.replace(TINY_NET, critic_heads=heads)
    torch.manual_seed(0)
    actor, critic = build_actor(net), build_critic(net)
    twins = []
    for graphs in (False, True):
        a, c = actor.__class__(net), critic.__class__(net)
        a.load_state_dict(actor.state_dict())
        c.load_state_dict(critic.state_dict())
        twins.append(RecurrentSAC(a, c, SacSettings(target_heads=target_heads), device, cuda_graphs=graphs))
    return twins[0], twins[1]


@pytest.mark.cuda
@pytest.mark.skipif(
    not CUDA, reason=f"CUDA is absent here (torch {torch.__version__}); tools/gpu-check.sh runs it"
)
# 4 heads: the target's heads are drawn inside the graph
@pytest.mark.parametrize("heads, target_heads", [(2, None), (4, 2)])
def test_graphed_updates_replay_one_capture_and_learn_as_the_eager_ones(heads, target_heads):
    trainer = filled_trainer("cpu")
    rng = np.random.default_rng(0)
    samples = [trainer.replay.sample(4, rng, trim=False) for _ in range(9)]
    eager, graphed = _twin_sacs("cuda", heads, target_heads)
    with full_fp32():
        for k, sample in enumerate(samples):
            batch = to_batch(sample, "cuda")
            torch.cuda.manual_seed(
                100 + k
            )  # the same noise for both (a replay draws at the generator's offset)
            want = eager.update_tensors(batch)
            torch.cuda.manual_seed(100 + k)
            got = graphed.update_tensors(batch)
            assert graphed.updates == eager.updates == k + 1
            for name in ("critic_loss", "actor_loss", "alpha"):
                assert float(got[name]) == pytest.approx(float(want[name]), rel=1e-4, abs=1e-6), (k, name)
    graph = graphed._graphed
    assert graph is not None and graph.enabled and graph.captures == 1  # 3 eager, then one graph replayed
    for p, q in zip(eager.actor.parameters(), graphed.actor.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=1e-4, atol=1e-5)
    for p, q in zip(eager.critic_target.parameters(), graphed.critic_target.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=1e-4, atol=1e-5)
