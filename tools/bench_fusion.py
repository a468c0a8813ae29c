#!/usr/bin/env python3
"""Per-frame cost of the learned fusion in the daemon's tick (issue 30), for 1 and 2 people, as JSON.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

What the daemon does per tick and person, on a simulated 60 Hz stream of real CMU motion (the development split's
CMU clip, each person a copy turned and moved): the IMU-only solve of the person's 13-IMU suit (every tick), on
every ``stride``-th tick the learned frame (grid centre, joint channels, carving the two-channel PVH, the PVH
network, the temporal graph), and the person's LM solve with the learned joints as E_J ("both"). The baseline,
in the same process on the same frames: the LM solve alone ("solver"). The mattes are rendered before the clock
starts (a live rig's come from its cameras); the background subtraction of a live camera frame is timed apart
(``mog2_ms_per_camera_frame``, 1920×1080 frames).

Usage::

    .venv/bin/python tools/bench_fusion.py [--model DIR] [--cams 8 4] [--people 1 2] [--seconds 6] [--networks]

Medians and 90th percentiles in ms; ``tick_*`` is the whole tick (all people), ``per_tick_mean`` amortises the
learned frames over the ticks between them. BLAS and onnxruntime use one thread each, so the thread's CPU time
(``cpu``: the same ticks by ``time.thread_time``) is the cost; wall time adds whatever else the machine runs.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from mocapd.core.imu import IMU_SET_13, default_mounts
from mocapd.core.keypoints import coco17_targets
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.eval.data import load_clip
from mocapd.eval.fusion_data import rotate_clip, training_clips
from mocapd.eval.harness import make_sequence
from mocapd.eval.simulate import DetectionNoise, ImuNoise, totalcapture_ring
from mocapd.io.prior import load_default_prior
from mocapd.pipeline.fusion import F32, FusionModels, FusionStage
from mocapd.pipeline.mattes import BackgroundMatte
from mocapd.sim.silhouettes import MatteNoise, simulated_matte


def _ms(xs: list[float]) -> dict[str, float]:
    a = np.asarray(xs) * 1e3
    return {"median": round(float(np.median(a)), 3), "p90": round(float(np.percentile(a, 90)), 3)}


def _ticks(solver: list[float], both: list[float]) -> dict[str, Any]:
    """A tick's times (wall or CPU, s) for the solver alone and with the learned fusion: distributions, means and
    the share of one core at the 60 Hz output."""
    period = 1 / 60
    return {
        "tick_solver_ms": _ms(solver),
        "tick_both_ms": _ms(both),
        "per_tick_mean_ms": {k: round(1e3 * float(np.mean(v)), 3) for k, v in (("solver", solver), ("both", both))},
        "share_of_one_core_at_60hz": {
            k: round(float(np.mean(v)) / period, 3) for k, v in (("solver", solver), ("both", both))
        },
    }


def bench(models: FusionModels, n_cams: int, n_people: int, seconds: float) -> dict[str, Any]:
    clip = load_clip(training_clips()[1][0])
    n = min(clip.n_frames, round(60 * seconds))
    ring = totalcapture_ring(8)[:n_cams]
    prior = load_default_prior()
    cost = CostOptions()
    seqs = []
    for p in range(n_people):
        c = rotate_clip(clip, 2.0 * p, np.array([1.2 * p - 0.6 * (n_people - 1), 0.0]))
        seqs.append(make_sequence(c, 100 + p, DetectionNoise(), ImuNoise()))
    targets = coco17_targets(clip.skeleton)
    mounts = default_mounts(IMU_SET_13, clip.skeleton)
    rng = np.random.default_rng(0)
    grid = models.grid
    mattes = [
        [
            simulated_matte(cam, [(s.clip.positions[t], s.clip.skeleton.height) for s in seqs], grid.scale,
                            MatteNoise(), rng)
            for cam in ring
        ]
        for t in range(n)
    ]  # fmt: skip
    stage = FusionStage(models, ring, targets, prior, cost)
    base = [PoseSolver(clip.skeleton, ring, targets, mounts, prior, cost) for _ in seqs]
    both = [PoseSolver(clip.skeleton, ring, targets, mounts, prior, cost) for _ in seqs]
    for s, b, q in zip(base, both, seqs, strict=True):
        s.reset(q.clip.theta[0])
        b.reset(q.clip.theta[0])
    tick_solver: list[float] = []
    tick_both: list[float] = []
    learned_ticks: list[float] = []
    cpu_solver: list[float] = []
    cpu_both: list[float] = []
    other_ticks: list[float] = []
    parts: dict[str, list[float]] = {"imu_solve": [], "pvh": [], "cnn": [], "temporal": []}
    solve_alone, solve_ej = [], []
    for t in range(n):
        obs = []
        for q in seqs:
            uv, cf = q.uv[t, :n_cams], q.conf[t, :n_cams]
            obs.append(
                Observations(
                    keypoints=uv,
                    confidences=cf,
                    imu_orientations=q.q13[t],
                    imu_accelerations=q.acc13[t] if t >= 2 else None,
                    dt=1 / 60,
                )
            )
        t0, c0 = time.perf_counter(), time.thread_time()
        for s, o in zip(base, obs, strict=True):
            a0 = time.perf_counter()
            s.solve(o)
            solve_alone.append(time.perf_counter() - a0)
        t1, c1 = time.perf_counter(), time.thread_time()
        learned_tick = False
        frame_mattes: list[F32 | None] = list(mattes[t])
        for p, (b, o) in enumerate(zip(both, obs, strict=True)):
            imu = (mounts, Observations(imu_orientations=o.imu_orientations, imu_accelerations=o.imu_accelerations,
                                        dt=o.dt))  # fmt: skip
            assert o.keypoints is not None and o.confidences is not None
            lj = stage.step(
                f"p{p}", clip.skeleton, b.theta, np.nan_to_num(o.keypoints), o.confidences,
                functools.partial(list, frame_mattes), 1 / 60, imu,
            )  # fmt: skip
            for k, v in stage.last_ms.items():
                parts[k].append(v / 1e3)
            a0 = time.perf_counter()
            b.solve(o if lj is None else replace(o, joint_positions=lj.joints))
            if lj is not None:
                solve_ej.append(time.perf_counter() - a0)
                learned_tick = True
        t2, c2 = time.perf_counter(), time.thread_time()
        tick_solver.append(t1 - t0)
        tick_both.append(t2 - t1)
        cpu_solver.append(c1 - c0)
        cpu_both.append(c2 - c1)
        (learned_ticks if learned_tick else other_ticks).append(t2 - t1)
    return {
        "cameras": n_cams,
        "people": n_people,
        "ticks": n,
        **_ticks(tick_solver, tick_both),
        "tick_both_learned_frame_ms": _ms(learned_ticks),
        "tick_both_other_ms": _ms(other_ticks),
        "cpu": _ticks(cpu_solver, cpu_both),
        "per_person_learned_frame_ms": {k: _ms(v) for k, v in parts.items() if v},
        "lm_solve_ms": {"alone": _ms(solve_alone), "with_learned_joints": _ms(solve_ej)},
    }


def carve_cost(reps: int = 5) -> dict[str, Any]:
    """Carving one person's 30³ two-channel PVH from 8 cameras with 1, 2 and 3 fine voxels per coarse voxel and
    axis (seed 001 carves ~10 mm voxels: 200³), and how much the supersampled hull differs from the coarse one."""
    from mocapd.core.pvh import PvhGrid, carve, joint_map, joint_sigma, log_channels, person_centre, scaled_pixels

    clip = load_clip(training_clips()[1][0])
    seq = make_sequence(clip, 7, DetectionNoise(), ImuNoise())
    ring = totalcapture_ring(8)
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {}
    vols = {}
    t = clip.n_frames // 2
    for ss in (1, 2, 3):
        g = PvhGrid(supersample=ss)
        centre = person_centre(ring, seq.uv[t], seq.conf[t])
        assert centre is not None
        imgs = []
        for c, cam in enumerate(ring):
            m = simulated_matte(cam, [(clip.positions[t], clip.skeleton.height)], g.scale, MatteNoise.clean(), rng)
            jm = joint_map(scaled_pixels(np.nan_to_num(seq.uv[t, c]), g.scale), seq.conf[t, c], m.shape,
                           joint_sigma(cam, centre, g.scale))  # fmt: skip
            imgs.append(log_channels(np.stack((m, jm))))
        valid = np.ones((8, 2), dtype=bool)
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            vols[ss] = carve(g, centre, ring, imgs, valid)
            times.append(time.perf_counter() - t0)
        out[f"supersample_{ss}"] = {"fine_voxels": (30 * ss) ** 3, "carve_ms_8_cameras": _ms(times)}
    for ss in (2, 3):
        d = np.abs(vols[ss] - vols[1])
        out[f"supersample_{ss}"]["mean_abs_difference_from_1"] = round(float(d.mean()), 4)
        out[f"supersample_{ss}"]["body_voxels_changed_by_over_0.2"] = round(float((d[0] > 0.2).mean()), 4)
    return out


def network_cost(reps: int = 10) -> dict[str, Any]:
    """Seed 001 Table 1's PVH network against mocapd's quarter-width one: onnxruntime inference per person-frame
    (one thread) and torch training time per sample (batch 32). Needs the ``[train]`` extra."""
    import tempfile
    import warnings

    import onnxruntime as ort
    import torch

    from mocapd.eval.fusion_train import PvhNet

    torch.set_num_threads(1)
    out: dict[str, Any] = {}
    for name, widths, fc in (("table_1", (64, 96, 96, 96), 1024), ("mocapd", (16, 24, 24, 32), 256)):
        net = PvhNet(2, widths, fc, 30)
        x = torch.rand(32, 2, 30, 30, 30)
        opt = torch.optim.Adam(net.parameters(), 1e-3)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            opt.zero_grad()
            loss = net(x).pow(2).mean()
            loss.backward()
            opt.step()
            times.append((time.perf_counter() - t0) / 32)
        with tempfile.TemporaryDirectory() as tmp:
            path = f"{tmp}/net.onnx"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                torch.onnx.export(net.eval(), (x[:1],), path, input_names=["pvh"], dynamo=False)
            so = ort.SessionOptions()
            so.intra_op_num_threads = 1
            sess = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
            one = x[:1].numpy()
            sess.run(None, {"pvh": one})
            inf = []
            for _ in range(reps):
                t0 = time.perf_counter()
                sess.run(None, {"pvh": one})
                inf.append(time.perf_counter() - t0)
        out[name] = {
            "parameters": sum(p.numel() for p in net.parameters()),
            "onnxruntime_ms_per_person_frame": _ms(inf),
            "torch_train_ms_per_sample": _ms(times),
        }
    return out


def mog2_cost(frames: int = 60) -> dict[str, Any]:
    """Background subtraction of one 1920×1080 camera frame (resize to 1/8 + MOG2 + blur): wall time, and the
    process's CPU time (OpenCV may use threads)."""
    rng = np.random.default_rng(0)
    bm = BackgroundMatte()
    img = rng.integers(0, 255, size=(1080, 1920, 3), dtype=np.uint8)
    times, cpu = [], []
    for _ in range(frames):
        t0, c0 = time.perf_counter(), time.process_time()
        bm.apply(img)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {**_ms(times), "cpu": _ms(cpu)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--model",
        type=Path,
        default=None,
        help="networks folder (default: ~/.cache/mocapd/fusion, from tools/train_fusion.py)",
    )
    ap.add_argument("--cams", type=int, nargs="+", default=[8, 4])
    ap.add_argument("--people", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--networks", action="store_true", help="also Table 1's network against ours (needs torch)")
    args = ap.parse_args()
    load0 = os.getloadavg()
    with threadpool_limits(1):
        models = FusionModels(args.model, threads=1)
        runs = [bench(models, c, p, args.seconds) for c in args.cams for p in args.people]
        mog2 = mog2_cost()
        carving = carve_cost()
    out = {
        "stride": models.stride,
        "learned_rate_hz": 60.0 / models.stride,
        "grid": {"size": models.grid.size, "extent_m": models.grid.extent, "supersample": models.grid.supersample},
        "model": str(models.directory),
        "runs": runs,
        "mog2_ms_per_camera_frame": mog2,
        "carve_supersample": carving,
        "networks": network_cost() if args.networks else None,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "loadavg_start": [round(x, 2) for x in load0],
            "loadavg_end": [round(x, 2) for x in os.getloadavg()],
        },
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
