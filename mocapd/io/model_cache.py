"""Where fetched artefacts live: the project's cache directory (never committed).

``$MOCAPD_CACHE`` when set, else ``.cache/`` at the root of the checkout. Models go to ``models/``, the
Pose2Sim demo wheel to ``pose2sim/``.
"""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[2]


def cache_dir() -> Path:
    """The cache root (not created)."""
    env = os.environ.get("MOCAPD_CACHE")
    return Path(env) if env else _REPO_ROOT / ".cache"


def model_dir() -> Path:
    """Directory of exported detector models."""
    return cache_dir() / "models"


def default_model_path(width: int = 640, height: int = 640) -> Path:
    """The default YOLO11n-pose ONNX export for a ``width x height`` input."""
    suffix = f"{width}" if width == height else f"{width}x{height}"
    return model_dir() / f"yolo11n-pose-{suffix}.onnx"
