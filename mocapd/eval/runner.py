"""Runs every experiment of the harness and writes the results directory (JSON, markdown, PNG)."""

from __future__ import annotations

import json
import os
import platform
import time
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.terms import CostOptions
from mocapd.eval.baselines import LIMB_JOINTS
from mocapd.eval.data import load_clip, load_splits
from mocapd.eval.fusion_eval import SCENARIOS, FusionEvalOptions, evaluate_sequences, run_scenarios
from mocapd.eval.fusion_eval import markdown as fusion_markdown
from mocapd.eval.harness import (
    Errors,
    RunConfig,
    Sequence,
    make_sequence,
    run_imu_only,
    run_triangulation,
    solver_errors,
    windows,
)
from mocapd.eval.report import write_report
from mocapd.eval.simulate import DetectionNoise, ImuNoise
from mocapd.io.prior import resolve_prior
from mocapd.io.progress import Progress
from mocapd.pipeline.fusion import FusionModels, available_variants

ABLATION_TERMS = ("position", "orientation", "acceleration", "prior_projection", "prior_deviation", "floor")
SUBSAMPLING = ((1, 1), (1, 2), (2, 4), (3, 6), (1, 4), (2, 8), (3, 12), (1, 8), (2, 16), (3, 24))


@dataclass(frozen=True)
class EvalOptions:
    """What ``mocapd eval accuracy`` runs."""

    split: str = "evaluation"
    max_frames: int | None = None
    """Cap per sequence for the main table (None: whole sequences)."""
    sweep_frames: int = 120
    """Cap per sequence for the sweep, the ablation and the sub-sampling study."""
    sweep_cams: tuple[int, ...] = tuple(range(9))
    sweep_imus: tuple[int, ...] = (0, 6, 13)
    max_sequences: int | None = None
    seed: int = 0
    detections: DetectionNoise = field(default_factory=DetectionNoise.realistic)
    imus: ImuNoise = field(default_factory=ImuNoise)
    cost: CostOptions = field(default_factory=CostOptions.seed_003)
    cost_label: str = "CostOptions.seed_003() (seed 003's weights)"
    prior: str = "default"
    progress: bool = True
    fusion: FusionEvalOptions | None = None
    """Also seed 001's Table 6: the learned fusion beside the solver (issue 30, docs/learned-fusion.md)."""
    only_fusion: bool = False
    """Run the learned-fusion evaluation alone (no main table, sweep, ablation or sub-sampling)."""

    @classmethod
    def quick(cls) -> EvalOptions:
        """The CI smoke run: the ``quick`` split, short sequences, a coarse sweep."""
        return cls(split="quick", max_frames=240, sweep_frames=90, sweep_cams=(0, 1, 2, 4, 8), max_sequences=4)


def _head(seq: Sequence, n: int | None) -> Sequence:
    if n is None or seq.clip.n_frames <= n:
        return seq
    c = seq.clip
    clip = replace(
        c,
        theta=c.theta[:n],
        positions=c.positions[:n],
        rotations=c.rotations[:n],
        source_positions=c.source_positions[:n],
    )
    return Sequence(
        seq.name,
        clip,
        seq.uv[:n],
        seq.conf[:n],
        seq.h_px[:n],
        seq.arc_uv[:n],
        seq.arc_conf[:n],
        seq.arc_h_px[:n],
        seq.q13[:n],
        seq.acc13[:n],
    )


def prepare(opts: EvalOptions, data_root: Path | None) -> list[Sequence]:
    """Load, retarget, cut and simulate the split's sequences (seeded per sequence name)."""
    seqs = []
    for f in load_splits(data_root)[opts.split]:
        for w in windows(load_clip(f)):
            seed = zlib.crc32(f"{opts.seed}:{w.name}".encode())
            seqs.append(make_sequence(w, seed, opts.detections, opts.imus))
    if opts.max_sequences is not None:
        seqs = seqs[: opts.max_sequences]
    return seqs


