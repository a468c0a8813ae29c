"""The command line's parser imports no command's implementation.

Every ``mocapd`` command builds the whole parser first: ``mocapd --help`` or ``mocapd reset-heading`` used to import
the daemon's assembly, the config schema, OpenCV, NumBa, SciPy and onnxruntime on the way (3.4 s of CPU on a loaded
machine), and so did each of the test suite's daemon subprocesses before they started. Each command now imports what
it runs when it runs.
"""

from __future__ import annotations

import json
import subprocess
import sys

#: what no parser may import: the solver's, detector's, cameras' and config schema's libraries
HEAVY = ("scipy", "numba", "llvmlite", "onnxruntime", "cv2", "gi", "pydantic", "PIL", "zenoh", "websockets")

#: the mocapd modules outside the CLI the parser may import: their constants are its choices and defaults
ALLOWED = {
    # NumPy with them: the keypoint sets (--keypoints choices), body segments and their default lengths
    # (import mvnx/mtw --thigh ...), the reference height, the IMU calibration's poses and stillness thresholds
    "mocapd.core",
    # the shipped [detector.packing] defaults of `bench detector` (a dataclass; the package itself is empty)
    "mocapd.pipeline",
    "mocapd.pipeline.detector_config",
    # `bench capture`'s options (its fake cameras are started by the command)
    "mocapd.service",
    "mocapd.service.bench",
    "mocapd.service.bench.capture",
}

_CODE = """
import json, sys
from mocapd.service.cli.commands import build_parser
build_parser()
print(json.dumps(sorted(sys.modules)))
"""


def _modules_after_building_the_parser() -> list[str]:
    # A fresh interpreter: this one has imported everything the other tests did.
    out = subprocess.run([sys.executable, "-c", _CODE], capture_output=True, text=True, check=True, timeout=600)
    modules: list[str] = json.loads(out.stdout)
    return modules


def test_building_the_parser_imports_no_heavy_library() -> None:
    modules = _modules_after_building_the_parser()
    assert "mocapd.service.cli.commands" in modules  # the import above did run
    heavy = sorted(m for m in modules if m.split(".")[0] in HEAVY)
    assert not heavy, heavy


def test_building_the_parser_imports_no_commands_implementation() -> None:
    modules = _modules_after_building_the_parser()
    implementation = sorted(
        m
        for m in modules
        if m.startswith(("mocapd.pipeline", "mocapd.service", "mocapd.eval"))
        and not m.startswith("mocapd.service.cli")
        and m not in ALLOWED
    )
    assert not implementation, implementation
    # The parts of the core the parser reads constants from, never the solver's or the cameras' models.
    assert not [m for m in modules if m in ("mocapd.core.solver", "mocapd.core.camera", "mocapd.core.assignment")]


# `mocapd check-config` on the shipped file, in a fresh interpreter: the schema's defaults used to import the
# solver's, the cameras' and the learned fusion's modules, and the rig's check the detector's, the scheduler's and
# the daemon's (NumBa, onnxruntime, OpenCV, SciPy: 2.9 s of CPU per check, and as much again in every one of the
# test suite's daemons before its config was validated). They are imported where a default the file leaves out or
# a part of the rig needs them.
_CHECK_CONFIG = """
import json, sys
from mocapd.service.cli import main
code = main(["check-config"])
print(json.dumps([code, sorted(sys.modules)]))
"""

#: what checking the shipped config may not import: the rig's implementation (a config check opens no device)
RIG_IMPLEMENTATION = (
    "mocapd.core.solver",
    "mocapd.core.camera",
    "mocapd.pipeline.detector",
    "mocapd.pipeline.detector_pool",
    "mocapd.pipeline.scheduler",
    "mocapd.pipeline.fusion",
    "mocapd.service.rig",
    "mocapd.service.daemon",
    "mocapd.service.assembly",
)


def test_checking_the_shipped_config_imports_no_detector_solver_or_daemon() -> None:
    out = subprocess.run([sys.executable, "-c", _CHECK_CONFIG], capture_output=True, text=True, check=True,
                         timeout=600)  # fmt: skip
    code, modules = json.loads(out.stdout.strip().splitlines()[-1])
    assert code == 0, out  # the shipped file is valid (and describes no rig)
    assert "mocapd.service.config" in modules  # the file was read (and checked: the rig's check is the last step)
    heavy = sorted({m.split(".")[0] for m in modules} & {"numba", "llvmlite", "onnxruntime", "onnx", "cv2", "scipy"})
    assert not heavy, heavy
    assert not [m for m in RIG_IMPLEMENTATION if m in modules]
