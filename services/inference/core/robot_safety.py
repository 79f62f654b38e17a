"""The robot side's own safety rules, apart from transport: when must the arm hold, whatever the server says.

The server's envelope shapes every action it sends; these rules cover what it cannot see: the
server or the operator gone, an e-stop the server has not heard of, and commands that stop
arriving. ``RobotSafety.reason(now)`` gives the first that applies (None: the arm may move):

* ``estop``: an operator's e-stop is engaged (latched until a release);
* ``operator_lost``: an operator is required and none holds a liveliness token;
* ``server_lost``: the inference server's liveliness token is gone;
* ``watchdog``: commanding, and no command arrived for ``command_timeout`` seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

ROBOT_HOLD_REASONS = ("estop", "operator_lost", "server_lost", "watchdog", "no_reply", "bad_reply")
"""Why the robot side held (the last two: a request got no reply in time; a reply did not answer it)."""


@dataclass
class RobotSafety:
    command_timeout: float = 1.0
    require_operator: bool = False
    estop: bool = False
    server_alive: bool = False
    operator_alive: bool = False
    last_command: float | None = None
    """Monotonic time of the last command executed; None while not commanding (between episodes)."""

    def reason(self, now: float) -> str | None:
        if self.estop:
            return "estop"
        if self.require_operator and not self.operator_alive:
            return "operator_lost"
        if not self.server_alive:
            return "server_lost"
        if self.last_command is not None and now - self.last_command > self.command_timeout:
            return "watchdog"
        return None
