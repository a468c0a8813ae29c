"""Per-second output of ``mocapd demo --synthetic``: the stall around t ≈ 10-13 s (issue 32), measured.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Runs the synthetic demo for ``--seconds`` in a private network namespace, ``--runs`` times, and reads its
per-second status lines (``t=  11.2 s  output  60 Hz  missed 3 ...``): each second's output rate and the ticks it
missed. With ``--baseline DIR`` (another checkout, e.g. main before the fix) the runs alternate between the two
trees, so a change of load on a shared machine hits both alike. Prints JSON: per tree, the worst second of each
run (its time, rate and missed ticks), the longest gap between two status lines of each run (they come once a
second from the event loop: a gap is the loop stalled), the missed ticks in t = 8-16 s against those of the
other seconds (per second), and the load average.

    .venv/bin/python tools/bench_stall.py --runs 3 --seconds 30 --baseline /work/main
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from statistics import median
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"^t=\s*([\d.]+) s\s+output\s+(\d+) Hz\s+missed (\d+)")
WINDOW = (8.0, 16.0)


def one_run(tree: Path, seconds: float) -> list[tuple[float, int, int]]:
    """(t, Hz, missed ticks in that second) per status line of one demo run from ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = ["unshare", "-rn", "sh", "-c", f"ip link set lo up && exec {sys.executable} -m mocapd demo --synthetic "
           f"--http-port 0 --seconds {seconds:g}"]  # fmt: skip
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=seconds + 600, check=True)
    rows, last = [], 0
    for line in out.stdout.splitlines():
        m = LINE.match(line)
        if m:
            t, hz, missed = float(m[1]), int(m[2]), int(m[3])
            rows.append((t, hz, missed - last))
            last = missed
    return rows


def summary(runs: list[list[tuple[float, int, int]]]) -> dict[str, Any]:
    worst, gaps = [], []
    inside, outside = [], []
    for rows in runs:
        # The status line comes once a second from the event loop: a stall of the loop is a gap between two.
        t_gap, gap = max(((b[0], b[0] - a[0]) for a, b in itertools.pairwise(rows)), key=lambda g: g[1])
        gaps.append({"ends_at_t_s": t_gap, "gap_s": round(gap, 1)})
        t, hz, missed = min(rows[1:], key=lambda r: r[1])  # the first second is the start-up's
        worst.append({"t_s": t, "hz": hz, "missed": missed})
        inside += [m for t, _, m in rows[1:] if WINDOW[0] <= t < WINDOW[1]]
        outside += [m for t, _, m in rows[1:] if not WINDOW[0] <= t < WINDOW[1]]
    return {
        "longest_gap_between_status_lines_per_run": gaps,
        "worst_second_per_run": worst,
        "missed_per_second_in_8_16_s": {"max": max(inside, default=0), "median": median(inside) if inside else 0},
        "missed_per_second_elsewhere": {"max": max(outside, default=0), "median": median(outside) if outside else 0},
        "per_second": [[(t, hz, m) for t, hz, m in rows] for rows in runs],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--baseline", type=Path, default=None, help="another checkout to alternate with")
    args = p.parse_args()
    trees = {"this": ROOT, **({"baseline": args.baseline.resolve()} if args.baseline else {})}
    runs: dict[str, list[list[tuple[float, int, int]]]] = {k: [] for k in trees}
    load0 = os.getloadavg()
    for _ in range(args.runs):
        for name, tree in trees.items():
            runs[name].append(one_run(tree, args.seconds))
    print(json.dumps({"trees": {k: str(v) for k, v in trees.items()},
                      **{k: summary(v) for k, v in runs.items()},
                      "loadavg": {"start": [round(x, 2) for x in load0],
                                  "end": [round(x, 2) for x in os.getloadavg()]}}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
