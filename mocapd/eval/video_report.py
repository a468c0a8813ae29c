"""The report of ``mocapd eval video``: markdown tables (``report.md``) and the held-out pictures (PNG).

Each picture is one camera of a take at a few frames: the camera's own image, its detections (white dots, a
ring on confident ones) and, in one colour per system, the skeleton that system reconstructed *without* this
camera, projected into it. What the held-out-view error measures is the distance between the two.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mocapd.eval.heldout import COCO17_GROUPS
from mocapd.io.media_files import open_video

if TYPE_CHECKING:
    from mocapd.eval.video import TakeRun

COLOURS = {  # BGR; drawn in this order, so mocapd's skeletons lie on top
    "Pose2Sim": (200, 40, 200),
    "Pose2Sim filtered": (120, 0, 120),
    "naive DLT": (230, 120, 20),
    "mocapd resolve": (0, 165, 255),
    "mocapd live": (0, 0, 235),
}
WIDTHS = {"Pose2Sim": 10, "Pose2Sim filtered": 9, "naive DLT": 8, "mocapd resolve": 7, "mocapd live": 4}
EDGES = ((5, 7), (7, 9), (6, 8), (8, 10), (5, 6), (11, 12), (5, 11), (6, 12), (11, 13), (13, 15), (12, 14), (14, 16),
         (0, 5), (0, 6))  # fmt: skip
TILE_WIDTH = 272


def _f(v: Any, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}"


def _take_tables(res: dict[str, Any]) -> list[str]:
    sy = res["systems"]
    names = list(sy)
    lines = [f"### {res['take']} ({res['frames']} frames, cameras {', '.join(res['cameras'])})", ""]
    lines += [
        "| system | held-out median px (common) | p90 (common) | held-out median px (own) | compared (own) | "
        "jitter median m/s² | bone-length CV (median) | identities | performers: frames | bystanders enrolled "
        "| identity switches | L/R flips accepted / found |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in names:
        h, p = sy[s]["held_out"], sy[s]["people"]
        frames = ", ".join(f"{p['frames'][i]}" for i in p["performers"]) or "–"
        acc, fnd = sum(p["flips_accepted"].values()), sum(p["flips_found"].values())
        lines.append(
            f"| {s} | **{_f(h['common']['all']['median'])}** | {_f(h['common']['all']['p90'])} | "
            f"{_f(h['own']['all']['median'])} | {h['own']['all']['n']} | {_f(sy[s]['jitter']['median'], 2)} | "
            f"{_f(sy[s]['bone_cv']['median'], 3)} | {p['identities']} | {frames} | {p['bystanders_enrolled']} | "
            f"{p['identity_switches']} | {acc} / {fnd} |"
        )
    lines += ["", "Held-out median / p90 px per joint group (common set):", ""]
    groups = ["all", *COCO17_GROUPS]
    lines += ["| system | " + " | ".join(groups) + " |", "|---" * (len(groups) + 1) + "|"]
    for s in names:
        c = sy[s]["held_out"]["common"]
        lines.append(f"| {s} | " + " | ".join(f"{_f(c[g]['median'])} / {_f(c[g]['p90'])}" for g in groups) + " |")
    lines += ["", "Held-out median px per held-out camera (common set; own set in brackets):", ""]
    cams = res["cameras"]
    lines += ["| system | " + " | ".join(cams) + " |", "|---" * (len(cams) + 1) + "|"]
    for s in names:
        pc, po = sy[s]["held_out"]["per_camera_common"], sy[s]["held_out"]["per_camera"]
        lines.append(f"| {s} | " + " | ".join(f"{_f(pc[c]['median'])} ({_f(po[c]['median'])})" for c in cams) + " |")
    lines += ["", "Left/right flips per camera, accepted into the solution / found (all cameras):", ""]
    lines += ["| system | " + " | ".join(cams) + " |", "|---" * (len(cams) + 1) + "|"]
    for s in names:
        p = sy[s]["people"]
        lines.append(f"| {s} | " + " | ".join(f"{p['flips_accepted'][c]} / {p['flips_found'][c]}" for c in cams) + " |")
    lines += ["", "Bone-length coefficient of variation over the take (all cameras):", ""]
    bones = [b for b in next(iter(sy.values()))["bone_cv"] if b != "median"]
    lines += ["| system | " + " | ".join(bones) + " |", "|---" * (len(bones) + 1) + "|"]
    for s in names:
        lines.append(f"| {s} | " + " | ".join(_f(sy[s]["bone_cv"][b], 3) for b in bones) + " |")
    seg = res.get("segment_lengths", {})
    if seg:
        lines += ["", "Segment lengths mocapd estimated (m):", "", "| identity | height | upper arm | forearm | thigh "
                  "| shank |", "|---|---|---|---|---|---|"]  # fmt: skip
        for i, v in seg.items():
            lines.append(f"| {i} | {v['height']} | {v['upper_arm']} | {v['forearm']} | {v['thigh']} | {v['shank']} |")
    lines += ["", "Targets:", "", "| target | met |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in res["targets"].items()]
    for k, v in res.get("notes", {}).items():
        lines += ["", f"{k}: {v}"]
    for img in res.get("images", []):
        lines += ["", f"![{img}]({img})"]
    return [*lines, ""]


def markdown(results: dict[str, Any]) -> str:
    """The report of :func:`mocapd.service.video_eval.run_video_eval` as markdown."""
    s = results["setup"]
    lines = [
        "# mocapd eval video",
        "",
        f"Config: {s['config']}; detector precision {s['precision']}; "
        f"BlazePose landmarks: {s.get('landmarks', 'off')}; Pose2Sim: {s['pose2sim']}; "
        f"wall time {s['wall_s']} s.",
        "",
        "Held-out-view error: each system reconstructs the take without one camera, its people are projected into "
        "that camera and compared with the camera's own detections (confidence >= 0.5). *Common*: only the "
        "keypoints every system was compared on. Jitter (median joint acceleration, second differences at the "
        "videos' 60 Hz) and bone-length CV: the performers only (a bystander standing still would lower them).",
        "",
    ]
    for res in results["takes"].values():
        lines += _take_tables(res)
    return "\n".join(lines)


def write_report(results: dict[str, Any], path: Path) -> None:
    path.write_text(markdown(results))


def draw_held_out(run: TakeRun, folder: Path, n_frames: int) -> list[Path]:
    """Per camera, ``n_frames`` evenly spread frames side by side: the held-out image, its detections and every
    system's projection from the run without that camera. Returns the PNG paths."""
    from mocapd.eval.video import _stack

    take, dets = run.take, run.detections
    n = dets.n_frames
    picks = sorted({round((i + 1) * n / (n_frames + 1)) for i in range(n_frames)})
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (cam, video) in enumerate(zip(take.cameras, take.videos, strict=True)):
        images = _read_frames(video, picks)
        tiles = []
        for f, img in zip(picks, images, strict=True):
            canvas = img.copy()
            for name, colour in COLOURS.items():
                people = run.people.get(name, {}).get(f"no_{cam.name}", {})
                pts = _stack(people, n)[f] if people else np.zeros((0, 17, 3))
                for person in pts:
                    _skeleton(canvas, cam.project(person), colour, WIDTHS[name])
            det = dets.frames[f][k]
            for i in range(len(det)):
                for (x, y), c in zip(det.keypoints[i], det.confidences[i], strict=True):
                    if c >= 0.3:
                        cv2.circle(canvas, (int(x), int(y)), 9, (255, 255, 255), -1, cv2.LINE_AA)
                    if c >= 0.5:
                        cv2.circle(canvas, (int(x), int(y)), 13, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(canvas, f"{cam.name} f{f}", (20, 70), cv2.FONT_HERSHEY_SIMPLEX, 2.2, (255, 255, 255), 5)
            h = round(canvas.shape[0] * TILE_WIDTH / canvas.shape[1])
            tiles.append(cv2.resize(canvas, (TILE_WIDTH, h), interpolation=cv2.INTER_AREA))
        strip = np.hstack(tiles)
        legend = _legend(strip.shape[1])
        path = folder / f"{take.name}_{cam.name}.png"
        cv2.imwrite(str(path), np.vstack([strip, legend]), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        paths.append(path)
    return paths


def _read_frames(video: Path, picks: list[int]) -> list[np.ndarray]:
    cap = open_video(video)
    out = []
    try:
        for f in range(max(picks) + 1):
            ok, img = cap.read()
            if not ok:
                raise OSError(f"{video}: frame {f} unreadable")
            if f in picks:
                out.append(img)
    finally:
        cap.release()
    return out


def _skeleton(img: np.ndarray, uv: np.ndarray, colour: tuple[int, int, int], width: int) -> None:
    h, w = img.shape[:2]
    for a, b in EDGES:
        if np.all(np.isfinite(uv[[a, b]])) and np.all(np.abs(uv[[a, b]]) < 4 * max(h, w)):
            pa = (int(uv[a, 0]), int(uv[a, 1]))
            pb = (int(uv[b, 0]), int(uv[b, 1]))
            cv2.line(img, pa, pb, colour, width, cv2.LINE_AA)
    for j in (5, 7, 9, 11, 13, 15):  # the person's left side: filled joints
        if np.all(np.isfinite(uv[j])) and np.all(np.abs(uv[j]) < 4 * max(h, w)):
            cv2.circle(img, (int(uv[j, 0]), int(uv[j, 1])), width + 5, colour, -1, cv2.LINE_AA)


def _legend(width: int) -> np.ndarray:
    band = np.full((40, width, 3), 255, np.uint8)
    x = 6
    for name in reversed(COLOURS):
        colour = COLOURS[name]
        cv2.rectangle(band, (x, 14), (x + 18, 30), colour, -1)
        cv2.putText(band, name, (x + 22, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        x += 26 + 8 * len(name)
    return band
