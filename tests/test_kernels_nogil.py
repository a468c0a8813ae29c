"""Every compiled kernel of ``mocapd/core/_*kernel.py`` releases the interpreter lock while it runs (``nogil=True``).

The tick solves on its own thread (``[daemon] tick_thread``) and its people on the solve pool: a kernel that held
the lock would stop the event loop (capture, IMU reads, publishing) for as long as it runs, and the threads would
buy nothing. Issue 39 found the LM loop's kernel released it but the cost evaluation, the sorting, the hands' and
the learned term's kernels did not.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from numba.core.registry import CPUDispatcher

import mocapd.core

CORE = Path(mocapd.core.__file__).parent


def _kernel_modules() -> list[str]:
    return sorted(f"mocapd.core.{p.stem}" for p in CORE.glob("_*kernel.py"))


def test_the_kernel_modules_are_found() -> None:
    # The check below must not pass on an empty list: the modules the tick calls are among those found.
    names = _kernel_modules()
    for expected in ("_kernel", "_lm_kernel", "_flip_kernel", "_sorting_kernel", "_hand_kernel", "_learned_kernel",
                     "_undistort_kernel", "_lk_kernel"):  # fmt: skip
        assert f"mocapd.core.{expected}" in names


def test_every_compiled_kernel_releases_the_interpreter_lock() -> None:
    held = []
    for name in _kernel_modules():
        module = importlib.import_module(name)
        kernels = {k: v for k, v in vars(module).items() if isinstance(v, CPUDispatcher) and v.__module__ == name}
        assert kernels, f"{name}: no compiled kernel found"
        held += [f"{name}.{k}" for k, v in kernels.items() if not v.targetoptions.get("nogil")]
    assert held == [], f"compiled without nogil=True (they hold the interpreter lock): {held}"
