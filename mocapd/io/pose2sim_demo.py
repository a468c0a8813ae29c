"""The Pose2Sim demo data (BSD-3-Clause): 4 synchronised 60 fps portrait videos and a Qualisys calibration.

The set-up step ``setup/steps/31-pose2sim-demo.sh`` downloads the ``pose2sim`` wheel with
``pip download --no-deps`` into ``<cache>/pose2sim/``; this module unpacks the few demo files it needs next to
it on first use. Nothing of it is committed.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from mocapd.errors import MocapdError
from mocapd.io.model_cache import cache_dir

DEMOS = ("Demo_SinglePerson", "Demo_MultiPerson")
CAMERAS = ("cam01", "cam02", "cam03", "cam04")


def pose2sim_wheel() -> Path:
    """The downloaded pose2sim wheel (newest if several)."""
    wheels = sorted((cache_dir() / "pose2sim").glob("pose2sim-*.whl"))
    if not wheels:
        raise MocapdError(
            f"no pose2sim wheel in {cache_dir() / 'pose2sim'}; run the set-up (make setup) to download it"
        )
    return wheels[-1]


def demo_file(demo: str, relative: str) -> Path:
    """Path of ``Pose2Sim/<demo>/<relative>`` unpacked from the wheel (unpacked once, then reused)."""
    wheel = pose2sim_wheel()
    target_root = cache_dir() / "pose2sim" / "unpacked" / wheel.stem
    member = f"Pose2Sim/{demo}/{relative}"
    target = target_root / member
    if not target.is_file():
        with zipfile.ZipFile(wheel) as zf:
            try:
                info = zf.getinfo(member)
            except KeyError:
                raise MocapdError(f"{wheel.name} has no {member}") from None
            tmp = target.with_suffix(target.suffix + ".part")
            tmp.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(info) as src, tmp.open("wb") as dst:
                dst.write(src.read())
            tmp.replace(target)  # atomic: a concurrent reader never sees half a file
    return target


def demo_video(demo: str, camera: str) -> Path:
    """A demo video, e.g. ``demo_video("Demo_SinglePerson", "cam01")``."""
    return demo_file(demo, f"videos/{camera}.mp4")


def demo_calibration(demo: str) -> Path:
    """The demo's Qualisys calibration ``Calib.qca.txt``."""
    return demo_file(demo, "calibration/Calib.qca.txt")
