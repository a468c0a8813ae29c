"""Config files of small rigs, as a user writes them, for tests that run ``mocapd run`` / ``check-config``."""

from __future__ import annotations

from pathlib import Path

from tests.pose2sim_data import demo_root


def synthetic_toml(cameras: int = 4, extra: str = "") -> str:
    """A rig of ``cameras`` synthetic cameras (the simulated rig of ``[synthetic]``), on any free ports."""
    tables = "".join(f'[[cameras]]\nname = "cam{i}"\nsource = "synthetic"\n\n' for i in range(cameras))
    return tables + "[daemon]\nhttp_port = 0\n\n[websocket]\nport = 0\n\n" + extra


def video_rig_toml(extra: str = "") -> str:
    """Two cameras replaying the Pose2Sim multi-person videos, with the demo's Qualisys calibration (absolute
    paths: the file may be written anywhere)."""
    demo = demo_root() / "Demo_MultiPerson"
    tables = "".join(
        f'[[cameras]]\nname = "{cam}"\nsource = "video"\npath = "{demo / "videos" / f"{cam}.mp4"}"\n\n'
        for cam in ("cam01", "cam02")
    )
    calib = demo / "calibration" / "Calib.qca.txt"
    return tables + f'[calibration]\nfile = "{calib}"\n\n[daemon]\nhttp_port = 0\n\n[websocket]\nport = 0\n\n' + extra


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path
