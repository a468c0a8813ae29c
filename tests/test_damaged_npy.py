"""A .npy header that numpy's own parser chokes on (tokenize.TokenError) is a clear error, not a crash."""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import pytest

from mocapd.errors import InputError
from mocapd.service.session.solve import _prior


def _npz_with_header(header: str) -> bytes:
    h = header.encode("latin1")
    h += b" " * (64 - (10 + len(h) + 1) % 64) + b"\n"
    npy = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h + b"\0" * 24
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name in ("M", "mu", "sigma"):
            z.writestr(f"{name}.npy", npy)
    return buf.getvalue()


@pytest.mark.parametrize(
    "header",
    [
        "{'descr': '<f8', 'fortran_order': False, 'shape': (3,), '''",  # a string never closed
        "{'descr': '<f8', 'fortran_order': False, 'shape': (3,",  # a bracket never closed
    ],
)
def test_a_session_prior_with_a_damaged_header_is_refused_in_one_line(header: str, tmp_path: Path) -> None:
    path = tmp_path / "prior.npz"
    path.write_bytes(_npz_with_header(header))
    with pytest.raises(InputError, match="cannot read the session's pose prior"):
        _prior(path)
