"""CPU seconds of starting ``mocapd`` commands, this checkout against another.

Developer benchmark, not a ``mocapd bench`` verb. For each round, in alternating order, runs ``mocapd --help``,
``mocapd run --help``, ``mocapd check-config`` (the shipped file) and ``mocapd check-config RIG`` (a synthetic
4-camera rig) and takes each child's CPU (user + system, ``getrusage`` of the children around it), then starts
``mocapd run`` on that rig and takes its CPU (with its children's) at its first line (``mocapd run: <rig>``, printed
once the config and the rig are validated: "run to validated") and at its ``ready:`` line. CPU seconds, not wall:
on a shared machine they are the fair number. JSON on stdout: the CPU's name, every round's values and the
medians of all rounds but the first (which may compile the solver kernel into a cold NumBa cache of a fresh
checkout)::

    .venv/bin/python tools/bench_cli_startup.py --other /tmp/old [--rounds 6]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {"--help": ["--help"], "run --help": ["run", "--help"], "check-config": ["check-config"],
            "check-config RIG": ["check-config", "RIG"]}  # fmt: skip
RIG = "".join(f'[[cameras]]\nname = "cam{i}"\nsource = "synthetic"\n\n' for i in range(4))
RIG += "[daemon]\nhttp_port = 0\n\n[websocket]\nport = 0\n"


def _env(repo: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(repo)}


def command_cpu(repo: Path, args: list[str]) -> float:
    """CPU seconds of ``python -m mocapd ARGS`` run from ``repo``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "mocapd", *args], env=_env(repo), cwd=repo, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, check=False, timeout=600)  # fmt: skip
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run_cpu(repo: Path, config: Path) -> tuple[float, float]:
    """CPU seconds of ``mocapd run --config CONFIG`` (with its children) when its config is validated (its first
    line, the rig's summary) and when it prints ``ready:``."""
    proc = subprocess.Popen([sys.executable, "-m", "mocapd", "run", "--config", str(config)], env=_env(repo),
                            cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
    assert proc.stdout is not None
    validated = ready = float("nan")
    try:
        for line in proc.stdout:
            t = psutil.Process(proc.pid).cpu_times()
            cpu = t.user + t.system + t.children_user + t.children_system
            if line.startswith("mocapd run: ") and math.isnan(validated):  # the first such line
                validated = cpu
            if line.startswith("ready:"):
                ready = cpu
                break
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    return validated, ready


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", type=Path, required=True, help="the other checkout (e.g. main's worktree)")
    ap.add_argument("--rounds", type=int, default=6, help="rounds (the first is left out of the medians)")
    a = ap.parse_args()
    repos = {"this": REPO, "other": a.other.resolve()}
    marks = ["run to validated", "run to ready"]
    runs: dict[str, dict[str, list[float]]] = {r: {k: [] for k in [*COMMANDS, *marks]} for r in repos}
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "rig.toml"
        config.write_text(RIG, encoding="utf-8")
        for i in range(a.rounds):
            order = list(repos) if i % 2 == 0 else list(repos)[::-1]
            for name, args in COMMANDS.items():
                for r in order:
                    runs[r][name].append(command_cpu(repos[r], [str(config) if a == "RIG" else a for a in args]))
            for r in order:
                for mark, seconds in zip(marks, run_cpu(repos[r], config), strict=True):
                    runs[r][mark].append(seconds)
    medians = {r: {k: round(statistics.median(v[1:] or v), 3) for k, v in d.items()} for r, d in runs.items()}
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), "?")  # fmt: skip
    print(json.dumps({"cpu": cpu, "repos": {r: str(p) for r, p in repos.items()}, "medians_cpu_s": medians,
                      "rounds_cpu_s": runs}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
