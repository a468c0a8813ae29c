"""Fetch the hand landmark models (full, lite) from the npm package ``@mediapipe/hands`` into the cache (issue 44).

Nothing here is committed. ``@mediapipe/hands`` (Google, Apache-2.0 per its ``package.json``) ships MediaPipe's hand
landmark models as plain files of its tarball (``hand_landmark_{full,lite}.tflite``: 224 x 224 RGB in, 21 landmarks
in crop pixels, a hand-presence score, a handedness score and 21 world landmarks out); the palm detector sits in
``hands_solution_packed_assets.data`` and is not used: the body's keypoints place the crops. So
:func:`build_hand_models`:

1. runs ``npm pack @mediapipe/hands@0.4.1675469240`` (the ordinary npm client, into a temporary directory) and
   checks the tarball's sha256 against the one pinned here;
2. takes ``package/hand_landmark_<variant>.tflite`` out of it and checks its sha256 against the pinned one;
3. writes ``hand_landmark_<variant>.tflite`` and a sidecar ``hand_landmark_<variant>.json`` (package, version,
   tarball and model sha256, licence, date, input size, keypoint set) into the cache's ``models/`` directory.

LiteRT runs the .tflite files as they are (as the body landmarks, :mod:`mocapd.pipeline.landmarks`).
"""

from __future__ import annotations

import datetime as dt
import json
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from mocapd.errors import ModelError
from mocapd.io.landmark_build import extract_pinned, model_is_current, npm_pack, sidecar_path
from mocapd.io.model_cache import hand_model_path

NPM_PACKAGE = "@mediapipe/hands"
NPM_VERSION = "0.4.1675469240"
TARBALL_SHA256 = "bdd5be939c60cbd72a49f4b6141407683cf2a67263598e1a44757d70b3dfcb8a"
MODEL_SHA256 = {
    "full": "8c026882c9ec059ce0f8e75266bee5a9a23c341a40e0000df755374d3d1b9b68",
    "lite": "d7fde8ac11f8ce03f8663775bfc323f4fc9f2a38062b4f4efa142874ef5b2a48",
}
VARIANTS = tuple(MODEL_SHA256)
LICENCE = "Apache-2.0 (@mediapipe/hands, Google: MediaPipe hand landmark models)"
INPUT_SIZE = 224


def _member(variant: str) -> str:
    return f"package/hand_landmark_{variant}.tflite"


def hand_model_is_current(model: Path, variant: str) -> bool:
    """Whether ``model`` exists, matches its sidecar's sha256, and is the pinned package's ``variant``."""
    return model_is_current(model, MODEL_SHA256.get(variant))


def _extract(tarball: Path, variant: str, dest: Path) -> None:
    """This package's ``variant`` out of its ``tarball`` into ``dest``, checked against the pinned sha256."""
    extract_pinned(tarball, _member(variant), dest, MODEL_SHA256[variant])


def build_hand_models(
    variants: Sequence[str] = VARIANTS,
    *,
    force: bool = False,
    log: Callable[[str], None] = print,
    npm: str = "npm",
) -> list[Path]:
    """Fetch the hand landmark models ``variants`` (``"full"``, ``"lite"``) into the cache, skipping current ones.

    Returns
    -------
    list of Path
        The .tflite files, in the order of ``variants``.

    Raises
    ------
    ModelError
        When a variant is unknown, npm is missing, the download fails, or a checksum differs from the pinned one.
    """
    unknown = [v for v in variants if v not in MODEL_SHA256]
    if unknown:
        raise ModelError(f"unknown hand landmark model {unknown[0]!r}; known: {list(VARIANTS)}")
    targets = [hand_model_path(v) for v in variants]
    todo = [(v, t) for v, t in zip(variants, targets, strict=True) if force or not hand_model_is_current(t, v)]
    for v, t in zip(variants, targets, strict=True):
        if (v, t) not in todo:
            log(f"model up to date: {t}")
    if not todo:
        return targets
    targets[0].parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="mocapd-hands-") as tmp_s:
        tarball = npm_pack(NPM_PACKAGE, NPM_VERSION, TARBALL_SHA256, Path(tmp_s), log, npm)
        for variant, target in todo:
            part = target.with_suffix(".tflite.part")
            _extract(tarball, variant, part)
            meta: dict[str, Any] = {
                "model": f"mediapipe-hand-landmark-{variant}",
                "source_package": NPM_PACKAGE,
                "source_version": NPM_VERSION,
                "source_member": _member(variant),
                "tarball_sha256": TARBALL_SHA256,
                "sha256": MODEL_SHA256[variant],
                "licence": LICENCE,
                "runtime": "ai-edge-litert",
                "input_width": INPUT_SIZE,
                "input_height": INPUT_SIZE,
                "keypoint_format": "hand21",
                "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            }
            part.replace(target)
            sidecar_path(target).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
            log(f"wrote {target} ({target.stat().st_size // 1024} KiB) and {sidecar_path(target).name}")
    return targets
