"""The transport benchmark runs end to end on 127.0.0.1 and prints exactly one JSON object."""

from __future__ import annotations

import json
import math

import pytest

from mea_tools.bench.transport import TransportBenchConfig, run


def _reject_constant(name: str) -> float:
    raise AssertionError(f"non-standard JSON constant {name} in the output")


def _positive_finite(row: dict, *keys: str) -> None:
    for k in keys:
        v = row[k]
        assert isinstance(v, (int, float)) and math.isfinite(v) and v > 0, (k, v)


@pytest.mark.e2e
@pytest.mark.timeout(120)
def test_transport_bench_json(capsys: pytest.CaptureFixture[str]) -> None:
    cfg = TransportBenchConfig(episodes=6, repeats=2, pulls=4, warmup=1, blob_sizes_mb=(0.1,), json=True)
    returned = run(cfg)

    out = capsys.readouterr().out
    assert out.endswith("\n") and out.count("\n") == 1, out[:500]
    result = json.loads(out, parse_constant=_reject_constant)
    assert result["benchmark"] == "transport"
    assert result["results"] == json.loads(json.dumps(returned["results"]))
    assert set(result["results"]) == {"episode_codec", "episode_pubsub", "weights_pull"}

    codec = result["results"]["episode_codec"]
    assert len(codec) == 3
    for row in codec:
        _positive_finite(row, "encoded_mb", "encode_ms", "decode_ms", "encode_mb_s", "decode_mb_s")
    sizes = [row["encoded_mb"] for row in codec]
    assert sizes[0] < sizes[1] < sizes[2]  # points < + uint8 images < + float32 images

    (pubsub,) = result["results"]["episode_pubsub"]
    assert pubsub["sent"] == cfg.episodes
    assert pubsub["received"] == pubsub["sent"]
    assert pubsub["all_received"] is True
    assert pubsub["rejected"] == 0
    _positive_finite(pubsub, "episode_mb", "seconds", "episodes_per_s", "mb_per_s", "publish_episodes_per_s")

    (weights,) = result["results"]["weights_pull"]
    assert weights["blob_mb"] == pytest.approx(0.1)
    assert weights["pulls"] == cfg.pulls
    _positive_finite(
        weights,
        "encoded_mb",
        "pull_p50_ms",
        "pull_p99_ms",
        "pull_mb_s_at_p50",
        "announce_to_pulled_p50_ms",
        "announce_to_pulled_p99_ms",
        "local_decode_ms",
    )
    assert weights["pull_p99_ms"] >= weights["pull_p50_ms"]
    assert weights["announce_to_pulled_p99_ms"] >= weights["announce_to_pulled_p50_ms"]

    # transport measures none of the three reference targets
    ratios = result["reference_ratios"]
    assert len(ratios) == 3
    assert all(r["measured"] is None and r["met"] is None for r in ratios)
