"""`mea serve` settings: where the weights come from, the timing rules, and each robot's envelope.

Per-robot envelopes come from a JSON file (``--limits-file``)::

    {"default": {"max_translation": 0.03, "workspace_low": [-0.2, -0.2, 0.0], ...},
     "robots": {"psm1": {"metres_per_unit": 0.01, "max_translation": 0.005}}}

Keys are ``services.inference.core.envelope.Limits`` fields (SI units, the robot's base frame); a robot
(a session id) takes ``default`` overlaid with its own entry; anything unset keeps the built-in
default. Unknown keys and bad values are refused when the server starts, naming the key.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

from services.common.config import ServiceConfig
from services.inference.core.envelope import Limits
from services.inference.core.sessions import ServeSettings


@dataclasses.dataclass(frozen=True)
class ServeConfig:
    """Serve the newest policy to robots: act(observation) -> action over Zenoh, behind a safety envelope."""

    weights: str = ""
    """Serve this weights file (or a run dir's newest); empty: follow the bus."""
    version: int = -1
    """With --weights naming a directory: the version to serve (-1: the newest file there)."""
    run_id: str = ""
    """Serve only weights of this training run (empty: the lineage of the first version loaded)."""
    limits_file: str = ""
    """JSON file of per-robot envelopes; empty: the built-in defaults."""
    max_observation_age: float = 0.5
    """Watchdog: an observation stamped longer ago than this (s) is answered with a hold."""
    session_timeout: float = 600.0
    """Drop a session not heard from for this long (s)."""
    max_sessions: int = 64
    """Most robots served at once."""
    stochastic: bool = False
    """Sample actions instead of serving the mean (the evaluator's deterministic policy)."""
    torch_threads: int = 1
    """torch intra-op threads (0: torch's default)."""
    service: ServiceConfig = ServiceConfig()
    """Identity, transport, metrics and logs."""

    def __post_init__(self) -> None:
        if self.max_observation_age <= 0 or self.session_timeout <= 0 or self.max_sessions < 1:
            raise ValueError("max_observation_age and session_timeout must be > 0, max_sessions >= 1")
        if self.torch_threads < 0:
            raise ValueError("torch_threads must be >= 0")
        if self.limits_file:
            load_limits(Path(self.limits_file))  # fail while parsing flags, naming the key
        if self.weights and not Path(self.weights).exists():
            raise ValueError(f"--weights {self.weights}: the path does not exist (a weights file, a run "
                             "directory or a folder of weights files)")  # fmt: skip

    def settings(self) -> ServeSettings:
        return ServeSettings(max_observation_age=self.max_observation_age, session_timeout=self.session_timeout,
                             max_sessions=self.max_sessions, deterministic=not self.stochastic,
                             run_id=self.run_id)  # fmt: skip

    def limits_for(self) -> Callable[[str], Limits]:
        if not self.limits_file:
            return lambda _session: Limits()
        default, robots = load_limits(Path(self.limits_file))
        return lambda session: robots.get(session, default)


def _limits(base: Limits, entry: object, where: str) -> Limits:
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: expected an object of Limits fields")
    names = {f.name for f in dataclasses.fields(Limits)}
    unknown = sorted(set(entry) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; known: {sorted(names)}")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in entry.items()}
    try:
        return dataclasses.replace(base, **values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None


def load_limits(path: Path) -> tuple[Limits, dict[str, Limits]]:
    """(default envelope, envelope by robot) from a limits file; ValueError naming what is wrong."""
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"limits file {path}: cannot read it ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"limits file {path}: not JSON ({exc})") from None
    if not isinstance(data, dict) or set(data) - {"default", "robots"}:
        raise ValueError(f"limits file {path}: expected an object with `default` and/or `robots`")
    default = _limits(Limits(), data.get("default", {}), f"limits file {path}: default")
    robots = data.get("robots", {})
    if not isinstance(robots, dict):
        raise ValueError(f"limits file {path}: `robots` must map robot ids to Limits fields")
    return default, {r: _limits(default, e, f"limits file {path}: robots.{r}") for r, e in robots.items()}


PRESETS = {"default": ServeConfig()}
