"""Running real Blender (the ``bpy`` wheel, in its own venv ``.venv-bpy`` made by ``setup/steps/40-bpy.sh``)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

from mocapd.io.lifecycle import guarded_command

ROOT = Path(__file__).resolve().parent.parent


def bpy_python() -> Path:
    """The Python that has ``bpy``: ``$MOCAPD_BPY_PYTHON`` or the checkout's ``.venv-bpy``."""
    env = os.environ.get("MOCAPD_BPY_PYTHON")
    path = Path(env) if env else ROOT / ".venv-bpy" / "bin" / "python"
    assert path.exists(), f"Blender's Python not found at {path}: run `bash setup/steps/40-bpy.sh` (make test does)"
    return path


def run_blender_script(script: Path, *args: str, timeout: float = 300.0) -> dict[str, Any]:
    """Run ``script`` under Blender's Python; return the JSON it printed after ``MOCAPD-REPORT``."""
    proc = subprocess.run(  # guarded: Blender ends with the test, however that ends
        guarded_command([str(bpy_python()), str(script), *args]),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("MOCAPD-REPORT ")]
    assert proc.returncode == 0 and lines, f"Blender script failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    report: dict[str, Any] = json.loads(lines[-1].removeprefix("MOCAPD-REPORT "))
    return report
