"""Simulated tasks (pybullet only: no transport, metrics or storage imports).

``make_env(name)`` builds a ManipulationEnv for a registered task.
"""

from __future__ import annotations

import importlib

from services.tasks.env import EXPERT_STYLES, EnvSettings, ManipulationEnv, Observation, Task

# task name -> "module:Class"; modules import lazily so one task's import cost is paid only when used
TASKS: dict[str, str] = {
    "block_pull": "services.tasks.block_pull:BlockPull",
    "block_pick": "services.tasks.block_pick:BlockPick",
    "drawer_open": "services.tasks.drawer_open:DrawerOpen",
}


def task_class(name: str) -> type[Task]:
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose from {sorted(TASKS)}")
    module, _, cls = TASKS[name].partition(":")
    return getattr(importlib.import_module(module), cls)


def make_env(name: str, settings: EnvSettings | None = None) -> ManipulationEnv:
    return ManipulationEnv(task_class(name)(), settings or EnvSettings())


__all__ = [
    "EXPERT_STYLES",
    "TASKS",
    "EnvSettings",
    "ManipulationEnv",
    "Observation",
    "Task",
    "make_env",
    "task_class",
]
