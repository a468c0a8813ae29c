"""A JSON-lines pose sink: one line per published frame, buffered, flushed and closed at shutdown.

Line format (version 1): ``{"v": 1, "frame": int, "t_solve_ns": int, "people": [{"id": str, "suit": str|null,
"theta": [66 floats], "joints": [[x, y, z] × 21], "confidence": float, "views": int, "imus": int}]}``.
"""

from __future__ import annotations

import json
from pathlib import Path

from mocapd.pipeline.scheduler import PoseFrame


class JsonLinesPoseSink:
    """Appends frames to ``path`` (created or truncated)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh = self.path.open("w", encoding="utf-8", buffering=1 << 16)
        self.frames = 0

    def publish(self, frame: PoseFrame) -> None:
        people = [
            {"id": p.identity, "suit": p.suit, "theta": [round(float(v), 6) for v in p.theta],
             "joints": [[round(float(v), 5) for v in j] for j in p.joints], "confidence": round(p.confidence, 4),
             "views": p.views, "imus": p.imus}
            for p in frame.people
        ]  # fmt: skip
        self._fh.write(json.dumps({"v": 1, "frame": frame.frame, "t_solve_ns": frame.t_solve_ns, "people": people}))
        self._fh.write("\n")
        self.frames += 1

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        if not self._fh.closed:
            self._fh.flush()
            self._fh.close()
