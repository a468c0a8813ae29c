"""The batched still-window search (:func:`stillest_common_window`) chooses exactly the window of scoring every
window one by one (:func:`_stillest_common_window_reference`, the search as it was), on real recordings and on
random ones, and its error bounds hold."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu_calibration import (
    FloatArray,
    Samples,
    _batchable,
    _batched_scores,
    _stillest_common_window_reference,
    _window_starts,
    _window_worst,
    stillest_common_window,
)
from mocapd.core.rotations import quat_from_rotvec, quat_multiply, random_quat
from mocapd.errors import CalibrationError
from mocapd.eval.data import default_data_root
from mocapd.eval.ground_real import MTW_ASSIGNMENT
from mocapd.io.session import open_session
from mocapd.service.cli import main
from mocapd.service.session.calibrate import session_samples

MVNX = default_data_root() / "imu" / "mvnx" / "mpiea_upperbody_test_mocap.mvnx"


def _imported(tmp: Path, args: list[str]) -> dict[str, tuple[FloatArray, FloatArray, FloatArray]]:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["import", *args, "-o", str(tmp)]) == 0
    return session_samples(open_session(tmp))


@pytest.fixture(scope="module")
def mtw(tmp_path_factory: pytest.TempPathFactory) -> Samples:
    files = sorted(str(p) for p in (default_data_root() / "imu" / "opensense_mtw").glob("*.txt"))
    assign = [a for sid, bone in MTW_ASSIGNMENT.items() for a in ("--assign", f"{sid}={bone}")]
    samples = _imported(tmp_path_factory.mktemp("mtw"), ["mtw", *files, *assign])
    return {s: samples[s] for s in MTW_ASSIGNMENT}


def _same(samples: Samples, window_s: float, span: tuple[float, float] | None, **limits: float) -> None:
    assert stillest_common_window(samples, window_s, span, **limits) == _stillest_common_window_reference(
        samples, window_s, span, **limits
    )


@pytest.mark.parametrize(
    ("window_s", "span", "limits"),
    [
        (1.0, None, {}),  # what `mocapd calibrate imu --from` searches
        (0.5, (3.217, 9.5), {"max_turn_deg": 1.0}),
        (2.0, None, {"max_acc_std": 0.05}),
        (1.0, (20.0, 21.0), {}),  # a span that holds one window
    ],
)
def test_the_real_mtw_take_gets_the_window_of_the_reference(
    mtw: Samples, window_s: float, span: tuple[float, float] | None, limits: dict[str, float]
) -> None:
    assert _batchable(mtw, 4.0, 0.5)  # the batched path, not its fallback, is what is compared
    _same(mtw, window_s, span, **limits)
    _same({s: mtw[s] for s in list(mtw)[:3]}, window_s, span, **limits)


def test_the_real_mvnx_take_gets_the_window_of_the_reference(tmp_path: Path) -> None:
    samples = _imported(tmp_path / "mvn", ["mvnx", str(MVNX)])
    assert _batchable(samples, 4.0, 0.5)
    _same(samples, 1.0, None)
    _same(samples, 0.25, (1.0, 4.0), max_turn_deg=0.5)


def _random_take(rng: np.random.Generator, sensors: int) -> dict[str, tuple[FloatArray, FloatArray, FloatArray]]:
    """Sensors at their own rates with jittered clocks, dropouts, still stretches and movements of every size."""
    out = {}
    for k in range(sensors):
        rate = float(rng.choice([20.0, 60.0, 100.0]))
        t = rng.uniform(0.0, 0.5) + np.arange(int(rate * rng.uniform(3.0, 6.0))) / rate
        t = np.sort(t + rng.normal(0.0, 0.1 / rate, len(t)))
        if rng.random() < 0.5:  # a dropout: some windows hold fewer than two samples
            gap = rng.uniform(0.5, 2.5)
            t = t[(t < gap) | (t > gap + rng.uniform(0.2, 1.5))]
        scale = rng.choice([0.0, 1e-6, 1e-3, 0.02, 0.3], size=len(t))
        steps = quat_from_rotvec(rng.normal(size=(len(t), 3)) * scale[:, None])
        q = random_quat(rng)
        quat = np.empty((len(t), 4))
        for i, s in enumerate(steps):
            q = quat_multiply(q, s)
            quat[i] = q / np.linalg.norm(q)
        if rng.random() < 0.3:  # signs flip (the same orientations)
            quat *= rng.choice([-1.0, 1.0], size=(len(t), 1))
        acc = np.array([0.0, 0.0, 9.81]) + rng.normal(size=(len(t), 3)) * rng.choice([0.0, 0.01, 0.5])
        out[f"s{k}"] = (t, quat, acc)
    return out


@pytest.mark.parametrize("seed", range(12))
def test_random_takes_get_the_window_of_the_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    samples = _random_take(rng, int(rng.integers(1, 5)))
    for window_s, span in [(1.0, None), (0.3, None), (0.5, (1.013, 2.7))]:
        try:
            expected = _stillest_common_window_reference(samples, window_s, span, max_turn_deg=2.0)
        except CalibrationError as exc:
            with pytest.raises(CalibrationError, match=str(exc).replace(".", r"\.")):
                stillest_common_window(samples, window_s, span, max_turn_deg=2.0)
            continue
        assert stillest_common_window(samples, window_s, span, max_turn_deg=2.0) == expected


def test_ties_and_inputs_it_does_not_bound_get_the_window_of_the_reference() -> None:
    t = np.arange(300) / 100.0
    still = (t, np.tile([1.0, 0.0, 0.0, 0.0], (300, 1)), np.tile([0.0, 0.0, 9.81], (300, 1)))
    _same({"a": still, "b": still}, 1.0, None)  # every window scores 0: the first is chosen
    nan_acc = still[2].copy()
    nan_acc[40] = np.nan
    assert not _batchable({"a": (t, still[1], nan_acc)}, 4.0, 0.5)
    _same({"a": (t, still[1], nan_acc)}, 0.5, None)
    assert not _batchable({"a": (t, still[1].astype(np.float32), still[2])}, 4.0, 0.5)
    _same({"a": (t, still[1].astype(np.float32), still[2])}, 0.5, None)


@pytest.mark.parametrize("seed", range(4))
def test_each_batched_score_is_within_its_bound_of_the_one_by_one_score(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    (sid, (t, q, a)), *_ = _random_take(rng, 1).items()
    starts = _window_starts({sid: (t, q, a)}, 0.5, None)
    score, bound = _batched_scores(t, q, a, starts, 0.5, 2.0, 0.5)
    exact = np.array([_window_worst({sid: (t, q, a)}, s, 0.5, 2.0, 0.5) for s in starts])
    assert np.array_equal(np.isinf(score), np.isinf(exact))
    finite = np.isfinite(exact)
    assert np.all(np.abs(score[finite] - exact[finite]) <= bound[finite])
