"""The algorithms, by the name their weights carry (``WeightsBlob.algorithm``, ``--algorithm``): each
name's config type, policy spec and policy runtime (``algorithm.Registration``). The one place that
knows them all: everything else asks here, or asks the config it was given."""

from __future__ import annotations

from services.algorithms.algorithm import Registration
from services.algorithms.gasv2.algorithm import GasV2Config
from services.algorithms.gasv2.policy import GasV2Spec, LatentRuntime
from services.algorithms.sac.algorithm import SacConfig
from services.algorithms.sac.policy import ActorRuntime, PolicySpec

SAC = Registration(SacConfig, PolicySpec.from_json, ActorRuntime)
GASV2 = Registration(GasV2Config, GasV2Spec.from_json, LatentRuntime)

ALGORITHMS: dict[str, Registration] = {"equi_rsac": SAC, "rsac": SAC, "gasv2": GASV2}


def lookup(name: str) -> Registration:
    """The registration of ``name``; ValueError naming the algorithms otherwise."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; the learners are {', '.join(ALGORITHMS)}") from None


__all__ = ["ALGORITHMS", "lookup"]
