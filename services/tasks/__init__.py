"""Simulated tasks (pybullet only: no transport, metrics or storage imports).

``make_env(name)`` builds the env of a registered task: a ManipulationEnv around the task for the
general-manipulation tasks, or the task's own env where its class has a ``make_env`` factory
(``surgical_grasp_any``: discrete actions, hybrid control, FSM rewards). Task names are the wire's
(:data:`proto.episode.TASKS`); :data:`TASK_CLASSES` holds the ones implemented here and
:data:`GENERAL_TASKS` those of the general-manipulation domain.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import sys


def _import_pybullet_quietly() -> None:
    """pybullet's C code prints its build time (on fd 2 in this build) when imported; every task
    module imports it after this package, so importing it here first with fds 1 and 2 on /dev/null
    keeps that line off the user's terminal. C's buffers are flushed before the fds return."""
    if "pybullet" in sys.modules:
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()
    saved: dict[int, int] = {}
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in (1, 2):
            with contextlib.suppress(OSError):  # a closed fd has nothing to protect
                saved[fd] = os.dup(fd)
                os.dup2(null, fd)
        importlib.import_module("pybullet")
        ctypes.CDLL(None).fflush(None)
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


_import_pybullet_quietly()

from services.tasks.env import (  # noqa: E402
    DEPTH_IMAGE_REVISION,
    EXPERT_STYLES,
    EnvSettings,
    ManipulationEnv,
    Observation,
    Task,
)

TASK_CLASSES: dict[str, str] = {
    "block_pull": "services.tasks.block_pull:BlockPull",
    "block_pick": "services.tasks.block_pick:BlockPick",
    "drawer_open": "services.tasks.drawer_open:DrawerOpen",
    "surgical_grasp_any": "services.tasks.surgical.env:SurgicalGraspAny",
}
"""Wire task name (one of :data:`proto.episode.TASKS`) -> ``"module:Class"`` for every task implemented
here (the wire also names planned ones). Modules import lazily, so a task's import cost is paid only
when it is used."""
GENERAL_TASKS: tuple[str, ...] = ("block_pull", "block_pick", "drawer_open")
"""The general-manipulation domain: ManipulationEnv tasks with two look-alike objects (one immovable)
and probe/direct experts. The others bring their own env."""


def task_class(name: str) -> type:
    """The registered class of ``name``: a :class:`Task` (general tasks) or a task with its own env."""
    if name not in TASK_CLASSES:
        raise ValueError(f"unknown task {name!r}; choose from {sorted(TASK_CLASSES)}")
    module, _, cls = TASK_CLASSES[name].partition(":")
    return getattr(importlib.import_module(module), cls)


def make_env(name: str, settings=None):
    """The env of task ``name``. ``settings``: EnvSettings (every task takes them; the surgical task
    keeps their points per segment) or the task's own settings class."""
    cls = task_class(name)
    factory = getattr(cls, "make_env", None)
    if factory is not None:
        return factory(settings)
    return ManipulationEnv(cls(), settings or EnvSettings())


__all__ = [
    "DEPTH_IMAGE_REVISION",
    "EXPERT_STYLES",
    "GENERAL_TASKS",
    "TASK_CLASSES",
    "EnvSettings",
    "ManipulationEnv",
    "Observation",
    "Task",
    "make_env",
    "task_class",
]
