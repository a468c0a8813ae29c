"""The lockstep suit rig of :mod:`mocapd.sim.lockstep` with the shipped configuration's solver and prior."""

from __future__ import annotations

from mocapd.io.prior import resolve_prior
from mocapd.pipeline.scheduler import SchedulerOptions
from mocapd.service.config import load_config
from mocapd.sim.lockstep import MS, S, SuitLockstep
from mocapd.sim.lockstep import suit_lockstep as _build

__all__ = ["MS", "S", "SuitLockstep", "suit_lockstep"]


def suit_lockstep(
    options: SchedulerOptions | None = None,
    *,
    n_people: int = 1,
    keypoints: str = "coco17",
    rate_hz: int = 60,
    n_cams: int = 4,
) -> SuitLockstep:
    """:func:`mocapd.sim.lockstep.suit_lockstep` with ``config.toml``'s solver weights, LM options and prior."""
    config = load_config()
    prior = resolve_prior(config.solver.prior)
    return _build(options, cost=config.solver.cost, lm=config.solver.lm.options(), prior=prior,
                  n_people=n_people, keypoints=keypoints, rate_hz=rate_hz, n_cams=n_cams)  # fmt: skip