def run_fusion(
    opts: EvalOptions, seqs: list[Sequence], prior: PcaPrior | None, data_root: Path | None
) -> dict[str, Any]:
    """The learned-fusion rows (Table 6) on the main table's sequences, and the scenarios."""
    assert opts.fusion is not None
    fo = opts.fusion
    t0 = time.perf_counter()
    models = FusionModels(fo.model, variants=available_variants(fo.model), raw_imu=True)
    table_seqs = [_head(s, fo.max_frames or opts.max_frames) for s in seqs]
    n = sum(s.clip.n_frames for s in table_seqs)
    clips = [_head(s, fo.scenario_frames).clip for s in seqs] if fo.scenarios else []
    n_sc = sum(c.n_frames for c in clips) * len(SCENARIOS) * len(fo.scenario_configs)
    bar = Progress(n * len(fo.camera_counts) * len(fo.imu_sets) + n_sc, "learned fusion", enabled=opts.progress)
    out: dict[str, Any] = {
        "table6": evaluate_sequences(table_seqs, fo, models, prior, opts.cost, bar),
        "scenarios": run_scenarios(clips, fo, models, prior, opts.cost, bar) if fo.scenarios else None,
    }
    bar.close()
    out["setup"] = {
        "sequences": len(table_seqs),
        "frames": n,
        "scenario_frames_per_sequence": fo.scenario_frames,
        "stride": models.stride,
        "look_back": models.look_back,
        "grid": {"size": models.grid.size, "extent_m": models.grid.extent, "supersample": models.grid.supersample},
        "model": str(models.directory),
        "model_date": models.provenance.get("date"),
        "variants": list(models.variants),
        "lambda_learned": fo.lambda_learned,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    return out


def run_eval(opts: EvalOptions, out_dir: Path, data_root: Path | None = None) -> dict[str, Any]:
    t_start = time.perf_counter()
    load0 = os.getloadavg()
    prior: PcaPrior | None = resolve_prior(opts.prior)
    seqs = prepare(opts, data_root)
    if opts.only_fusion:
        only: dict[str, Any] = {"fusion": run_fusion(opts, seqs, prior, data_root)}
        only["setup"] = {"split": opts.split, "sequences": [s.name for s in seqs], "seed": opts.seed,
                            "cost": opts.cost_label, "wall_s": round(time.perf_counter() - t_start, 1),
                            "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg())}  # fmt: skip
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "results.json").write_text(json.dumps(_clean(only), indent=2) + "\n", encoding="utf-8")
        (out_dir / "tables.md").write_text(fusion_markdown(only["fusion"]), encoding="utf-8")
        return only
    main = [_head(s, opts.max_frames) for s in seqs]
    short = [_head(s, opts.sweep_frames) for s in seqs]
    n_main = sum(s.clip.n_frames for s in main)
    n_short = sum(s.clip.n_frames for s in short)
    sweep_cfgs = [(c, i) for i in opts.sweep_imus for c in opts.sweep_cams]
    total = n_main * 6 + n_short * (len(sweep_cfgs) + len(ABLATION_TERMS) + len(SUBSAMPLING))
    bar = Progress(total, "accuracy", enabled=opts.progress)
    cost = opts.cost
    results: dict[str, Any] = {}

    # -- main table: the solver and the baselines on the same inputs --------------------------------------
    per_seq: dict[str, Any] = {}
    main_rows: dict[str, Errors] = {}
    t0 = time.perf_counter()
    for label, cfg in (
        ("solver 8 cams + 13 IMUs", RunConfig(8, 13)),
        ("solver 4 cams + 6 IMUs", RunConfig(4, 6)),
        ("solver arc 4 cams + 13 IMUs", RunConfig(4, 13, "arc")),
    ):
        bar.label = label
        main_rows[label] = solver_errors(main, cfg, prior, cost, bar, per_seq.setdefault(label, {}))
    solve_s = time.perf_counter() - t0
    for label, n, rig in (
        ("triangulation 8 cams", 8, "ring"),
        ("triangulation 4 cams", 4, "ring"),
        ("triangulation arc 4 cams", 4, "arc"),
    ):
        bar.label = label
        e = Errors.empty()
        for s in main:
            e.add(run_triangulation(s, n, rig), s.clip, None)
        bar(n_main // 3)
        main_rows[label] = e
    for label, n in (("IMU-only FK 13 IMUs", 13), ("IMU-only FK 6 IMUs", 6)):
        e = Errors.empty()
        for s in main:
            fk = Kinematics(s.clip.skeleton).forward(run_imu_only(s, n))
            e.add(fk.positions, s.clip, fk.rotations)
        main_rows[label] = e
    results["main"] = {k: v.table() for k, v in main_rows.items()}
    results["main_limb12"] = {k: v.table(LIMB_JOINTS) for k, v in main_rows.items()}
    results["per_sequence"] = per_seq
    results["targets"] = _targets(results)

    # -- sweep: cameras 0..8 × IMUs 0/6/13 (Figure 7 analog) -----------------------------------------------
    sweep: dict[str, Any] = {}
    for c, i in sweep_cfgs:
        bar.label = f"sweep {c} cams {i} IMUs"
        sweep[f"{c}c_{i}i"] = {"cams": c, "imus": i, **solver_errors(short, RunConfig(c, i), prior, cost, bar).table()}
    results["sweep"] = sweep

    # -- ablation: each term omitted, relative to the full cost (Table 3 analog) -------------------------
    base = solver_errors(short, RunConfig(8, 13), prior, cost, lambda n: None).table()
    abl: dict[str, Any] = {"full": base}
    for term in ABLATION_TERMS:
        bar.label = f"ablation -{term}"
        off: dict[str, Any] = {f"use_{term}": False}
        c2 = replace(cost, **off)
        abl[f"without {term}"] = solver_errors(short, RunConfig(8, 13, cost=c2), prior, cost, bar).table()
    results["ablation"] = {"absolute": abl, "relative": _relative(abl)}

    # -- detection sub-sampling N_o/N_p (seed 000 Figure 4 analog) ----------------------------------------
    ss: dict[str, Any] = {}
    for no, np_ in SUBSAMPLING:
        bar.label = f"subsampling {no}/{np_}"
        ss[f"{no}/{np_}"] = {
            "N_o": no,
            "N_p": np_,
            **solver_errors(short, RunConfig(8, 13, subsample=(no, np_)), prior, cost, bar).table(),
        }
    results["subsampling"] = ss
    bar.close()
    if opts.fusion is not None:
        results["fusion"] = run_fusion(opts, seqs, prior, data_root)

    results["setup"] = {
        "split": opts.split,
        "sequences": [s.name for s in seqs],
        "frames_main": n_main,
        "frames_sweep": n_short,
        "max_frames": opts.max_frames,
        "sweep_frames": opts.sweep_frames,
        "seed": opts.seed,
        "detections": opts.detections.__dict__,
        "imus": opts.imus.__dict__,
        "cost": opts.cost_label,
        "prior": opts.prior if prior is None else f"{opts.prior} ({prior.n_components} components)",
        "rate_hz": 60.0,
        "solver_ms_per_frame_main": round(1e3 * solve_s / max(3 * n_main, 1), 3),
        "wall_s": round(time.perf_counter() - t_start, 1),
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "loadavg_start": [round(x, 2) for x in load0],
            "loadavg_end": [round(x, 2) for x in os.getloadavg()],
        },
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(json.dumps(_clean(results), indent=2) + "\n", encoding="utf-8")
    write_report(results, out_dir)
    return results


def _targets(r: dict[str, Any]) -> dict[str, Any]:
    m, l12 = r["main"], r["main_limb12"]

    def ratio(tab: dict[str, Any], a: str, b: str) -> float:
        return round(float(tab[a]["global_mm"]["mean"]) / float(tab[b]["global_mm"]["mean"]), 3)

    out = {
        "8c13i_vs_triangulation_8c_global_mean_ratio": ratio(m, "solver 8 cams + 13 IMUs", "triangulation 8 cams"),
        "4c6i_vs_triangulation_4c_global_mean_ratio": ratio(m, "solver 4 cams + 6 IMUs", "triangulation 4 cams"),
        "8c13i_vs_triangulation_8c_limb12_ratio": ratio(l12, "solver 8 cams + 13 IMUs", "triangulation 8 cams"),
        "4c6i_vs_triangulation_4c_limb12_ratio": ratio(l12, "solver 4 cams + 6 IMUs", "triangulation 4 cams"),
        "8c13i_orientation_mean_deg": m["solver 8 cams + 13 IMUs"]["orientation_deg"]["mean"],
    }
    out["met"] = {
        "ratio_8c13i_le_0.7": out["8c13i_vs_triangulation_8c_global_mean_ratio"] <= 0.7,
        "ratio_4c6i_le_0.7": out["4c6i_vs_triangulation_4c_global_mean_ratio"] <= 0.7,
        "orientation_le_7.5deg": out["8c13i_orientation_mean_deg"] <= 7.5,
    }
    return out


def _relative(abl: dict[str, Any]) -> dict[str, Any]:
    full = abl["full"]
    out = {}
    for k, v in abl.items():
        if k == "full":
            continue
        row = {}
        for m in ("global_mm", "root_relative_mm", "procrustes_mm", "orientation_deg"):
            a, b = v[m], full[m]
            row[m] = {"mean": round(a["mean"] / b["mean"], 2), "std": round(a["std"] / max(b["std"], 1e-9), 2)}
        out[k] = row
    return out


def _clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return x.item()
    return x
