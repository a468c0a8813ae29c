"""The Pose2Sim demo data fetched by setup/steps/21-pose2sim-demo.sh (test modules wrap demo_root() in a fixture)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
POSE2SIM = ROOT / ".cache" / "pose2sim" / "Pose2Sim"


def demo_root() -> Path:
    """Folder holding Demo_SinglePerson/ and Demo_MultiPerson/ (run `make setup` to fetch it)."""
    if not (POSE2SIM / "Demo_MultiPerson" / "videos").is_dir():
        raise FileNotFoundError(f"{POSE2SIM} is missing: run `make setup` (setup/steps/21-pose2sim-demo.sh)")
    return POSE2SIM
