"""End to end: a SlimeVR suit emulated by the PyPI ``slimevr-tracker-emulator`` connects to the daemon's SlimeVR
server; its trackers are listed in /status, their quaternions land in the IMU ring buffers, and the suit binds to
the person the synthetic cameras see and drives the solved skeleton."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from mocapd.pipeline.ringbuffer import IMU_FIELDS
from mocapd.service.config import load_config
from tests.test_daemon import Recorder, http_get, wait_for
from tools.slimevr_rig import EMULATOR_MAC, build_slimevr_daemon, emulated_suit


@pytest.mark.asyncio
async def test_emulated_slimevr_suit_drives_the_solved_skeleton() -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0})})
    rec = Recorder()
    rig = build_slimevr_daemon(cfg, cameras=4, sinks=[rec])
    d = rig.daemon
    task = asyncio.create_task(d.run())
    try:
        await asyncio.wait_for(d.ready.wait(), 120)
        assert d.imu.slimevr is not None
        await wait_for(lambda: d.imu.slimevr is not None and d.imu.slimevr.port != 0, 10, "the SlimeVR server")
        async with emulated_suit(rig, d.imu.slimevr.port):

            def suited() -> bool:  # 13 sensors, of which a busy machine may leave a few without a fresh sample
                return bool(rec.frames) and any(p.suit == "suit0" and p.imus >= 10 for p in rec.frames[-1].people)

            await wait_for(suited, 90, "the SlimeVR suit bound with its sensors")
            frames_bound = len(rec.frames)
            await wait_for(lambda: len(rec.frames) > frames_bound + 120, 30, "two more seconds of poses")

            st = json.loads((await http_get(d.http.port, "/status"))[2])
            (tracker,) = st["imu"]["slimevr"]["trackers"]
            assert tracker["id"] == EMULATOR_MAC and tracker["connected"]
            assert [s["id"] for s in tracker["sensors"]] == [f"{EMULATOR_MAC}/{k}" for k in range(13)]
            assert st["imu"]["slimevr"]["bad_datagrams"] == 0 and tracker["reordered"] == 0
            assert {f"{EMULATOR_MAC}/{k}" for k in range(13)} <= set(st["imu"]["sensors"])

            # The buffered orientations are the emulator's, float32 on the wire (held repeats included).
            sent = {tuple(np.float32(v) for v in q) for frame in rig.sent for q in frame.values()}
            stream = d.imu.ingest.streams[f"{EMULATOR_MAC}/4"]
            quats = stream.buffer.rows()[-50:, 0:4]
            assert IMU_FIELDS[0].name == "quat"
            matched = sum(tuple(np.float32(v) for v in q) in sent for q in quats)
            assert matched >= 40  # the oldest rows may predate the kept history of what was sent
    finally:
        d.request_stop()
        try:
            assert await asyncio.wait_for(task, 10) == 0
        finally:
            rig.close()

    # The suit drives a person whose keypoint sites follow the truth (every frame since it first bound; on a loaded
    # machine the binding can come and go, which the suit binder's own tests cover).
    t0 = rig.epoch_ns
    bound = [(f, p) for f in rec.frames[frames_bound - 1 :] for p in f.people if p.suit == "suit0" and p.imus >= 10]
    assert len(bound) >= 60
    errors = [rig.world.nearest_site_error(p.theta, p.skeleton, (f.t_solve_ns - t0) / 1e9)[0] for f, p in bound]
    assert float(np.median(errors)) < 0.05
