"""``[detector] landmarks = "auto"`` (issue 40): the choice from measured costs (pure), the governor's step that
sheds the landmark model, and the real models on real demo frames picking and reporting a mode."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.errors import ConfigError
from mocapd.io.pose2sim_demo import demo_video
from mocapd.pipeline.detector_config import DetectorConfig, PackingConfig
from mocapd.pipeline.detector_pool import PooledDetector, detector_status, landmark_fronts, make_detector
from mocapd.pipeline.governor import LADDER, Governor, GovernorOptions, ladder
from mocapd.pipeline.landmark_auto import (
    REPROBE_NS,
    AutoLandmarks,
    LandmarkBudget,
    LandmarkCosts,
    choose_landmarks,
    shed_landmarks,
    status_field,
)
from mocapd.pipeline.landmarks import LandmarkRunner
from mocapd.protocols.ws_stream import health_subset
from mocapd.service.assembly import assembled
from mocapd.service.config import load_config
from tests.rigs import synthetic_toml, video_rig_toml, write

EXTRA = [BLAZEPOSE33.index(n) for n in ("left_heel", "right_foot_index", "left_pinky", "right_thumb")]


def _costs(yolo: float, idle: float, crops: float, full: float | None, heavy: float | None) -> LandmarkCosts:
    return LandmarkCosts(yolo, idle, crops, {"full": full, "heavy": heavy})


def test_a_gpu_like_budget_runs_heavy_on_every_pass() -> None:
    # YOLO 6 ms, the worker waits 25 ms for frames: two heavy crops (20 ms) fit every pass.
    c = choose_landmarks(_costs(6.0, 25.0, 2.0, 3.0, 10.0))
    assert (c.variant, c.every) == ("heavy", 1)


def test_a_loaded_laptop_runs_full_at_the_rate_that_fits_and_heavy_not_at_all() -> None:
    # YOLO 80 ms back to back (no idle), one person in two views; full 60 ms, heavy 260 ms a crop: a heavy pass
    # (520 ms) is longer than a pass may take, full's 120 ms fits every 3rd pass (40 ms a pass on average).
    c = choose_landmarks(_costs(80.0, 0.0, 2.0, 60.0, 260.0))
    assert (c.variant, c.every) == ("full", 3) and "full every 3" in c.reason
    # Heavy wins while it runs at least half as often as full: full every 1, heavy every 2.
    c = choose_landmarks(_costs(80.0, 0.0, 1.0, 30.0, 70.0))
    assert (c.variant, c.every) == ("heavy", 2)
    # Neither fits: off, YOLO's keypoints with tracking between.
    c = choose_landmarks(_costs(40.0, 0.0, 6.0, 60.0, 260.0))
    assert c.variant is None and "off" in c.reason
    # Rarer than every max_every-th pass is off too.
    c = choose_landmarks(_costs(20.0, 0.0, 2.0, 50.0, None), LandmarkBudget(max_every=8))
    assert c.variant is None


def test_unmeasured_models_are_measured_first_and_heavy_is_estimated_from_full() -> None:
    assert choose_landmarks(_costs(50.0, 0.0, 1.0, None, None)).reason == "measuring full's cost per crop"
    c = choose_landmarks(_costs(6.0, 30.0, 1.0, 5.0, None))  # heavy estimated at 16 ms: fits every pass
    assert c.variant == "heavy" and "measuring" in c.reason
    assert choose_landmarks(_costs(6.0, 30.0, 1.0, 5.0, 10.0), allowed=()).variant is None


def test_a_models_cost_measured_under_load_follows_yolos_cost_since() -> None:
    # Full measured at 250 ms a crop while YOLO took 1000 ms a pass; YOLO now takes 100 ms: full is taken as 25 ms
    # (no new run needed to see the load gone), and "auto" comes back from off.
    front = AutoLandmarks({"full": LandmarkRunner("full"), "heavy": LandmarkRunner("heavy")})  # lazy: nothing loads
    front._per_crop["full"].value, front._yolo_then["full"] = 250.0, 1000.0
    front._yolo.value, front._crops.value = 1000.0, 2.0
    assert front.costs().landmark_ms["full"] == pytest.approx(250.0) and front.decide().variant is None
    front._yolo.value = 100.0
    assert front.costs().landmark_ms["full"] == pytest.approx(25.0)
    assert (front.decide().variant, front.decide().every) == ("full", 1)


def test_the_governors_ladder_sheds_the_landmark_model_first_and_keeps_it_off_after() -> None:
    assert LADDER[0].landmarks and not LADDER[1].landmarks and LADDER[1].name == "landmark model off"
    assert all(not lv.landmarks for lv in LADDER[1:])
    assert (LADDER[1].tracking_rate, LADDER[1].detector_duty) == (1.0, 1.0)
    g = Governor(16_666_667, GovernorOptions(settle_s=0.0))
    g.observe(0)
    g.step(0)  # the first tick
    changed = []
    for k in range(240):  # two windows of ticks taking three periods each
        g.observe(50_000_000)
        changed.append(g.step((k + 1) * 16_666_667))
    assert changed.count(True) == 1 and g.step_index == 1 and g.status()["landmarks"] is False
    # A daemon without "auto" has no landmark step: its first step rests the detector.
    assert ladder(False)[1].name == "detector at 75 % duty" and len(ladder(False)) == len(LADDER) - 1


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    cap = cv2.VideoCapture(str(demo_video("Demo_SinglePerson", "cam01")))
    ok, img = cap.read()
    assert ok
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8)


def test_auto_with_the_real_models_picks_reports_and_is_shed(frame: np.ndarray) -> None:
    cfg = DetectorConfig(intra_op_threads=2, landmarks="auto", packing=PackingConfig(enabled=False))
    det = make_detector(cfg, [(frame.shape[1], frame.shape[0])])
    assert isinstance(det, PooledDetector)
    try:
        (front,) = landmark_fronts(det)
        assert isinstance(front, AutoLandmarks)
        first = det(frame)  # nothing measured yet: full runs, to measure its cost per crop
        assert first.keypoints.shape[1:] == (33, 2) and first.confidences[:, EXTRA].max() > 0.3
        st = detector_status(det)["landmarks"]
        assert isinstance(st, dict) and st["asked"] == "auto" and st["landmark_passes"] == {"heavy": 0, "full": 1}
        # Its first run loaded the model: not its cost (a fresh daemon measured full at several times its cost on
        # that run, chose off, and never ran it again). The next pass measures it.
        assert st["costs"]["landmark_ms_per_crop"]["full"] is None and st["crops"] >= 1
        assert front.decide().reason == "measuring full's cost per crop"
        det(frame)
        st = detector_status(det)["landmarks"]
        assert isinstance(st, dict) and st["landmark_passes"] == {"heavy": 0, "full": 2}
        assert st["costs"]["landmark_ms_per_crop"]["full"] > 0
        # Injected costs (no wall clock decides): full dearer than any pass may take → off, YOLO's points alone.
        front._per_crop["full"].value = front._per_crop["heavy"].value = 10_000.0
        off = det(frame)
        assert front.choice.variant is None and "no model fits" in front.choice.reason
        assert off.confidences[:, EXTRA].max() == 0.0 and off.confidences[:, BLAZEPOSE33.index("left_hip")].max() > 0.3
        # Off by its costs, the cheapest model still runs once every REPROBE_NS to measure itself again (here: its
        # last run moved 20 s back), and only once.
        front._ran_ns["full"] -= REPROBE_NS
        probe = det(frame)
        assert probe.confidences[:, EXTRA].max() > 0.3 and front.landmark_passes["full"] == 3
        assert front._per_crop["full"].value < 10_000.0 and front.choice.variant is None
        assert det(frame).confidences[:, EXTRA].max() == 0.0 and front.landmark_passes["full"] == 3
        # Cheap and an idle detector → heavy every pass, with its points.
        front._per_crop["full"].value, front._per_crop["heavy"].value = 1.0, 2.0
        front._idle.value = 1_000.0
        heavy = det(frame)  # heavy's first run: loads it, not counted (its injected cost stays)
        chosen = front.current()
        assert (chosen.variant, chosen.every) == ("heavy", 1) and heavy.confidences[:, EXTRA].max() > 0.3
        # The governor's hook holds it off, with its reason, and gives it back.
        shed_landmarks(landmark_fronts(det), "step 1, tick p95 50.0 ms")
        det(frame)
        st = detector_status(det)["landmarks"]
        assert isinstance(st, dict) and st["running"] == "off" and st["shed"] and "step 1" in str(st["reason"])
        shed_landmarks(landmark_fronts(det), None)
        front._per_crop["full"].value, front._per_crop["heavy"].value = 1.0, 2.0  # heavy's real run measured it
        det(frame)
        st = detector_status(det)["landmarks"]
        assert isinstance(st, dict) and st["running"] == "heavy" and st["passes"] == 8
        assert st["landmark_passes"] == {"heavy": 2, "full": 3}
        assert set(st["cameras"]["all"]) == {"detect_hz", "landmark_hz"}
        line = status_field(landmark_fronts(det))
        assert line is not None and line.startswith("landmarks heavy (")
        sub = health_subset({"detector": {"landmarks": st}})
        assert sub["landmarks"]["running"] == "heavy" and "cameras" in sub["landmarks"]
    finally:
        det.close()


def test_the_daemons_governor_applies_the_landmark_step_to_the_cameras_detector(tmp_path: Path) -> None:
    text = video_rig_toml('[detector]\nlandmarks = "auto"\nintra_op_threads = 1\n')
    text = text.replace("[daemon]\nhttp_port = 0\n", "[daemon]\nhttp_port = 0\ngovernor = true\n")
    with assembled(load_config(write(tmp_path / "config.toml", text))) as built:
        daemon = built.daemon
        assert daemon.governor is not None and daemon.governor.ladder == LADDER  # with the landmark step
        fronts = daemon._landmark_fronts()
        assert fronts and all(isinstance(f, AutoLandmarks) and f.shed is None for f in fronts)
        daemon.governor.step_index = 1  # as after one overrun window
        daemon.governor.last_reason = "tick p95 50.0 ms of a 16.7 ms period"
        daemon._apply_governor()
        assert all(isinstance(f, AutoLandmarks) and "tick p95 50.0 ms" in str(f.shed) for f in fronts)
        assert "landmarks off (" in daemon.status_line_text()
        assert "step 1" in str(daemon.status()["detector"]["landmarks"]["reason"])  # /status says it at once
        daemon.governor.step_index = 0
        daemon._apply_governor()
        assert all(isinstance(f, AutoLandmarks) and f.shed is None for f in fronts)


def test_a_pinned_governor_step_is_applied_from_the_start_and_one_the_ladder_lacks_is_refused(tmp_path: Path) -> None:
    """``[daemon] governor_pin_step`` (a developer measures what a step saves): the daemon runs at that step from
    its first tick, says so in ``/status``, and never moves; a step the rig's ladder does not have (the synthetic
    rig's ladder is step 0 and the half-rate solve) is refused with the ladder named."""
    text = video_rig_toml('[detector]\nlandmarks = "auto"\nintra_op_threads = 1\n')
    text = text.replace("[daemon]\nhttp_port = 0\n", "[daemon]\nhttp_port = 0\ngovernor_pin_step = 3\n")
    with assembled(load_config(write(tmp_path / "config.toml", text))) as built:
        daemon = built.daemon
        assert daemon.governor is not None and daemon.governor.pinned and daemon.governor.step_index == 3
        assert all(
            isinstance(f, AutoLandmarks) and "pinned at step 3" in str(f.shed) for f in daemon._landmark_fronts()
        )
        groups = {id(g): g for s in daemon.rig.sources if (g := getattr(s, "group", None)) is not None}
        assert groups and all(g.duty == 0.5 for g in groups.values())  # step 3: the detector at 50 % duty
        st = daemon.status()["governor"]
        assert st["pinned"] is True and st["shed"] == "detector at 50 % duty" and "governor_pin_step" in st["reason"]
    # The synthetic rig's ladder: step 0 and the people solved at half rate, which the scheduler is told.
    half = write(
        tmp_path / "half.toml",
        synthetic_toml(2, "").replace("http_port = 0\n", "http_port = 0\ngovernor_pin_step = 1\n"),
    )
    with assembled(load_config(half)) as built:
        assert built.daemon.scheduler.solve_every == 2
        assert built.daemon.status()["governor"]["shed"] == "people solved at half rate"
    bad = write(
        tmp_path / "synthetic.toml",
        synthetic_toml(2, "").replace("http_port = 0\n", "http_port = 0\ngovernor_pin_step = 3\n"),
    )
    with (
        pytest.raises(
            ConfigError,
            match=r"daemon.governor_pin_step: step 3 is not on this rig's ladder \(steps 0..2: nothing shed, "
            r"people solved at half rate, people solved on every third tick\)",
        ),
        assembled(load_config(bad)),
    ):
        pass
