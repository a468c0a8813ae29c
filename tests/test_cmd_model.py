"""``mocapd model fetch``: argument parsing and the no-op path when the cached model is current."""

from __future__ import annotations

import pytest

from mocapd.service.cli import build_parser, main


def test_size_arguments() -> None:
    args = build_parser().parse_args(["model", "fetch", "--size", "640", "--size", "1280x736"])
    assert args.size == [(640, 640), (1280, 736)]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["model", "fetch", "--size", "650"])  # not a multiple of the stride
    with pytest.raises(SystemExit):
        build_parser().parse_args(["model", "fetch", "--size", "big"])


def test_fetch_is_a_no_op_when_the_model_is_current(capsys: pytest.CaptureFixture[str]) -> None:
    # The set-up step built it; a second fetch must only check the sidecar's sha256.
    assert main(["model", "fetch", "--size", "640"]) == 0
    assert "model up to date" in capsys.readouterr().out
