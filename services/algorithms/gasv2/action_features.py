"""The world model's action input for Surgical Grasp Any: one 5-vector per executed action that does
not depend on the jaw's state, so that imagination can feed the actor's discrete choices without
tracking the jaw.

A stored action (``proto.discrete_actions``) is ``(jaw, dx, dy, dz, dtheta)`` whose jaw component is
the jaw command *after* the step (>= 0 open). Its feature is ``(toggle, dx, dy, dz, dtheta)`` with
``toggle`` 1 where the step changed the jaw command and 0 otherwise (the jaw opens before the first
step). So the nine discrete actions have nine fixed features (``DISCRETE_FEATURES``: a toggle is
``(1, 0, 0, 0, 0)``, +x is ``(0, 1, 0, 0, 0)``, ...) and the hybrid controller's continuous approach
steps (jaw open, continuous ``(dx, dy, dz)``) keep their motion with toggle 0.
"""

from __future__ import annotations

import numpy as np

from proto.actions import ACTION_DIM, JAW
from proto.discrete_actions import NAMES, to_vector

FEATURE_DIM = ACTION_DIM
TOGGLE = JAW
"""Index of the toggle component in a feature (where the jaw command sits in an action)."""


def features(actions: np.ndarray, jaw_open_at_start: bool = True) -> np.ndarray:
    """float32 (T, 5) features of an episode's executed actions (T, 5), in order."""
    a = np.asarray(actions, np.float32)
    if a.ndim != 2 or a.shape[1] != ACTION_DIM:
        raise ValueError(f"actions must have shape (T, {ACTION_DIM}), got {a.shape}")
    open_after = a[:, JAW] >= 0.0
    open_before = np.concatenate([[bool(jaw_open_at_start)], open_after[:-1]])
    out = a.copy()
    out[:, TOGGLE] = (open_after != open_before).astype(np.float32)
    return out


def _discrete_table() -> np.ndarray:
    """Each discrete action taken with the jaw open: only the toggle changes the command (to closed)."""
    table = np.stack([to_vector(i, jaw_open_before=True) for i in range(len(NAMES))]).astype(np.float32)
    return np.stack([features(row[None])[0] for row in table])


DISCRETE_FEATURES = _discrete_table()
"""float32 (9, 5): the feature of each discrete action (``proto.discrete_actions.NAMES`` order)."""
