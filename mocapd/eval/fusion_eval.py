"""Seed 001's Table 6 on the accuracy harness (issue 30): every part of the learned fusion beside the LM solver.

On the harness's sequences (the same clips, detections and IMU readings the solver rows of ``mocapd eval accuracy``
use), for 4 and 8 ring cameras and 0, 6 and 13 IMUs:

- the PVH network on **matte**-only, **joint-channel**-only and **two-channel** PVHs, the vision **+ LSTM**, the
  **solved-IMU** stream (mocapd's IMU-only solve) and its LSTM, the **raw-IMU LSTM**, the **mean of the streams**
  and the **fused** output: joints only, evaluated on the learned stream's frames (every
  :data:`~mocapd.core.fusion_features.STRIDE`-th, as in the daemon);
- three solves on every frame: the **LM solver** (today's), **learned** (the skeleton fitted to the learned joints,
  extrapolated between learned frames as the daemon does: ``[fusion] mode = "learned"``) and **both** (the learned
  joints as E_J observations in the LM solve on the learned frames: ``mode = "both"``).

The IMU streams measure no position: their global error puts their root-relative joints on the IMU-only solve's root
(foot contacts), which drifts; their root-relative and Procrustes errors are the fair ones. The networks output
joints, not bone rotations: their "bone direction" column is the angle between solved and true bone vectors (no
twist); the full orientation error exists for the three solves.

:func:`run_scenarios` asks where the learned stack helps: the same comparison under clean inputs, realistic ones,
detector failures (left/right swaps and outliers), heavy occlusion, IMU heading drift, and few cameras.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.fusion_features import (
    JOINT_DIM,
    N_JOINTS,
    feature_windows,
    imu_windows,
    mean_of_streams,
    vision_windows,
)
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.retarget import Retargeted
from mocapd.core.skeleton import PARENTS
from mocapd.core.terms import CostOptions
from mocapd.eval.fusion_data import raw_imu, sequence_vision, solved_imu
from mocapd.eval.harness import Errors, RunConfig, Sequence, make_sequence, run_solver
from mocapd.eval.metrics import stats
from mocapd.eval.simulate import DetectionNoise, ImuNoise
from mocapd.pipeline.fusion import FusionModels
from mocapd.sim.silhouettes import MatteNoise

FloatArray = NDArray[np.float64]

NETWORK_ROWS = (
    "matte PVH",
    "joint-channel PVH",
    "two-channel PVH",
    "+ LSTM",
    "solved-IMU",
    "solved-IMU + LSTM",
    "raw-IMU LSTM",
    "mean of streams",
    "fused",
)
SOLVE_ROWS = ("LM solver", "learned (skeleton fit)", "both")
_VARIANT_ROWS = {"matte": "matte PVH", "joints": "joint-channel PVH", "both": "two-channel PVH"}


@dataclass(frozen=True)
class FusionEvalOptions:
    """What the learned-fusion part of ``mocapd eval accuracy`` runs."""

    camera_counts: tuple[int, ...] = (4, 8)
    imu_sets: tuple[int, ...] = (0, 6, 13)
    max_frames: int | None = None
    """Cap per sequence for Table 6 (None: the whole sequences of the main table)."""
    scenario_frames: int = 120
    scenario_configs: tuple[tuple[int, int], ...] = ((8, 13), (4, 6), (3, 13))
    scenarios: bool = True
    model: Path | None = None
    """Folder of the networks (None: ~/.cache/mocapd/fusion, written by tools/train_fusion.py)."""
    seed: int = 0
    ablation_variants: tuple[str, ...] = ("matte", "joints")
    """Single-channel PVH networks to evaluate when their files exist (``tools/train_fusion.py --ablation``)."""
    lambda_learned: float = CostOptions.lambda_learned
    extra: dict[str, Any] = field(default_factory=dict)


def bone_direction_errors(pred: FloatArray, truth: FloatArray) -> FloatArray:
    """Angle (deg) between predicted and true bone vectors (parent joint → joint), shape (f, 20)."""
    child = np.array([b for b, p in enumerate(PARENTS) if p >= 0])
    par = np.array([PARENTS[b] for b in child])
    a = pred[:, child] - pred[:, par]
    b = truth[:, child] - truth[:, par]
    cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
    return np.asarray(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclass
class _Rows:
    """Errors of every row of one configuration."""

    errors: dict[str, Errors] = field(default_factory=dict)
    bones: dict[str, list[FloatArray]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)

    def add(
        self, row: str, pos: FloatArray, truth: Retargeted, rot: FloatArray | None, seconds: float, bad: int = 0
    ) -> None:
        self.errors.setdefault(row, Errors.empty()).add(pos, truth, rot, bad)
        self.bones.setdefault(row, []).append(bone_direction_errors(pos, truth.positions))
        self.seconds[row] = self.seconds.get(row, 0.0) + seconds
        self.frames[row] = self.frames.get(row, 0) + pos.shape[0]

    def table(self) -> dict[str, Any]:
        out = {}
        for row, e in self.errors.items():
            t = e.table()
            t["bone_direction_deg"] = stats(np.concatenate(self.bones[row]))
            t["ms_per_frame"] = round(1e3 * self.seconds[row] / max(self.frames[row], 1), 3)
            out[row] = t
        return out


def _subset(clip: Retargeted, frames: NDArray[np.intp]) -> Retargeted:
    return replace(
        clip,
        theta=clip.theta[frames],
        positions=clip.positions[frames],
        rotations=clip.rotations[frames],
        source_positions=clip.source_positions[frames],
    )


@dataclass
class _Vision:
    """The vision stream of one sequence and camera count on its learned frames."""

    frames: NDArray[np.intp]
    centre: FloatArray
    views: FloatArray
    per_frame: dict[str, FloatArray]  # variant -> world joints (n, 21, 3)
    lstm: FloatArray  # (n, 21, 3) world
    pvh_s: float
    cnn_s: float
    lstm_s: float


def _vision(seq: Sequence, n_cams: int, models: FusionModels, variants: tuple[str, ...], seed: int) -> _Vision:
    stride = models.stride
    frames = np.arange(0, seq.clip.n_frames, stride)
    vi = sequence_vision(seq, n_cams, models.grid, MatteNoise(), seed, frames=frames)
    pvh = vi.pvh.astype(np.float32) / np.float32(255.0)
    per: dict[str, FloatArray] = {}
    cnn_s = 0.0
    for v in variants:
        ch = {"both": [0, 1], "matte": [0], "joints": [1]}[v]
        c0 = time.perf_counter()
        rel = np.concatenate([models.cnn(pvh[i : i + 64][:, ch], v) for i in range(0, len(pvh), 64)])
        if v == "both":
            cnn_s = time.perf_counter() - c0
        per[v] = rel.astype(np.float64).reshape(-1, N_JOINTS, 3) + vi.centre[:, None, :]
    t2 = time.perf_counter()
    win = vision_windows(per["both"], vi.centre, models.look_back)
    v_rel, _, _ = models.temporal(
        win.astype(np.float32), np.zeros_like(win, dtype=np.float32), vi.views[:, None].astype(np.float32)
    )
    lstm = v_rel.astype(np.float64).reshape(-1, N_JOINTS, 3) + vi.centre[:, None, :]
    return _Vision(frames, vi.centre, vi.views, per, lstm, vi.seconds, cnn_s, time.perf_counter() - t2)


def _extrapolated(frames: NDArray[np.intp], joints: FloatArray, n: int, stride: int) -> dict[int, FloatArray]:
    """Per frame, the learned joints of the daemon's ``mode = "learned"``: the learned frame's own, and between
    learned frames the last one carried at the velocity of the last two."""
    out: dict[int, FloatArray] = {}
    for k, f in enumerate(frames):
        step = (joints[k] - joints[k - 1]) / stride if k > 0 else np.zeros_like(joints[k])
        for d in range(stride):
            if f + d < n:
                out[int(f + d)] = joints[k] + d * step
    return out


def evaluate_sequences(
    seqs: list[Sequence],
    opts: FusionEvalOptions,
    models: FusionModels,
    prior: PcaPrior | None,
    cost: CostOptions,
    tick: Callable[[int], None] = lambda n: None,
    configs: tuple[tuple[int, int], ...] | None = None,
    network_rows: bool = True,
) -> dict[str, Any]:
    """Every row for every (cameras, IMUs) configuration; ``{"8c13i": {row: table}}``."""
    configs = configs or tuple((c, i) for c in opts.camera_counts for i in opts.imu_sets)
    variants = ("both", *(v for v in opts.ablation_variants if v in models.variants))
    rows = {f"{c}c{i}i": _Rows() for c, i in configs}
    cost_j = replace(cost, lambda_learned=opts.lambda_learned)
    stride = models.stride
    for seq in seqs:
        clip = seq.clip
        n = clip.n_frames
        kin = Kinematics(clip.skeleton)
        solved: dict[int, tuple[FloatArray, float]] = {}
        for i in sorted({i for _, i in configs if i}):
            t0 = time.perf_counter()
            solved[i] = (solved_imu(seq, i, prior, cost), time.perf_counter() - t0)
        for n_cams in sorted({c for c, _ in configs}):
            vis = _vision(seq, n_cams, models, variants if network_rows else ("both",), opts.seed)
            frames = vis.frames
            truth = _subset(clip, frames)
            nl = len(frames)
            for c, i in configs:
                if c != n_cams:
                    continue
                r = rows[f"{c}c{i}i"]
                per_pvh = (vis.pvh_s + vis.cnn_s) / nl
                if network_rows:
                    for v, joints in vis.per_frame.items():
                        r.add(_VARIANT_ROWS[v], joints, truth, None, per_pvh * nl)
                    r.add("+ LSTM", vis.lstm, truth, None, (vis.pvh_s + vis.cnn_s + vis.lstm_s))
                learned = vis.lstm
                if i:
                    sj, s_time = solved[i]
                    sjl = sj[frames]
                    t0 = time.perf_counter()
                    iw = imu_windows(sjl, models.look_back)
                    rw = feature_windows(raw_imu(seq, i)[frames], models.look_back)
                    vw = vision_windows(vis.per_frame["both"], vis.centre, models.look_back)
                    _, i_rel, fused = models.temporal(
                        vw.astype(np.float32), iw.astype(np.float32), vis.views[:, None].astype(np.float32)
                    )
                    t_temporal = time.perf_counter() - t0
                    i_rel64 = i_rel.astype(np.float64).reshape(nl, N_JOINTS, 3)
                    fused_w = fused.astype(np.float64).reshape(nl, N_JOINTS, 3) + vis.centre[:, None, :]
                    root = sjl[:, :1]  # the IMU-only solve's own root
                    if network_rows:
                        r.add("solved-IMU", sjl, truth, None, s_time / n * nl)
                        r.add("solved-IMU + LSTM", i_rel64 - i_rel64[:, :1] + root, truth, None, s_time / n * nl)
                        raw_rel = models.raw_imu(rw.astype(np.float32)).astype(np.float64).reshape(nl, N_JOINTS, 3)
                        r.add("raw-IMU LSTM", raw_rel - raw_rel[:, :1] + root, truth, None, 0.0)
                        v_rel = vis.lstm - vis.centre[:, None, :]
                        mean = mean_of_streams(v_rel, i_rel64) + vis.centre[:, None, :]
                        r.add("mean of streams", mean, truth, None, (vis.pvh_s + vis.cnn_s + vis.lstm_s) + s_time)
                        r.add("fused", fused_w, truth, None, vis.pvh_s + vis.cnn_s + t_temporal + s_time)
                    learned = fused_w
                t_learned = vis.pvh_s + vis.cnn_s + vis.lstm_s + (solved[i][1] if i else 0.0)
                solves: tuple[tuple[str, RunConfig, dict[int, FloatArray] | None], ...] = (
                    ("LM solver", RunConfig(c, i), None),
                    ("learned (skeleton fit)", RunConfig(0, 0), _extrapolated(frames, learned, n, stride)),
                    ("both", RunConfig(c, i), {int(f): learned[k] for k, f in enumerate(frames)}),
                )
                for row, cfg, targets in solves:
                    t0 = time.perf_counter()
                    theta, bad = run_solver(seq, cfg, prior, cost_j, learned=targets)
                    dt = time.perf_counter() - t0 + (t_learned if targets is not None else 0.0)
                    fk = kin.forward(theta)
                    r.add(row, fk.positions, clip, fk.rotations, dt, bad)
            tick(n * len([1 for c, _ in configs if c == n_cams]))
    return {k: v.table() for k, v in rows.items()}


SCENARIOS: dict[str, tuple[DetectionNoise, ImuNoise, str]] = {
    "clean": (DetectionNoise.clean(), ImuNoise.clean(), "σ = 1 px, no misses, outliers or swaps; noiseless IMUs"),
    "realistic": (DetectionNoise(), ImuNoise(), "the harness's realistic detections and IMUs"),
    "detector failures": (
        DetectionNoise(outlier=0.20, swap=0.25),
        ImuNoise(),
        "20 % gross outliers, left/right swaps in 25 % of person-frames per camera",
    ),
    "occlusion": (DetectionNoise(missed=0.40), ImuNoise(), "40 % of keypoints missed (on top of self-occlusion)"),
    "IMU drift": (
        DetectionNoise(),
        ImuNoise(calibration_deg=10.0, heading_walk_deg_per_sqrt_min=30.0),
        "10° mounting error, heading random walk 30°/√min",
    ),
}


def run_scenarios(
    clips: list[Retargeted],
    opts: FusionEvalOptions,
    models: FusionModels,
    prior: PcaPrior | None,
    cost: CostOptions,
    tick: Callable[[int], None] = lambda n: None,
) -> dict[str, Any]:
    """The solves and the fused joints under each scenario's sensor noise (first ``scenario_frames`` of each
    clip); ``{scenario: {"8c13i": {row: table}}}``."""
    out: dict[str, Any] = {}
    for name, (det, imu, what) in SCENARIOS.items():
        seqs = [make_sequence(c, zlib.crc32(f"{opts.seed}:scenario:{name}:{c.name}".encode()), det, imu) for c in clips]
        res = evaluate_sequences(seqs, opts, models, prior, cost, tick, opts.scenario_configs, network_rows=False)
        out[name] = {"what": what, "results": res}
    return out


def markdown(res: dict[str, Any]) -> str:
    """Markdown tables of a learned-fusion evaluation (the ``fusion`` part of ``results.json``)."""
    t6 = res["table6"]
    configs = list(t6)
    lines = [
        "## Learned fusion: seed 001 Table 6 on the evaluation split",
        "",
        f"Network rows on the learned frames (every {res['setup']['stride']} frames:"
        f" {60 / res['setup']['stride']:.0f} Hz), solves on every frame."
        " IMU rows' global error puts their root-relative joints on the IMU-only solve's (drifting) root.",
        "",
        "### Global mean joint error (mm)",
        "",
        "| method | " + " | ".join(_config_name(c) for c in configs) + " |",
        "|---|" + "---|" * len(configs),
    ]
    rows = [*NETWORK_ROWS, *SOLVE_ROWS]
    for metric, title in (
        ("global_mm", None),
        ("root_relative_mm", "### Root-relative mean joint error (mm)"),
        ("procrustes_mm", "### Procrustes-aligned mean joint error (mm)"),
        ("bone_direction_deg", "### Bone direction error (deg, all rows) / orientation error (deg, solves)"),
    ):
        if title is not None:
            lines += [
                "",
                title,
                "",
                "| method | " + " | ".join(_config_name(c) for c in configs) + " |",
                "|---|" + "---|" * len(configs),
            ]
        for row in rows:
            cells = []
            for c in configs:
                r = t6[c].get(row)
                if r is None:
                    cells.append("–")
                    continue
                v = r[metric]["mean"]
                cell = f"{v:.1f}"
                if metric == "bone_direction_deg" and r.get("orientation_deg"):
                    cell += f" / {r['orientation_deg']['mean']:.1f}"
                cells.append(cell)
            if any(x != "–" for x in cells):
                lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "### Cost per frame (ms, measured inside the evaluation on the shared machine: indicative only)",
        "",
        "| method | " + " | ".join(_config_name(c) for c in configs) + " |",
        "|---|" + "---|" * len(configs),
    ]
    for row in rows:
        cells = [f"{t6[c][row]['ms_per_frame']:.2f}" if row in t6[c] else "–" for c in configs]
        if any(x != "–" for x in cells):
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    sc = res.get("scenarios")
    if sc:
        lines += [
            "",
            "### Where the learned stack helps: global / Procrustes mean joint error (mm), orientation (deg)",
            "",
        ]
        cfgs = list(next(iter(sc.values()))["results"])
        lines += [
            "| scenario | method | " + " | ".join(_config_name(c) for c in cfgs) + " |",
            "|---|---|" + "---|" * len(cfgs),
        ]
        for name, s in sc.items():
            for row in SOLVE_ROWS:
                cells = []
                for c in cfgs:
                    r = s["results"][c][row]
                    cells.append(
                        f"{r['global_mm']['mean']:.1f} / {r['procrustes_mm']['mean']:.1f} / "
                        f"{r['orientation_deg']['mean']:.1f}°"
                    )
                lines.append(f"| {name} | {row} | " + " | ".join(cells) + " |")
        lines += ["", "Scenarios: " + "; ".join(f"**{k}**: {v['what']}" for k, v in sc.items()) + "."]
    lines.append("")
    return "\n".join(lines)


def _config_name(c: str) -> str:
    cams, imus = c.rstrip("i").split("c")
    return f"{cams} cams + {imus} IMUs"


__all__ = ["JOINT_DIM", "FusionEvalOptions", "evaluate_sequences", "markdown", "run_scenarios"]
