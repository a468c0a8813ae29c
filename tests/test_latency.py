"""Latency histogram and percentiles."""

from __future__ import annotations

from mocapd.pipeline.latency import LatencyStats

MS = 1_000_000


def test_histogram_percentiles_and_prometheus_lines() -> None:
    s = LatencyStats(window=100)
    for v in range(1, 101):
        s.add(v * MS)
    summary = s.summary()
    assert summary["count"] == 100
    assert abs(summary["p50"] - 50.5) < 1e-6
    assert abs(summary["mean_ms"] - 50.5) < 1e-6
    lines = s.prometheus("x_seconds", 'stage="solve"')
    assert 'x_seconds_bucket{stage="solve",le="0.05"} 50' in lines
    assert 'x_seconds_bucket{stage="solve",le="0.1"} 100' in lines
    assert 'x_seconds_bucket{stage="solve",le="+Inf"} 100' in lines
    assert 'x_seconds_count{stage="solve"} 100' in lines
    s.add(5000 * MS)  # beyond the last bucket; the window keeps only the last 100 values
    assert s.bucket_counts[-1] == 1
    assert len(s.recent()) == 100
    assert LatencyStats().summary()["p95"] is None
