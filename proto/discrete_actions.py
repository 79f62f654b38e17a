"""The discrete action space of Surgical Grasp Any (the paper's A_d) and how it travels as the
project's 5-vector action ``(jaw, dx, dy, dz, dtheta)`` (``proto.actions``).

Nine actions: +-x, +-y, +-z, +-yaw and a jaw toggle. On the wire each is a normalised action with
one translation or rotation component at +-1 (the rest 0), and the jaw component is the jaw command
*after* the step: +1 open, -1 closed. So a toggle is the one action whose jaw component differs from
the previous command; every other action repeats it. A continuous action (the hybrid P-controller's
approach) is stored as it was executed and is not one of the nine (``index_of`` returns None).

C4 acts on the x/y translations only (a rotation by k quarter turns about the vertical axis,
counter-clockwise seen from above: +x -> +y -> -x -> -y); +-z, +-yaw and the toggle are invariant
(the paper's trivial set A'_d).
"""

from __future__ import annotations

import numpy as np

from proto.actions import ACTION_DIM, JAW, THETA

NAMES = ("+x", "-x", "+y", "-y", "+z", "-z", "+yaw", "-yaw", "jaw")
"""Index -> name of the nine discrete actions."""
TOGGLE = NAMES.index("jaw")
TRIVIAL = frozenset(NAMES.index(n) for n in ("+z", "-z", "+yaw", "-yaw", "jaw"))
"""Actions MEA keeps as they are (the paper's A'_d)."""
_AXIS = {0: (1, 1.0), 1: (1, -1.0), 2: (2, 1.0), 3: (2, -1.0), 4: (3, 1.0), 5: (3, -1.0), 6: (THETA, 1.0), 7: (THETA, -1.0)}  # fmt: skip
_C4 = (0, 2, 1, 3)  # +x, +y, -x, -y in counter-clockwise order (indices into NAMES)


def jaw_command(open_: bool) -> float:
    return 1.0 if open_ else -1.0


def to_vector(index: int, jaw_open_before: bool) -> np.ndarray:
    """The normalised 5-vector of discrete action ``index`` taken with the jaw open or closed."""
    if not 0 <= index < len(NAMES):
        raise ValueError(f"discrete action must be in [0, {len(NAMES)}), got {index}")
    a = np.zeros(ACTION_DIM, np.float32)
    jaw_open_after = (not jaw_open_before) if index == TOGGLE else jaw_open_before
    a[JAW] = jaw_command(jaw_open_after)
    if index != TOGGLE:
        axis, sign = _AXIS[index]
        a[axis] = sign
    return a


def index_of(action: np.ndarray, jaw_open_before: bool) -> int | None:
    """The discrete action a 5-vector encodes (None if it is not one of the nine)."""
    a = np.asarray(action, dtype=np.float64)
    moves = [i for i in range(ACTION_DIM) if i != JAW and a[i] != 0.0]
    toggled = (a[JAW] > 0) != jaw_open_before
    if abs(a[JAW]) != 1.0:
        return None
    if toggled:
        return TOGGLE if not moves else None
    if len(moves) != 1 or abs(a[moves[0]]) != 1.0:
        return None
    return next(k for k, (axis, sign) in _AXIS.items() if axis == moves[0] and sign == a[moves[0]])


def rotate_c4(index: int, quarter_turns: int) -> int:
    """``index`` rotated by ``quarter_turns`` x 90 degrees about the vertical axis (trivial actions
    are unchanged)."""
    if index in TRIVIAL:
        return index
    return _C4[(_C4.index(index) + quarter_turns) % 4]
