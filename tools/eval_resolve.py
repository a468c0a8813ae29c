"""Resolve accuracy against the synthetic truth (JSON): live solve vs the offline passes.

Records ``--seconds`` of ``mocapd demo --synthetic`` (the real daemon: simulated Xsens IMUs on ptys, synthetic
keypoint sources, the shipped config) into a session, or takes ``--session DIR``, then scores against the
synthetic world's truth, on the same person-frames (after the first second; and again from half a second after
the live daemon bound the suit, once enrolment and binding are over):

- ``live``: the poses the daemon published;
- ``forward_20``: the forward re-solve with the live LM budget (20 iterations, live tolerances);
- ``forward_100``: the forward re-solve with ``mocapd resolve``'s budget (100 iterations, 1e-10 tolerances);
- ``resolved``: ``forward_100`` + the RTS smoother (what ``mocapd resolve`` writes).

Usage: ``.venv/bin/python tools/eval_resolve.py [--seconds 20] [--session DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from mocapd.io.session import open_session  # noqa: E402
from mocapd.service.session.solve import ResolveOptions, forward_resolve, session_rig, smooth_frames  # noqa: E402
from mocapd.service.session.truth import truth_report  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--session", type=Path, default=None, help="score this synthetic session instead of recording")
    args = ap.parse_args()
    path = args.session
    if path is None:
        path = Path(tempfile.mkdtemp(prefix="eval-resolve-")) / "session"
        cmd = [sys.executable, "-m", "mocapd", "demo", "--synthetic", "--http-port", "0",
               "--seconds", str(args.seconds), "--record", str(path)]  # fmt: skip
        subprocess.run(cmd, cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    s = open_session(path)
    s.check()
    live = s.poses()
    opts = ResolveOptions()
    timings = {}
    t0 = time.perf_counter()
    fw20 = forward_resolve(s, replace(opts, max_iterations=20, tolerance=1e-6))
    timings["forward_20_s"] = round(time.perf_counter() - t0, 2)
    t0 = time.perf_counter()
    fw100 = forward_resolve(s, opts)
    timings["forward_100_s"] = round(time.perf_counter() - t0, 2)
    t0 = time.perf_counter()
    smoothed = smooth_frames(fw100, session_rig(s).skeleton, opts)
    timings["smoother_s"] = round(time.perf_counter() - t0, 2)
    streams = {"live": live, "forward_20": fw20, "forward_100": fw100, "resolved": smoothed}
    report = truth_report(s, streams)
    # Steady state: from half a second after the live daemon had bound the suit (enrolment and binding over).
    bound = next((f.t_solve_ns for f in live if any(p.suit is not None for p in f.people)), None)
    steady = truth_report(s, streams, from_ns=bound + 500_000_000) if bound is not None else None
    missed = (live[-1].t_solve_ns - live[0].t_solve_ns) // round(1e9 / 60) + 1 - len(live) if live else 0
    out = {
        "session": str(path),
        "live_frames": len(live),
        "live_missed_ticks": int(missed),
        "resolved_frames": len(smoothed),
        "error_vs_truth_mm": report,
        "error_vs_truth_mm_after_live_suit_binding": steady,
        "timings": timings,
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
