"""Run by :mod:`mocapd.io.model_build` inside its throw-away venv (torch + ultralytics), never by mocapd.

Usage: ``python _yolo_export.py WEIGHTS.pt OUT_DIR WIDTH HEIGHT``. Exports a fixed-size ONNX model without
NMS (output ``(1, 56, N)``) into OUT_DIR.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    weights, out_dir, width, height = Path(argv[0]), Path(argv[1]), int(argv[2]), int(argv[3])
    from ultralytics import YOLO  # only importable inside the export venv

    work = out_dir / weights.name
    shutil.copyfile(weights, work)  # ultralytics writes the export next to the weights
    model = YOLO(str(work))
    produced = model.export(format="onnx", imgsz=(height, width), dynamic=False, simplify=True, opset=17)
    work.unlink()
    print(f"exported {produced}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
