"""Saving the running cameras to the calibration file (``POST /calibration/save``, issue 43): refused with a clear
reason where the next start could not read what would be written, or there is nowhere to write; the old file left
alone then. The round trip through the running daemon is in tests/test_camera_watch_daemon.py."""

from __future__ import annotations

import datetime
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.synthetic import ring_rig
from mocapd.errors import InputError
from mocapd.io.calibration_files import read_any
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.calibration_save import backup_path, save_cameras
from tools.bench_camera_bump import bump_config


def test_a_save_writes_the_cameras_and_keeps_the_old_file(tmp_path: Path) -> None:
    rig = ring_rig(3)
    target = tmp_path / "rig.toml"
    first = save_cameras(rig, target, source="test")
    assert first.backup is None and read_any(target).names == ["cam0", "cam1", "cam2"]
    old = target.read_bytes()
    turned = [*rig[:2], replace(rig[2], R=rig[0].R)]
    second = save_cameras(turned, target, source="test")
    assert second.backup is not None and second.backup.read_bytes() == old
    assert np.allclose(read_any(target)["cam2"].R, rig[0].R)
    now = datetime.datetime(2026, 11, 29, 7, 55, 0)
    assert backup_path(target, now).name == "rig.toml.20261129T075500.bak"
    # Saves within one second: the names still list in the order they were made (CI once saved twice in a second).
    made = []
    for _ in range(3):
        made.append(backup_path(target, now))
        made[-1].write_bytes(b"")
    assert [p.name for p in made] == [f"rig.toml.20261129T075500{s}.bak" for s in ("", "_2", "_3")]
    assert sorted(made) == made


def test_a_save_is_refused_where_the_next_start_could_not_read_it(tmp_path: Path) -> None:
    rig = ring_rig(3)
    with pytest.raises(InputError, match=r"needs a \.toml name; set \[calibration\] save_to"):
        save_cameras(rig, tmp_path / "rig.qca.txt", source="test")
    damaged = tmp_path / "rig.toml"
    damaged.write_text("this is = = not toml\n")
    with pytest.raises(InputError, match="not a calibration this daemon reads"):
        save_cameras(rig, damaged, source="test")
    assert damaged.read_text() == "this is = = not toml\n" and sorted(tmp_path.iterdir()) == [damaged]


def test_a_synthetic_rig_without_save_to_has_nowhere_to_save() -> None:
    with (
        assembled(bump_config(), RunOptions()) as demo,
        pytest.raises(InputError, match=r"nowhere to save the cameras.*save_to"),
    ):
        demo.daemon.save_calibration("test")
