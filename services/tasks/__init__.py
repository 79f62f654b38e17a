"""Simulated tasks (pybullet only: no transport, metrics or storage imports).

``make_env(name)`` builds a ManipulationEnv for a registered task. Task names are the wire's
(:data:`proto.episode.TASKS`); :data:`TASK_CLASSES` holds the ones implemented here.
"""

from __future__ import annotations

import importlib

from services.tasks.env import EXPERT_STYLES, EnvSettings, ManipulationEnv, Observation, Task

TASK_CLASSES: dict[str, str] = {
    "block_pull": "services.tasks.block_pull:BlockPull",
    "block_pick": "services.tasks.block_pick:BlockPick",
    "drawer_open": "services.tasks.drawer_open:DrawerOpen",
}
"""Wire task name (one of :data:`proto.episode.TASKS`) -> ``"module:Class"`` for every task implemented
here (the wire also names planned ones). Modules import lazily, so a task's import cost is paid only
when it is used."""


def task_class(name: str) -> type[Task]:
    if name not in TASK_CLASSES:
        raise ValueError(f"unknown task {name!r}; choose from {sorted(TASK_CLASSES)}")
    module, _, cls = TASK_CLASSES[name].partition(":")
    return getattr(importlib.import_module(module), cls)


def make_env(name: str, settings: EnvSettings | None = None) -> ManipulationEnv:
    return ManipulationEnv(task_class(name)(), settings or EnvSettings())


__all__ = [
    "EXPERT_STYLES",
    "TASK_CLASSES",
    "EnvSettings",
    "ManipulationEnv",
    "Observation",
    "Task",
    "make_env",
    "task_class",
]
