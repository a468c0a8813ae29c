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


# The daemon's warm-up (every `mocapd run` and `demo` before READY) and its IMU offset estimate, in a fresh
# interpreter: the estimate's band-pass was SciPy's (`butter`, `sosfiltfilt`), and the warm-up ran it once so that its
# import (~1 s of CPU: SciPy's signal and stats packages) fell before READY, not in a tick. The band-pass is NumPy's
# now (mocapd.core.band_pass); nothing the daemon runs imports that package.
_WARM_UP = """
import json, sys
import numpy as np
from mocapd.pipeline.scheduler import Suit, estimate_imu_offsets
from mocapd.service.bench.solver import synthetic_prior
from mocapd.service.config import load_config
from mocapd.service.daemon import Daemon, Rig
from mocapd.pipeline.time_alignment import estimate_imu_lag
from mocapd.sim.world import SyntheticWorld

world = SyntheticWorld(2, 1, 0, seed=3)
suits = [Suit.from_calibration(s.id, world.calibration(s), world.skeleton) for s in world.suits]
daemon = Daemon(load_config(), Rig(world.cameras, [], world.skeleton, world.targets, synthetic_prior(), suits))
daemon._warm_up()
after_warm_up = sorted(sys.modules)
t = np.arange(0, 6_000_000_000, 10_000_000, dtype=np.int64)
height = 0.05 * np.sin(t / 1e9 * 2 * np.pi)
acc = -0.05 * (2 * np.pi) ** 2 * np.sin((t - 40_000_000) / 1e9 * 2 * np.pi)  # the IMU's stamps 40 ms ahead
est = estimate_imu_lag(t, height, t, acc)
print(json.dumps([after_warm_up, sorted(sys.modules), est.lag_ns if est else None]))
"""


def test_the_daemons_warm_up_and_imu_offset_estimate_import_no_scipy_signal() -> None:
    out = subprocess.run([sys.executable, "-c", _WARM_UP], capture_output=True, text=True, check=True, timeout=600)
    after_warm_up, after_estimate, lag_ns = json.loads(out.stdout.strip().splitlines()[-1])
    assert "mocapd.service.daemon" in after_warm_up  # the import above did run
    assert lag_ns is not None and abs(lag_ns - 40_000_000) < 2_000_000  # a real estimate
    for modules in (after_warm_up, after_estimate):
        assert not [m for m in modules if m == "scipy.signal" or m.startswith("scipy.signal.")]
