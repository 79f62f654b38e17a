"""Task names have one source, the wire's list (proto.episode.TASKS): every implemented task is one of
them, and configs accept only the implemented ones (the wire also names planned tasks)."""

from __future__ import annotations

import pytest

from proto.episode import OBJECT_SYMMETRY, TASKS
from services.actor.config import ActorConfig
from services.tasks import TASK_CLASSES, task_class
from services.tasks.gym_env import IDS

pytestmark = pytest.mark.contract


def test_every_registered_task_is_a_wire_task_name() -> None:
    assert TASK_CLASSES, "no task registered"
    assert not set(TASK_CLASSES) - set(TASKS), (
        f"not wire task names: {sorted(set(TASK_CLASSES) - set(TASKS))}"
    )


def test_every_wire_task_has_an_object_symmetry_and_every_gym_id_a_registered_task() -> None:
    assert set(OBJECT_SYMMETRY) == set(TASKS)
    assert set(IDS) <= set(TASK_CLASSES)


@pytest.mark.parametrize("name", sorted(TASK_CLASSES))
def test_registered_tasks_resolve_to_their_classes(name: str) -> None:
    assert task_class(name).__name__ == TASK_CLASSES[name].partition(":")[2]


def test_configs_accept_only_implemented_tasks() -> None:
    for name in TASK_CLASSES:
        assert ActorConfig(task=name).task == name
    planned = sorted(set(TASKS) - set(TASK_CLASSES))  # on the wire already, not implemented yet
    for name in [*planned, "no_such_task"]:
        with pytest.raises(ValueError, match="task must be one of"):
            ActorConfig(task=name)
        with pytest.raises(ValueError, match="unknown task"):
            task_class(name)
