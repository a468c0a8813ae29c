"""The one output convention of ``mocapd bench`` (issue 46): every benchmark's JSON names the machine it ran on.

A number from a benchmark means little without the CPU behind it: the same solver runs 3x faster on a core with
AVX-512 than on one without, onnxruntime's INT8 model needs VNNI (or AMX) to beat FP32, and a laptop's 4 cores are
not a server's 64. :func:`machine` is the ``"machine"`` entry of every bench JSON: the CPU's model name, the
instruction-set flags that decide mocapd's speed, the cores (present and usable by this process), the load
average and Python. :func:`emit` prints a report the one way every verb does: the JSON on stdout, one line for a
person on stderr.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path
from typing import Any

#: the /proc/cpuinfo flags that decide mocapd's speed: SIMD width for NumPy/BLAS, numba and onnxruntime's FP32
#: kernels (AVX2, FMA, AVX-512), its INT8 kernels (VNNI) and BF16 / AMX matrix units
SPEED_FLAGS = (
    "sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl", "avx512_vnni", "avx_vnni",
    "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_int8", "asimd", "sve",
)  # fmt: skip


def _cpuinfo(path: Path) -> dict[str, str]:
    """The first processor's fields of /proc/cpuinfo (empty where the file is missing: not Linux)."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return {}
    out: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if out:
                break  # the first processor's block ends at its blank line
            continue
        key, sep, value = line.partition(":")
        if sep:
            out.setdefault(key.strip(), value.strip())
    return out


def cpu(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """The CPU: ``model`` (its name), ``flags`` (those of :data:`SPEED_FLAGS` it has), ``cores`` (logical CPUs of
    the machine) and ``usable_cores`` (those this process may run on: a container or ``taskset`` gives fewer)."""
    info = _cpuinfo(cpuinfo)
    # x86 names it "model name"; ARM kernels give "Processor" or nothing but the "CPU part" number.
    model = info.get("model name") or info.get("Processor") or info.get("cpu model") or platform.processor()
    flags = set((info.get("flags") or info.get("Features") or "").split())
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "model": model or platform.machine() or "unknown",
        "flags": [f for f in SPEED_FLAGS if f in flags],
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "arch": platform.machine(),
    }


def machine() -> dict[str, Any]:
    """The ``"machine"`` entry of a bench JSON: :func:`cpu`, the load average now and Python's version."""
    return {
        "cpu": cpu(),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
    }


def cpu_line(description: dict[str, Any] | None = None) -> str:
    """A short CPU description for the human summary: ``Intel(R) Xeon(R) ..., 2/2 cores, avx512f amx_tile``."""
    c = description if description is not None else cpu()
    wide = [f for f in c["flags"] if f.startswith(("avx512f", "avx2", "amx_tile", "avx512_vnni", "asimd"))]
    return f"{c['model']}, {c['usable_cores']}/{c['cores']} cores" + (f", {' '.join(wide)}" if wide else "")


def emit(report: dict[str, Any], summary: str) -> None:
    """Print a bench report the one way: the JSON (with its ``"machine"`` entry, added here where the report has
    none; a report's own entry keeps its extra fields and gets the CPU) on stdout, and ``summary`` with the CPU on
    one line on stderr."""
    own = report.get("machine")
    report["machine"] = {**machine(), **own} if isinstance(own, dict) else machine()
    print(json.dumps(report, indent=2), flush=True)
    print(f"{summary} [{cpu_line(report['machine']['cpu'])}]", file=sys.stderr, flush=True)
