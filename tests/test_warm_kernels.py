"""``tools/warm_kernels.py`` (run by ``make test`` beside mypy) compiles every kernel of ``mocapd/core/_*kernel.py``.

A kernel it does not call compiles, on a clean checkout, inside whichever test reaches it first. The check runs the
warm-up in a fresh interpreter (numba's cache as configured: after ``make test``'s warm-up it only loads) and asks
each public kernel's dispatcher for its signatures. Private helpers are compiled inside their callers (a cache load
of the caller does not register them) and are not checked, except the one a test calls directly; nor are the two
public ones only other kernels call.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: called only from inside other kernels (the hand's LM loop, the LM step), never from Python
INNER = {"mocapd.core._hand_kernel.apply_step", "mocapd.core._kernel.cholesky_solve"}

PROBE = """
import importlib, json, pathlib
from numba.core.registry import CPUDispatcher
import mocapd.core
from tools import warm_kernels

warm_kernels.main()
counts = {}
for path in sorted(pathlib.Path(mocapd.core.__file__).parent.glob("_*kernel.py")):
    name = f"mocapd.core.{path.stem}"
    module = importlib.import_module(name)
    for key, value in vars(module).items():
        if isinstance(value, CPUDispatcher) and value.__module__ == name:
            if not key.startswith("_") or key == "_pairwise_sum":
                counts[f"{name}.{key}"] = len(value.signatures)
print("COUNTS " + json.dumps(counts))
"""


def test_the_warm_up_compiles_every_public_kernel() -> None:
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, check=True)
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("COUNTS "))
    counts: dict[str, int] = json.loads(line.removeprefix("COUNTS "))
    # the modules' public kernels are all found (the check below must not pass on an empty dict)
    for expected in ("_kernel.evaluate", "_lm_kernel.lm_solve", "_flip_kernel.choose_swaps", "_lk_kernel.track",
                     "_sorting_kernel.candidate_pairs", "_hand_kernel.solve_lm", "_learned_kernel.learned_term",
                     "_undistort_kernel.normalize_points"):  # fmt: skip
        assert f"mocapd.core.{expected}" in counts
    missing = sorted(k for k, n in counts.items() if n == 0 and k not in INNER)
    assert missing == [], f"kernels tools/warm_kernels.py does not compile (add a call): {missing}"
