"""Shared fixtures: a synthetic single-person scene with exact measurements."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

from mocapd.core.camera import Camera
from mocapd.core.imu import IMU_SET_13, ImuMount, default_mounts
from mocapd.core.keypoints import TrackTargets, coco17_targets
from mocapd.core.prior import PcaPrior
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import Observations
from mocapd.core.synthetic import exact_observations, moving_sequence, ring_rig
from mocapd.io.log_throttle import RepeatFilter

# CI runs are reproducible (the same examples every run); local runs keep exploring new ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@dataclass
class Scene:
    skeleton: Skeleton
    cameras: list[Camera]
    targets: TrackTargets
    imus: tuple[ImuMount, ...]
    prior: PcaPrior
    truth: np.ndarray  # (n_frames, 66)
    observations: list[Observations]


@pytest.fixture(scope="session")
def scene() -> Scene:
    sk = Skeleton.from_height(1.75)
    cams = ring_rig(8)
    # Some lens distortion so the distortion path is exercised everywhere.
    for i, c in enumerate(cams):
        cams[i] = Camera(c.name, c.width, c.height, c.K, c.R, c.t, dist=np.array([-0.12, 0.05, 4e-4, -3e-4, -0.01]))
    targets = coco17_targets(sk)
    imus = default_mounts(IMU_SET_13, sk)
    truth = moving_sequence(sk, 40, seed=11)
    # A prior with the spread of one fitted on varied real motion: poses from several sequences, some with
    # larger excursions than the test motion (a narrow prior at the seed's weights would dominate the IMUs).
    pool = [moving_sequence(sk, 2000, seed=s, amplitude=a) for s, a in ((12, 1.0), (13, 2.0), (14, 3.0))]
    prior = PcaPrior.fit(np.concatenate(pool), 0.95)
    obs = exact_observations(sk, cams, targets, imus, truth)
    return Scene(sk, cams, targets, imus, prior, truth, obs)


@pytest.fixture(scope="session")
def tiny_fusion_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The learned fusion's networks from a seconds-long training run of the whole recipe (PVH networks with the
    single-channel ablation, LSTMs, fusion layer) and its ONNX export: the networks the tests run (the real ones,
    ~50 min of training, are not in the repository)."""
    from mocapd.eval.fusion_train import FusionRecipe, train

    out = tmp_path_factory.mktemp("fusion")
    train(FusionRecipe.tiny(), out, ablation=True)
    return out


@pytest.fixture(autouse=True)
def _no_log_filter_left_behind(request: pytest.FixtureRequest) -> Iterator[None]:
    """Take off the repeated-line filter a test's in-process command put on the log handlers
    (:func:`mocapd.io.lifecycle.setup_logging`). It lands on pytest's own handlers too, which live for the whole
    session, and then held back a later test's expected warning once its call site had logged its burst in the
    window (the full suite: ``test_imu_bridge``'s one rejection warning, never seen)."""
    yield
    plugin = request.config.pluginmanager.get_plugin("logging-plugin")
    handlers = list(logging.getLogger().handlers)
    handlers += [h for h in (getattr(plugin, n, None) for n in ("caplog_handler", "report_handler")) if h is not None]
    for handler in handlers:
        for f in [f for f in handler.filters if isinstance(f, RepeatFilter)]:
            handler.removeFilter(f)
