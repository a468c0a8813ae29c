"""The example clients in tools/clients/ against the real daemon on the synthetic rig: the Node.js receiver (ws +
@msgpack/msgpack, installed by setup/steps/26-node-clients.sh) and the Python receiver connect, get the hello
and frames with both people, print each subject's root position and exit 0."""

from __future__ import annotations

import asyncio
import itertools
import re
import sys
from pathlib import Path

import pytest

from mocapd.service.config import load_config
from tests.test_web_viewer import daemon, free_port

CLIENTS = Path(__file__).resolve().parents[1] / "tools" / "clients"
FRAME = re.compile(r"^frame (\d+) t_solve_ns \d+: (.*)$")


async def run(*argv: str | Path, cwd: Path | None = None) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(*map(str, argv), cwd=cwd, stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.PIPE)  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


def check_output(out: str, convention: str, units: str, rate: str) -> None:
    lines = out.splitlines()
    assert lines[0].startswith("hello v1: convention native (m), 60 Hz, 21 bones, skeletons default"), lines[0]
    # The answer to the client's subscribe (frames already on their way may come before it, in the old options).
    second = next(i for i, line in enumerate(lines) if i > 0 and line.startswith("hello"))
    assert lines[second].startswith(f"hello v1: convention {convention} ({units}), {rate} Hz"), lines[second]
    frames = [FRAME.match(line) for line in lines[1:] if line.startswith("frame ")]
    assert len(frames) == 20 and all(frames), out
    numbers = [int(m.group(1)) for m in frames if m]
    assert all(b > a for a, b in itertools.pairwise(numbers))
    last = frames[-1]
    assert last is not None and " root (" in last.group(2), out  # at least one tracked subject
    root = [float(v) for v in re.findall(r" root \(([^)]*)\)", last.group(2))[0].split(", ")]
    height = root[2] if convention == "unreal" else root[1]  # Unreal is Z-up in centimetres; Unity Y-up metres
    assert (50.0 < height < 150.0) if units == "cm" else (0.5 < height < 1.5), root


@pytest.mark.asyncio
async def test_node_and_python_receivers_against_the_daemon() -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"port": free_port()})})  # fmt: skip
    async with daemon(cfg):
        url = f"ws://127.0.0.1:{cfg.websocket.port}/"
        # Wait until both people are tracked, so the clients' frames carry subjects.
        code, out, err = await run(sys.executable, CLIENTS / "python_receiver.py", "--url", url, "--frames", "1")
        for _ in range(100):
            if out.count(" root (") == 2:
                break
            await asyncio.sleep(0.2)
            code, out, err = await run(sys.executable, CLIENTS / "python_receiver.py", "--url", url, "--frames", "1")
        assert out.count(" root (") == 2, (out, err)

        code, out, err = await run("node", "receiver.mjs", "--url", url, "--frames", "20", "--convention", "unity",
                                   cwd=CLIENTS / "node")  # fmt: skip
        assert code == 0, err
        check_output(out, "unity", "m", "60")

        code, out, err = await run(sys.executable, CLIENTS / "python_receiver.py", "--url", url, "--frames", "20",
                                   "--convention", "unreal", "--rate", "30")  # fmt: skip
        assert code == 0, err
        check_output(out, "unreal", "cm", "30")

        code, out, err = await run("node", "receiver.mjs", "--url", "ws://127.0.0.1:1/", "--frames", "5",
                                   cwd=CLIENTS / "node")  # fmt: skip
        assert code == 1 and "connection failed" in err
