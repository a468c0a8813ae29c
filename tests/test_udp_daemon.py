"""The real daemon on the synthetic rig streaming MVN, VMC and Rokoko Studio Live to loopback receivers; what arrives
decodes to the published frames' poses, and /status reports the streams' counters."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from mocapd.core.rotations import matrix_from_quat, matrix_from_rotvec
from mocapd.core.skeleton import BONE_INDEX
from mocapd.protocols.conventions import MVN, UNITY
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import load_config
from mocapd.service.config.udp import Destination, MvnStreamConfig, RokokoStreamConfig, UdpConfig, VmcStreamConfig
from mocapd.service.demo.synthetic import synthetic_config
from tests.test_daemon import Recorder, http_get, wait_for
from tests.test_mvn import read_datagram
from tests.test_rokoko import check_actor, decode

SUIT = "suit:suit0"


class Collect(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.datagrams: list[bytes] = []

    def datagram_received(self, data: bytes, addr: tuple[str | object, int]) -> None:
        self.datagrams.append(data)


@pytest.mark.asyncio
async def test_daemon_streams_mvn_vmc_and_rokoko_on_loopback() -> None:
    loop = asyncio.get_running_loop()
    mvn_t, mvn_rx = await loop.create_datagram_endpoint(Collect, local_addr=("127.0.0.1", 0))
    vmc_t, vmc_rx = await loop.create_datagram_endpoint(Collect, local_addr=("127.0.0.1", 0))
    rok_t, rok_rx = await loop.create_datagram_endpoint(Collect, local_addr=("127.0.0.1", 0))
    mvn_port = mvn_t.get_extra_info("sockname")[1]
    vmc_port = vmc_t.get_extra_info("sockname")[1]
    rok_port = rok_t.get_extra_info("sockname")[1]
    udp = UdpConfig(  # the suited person is pinned to MVN character 0, drives the one VMC avatar, is Rokoko's "Suited"
        mvn=MvnStreamConfig(enabled=True, destinations=(Destination("127.0.0.1", mvn_port),),
                            character_ids={"suit:suit0": 0}),
        vmc=VmcStreamConfig(enabled=True, destinations=(Destination("127.0.0.1", vmc_port),),
                            subjects=("suit:suit0",)),
        rokoko=RokokoStreamConfig(enabled=True, destinations=(Destination("127.0.0.1", rok_port),),
                                  actor_names={"suit:suit0": "Suited"}),
    )  # fmt: skip
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}), "udp": udp,
                                 "websocket": cfg.websocket.model_copy(update={"enabled": False})})  # fmt: skip
    rec = Recorder()
    try:
        with assembled(synthetic_config(cfg), RunOptions(sinks=[rec])) as demo:
            d = demo.daemon
            task = asyncio.create_task(d.run())
            await asyncio.wait_for(d.ready.wait(), 180)
            await wait_for(lambda: bool(rec.frames) and {p.identity for p in rec.frames[-1].people} >= {SUIT}
                           and len(rec.frames[-1].people) == 2, 120, "two people, one suited")  # fmt: skip
            n_mvn = len(mvn_rx.datagrams)
            await wait_for(lambda: len(mvn_rx.datagrams) > n_mvn + 20, 30, "MVN datagrams with two people")
            st = json.loads((await http_get(d.http.port, "/status"))[2])
            d.request_stop()
            assert await asyncio.wait_for(task, 5) == 0
            rig = d.rig.skeleton
    finally:
        mvn_t.close()
        vmc_t.close()
        rok_t.close()

    frames = {f.frame: f for f in rec.frames}
    for name in ("mvn", "vmc", "rokoko"):
        assert st["sinks"][name]["datagrams_sent"] > 0 and st["sinks"][name]["datagrams_dropped"] == 0
    assert st["sinks"]["mvn"]["slots"][SUIT] == 0 and st["sinks"]["vmc"]["slots"] == {SUIT: 0}

    # MVN: the sample counter is the frame number; each character's segments are one person's solved joints,
    # character 0 the suited person's.
    per_sample: dict[int, list[int]] = {}
    for raw in mvn_rx.datagrams[-20:]:
        dg = read_datagram(raw)
        assert dg.counter == 0x80 and dg.items == 23 and dg.body == 23
        pos = np.array([s[1] for s in dg.segments]) @ MVN.basis  # p_mvn = C p: back to mocapd axes
        f = frames[dg.sample]
        matches = [p for p in f.people if np.allclose(pos[0], p.joints[BONE_INDEX["Hips"]], atol=1e-5)]
        assert len(matches) == 1
        p = matches[0]
        np.testing.assert_allclose(pos[6], p.joints[BONE_INDEX["Head"]], atol=1e-5)
        np.testing.assert_allclose(pos[22], p.joints[BONE_INDEX["LeftToes"]], atol=1e-5)
        assert (dg.character == 0) == (p.identity == SUIT)
        per_sample.setdefault(dg.sample, []).append(dg.character)
    assert all(len(set(c)) == len(c) for c in per_sample.values())
    assert max(len(c) for c in per_sample.values()) == 2

    # VMC: the suited person's avatar; /VMC/Ext/T is seconds since the first published frame.
    t0 = rec.frames[0].t_solve_ns
    by_t = {round((f.t_solve_ns - t0) / 1e6): f for f in rec.frames}
    msgs = [m for raw in vmc_rx.datagrams[-40:] for m in OscBundle(raw) if isinstance(m, OscMessage)]
    hips: list[float] | None = None
    matched = 0
    for m in msgs:
        if m.address == "/VMC/Ext/Bone/Pos" and m.params[0] == "Hips":
            hips = [float(v) for v in m.params[1:]]
        elif m.address == "/VMC/Ext/T" and hips is not None:
            f = by_t[round(float(m.params[0]) * 1e3)]
            p = next(x for x in f.people if x.identity == SUIT)
            np.testing.assert_allclose(UNITY.positions(np.array(hips[:3])), p.theta[:3], atol=1e-5)
            x, y, z, w = hips[3:]
            R = UNITY.matrices(matrix_from_quat(np.array([w, x, y, z])))
            np.testing.assert_allclose(R, matrix_from_rotvec(p.theta[3:6]), atol=1e-5)
            matched += 1
            hips = None
    assert matched >= 10

    # Rokoko: one scene per published frame (its frame counter), each person an actor (the suited one named by
    # actor_names), every joint from the published pose; the timestamp counts from the first published frame.
    both = 0
    for raw in rok_rx.datagrams[-20:]:
        doc = decode(raw)
        f = frames[doc["frame"]]
        assert doc["fps"] == 60 and doc["scene"]["timestamp"] == pytest.approx((f.t_solve_ns - t0) / 1e9, abs=2e-6)
        names = {"Suited" if p.identity == SUIT else p.identity: p for p in f.people}
        # a subject lost a moment ago stays in the scene at its last pose with hasBody false (slot order is kept)
        shown = [a for a in doc["scene"]["actors"] if a["meta"]["hasBody"]]
        assert sorted(a["name"] for a in shown) == sorted(names)
        for actor in shown:
            p = names[actor["name"]]
            check_actor(actor, p.skeleton or rig, p.theta)
        both += len(names) == 2
    assert both >= 10
    assert st["sinks"]["rokoko"]["oversize_actors"] == 0 and st["sinks"]["rokoko"]["compression"] == "lz4"
