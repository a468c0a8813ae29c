"""Where fetched artefacts live: the user's cache directory (never the package, never committed).

``$MOCAPD_CACHE`` when set, else ``$XDG_CACHE_HOME/mocapd``, else ``~/.cache/mocapd`` (the XDG base directory
default), so an installed wheel, a checkout and a system service each find their own. Models go to ``models/``,
the Pose2Sim demo data to ``pose2sim/``.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """The cache root (not created)."""
    env = os.environ.get("MOCAPD_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    # The XDG spec: a relative $XDG_CACHE_HOME is invalid and must be ignored.
    base = Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".cache"
    return base / "mocapd"


def model_dir() -> Path:
    """Directory of exported detector models."""
    return cache_dir() / "models"


def default_model_path(width: int = 640, height: int = 640) -> Path:
    """The default YOLO11n-pose ONNX export for a ``width x height`` input."""
    suffix = f"{width}" if width == height else f"{width}x{height}"
    return model_dir() / f"yolo11n-pose-{suffix}.onnx"


def landmark_model_path(variant: str) -> Path:
    """The BlazePose landmark model ``variant`` (``"full"``, ``"heavy"``) from ``@mediapipe/pose``."""
    return model_dir() / f"pose_landmark_{variant}.tflite"


def hand_model_path(variant: str) -> Path:
    """The hand landmark model ``variant`` (``"full"``, ``"lite"``) from ``@mediapipe/hands``."""
    return model_dir() / f"hand_landmark_{variant}.tflite"
