"""Markdown tables and PNG plots of a harness run (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _s(st: dict[str, Any] | None) -> str:
    if not st or st.get("mean") is None:
        return "–"
    return f"{st['mean']:.1f} ({st['std']:.1f}) / {st['median']:.1f} ({st['mad']:.1f})"


def _table(rows: dict[str, Any], first: str = "method") -> list[str]:
    out = [
        f"| {first} | global mm | root-relative mm | Procrustes mm | orientation deg | frames | non-finite |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        out.append(
            f"| {name} | {_s(r['global_mm'])} | {_s(r['root_relative_mm'])} | {_s(r['procrustes_mm'])} | "
            f"{_s(r['orientation_deg'])} | {r['frames']} | {r['nonfinite_frames']} |"
        )
    return out


def markdown(res: dict[str, Any]) -> str:
    setup = res["setup"]
    lines = [
        f"# Accuracy: split `{setup['split']}` ({len(setup['sequences'])} sequences, {setup['frames_main']} frames"
        f" at 60 Hz; sweep/ablation/sub-sampling on the first {setup['sweep_frames']} frames of each:"
        f" {setup['frames_sweep']} frames)",
        "",
        "Cells: mean (std) / median (MAD) over all joints of all frames. Cost: " + str(setup["cost"]) + ".",
        "",
        "## Main table (seed 003 Table 1 analog), all 21 joints",
        "",
        *_table(res["main"]),
        "",
        "## The same on the 12 joints a keypoint observes directly (shoulders, elbows, wrists, hips, knees, ankles)",
        "",
        *_table(res["main_limb12"]),
        "",
        "## Targets",
        "",
        "| quantity | value | target | met |",
        "|---|---|---|---|",
    ]
    t = res["targets"]
    lines += [
        f"| global mean error, 8 cams + 13 IMUs / triangulation 8 cams (21 joints) | "
        f"{t['8c13i_vs_triangulation_8c_global_mean_ratio']} | ≤ 0.7 | {t['met']['ratio_8c13i_le_0.7']} |",
        f"| global mean error, 4 cams + 6 IMUs / triangulation 4 cams (21 joints) | "
        f"{t['4c6i_vs_triangulation_4c_global_mean_ratio']} | ≤ 0.7 | {t['met']['ratio_4c6i_le_0.7']} |",
        f"| same ratios on the 12 directly observed joints | {t['8c13i_vs_triangulation_8c_limb12_ratio']}, "
        f"{t['4c6i_vs_triangulation_4c_limb12_ratio']} | ≤ 0.7 | – |",
        f"| orientation error, 8 cams + 13 IMUs (deg) | {t['8c13i_orientation_mean_deg']} | ≤ 7.5 | "
        f"{t['met']['orientation_le_7.5deg']} |",
        "",
        "## Sweep: cameras × IMUs (seed 003 Figure 7 analog), mean (median) global / Procrustes mm, orientation deg",
        "",
        "| cameras | " + " | ".join(f"{i} IMUs" for i in sorted({v["imus"] for v in res["sweep"].values()})) + " |",
        "|---|" + "---|" * len({v["imus"] for v in res["sweep"].values()}),
    ]
    imus = sorted({v["imus"] for v in res["sweep"].values()})
    cams = sorted({v["cams"] for v in res["sweep"].values()})
    for c in cams:
        cells = []
        for i in imus:
            r = res["sweep"][f"{c}c_{i}i"]
            o = r["orientation_deg"]
            cells.append(
                f"{r['global_mm']['mean']:.0f} ({r['global_mm']['median']:.0f}) / {r['procrustes_mm']['mean']:.0f}"
                f" / {o['mean']:.1f}°" + (f" **{r['nonfinite_frames']} non-finite**" if r["nonfinite_frames"] else "")
            )
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    nonfinite = sum(r["nonfinite_frames"] for r in res["sweep"].values())
    lines += ["", f"Non-finite poses over the whole sweep: {nonfinite}.", ""]
    lines += [
        "## Ablation (seed 003 Table 3 analog): 8 cams + 13 IMUs, error with one term omitted / error of the full"
        " cost (mean, std ratios)",
        "",
        "| omitted term | global | root-relative | Procrustes | orientation |",
        "|---|---|---|---|---|",
    ]
    for k, r in res["ablation"]["relative"].items():
        cells = [
            f"{r[m]['mean']:.2f} ({r[m]['std']:.2f})"
            for m in ("global_mm", "root_relative_mm", "procrustes_mm", "orientation_deg")
        ]
        lines.append(f"| {k.removeprefix('without ')} | " + " | ".join(cells) + " |")
    full = res["ablation"]["absolute"]["full"]
    lines += [
        "",
        f"Full cost on these frames: global {_s(full['global_mm'])} mm, orientation {_s(full['orientation_deg'])} deg.",
        "",
        "## Detection sub-sampling N_o/N_p (seed 000 Figure 4 analog), 8 cams + 13 IMUs",
        "",
        "| N_o/N_p | detected fraction | global mm | Procrustes mm | orientation deg |",
        "|---|---|---|---|---|",
    ]
    for k, r in res["subsampling"].items():
        lines.append(
            f"| {k} | {r['N_o'] / r['N_p']:.3f} | {_s(r['global_mm'])} | {_s(r['procrustes_mm'])} | "
            f"{_s(r['orientation_deg'])} |"
        )
    lines += ["", "## Per sequence: solver global mean mm / Procrustes mean mm / orientation mean deg", ""]
    configs = list(res.get("per_sequence", {}))
    if configs:
        lines += ["| sequence | frames | " + " | ".join(configs) + " |", "|---|---|" + "---|" * len(configs)]
        for seq in res["per_sequence"][configs[0]]:
            cells = []
            for c in configs:
                r = res["per_sequence"][c][seq]
                g, p, o = r["global_mm"]["mean"], r["procrustes_mm"]["mean"], r["orientation_deg"]["mean"]
                cells.append(f"{g:.0f} / {p:.0f} / {o:.1f}")
            lines.append(f"| {seq} | {res['per_sequence'][configs[0]][seq]['frames']} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Solver: {setup['solver_ms_per_frame_main']} ms per frame (main table, whole loop incl. Python);"
        f" wall time {setup['wall_s']} s.",
        "",
        "![sweep](sweep.png)",
        "",
        "![subsampling](subsampling.png)",
        "",
    ]
    return "\n".join(lines)


def plots(res: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sw = res["sweep"]
    imus = sorted({v["imus"] for v in sw.values()})
    cams = sorted({v["cams"] for v in sw.values()})
    fig, axes = plt.subplots(1, 4, figsize=(17, 4))
    for ax, (m, title) in zip(
        axes,
        (
            ("global_mm", "global position (mm)"),
            ("root_relative_mm", "root-relative (mm)"),
            ("procrustes_mm", "Procrustes (mm)"),
            ("orientation_deg", "orientation (deg)"),
        ),
        strict=True,
    ):
        for i in imus:
            mean = [sw[f"{c}c_{i}i"][m]["mean"] for c in cams]
            med = [sw[f"{c}c_{i}i"][m]["median"] for c in cams]
            (ln,) = ax.plot(cams, med, "-o", label=f"{i} IMUs median")
            ax.plot(cams, mean, "--", color=ln.get_color(), label=f"{i} IMUs mean")
        ax.set_xlabel("cameras")
        ax.set_title(title)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "sweep.png", dpi=90)
    plt.close(fig)

    ss = res["subsampling"]
    fig, ax = plt.subplots(figsize=(6, 4))
    for no in sorted({v["N_o"] for v in ss.values()}):
        pts = sorted((v["N_p"] / v["N_o"], v["global_mm"]["mean"]) for v in ss.values() if v["N_o"] == no)
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-o", label=f"N_o = {no}")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("N_p / N_o (frames per detected frame)")
    ax.set_ylabel("global mean joint error (mm)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "subsampling.png", dpi=90)
    plt.close(fig)


def write_report(res: dict[str, Any], out: Path) -> None:
    text = markdown(res)
    if res.get("fusion"):
        from mocapd.eval.fusion_eval import markdown as fusion_markdown

        text += "\n" + fusion_markdown(res["fusion"])
    (out / "tables.md").write_text(text, encoding="utf-8")
    plots(res, out)
