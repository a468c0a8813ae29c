"""The Pose2Sim demo data (BSD-3-Clause): 4 synchronised 60 fps portrait videos and a Qualisys calibration.

The set-up step ``setup/steps/21-pose2sim-demo.sh`` downloads the ``pose2sim`` wheel and unpacks its two demo
folders into ``<cache>/pose2sim/Pose2Sim/`` (the one copy every tool and test reads). Nothing of it is
committed.
"""

from __future__ import annotations

from pathlib import Path

from mocapd.errors import MocapdError
from mocapd.io.model_cache import cache_dir

DEMOS = ("Demo_SinglePerson", "Demo_MultiPerson")
CAMERAS = ("cam01", "cam02", "cam03", "cam04")


def demo_root() -> Path:
    """The folder holding ``Demo_SinglePerson/`` and ``Demo_MultiPerson/``."""
    return cache_dir() / "pose2sim" / "Pose2Sim"


def demo_file(demo: str, relative: str) -> Path:
    """Path of ``Pose2Sim/<demo>/<relative>`` as the set-up step unpacked it.

    Raises
    ------
    MocapdError
        The file is not there (the set-up has not run, or ``demo`` is not one of :data:`DEMOS`).
    """
    target = demo_root() / demo / relative
    if not target.is_file():
        raise MocapdError(f"{target} is missing; run the set-up (make setup: setup/steps/21-pose2sim-demo.sh)")
    return target


def demo_video(demo: str, camera: str) -> Path:
    """A demo video, e.g. ``demo_video("Demo_SinglePerson", "cam01")``."""
    return demo_file(demo, f"videos/{camera}.mp4")


def demo_calibration(demo: str) -> Path:
    """The demo's Qualisys calibration ``Calib.qca.txt``."""
    return demo_file(demo, "calibration/Calib.qca.txt")
