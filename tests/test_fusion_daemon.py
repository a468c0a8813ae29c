"""The learned fusion in the daemon (issue 30): ``[fusion] mode = "both"`` on the synthetic rig, in-process, with
networks of the CI training recipe run by onnxruntime: the learned stream runs every third tick for both tracked
people (the suit wearer's with its IMU-only solve), its joints enter the LM solve, the poses stay on the synthetic
truth; and the configurations the fusion cannot run are refused with a clear message."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import numpy as np
import pytest

from mocapd.errors import ConfigError, ModelError
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import Rig, build_fusion
from mocapd.service.demo.synthetic import synthetic_config

from .test_daemon import Recorder, wait_for

MODEL = os.environ.get("MOCAPD_TEST_FUSION_MODEL")
"""The networks under test: the seconds-long training run's (conftest), or a folder from tools/train_fusion.py
while developing."""


@pytest.fixture
def networks(tiny_fusion_models: Path) -> str:
    return MODEL or str(tiny_fusion_models)


def _config(mode: str, networks: str) -> Config:
    cfg = load_config()
    return synthetic_config(
        cfg.model_copy(
            update={
                "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                "websocket": cfg.websocket.model_copy(update={"enabled": False}),
                "fusion": cfg.fusion.model_copy(update={"mode": mode, "model": networks}),
            }
        )
    )


@pytest.mark.asyncio
async def test_both_mode_feeds_the_learned_joints_into_every_persons_solve(networks: str) -> None:
    rec = Recorder()
    with assembled(_config("both", networks), RunOptions(sinks=[rec])) as demo:
        d = demo.daemon
        stage = d.scheduler.fusion
        assert stage is not None and d.scheduler.fusion_mode == "both"
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 120)
        await wait_for(lambda: bool(rec.frames) and len(rec.frames[-1].people) == 2, 60, "both people tracked")
        tracked_from = len(rec.frames)
        await wait_for(lambda: sum(len(f.people) for f in rec.frames[tracked_from:]) >= 240, 90, "240 person-frames")
        d.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
        status = d.scheduler.status()["fusion"]  # after the last tick: the counters below are of the same ticks

    # Every tracked person has a learned stream; the suit wearer also its IMU-only solve (every tick).
    assert status["mode"] == "both" and len(status["people"]) == 2
    solves = d.scheduler.counters["person_solves"]
    assert status["learned_frames"] >= solves // 3 - 2 * len(status["people"]) and status["learned_frames"] > 0
    assert status["imu_solves"] > 0 and status["no_centre"] == 0
    assert d.scheduler.counters["learned_observations"] == status["learned_frames"]
    # The solve with the learned joints stays on the synthetic truth (the same bound as the solver-only daemon).
    truth = demo.truth
    assert truth is not None
    errors: list[float] = []
    for f in reversed(rec.frames[tracked_from:]):
        t_s = (f.t_solve_ns - truth.epoch_ns) / 1e9
        errors += [truth.world.nearest_site_error(p.theta, p.skeleton, t_s)[0] for p in f.people]
    assert len(errors) >= 240 and float(np.median(errors)) < 0.03


def test_learned_modes_are_refused_where_they_cannot_run(networks: str) -> None:
    cfg = _config("both", networks)
    rig = Rig([], [], None, None)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="needs camera frames for the foreground mattes"):
        build_fusion(cfg, rig, None)
    fast = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"output_rate_hz": 100.0})})
    with pytest.raises(ConfigError, match=r"needs daemon\.output_rate_hz = 60"):
        build_fusion(fast, rig, object())  # type: ignore[arg-type]
    assert build_fusion(_config("solver", networks), rig, None) is None
    missing = cfg.model_copy(update={"fusion": cfg.fusion.model_copy(update={"model": str(Path("/nonexistent"))})})
    with pytest.raises(ModelError, match=r"train the networks with tools/train_fusion\.py"):
        build_fusion(missing, rig, object())  # type: ignore[arg-type]
