"""Native libraries' own error output goes through mocapd's handling, not straight to stderr (issue 45): a broken
TIFF decoded in a loop printed 450 libtiff lines in 40 s, a detector model failing at run time 376 onnxruntime
lines in 40 s, both past the log rate limit. Each case runs in a child process whose stderr is the libraries'."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from tests.test_fuzz_imports import REPO

_TIFFS = """
import cv2, numpy as np, random
import mocapd.io.media_files  # what every picture mocapd reads goes through
ok, good = cv2.imencode(".tiff", np.zeros((64, 64, 3), np.uint8))
random.seed(45)
undecoded = 0
for _ in range(40):
    bad = bytearray(good)
    for _ in range(8):
        bad[random.randrange(8, len(bad))] = random.randrange(256)
    undecoded += cv2.imdecode(np.frombuffer(bytes(bad), np.uint8), cv2.IMREAD_COLOR) is None
print(undecoded)
"""

_RUN = """
import sys, numpy as np, onnxruntime as ort
from mocapd.io.native_logs import quiet_session_options
session = ort.InferenceSession(sys.argv[1], quiet_session_options(ort.SessionOptions()),
                               providers=["CPUExecutionProvider"])
failed = 0
for _ in range(20):
    try:
        session.run(None, {"x": np.zeros(5, np.float32)})
    except Exception:  # onnxruntime's own untyped errors: the caller says them
        failed += 1
print(failed)
"""


def _child(script: str, *args: str) -> tuple[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_LOG_LEVEL"}
    proc = subprocess.run([sys.executable, "-c", script, *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120, check=True)  # fmt: skip
    return proc.stdout, proc.stderr


def test_opencv_says_nothing_of_a_broken_tiff_once_mocapd_reads_pictures() -> None:
    out, err = _child(_TIFFS)
    assert int(out) > 10  # damaged enough not to decode: each of those was several libtiff lines
    assert "TIFF" not in err and err.strip() == "", err[:2000]


def test_a_model_failing_at_run_time_raises_without_onnxruntime_lines(tmp_path: Path) -> None:
    """A model whose Reshape fails on every run: 20 runs, 20 exceptions, not one line of onnxruntime's own."""
    shape = helper.make_tensor("shape", TensorProto.INT64, [1], np.array([7], np.int64))
    graph = helper.make_graph([helper.make_node("Reshape", ["x", "shape"], ["y"])], "fails",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n"])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [7])], [shape])  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "fails.onnx"))
    out, err = _child(_RUN, str(tmp_path / "fails.onnx"))
    assert int(out) == 20
    assert "onnxruntime" not in err and err.strip() == "", err[:2000]
