"""Recorded clips for training and evaluation: the splits file, the data root, loading and retargeting."""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from mocapd.core.motion import SourceMotion
from mocapd.core.retarget import Retargeted, retarget
from mocapd.errors import ConfigError, InputError
from mocapd.io.asfamc import read_amc, read_asf
from mocapd.io.bvh import read_bvh

SPLITS = ("prior", "development", "evaluation", "quick")
OUTPUT_FPS = 60.0
"""Everything is resampled to the solver's 60 Hz output rate."""


def default_data_root() -> Path:
    """``$MOCAPD_DATA`` or ``../shared/data`` next to the repository."""
    env = os.environ.get("MOCAPD_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


@dataclass(frozen=True)
class Splits:
    """Clip paths (absolute) per split."""

    files: dict[str, tuple[Path, ...]]

    def __getitem__(self, split: str) -> tuple[Path, ...]:
        if split not in self.files:
            raise ConfigError(f"unknown split {split!r}; allowed: {list(self.files)}")
        return self.files[split]


def load_splits(data_root: Path | None = None, text: str | None = None) -> Splits:
    """Read ``mocapd/data/eval_splits.toml`` (or ``text``) and expand its globs under the data root."""
    root = default_data_root() if data_root is None else Path(data_root)
    raw = text if text is not None else resources.files("mocapd").joinpath("data", "eval_splits.toml").read_text()
    data = tomllib.loads(raw)
    out: dict[str, tuple[Path, ...]] = {}
    for split in SPLITS:
        pats = data.get(split, {}).get("files", [])
        found: list[Path] = []
        for pat in pats:
            matches = sorted(root.glob(pat))
            if not matches:
                raise ConfigError(f"split {split}: {pat!r} matches no file under {root}")
            found.extend(matches)
        out[split] = tuple(found)
    overlap = set(out["prior"]) & (set(out["development"]) | set(out["evaluation"]))
    overlap |= set(out["development"]) & set(out["evaluation"])
    if overlap:
        raise ConfigError(f"splits overlap: {sorted(str(p) for p in overlap)}")
    return Splits(out)


def read_motion(path: Path) -> SourceMotion:
    """Read a BVH file or an AMC file (with the ``NN.asf`` skeleton beside it)."""
    p = Path(path)
    if p.suffix.lower() == ".bvh":
        return read_bvh(p)
    if p.suffix.lower() == ".amc":
        asf = p.with_name(p.stem.split("_")[0] + ".asf")
        if not asf.exists():
            raise InputError(f"{p}: no ASF skeleton {asf.name} beside it")
        return read_amc(p, read_asf(asf))
    raise InputError(f"{p}: unsupported motion file type (BVH or AMC)")


def load_clip(path: Path, fps: float = OUTPUT_FPS) -> Retargeted:
    """A clip read, resampled to ``fps`` and retargeted onto the 21-bone skeleton."""
    return retarget(read_motion(path).resample(fps))
