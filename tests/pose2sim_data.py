"""The Pose2Sim demo data fetched by setup/steps/21-pose2sim-demo.sh (test modules wrap demo_root() in a fixture)."""

from __future__ import annotations

from pathlib import Path

from mocapd.io import pose2sim_demo


def demo_root() -> Path:
    """Folder holding Demo_SinglePerson/ and Demo_MultiPerson/ (run `make setup` to fetch it)."""
    root = pose2sim_demo.demo_root()
    if not (root / "Demo_MultiPerson" / "videos").is_dir():
        raise FileNotFoundError(f"{root} is missing: run `make setup` (setup/steps/21-pose2sim-demo.sh)")
    return root
