"""From a run's settings to each service's frozen config: the one place that knows how `mea run`
configures its services (the launcher starts them with these objects, in processes or threads, and
saves them under RUN_DIR/services/)."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from proto.seeds import actor_seed_base
from services.actor.config import ActorConfig
from services.augmenter.config import AugmenterConfig
from services.common import run_key
from services.common.bus.zenoh_bus import ZenohConfig
from services.common.config import ServiceConfig, override
from services.common.metrics import DEFAULT_PORTS
from services.evaluator.config import EvaluatorConfig
from services.learner import init_actor
from services.learner.config import PRESETS as LEARNER_PRESETS
from services.run_config import SERVICE_MODULES, SERVICE_ORDER, RunConfig
from services.variants import network_group, variant


@dataclass(frozen=True)
class ChildSpec:
    """One service instance to start: ``entry`` ("module:function") is called with ``config`` (a
    service's frozen config) or, for plugin entries, with ``argv``."""

    service: str
    instance: str
    entry: str
    argv: tuple[str, ...] = ()
    config: Any = None


def metrics_port(run: RunConfig, service: str, index: int) -> int:
    """/metrics port of instance ``index`` of ``service``: the run's port base (the launcher's port)
    plus the service's offset in the default layout (learner +1, augmenter +2, evaluator +3, actor i
    +10 + i), so two runs with different bases share a host; 0 (off) when the run turns metrics off."""
    if run.metrics_port == 0:
        return 0
    offset = DEFAULT_PORTS[service] - DEFAULT_PORTS["launcher"]
    return run.metrics_port + offset + (index if service == "actor" else 0)


def key_file(run: RunConfig, run_dir: Path) -> str:
    """The run's key file when the run authenticates its bus ("" otherwise)."""
    return str(run_dir / run_key.FILE_NAME) if run.authenticate else ""


def service_settings(run: RunConfig, run_dir: Path, service: str, index: int) -> ServiceConfig:
    """Identity, transport, metrics, logs and the run's key of one instance: it joins the run's
    router, serves /metrics at ``metrics_port`` and seals with the run's key."""
    return ServiceConfig(
        instance_id=f"{service}-{index}",
        zenoh=ZenohConfig(connect=(run.listen,), namespace=run.namespace),
        metrics_port=metrics_port(run, service, index),
        metrics_addr=run.metrics_addr,
        log_format=run.log_format,
        run_key_file=key_file(run, run_dir),
    )


def actor_config(
    run: RunConfig, index: int, service: ServiceConfig, run_dir: Path | None = None
) -> ActorConfig:
    """Actor ``index``: the learned policy when the run has a learner, here or on a host it connects
    to (random otherwise),
    demonstrations and the random prefill from actor 0 only (not again on resume or restart), the depth image where the variant
    observes it, a seed base that moves on with every resume (``proto.seeds``), and its TensorBoard
    points in RUN_DIR/tb."""
    return ActorConfig(
        task=run.task,
        index=index,
        envs=run.envs_per_actor,
        policy="learned" if "learner" in run.services or run.connect else "random",
        seed_base=actor_seed_base(run.seed, run.resumes),
        demos=run.resolved_demos() if index == 0 and run.resume is None else 0,
        random_steps=run.resolved_random_steps() if index == 0 and run.resume is None else 0,
        depth_image=variant(run.variant).depth_image,
        gripper_start=run.gripper_start,
        expert=run.expert,
        jump_start=run.jump_start if "learner" in run.services or run.connect else 0.0,
        jump_start_demos=run.resolved_demos() if run.jump_start > 0 else 0,
        jump_start_seed_base=actor_seed_base(run.seed, 0) if run.jump_start > 0 else 0,
        follow_gate=run.follow_gate,
        tensorboard_dir=None if run_dir is None else run_dir / "tb",
        service=service,
    )


def augmenter_config(run: RunConfig, service: ServiceConfig) -> AugmenterConfig:
    """What the variant augments: mea, isometric copies + MEA on what ``RunConfig.resolved_mea_on``
    says (demos in the paper); equiobs, isometric copies; equirsac, the same on the depth image."""
    v = variant(run.variant)
    base = AugmenterConfig().augment
    augment = dataclasses.replace(
        base,
        seed=run.seed,
        success_isometric_copies=run.resolved_success_rotations(),
        mea_on=run.resolved_mea_on() if v.mea else "none",
        # the discrete-action tasks' copies are re-rendered by the task's own pipeline (dsa)
        observation=base.observation if v.observation == "dsa" else v.observation,
    )
    return AugmenterConfig(augment=augment, service=service)


def learner_preset(run: RunConfig) -> str:
    """The learner preset of the run (``learner.config.PRESETS``): ``learner_preset`` in the table of
    the variant's algorithm (``RunConfig`` checked that it is there)."""
    return run.learner_preset_name()


def learner_config(run: RunConfig, run_dir: Path, service: ServiceConfig) -> Any:
    """The run's learner preset (``learner_preset``) with the variant's observation and the task's
    group for its algorithm (``AlgorithmConfig.for_run``), the run's budget, seed and torch threads
    (``learner_threads``, one by default: it shares the cores with actors and augmenter, and two
    OpenMP threads on a busy 2-core machine wait on each other), state under RUN_DIR/learner, resumed
    on --resume. ``learner_args`` change the preset before all that, so the run's own settings win."""
    # the run's device first too: a learner flag that needs a GPU (--cuda-graphs) is checked against it
    on_device = dataclasses.replace(LEARNER_PRESETS[learner_preset(run)], device=run.learner_device)
    preset = override(on_device, run.learner_args, "--learner-args")
    return dataclasses.replace(
        preset,
        algorithm=preset.algorithm.for_run(variant(run.variant).observation, network_group(run.task)),
        threads=run.learner_threads,
        device=run.learner_device,
        max_env_steps=run.env_steps,
        seed=run.seed,
        run_dir=run_dir / "learner",
        tensorboard_dir=run_dir / "tb",
        resume=run.resume is not None,
        init_actor=run.init_actor,
        service=service,
    )


def check_init_actor(run: RunConfig) -> None:
    """ValueError (naming the problem) unless the run's ``init_actor``, if any, is a readable weights
    file whose actor fits the run's learner (``services.learner.init_actor``): checked before the run
    writes or starts anything."""
    if run.init_actor is None or "learner" not in run.services:
        return
    _, blob = init_actor.read(run.init_actor)
    init_actor.check_fits(blob, learner_config(run, Path(run.run_dir or "."), ServiceConfig()).algorithm)


def evaluator_config(run: RunConfig, run_dir: Path, service: ServiceConfig) -> EvaluatorConfig:
    """The run's task, cadence and budget; the history under RUN_DIR/eval; the depth image where
    the variant observes it. With a learner (here or on a host the run connects to) the evaluator
    waits for its replay gate however long it takes, so no evaluation is recorded at env steps -1
    (the learner announces its first weights a moment before its first gate)."""
    learner = "learner" in run.services or bool(run.connect)
    return EvaluatorConfig(
        task=run.task,
        run_dir=run_dir,
        every_env_steps=run.eval_every,
        episodes=run.eval_episodes,
        final_env_steps=run.env_steps,
        final_episodes=run.final_eval_episodes,
        depth_image=variant(run.variant).depth_image,
        gripper_start=run.gripper_start,
        first_gate_wait=math.inf if learner else EvaluatorConfig.first_gate_wait,
        tensorboard_dir=run_dir / "tb",
        videos=run.eval_videos,
        service=service,
    )


def config_for(run: RunConfig, run_dir: Path, service: str, index: int) -> Any:
    """The frozen config of instance ``index`` of ``service`` in this run."""
    if service not in SERVICE_ORDER:
        raise ValueError(f"unknown service {service!r}; choose from {SERVICE_ORDER}")
    settings = service_settings(run, run_dir, service, index)
    if service == "actor":
        return actor_config(run, index, settings, run_dir)
    if service == "augmenter":
        return augmenter_config(run, settings)
    if service == "learner":
        return learner_config(run, run_dir, settings)
    return evaluator_config(run, run_dir, settings)


def service_available(service: str) -> bool:
    """Whether this build has ``service``'s shell (a build may ship a subset of the services)."""
    try:
        return importlib.util.find_spec(SERVICE_MODULES[service]) is not None
    except ModuleNotFoundError:
        return False


def child_specs(
    run: RunConfig, run_dir: Path, available: Callable[[str], bool] = service_available
) -> tuple[list[ChildSpec], list[str]]:
    """Instances to start, in start order, and the requested services ``available`` says this build
    lacks. Plugin entries (``extra_services``) get the command-line form of their settings."""
    specs, missing = [], []
    for service in SERVICE_ORDER:
        if service not in run.services:
            continue
        if not available(service):
            missing.append(service)
            continue
        for i in range(run.actors if service == "actor" else 1):
            cfg = config_for(run, run_dir, service, i)
            specs.append(ChildSpec(service, f"{service}-{i}", f"{SERVICE_MODULES[service]}:run", config=cfg))
    for i, entry in enumerate(run.extra_services):
        instance = f"extra-{i}"
        specs.append(ChildSpec("test", instance, entry, argv=tuple(plugin_args(run, run_dir, instance))))
    return specs, missing


def _torch_threads(n: int) -> str:
    return "torch's default threads" if n == 0 else f"{n} torch thread{'s' if n > 1 else ''}"


def _given(spec: ChildSpec) -> str:
    """What an instance is given besides its process: the learner's device and torch threads, the
    evaluator's torch threads (the others take the process's thread pools as they are)."""
    if spec.service == "learner":
        return f"{spec.config.device}, {_torch_threads(spec.config.threads)}"
    if spec.service == "evaluator":
        return _torch_threads(spec.config.torch_threads)
    return ""


def describe(specs: Sequence[ChildSpec]) -> str:
    """The instances of a run in start order, with what each is given, on one line; a run of
    instances given the same is one range: ``learner-0 (cuda, 1 torch thread), augmenter-0,
    evaluator-0 (1 torch thread), actor-0..3``."""
    groups: list[tuple[str, str, list[str]]] = []  # (service, given, instances)
    for spec in specs:
        given = _given(spec)
        if groups and groups[-1][:2] == (spec.service, given):
            groups[-1][2].append(spec.instance)
        else:
            groups.append((spec.service, given, [spec.instance]))
    parts = []
    for _, given, names in groups:
        name = names[0] if len(names) == 1 else f"{names[0]}..{names[-1].rsplit('-', 1)[-1]}"
        parts.append(f"{name} ({given})" if given else name)
    return ", ".join(parts)


def restarted(spec: ChildSpec, restarts: int) -> ChildSpec:
    """The spec that replaces ``spec`` after its ``restarts``-th restart: an actor records no demos
    again and takes a fresh seed stream; a learner resumes from its checkpoint (and its announced
    lineage); the others start as they did."""
    cfg = spec.config
    if spec.service == "actor":
        cfg = dataclasses.replace(cfg, demos=0, random_steps=0, incarnation=restarts)
    elif spec.service == "learner":
        cfg = dataclasses.replace(cfg, resume=True)
    return dataclasses.replace(spec, config=cfg)


def plugin_args(run: RunConfig, run_dir: Path, instance: str) -> list[str]:
    """The shared service settings as flags, for plugin services that parse their own argv."""
    args = ["--service.instance-id", instance, "--service.zenoh.connect", run.listen,
            "--service.zenoh.namespace", run.namespace, "--service.log-format", run.log_format,
            "--service.run-key-file", key_file(run, run_dir)]  # fmt: skip
    return args + (["--service.metrics-port", "0"] if run.metrics_port == 0 else [])
