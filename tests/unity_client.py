"""The Unity receiver (tools/clients/unity/MocapdReceiver.cs) outside Unity: compiled by Mono's mcs against a
minimal stand-in for the UnityEngine types it uses (tests/unity/UnityEngine.cs), run under mono by a harness that
plays Unity's player loop (tests/unity/Harness.cs), against a live daemon; every pose it applies is compared with
the same frame received by a second, independent WebSocket client (native convention, mocapd's own
conversions). Mono comes from setup/steps/27-mono.sh."""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.client import connect

from mocapd.core.rotations import matrix_from_quat, quat_multiply
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, PARENTS
from mocapd.protocols.conventions import UNITY
from tests.load import load_factor

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "tools" / "clients" / "unity" / "MocapdReceiver.cs", ROOT / "tests" / "unity" / "UnityEngine.cs",
           ROOT / "tests" / "unity" / "Harness.cs"]  # fmt: skip
# HumanBodyBones driven by the receiver <- mocapd bone (Spine2 has no humanoid bone: it flows on to UpperChest).
HUMAN = {
    "Hips": "Hips", "Spine": "Spine", "Chest": "Spine1", "UpperChest": "Spine3", "Neck": "Neck", "Head": "Head",
    **{f"{s}{p}": f"{s}{m}" for s in ("Left", "Right") for p, m in (("UpperArm", "UpperArm"), ("LowerArm", "LowerArm"),
       ("Hand", "Hand"), ("UpperLeg", "UpperLeg"), ("LowerLeg", "LowerLeg"), ("Foot", "Foot"), ("Toes", "Toes"))},
}  # fmt: skip


async def compile_receiver(out_dir: Path) -> Path:
    """``mcs`` the receiver, the stand-in and the harness into ``out_dir/harness.exe``."""
    mcs = shutil.which("mcs")
    assert mcs and shutil.which("mono"), "Mono not found: run `bash setup/steps/27-mono.sh` (make test does)"
    exe = out_dir / "harness.exe"
    proc = await asyncio.create_subprocess_exec(
        mcs, "-nologo", "-nowarn:649", f"-out:{exe}", "-r:System.Runtime.Serialization.dll", *map(str, SOURCES),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    out, _ = await asyncio.wait_for(proc.communicate(), 120)
    assert proc.returncode == 0, f"mcs failed:\n{out.decode()}"
    return exe


async def _reference(url: str, frames: dict[int, dict[str, Any]], ready: asyncio.Event) -> None:
    """A second client: every frame, native convention, by frame counter."""
    async with connect(url) as ws:
        await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "convention": "native", "globals": False}))
        async for raw in ws:
            if isinstance(raw, bytes):
                continue
            m = json.loads(raw)
            if m["type"] == "frame":
                frames[int(m["frame"])] = m
                ready.set()


def _parse(line: str) -> tuple[int, np.ndarray, dict[str, np.ndarray]]:
    parts = line.split()
    assert parts[0] == "frame" and parts[2] == "hips", line
    rot = {parts[k]: np.array([float(v) for v in parts[k + 1 : k + 5]]) for k in range(6, len(parts), 5)}
    return int(parts[1]), np.array([float(v) for v in parts[3:6]]), rot


async def check_unity_receiver(url: str, exe: Path, subject: str, frames: int = 20) -> int:
    """Run the compiled receiver against the daemon at ``url`` following ``subject``; every applied frame must
    match the reference client's copy of it: hips at the root, each driven bone's world rotation the subject's
    global rotation (converted to Unity's frame), the undriven shoulders at rest. Returns the frames compared."""
    ref: dict[int, dict[str, Any]] = {}
    ready = asyncio.Event()
    task = asyncio.create_task(_reference(url, ref, ready))
    try:
        await asyncio.wait_for(ready.wait(), 30 * load_factor())
        proc = await asyncio.create_subprocess_exec(
            "mono", str(exe), url, subject, str(frames), "60", stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        out, err = await asyncio.wait_for(proc.communicate(), 120 * load_factor())
        assert proc.returncode == 0, (out.decode(), err.decode())
        applied = out.decode().splitlines()
        last = _parse(applied[-1])[0] if applied else -1
        # The reference client's copy of the last frame applied (or a later one: it dropped that one), however late
        # a loaded machine delivers it to this process.
        async with asyncio.timeout(30 * load_factor()):
            while not any(n >= last for n in ref):
                await asyncio.sleep(0.02)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    lines = out.decode().splitlines()
    assert len(lines) == frames, lines
    compared = 0
    for line in lines:
        n, hips, rot = _parse(line)
        if n not in ref:  # dropped for the reference client (a slow client loses frames, never gets stale ones)
            continue
        s = next(x for x in ref[n]["subjects"] if x["id"] == subject)
        q = np.asarray(s["rot"], dtype=np.float64).reshape(len(BONE_NAMES), 4)
        glob = np.empty_like(q)
        for b, p in enumerate(PARENTS):
            glob[b] = q[b] if p < 0 else quat_multiply(glob[p], q[b])
        np.testing.assert_allclose(UNITY.positions(np.array(s["root"])), hips, atol=2e-6)
        for human, bone in HUMAN.items():
            x, y, z, w = rot[human]
            got = matrix_from_quat(np.array([w, x, y, z]))
            want = UNITY.matrices(matrix_from_quat(glob[BONE_INDEX[bone]]))
            np.testing.assert_allclose(got, want, atol=5e-5, err_msg=f"frame {n} {human}")
        for rest in ("LeftShoulder", "RightShoulder"):
            np.testing.assert_allclose(rot[rest], [0.0, 0.0, 0.0, 1.0])
        compared += 1
    assert compared >= 0.75 * frames, f"only {compared} of {frames} frames found in the reference stream"
    return compared
