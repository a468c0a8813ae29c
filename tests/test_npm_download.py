"""The demo profile's npm tarballs come straight from the registry, checked against their pinned sha256 (no npm)."""

from __future__ import annotations

import hashlib
import http.server
import io
import tarfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from mocapd.errors import ModelError
from mocapd.io.landmark_build import extract_pinned, npm_download


def _tarball() -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        data = b"export const answer = 42;\n"
        info = tarfile.TarInfo("package/lib/x.js")
        info.size = len(data)
        tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@pytest.fixture
def registry() -> Iterator[tuple[str, list[str]]]:
    """A loopback HTTP server answering the registry's tarball address of ``@scope/pkg@1.2.3``."""
    body = _tarball()
    paths: list[str] = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            paths.append(self.path)
            if self.path == "/@scope/pkg/-/pkg-1.2.3.tgz":
                self.send_response(200)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
            else:
                self.send_error(404)

        def log_message(self, format: str, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", paths
    finally:
        server.shutdown()
        server.server_close()


def test_a_pinned_tarball_is_downloaded_from_the_registrys_address(
    registry: tuple[str, list[str]], tmp_path: Path
) -> None:
    url, paths = registry
    digest = hashlib.sha256(_tarball()).hexdigest()
    got = npm_download("@scope/pkg", "1.2.3", digest, tmp_path, lambda _m: None, registry=url)
    assert paths == ["/@scope/pkg/-/pkg-1.2.3.tgz"]
    member_digest = hashlib.sha256(b"export const answer = 42;\n").hexdigest()
    extract_pinned(got, "package/lib/x.js", tmp_path / "x.js", member_digest)
    assert (tmp_path / "x.js").read_text() == "export const answer = 42;\n"


def test_a_tarball_that_is_not_the_pinned_one_is_refused(registry: tuple[str, list[str]], tmp_path: Path) -> None:
    url, _ = registry
    with pytest.raises(ModelError, match="is not the pinned"):
        npm_download("@scope/pkg", "1.2.3", "0" * 64, tmp_path, lambda _m: None, registry=url)


def test_a_missing_package_is_a_clear_error(registry: tuple[str, list[str]], tmp_path: Path) -> None:
    url, _ = registry
    with pytest.raises(ModelError, match=r"could not download @scope/pkg@9\.9\.9"):
        npm_download("@scope/pkg", "9.9.9", "0" * 64, tmp_path, lambda _m: None, registry=url)
