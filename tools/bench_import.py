"""Memory and time of ``mocapd import mtw`` on a large MT Manager export (issue 34: a 265 MB export took 2.5 GiB).

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Writes an export of ``--mb`` megabytes made of the rows of the OpenSense MTw file in ``tests/data`` (tab-separated,
26 columns, empty UTC cells, PacketCounter renumbered), then runs ``python -m mocapd import mtw`` on it in a child
process and reports the child's peak resident memory (``wait4``'s ``ru_maxrss``), its wall time and exit status,
beside the peak of a child that only imports the CLI (what any command costs before it reads a byte). JSON on
stdout::

    .venv/bin/python tools/bench_import.py --mb 265 [--repo PATH] [--keep DIR]

``--repo`` runs another checkout's mocapd (``PYTHONPATH=PATH``), e.g. the code before a change, for a comparison
on the same machine and file.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO / "tests" / "data" / "opensense_mtw" / "MT_012005D6_009-001_00B421E6.txt"


def write_export(path: Path, megabytes: float) -> int:
    """An MT Manager export of about ``megabytes`` MB; returns its number of data rows."""
    lines = SOURCE.read_text(encoding="utf-8").splitlines()
    head = [ln for ln in lines if ln.startswith("//")]
    names = lines[len(head)]
    cells = [ln.split("\t") for ln in lines[len(head) + 1 :] if ln.strip()]
    target = megabytes * 1e6
    size = 0
    n = 0
    with path.open("w", encoding="utf-8") as fh:
        fh.write("\n".join([*head, names]) + "\n")
        block: list[str] = []
        while size < target:
            row = list(cells[n % len(cells)])
            row[0] = f"{n % 65536:05d}"
            line = "\t".join(row) + "\n"
            block.append(line)
            size += len(line)
            n += 1
            if len(block) >= 100_000:
                fh.write("".join(block))
                block = []
        fh.write("".join(block))
    return n


def run(argv: list[str], pythonpath: Path) -> dict[str, float | int]:
    """A child process's exit status, wall time and peak RSS (MiB)."""
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, *argv], env=env, cwd=pythonpath, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )  # cwd: "python -m" puts it first on sys.path
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0 and proc.stderr is not None:
        sys.stderr.write(proc.stderr.read().decode(errors="replace")[-2000:])
    return {"exit": proc.returncode, "wall_s": round(wall, 2), "peak_rss_mib": round(usage.ru_maxrss / 1024, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mb", type=float, default=265.0, help="size of the export (MB, default 265)")
    ap.add_argument("--repo", type=Path, default=REPO, help="checkout whose mocapd runs (default: this one)")
    ap.add_argument("--keep", type=Path, default=None, help="write the export and the session here (kept)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        folder = a.keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        export = folder / "MT_bench_00B421E6.txt"
        rows = write_export(export, a.mb)
        baseline = run(["-c", "import mocapd.service.cli"], a.repo)
        session = folder / f"session-{os.getpid()}"
        result = run(["-m", "mocapd", "import", "mtw", str(export), "-o", str(session), "--assign",
                      "00B421E6=Hips"], a.repo)  # fmt: skip
        out = {
            "repo": str(a.repo),
            "file_mb": round(export.stat().st_size / 1e6, 1),
            "rows": rows,
            "import": result,
            "cli_import_only_peak_rss_mib": baseline["peak_rss_mib"],
            "import_over_baseline_mib": round(float(result["peak_rss_mib"]) - float(baseline["peak_rss_mib"]), 1),
            "loadavg": Path("/proc/loadavg").read_text().split()[:3],
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
