"""A synthetic capture world for ``mocapd demo --synthetic``, the latency benchmark and the daemon's tests.

People move in a ring rig, offset so they keep apart: by default with real recorded motion (CMU clips shipped as
``mocapd/data/demo_motion_cmu.npz``, built by ``tools/build_demo_motion.py``), or with the procedural
:func:`~mocapd.core.synthetic.moving_sequence` (``motion="procedural"``). The motion is a loop played forwards then
backwards (continuous, so tracking and warm starts never see a jump) and is a
function of host time, so every simulated device (keypoints per camera, each IMU) measures the same instant of
the same truth:

- :meth:`SyntheticWorld.detections` projects every person's keypoint targets (COCO-17 by default) into a
  camera at a time, adds pixel noise: what a detector reports for the frame captured then;
- :meth:`SyntheticWorld.imu_motion` gives each suit sensor's orientation (ENU, as a real Xsens device reports it)
  and sensor-frame specific force, sampled at the device rate over one loop: what the Xsens simulator streams;
- :meth:`SyntheticWorld.calibration` is the suit's calibration (R_ig from ENU to the +Y-up world, a random
  mounting R_ib per sensor) that turns those readings back into bone orientations (Eq. 8);
- :meth:`SyntheticWorld.heading_faults` draws per-sensor heading errors (offset + drift) for the simulated
  devices, which the calibration does not know about.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera, project_points, stack_cameras
from mocapd.core.imu import IMU_SET_13, ImuMount, default_mounts
from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.keypoints import TrackTargets, keypoint_format
from mocapd.core.kinematics import Kinematics
from mocapd.core.motion import resample_poses
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.rotations import (
    matrix_from_quat,
    quat_conjugate,
    quat_from_matrix,
    quat_multiply,
    quat_normalize,
    random_quat,
)
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.core.synthetic import moving_sequence, ring_rig
from mocapd.errors import ConfigError, ModelError
from mocapd.io.device_state import OpenState
from mocapd.pipeline.keypoint_source import KeypointSink
from mocapd.sim.xsens import HeadingFault

FloatArray = NDArray[np.float64]

#: ENU (x east, y north, z up) -> world (+Y up, Z south): world = R · enu
R_WORLD_FROM_ENU = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
Q_WORLD_FROM_ENU = quat_from_matrix(R_WORLD_FROM_ENU)
GRAVITY_WORLD = np.array([0.0, 9.81, 0.0])
TRUTH_FPS = 240.0
DEMO_MOTION = "demo_motion_cmu.npz"


@dataclass(frozen=True)
class SuitTruth:
    """One simulated suit: which person wears it, its sensors' ids, mounts and mounting rotations."""

    id: str
    person: int
    sensor_ids: tuple[int, ...]
    mounts: tuple[ImuMount, ...]
    q_ib: FloatArray  # (n, 4) sensor -> bone


class SyntheticWorld:
    """People moving in a ring rig, as a function of host time (seconds since ``epoch``).

    Parameters
    ----------
    n_cams : int
        Cameras in the ring (4 or 8 typical).
    n_people : int
        People in the volume.
    n_suits : int
        How many of them (the first ones) wear a 13-IMU suit.
    loop_s : float
        Duration of the motion before it plays backwards (the period is twice this).
    seed : int
    camera_names : sequence of str, optional
        The cameras' names (default ``cam0``, ``cam1``, ...).
    motion : {"recorded", "procedural"}
        Recorded CMU clips (person ``p`` plays clip ``p mod 4``, later laps start half-way through), or the
        procedural walk (each person a 1 m circle around their centre; ``loop_s`` applies to it only, recorded
        clips loop over their own length).
    keypoints : str
        The detector's keypoint format the cameras report ("coco17", "body25", "halpe26", "blazepose33").
    """

    def __init__(
        self,
        n_cams: int = 4,
        n_people: int = 2,
        n_suits: int = 1,
        loop_s: float = 6.0,
        seed: int = 0,
        motion: str = "recorded",
        camera_names: Sequence[str] | None = None,
        keypoints: str = "coco17",
    ) -> None:
        self.cameras: list[Camera] = ring_rig(n_cams)
        if camera_names is not None:
            self.cameras = [dataclasses.replace(c, name=n) for c, n in zip(self.cameras, camera_names, strict=True)]
        fmt = keypoint_format(keypoints)
        if motion == "recorded":
            clips, self.skeleton = load_demo_motion()
            self.loop_s = min(c.shape[0] for c in clips) / TRUTH_FPS
            n = int(self.loop_s * TRUTH_FPS)
            sequences = [
                np.roll(clips[p % len(clips)], (p // len(clips)) * n // 2, axis=0)[:n] for p in range(n_people)
            ]
        elif motion == "procedural":
            self.skeleton = Skeleton.from_height(1.75)
            self.loop_s = loop_s
            n = int(loop_s * TRUTH_FPS) + 1
            sequences = [moving_sequence(self.skeleton, n, fps=TRUTH_FPS, seed=seed + 17 * p) for p in range(n_people)]
        else:
            raise ConfigError(f"synthetic motion must be 'recorded' or 'procedural', got {motion!r}")
        self.targets: TrackTargets = fmt.track_targets(self.skeleton)
        self.kin = Kinematics(self.skeleton)
        self._site_models = PerSkeleton((self.kin, self.targets), lambda sk: (Kinematics(sk), fmt.track_targets(sk)))
        self.truth: list[FloatArray] = []
        for p, motion_p in enumerate(sequences):
            seq = motion_p.copy()
            # Centres 1.3 m from the middle of the volume, spread around it.
            angle = 2 * np.pi * p / max(n_people, 1)
            seq[:, [0, 2]] += (1.3 * np.sin(angle), 1.3 * np.cos(angle) + 1.0) if n_people > 1 else (0.0, 1.0)
            self.truth.append(seq)
        self._camera_stack = stack_cameras(self.cameras)
        self._target_seq = [self.kin.targets(self.kin.forward(s), self.targets.bones, self.targets.offsets)
                            for s in self.truth]  # fmt: skip
        rng = np.random.default_rng(seed + 1000)
        self.suits = [
            SuitTruth(
                id=f"suit{p}",
                person=p,
                sensor_ids=tuple(0x00B42000 + 0x100 * p + k for k in range(len(IMU_SET_13))),
                mounts=default_mounts(IMU_SET_13, self.skeleton),
                q_ib=random_quat(rng, (len(IMU_SET_13),)),
            )
            for p in range(min(n_suits, n_people))
        ]

    # ------------------------------------------------------------------------------------------ truth
    def _frame(self, t_s: float) -> tuple[int, int, float]:
        """Host time -> (frame a, frame b, alpha) of the truth sequences.

        The motion plays forwards then backwards, slowing smoothly to rest at each end
        (``u = L (1 - cos(π t / L)) / 2``): no jump and no velocity reversal in one sample, which an
        accelerometer would see as an impossible impulse.
        """
        u = 0.5 * self.loop_s * (1.0 - np.cos(np.pi * t_s / self.loop_s))
        f = u * TRUTH_FPS
        a = min(int(f), self.truth[0].shape[0] - 2) if self.truth else 0
        return a, a + 1, f - a

    def theta_at(self, person: int, t_s: float) -> FloatArray:
        """Person's pose at time ``t_s`` (66,) (linear between truth frames)."""
        a, b, w = self._frame(t_s)
        seq = self.truth[person]
        out: FloatArray = (1 - w) * seq[a] + w * seq[b]
        return out

    def sites_at(self, person: int, t_s: float) -> FloatArray:
        """Person's 17 keypoint sites (17, 3) at ``t_s``: what the simulated cameras observe."""
        a, b, w = self._frame(t_s)
        seq = self._target_seq[person]
        out: FloatArray = (1 - w) * seq[a] + w * seq[b]
        return out

    def nearest_site_error(self, theta: FloatArray, skeleton: Skeleton | None, t_s: float) -> tuple[float, int]:
        """Mean 3D distance (m) of a solved pose's 17 keypoint sites from the nearest true person's at ``t_s``, and
        that person's index.

        Sites, not joints: with per-person body sizing a solved skeleton differs from the world's, and joints no
        camera sees (the spine chain, the root inside the pelvis) sit at different places on two skeletons by
        definition. ``skeleton`` is the pose's own (None: the world's).
        """
        kin, targets = self._site_models.get(skeleton)
        sites = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
        errors = [float(np.linalg.norm(sites - self.sites_at(p, t_s), axis=1).mean()) for p in range(len(self.truth))]
        k = int(np.argmin(errors))
        return errors[k], k

    def joints_at(self, person: int, t_s: float) -> FloatArray:
        """Person's global joint positions (21, 3) at ``t_s``."""
        positions: FloatArray = self.kin.forward(self.theta_at(person, t_s)).positions
        return positions

    def bump(self, camera: int, rotation: FloatArray) -> None:
        """Turn camera ``camera`` on its mount by ``rotation`` (3x3, in its own frame): its detections from now on
        come from the turned camera, while the rig's calibration stays what it was (a knock during a run)."""
        c = self.cameras[camera]
        self.cameras[camera] = dataclasses.replace(c, R=rotation @ c.R, t=rotation @ c.t)
        self._camera_stack = stack_cameras(self.cameras)

    # ------------------------------------------------------------------------------------------ sensors
    def detections(self, cam: int, t_s: float, rng: np.random.Generator, noise_px: float = 1.0) -> Detections2D:
        """The people camera ``cam`` sees at ``t_s``, in a random order (a detector's output for that frame)."""
        a, b, w = self._frame(t_s)
        K, dist, R, t = (x[cam : cam + 1] for x in self._camera_stack)
        c = self.cameras[cam]
        kps, cfs = [], []
        if self._target_seq:
            # Every person in one projection and one draw of noise (the same draws, person after person): the
            # cameras' frames are made on the event loop, 120 a second in the demo.
            X = np.stack([(1 - w) * seq[a] + w * seq[b] for seq in self._target_seq])
            uv_all, _, valid_all = project_points(K, dist, R, t, X, jacobian=False)
            noisy = uv_all + rng.normal(scale=noise_px, size=uv_all.shape)
            for uv, valid in zip(noisy, valid_all, strict=True):
                inside = valid & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
                if inside.sum() >= 5:
                    kps.append(np.where(inside[:, None], uv, 0.0))
                    cfs.append(inside * 0.9)
        if not kps:
            return Detections2D.empty(len(self.targets))
        order = rng.permutation(len(kps))
        return Detections2D(np.stack(kps)[order], np.stack(cfs)[order])

    def imu_motion(self, suit: SuitTruth, rate_hz: float) -> tuple[FloatArray, FloatArray]:
        """One full period (forwards and back) of every sensor of ``suit`` at ``rate_hz``.

        Returns
        -------
        quat : array, shape (n_sensors, n_samples, 4)
            Sensor orientation in ENU, (w, x, y, z): ``R_i = R_ig⁻¹ · R_gb · R_ib``.
        acc : array, shape (n_sensors, n_samples, 3)
            Specific force in the sensor frame (m/s², gravity included), as an accelerometer measures it.
        """
        n = round(2.0 * self.loop_s * rate_hz)
        ts = np.arange(n) / rate_hz
        thetas = np.stack([self.theta_at(suit.person, float(t)) for t in ts])
        fk = self.kin.forward(thetas)
        bones = np.array([m.bone_index for m in suit.mounts], dtype=np.intp)
        offsets = np.array([m.t_ib for m in suit.mounts])
        sites = self.kin.targets(fk, bones, offsets)  # (n, n_imu, 3)
        # Periodic second difference: the loop is continuous, so sample n-1 neighbours sample 0.
        acc_world = (np.roll(sites, -1, axis=0) - 2 * sites + np.roll(sites, 1, axis=0)) * rate_hz**2
        q_gb = quat_from_matrix(fk.rotations[:, bones])  # (n, n_imu, 4)
        q_gi = quat_multiply(q_gb, suit.q_ib[None])  # world <- sensor: R_gi = R_ig R_i = R_gb R_ib
        q_i = quat_normalize(quat_multiply(quat_conjugate(Q_WORLD_FROM_ENU)[None, None], q_gi))
        R_gi = matrix_from_quat(q_gi)
        acc_sensor = np.einsum("nkji,nkj->nki", R_gi, acc_world + GRAVITY_WORLD)
        return np.transpose(q_i, (1, 0, 2)), np.transpose(acc_sensor, (1, 0, 2))

    @staticmethod
    def heading_faults(
        suit: SuitTruth, max_offset_deg: float = 45.0, drift_deg_per_min: float = 10.0, seed: int = 0
    ) -> dict[str, HeadingFault]:
        """Per sensor id of ``suit``: a heading error its simulated device reports and its calibration ignores.

        The offsets are spread evenly over ``±max_offset_deg`` (both extremes included) in a random order, each
        drifting by ``drift_deg_per_min`` in a random direction.
        """
        rng = np.random.default_rng(seed)
        n = len(suit.sensor_ids)
        offsets = rng.permutation(np.linspace(-max_offset_deg, max_offset_deg, n))
        signs = rng.choice((-1.0, 1.0), size=n)
        return {f"{sid:08X}": HeadingFault(float(o), float(s) * drift_deg_per_min)
                for sid, o, s in zip(suit.sensor_ids, offsets, signs, strict=True)}  # fmt: skip

    def calibration(self, suit: SuitTruth) -> ImuCalibration:
        """The suit's calibration: what ``mocapd calibrate imu`` would have produced for it."""
        ids = [f"{s:08X}" for s in suit.sensor_ids]
        return ImuCalibration(
            person=suit.id,
            facing_heading_deg=0.0,
            world_heading="north",
            q_ig=Q_WORLD_FROM_ENU.copy(),
            bones={sid: m.bone for sid, m in zip(ids, suit.mounts, strict=True)},
            q_ib={sid: q for sid, q in zip(ids, suit.q_ib, strict=True)},
            spread_deg=dict.fromkeys(ids, 0.0),
        )


def load_demo_motion() -> tuple[list[FloatArray], Skeleton]:
    """The shipped recorded clips, resampled to :data:`TRUTH_FPS`, and the skeleton they were retargeted to.

    Returns
    -------
    clips : list of arrays, shape (n_i, 66)
    skeleton : Skeleton
    """
    path = Path(str(resources.files("mocapd").joinpath("data", DEMO_MOTION)))
    try:
        with np.load(path) as z:
            fps = float(z["fps"])
            clips = [resample_poses(z[k].astype(np.float64), fps, TRUTH_FPS) for k in sorted(z.files)
                     if k.startswith("theta_")]  # fmt: skip
            skeleton = Skeleton(offsets=z["offsets"], root_height=float(z["root_height"]))
    except (OSError, KeyError, ValueError) as exc:
        raise ModelError(f"cannot load the synthetic rig's recorded motion {path}: {exc}") from exc
    return clips, skeleton


class SyntheticKeypointSource:
    """A detector's output for camera ``camera`` of a :class:`SyntheticWorld` (world time 0 at ``epoch_ns``)."""

    def __init__(
        self,
        world: SyntheticWorld,
        camera: int,
        *,
        epoch_ns: int,
        rate_hz: float = 30.0,
        delay_s: float = 0.05,
        noise_px: float = 1.0,
        seed: int = 0,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.world = world
        self.camera = camera
        self.name = world.cameras[camera].name
        self.epoch_ns = epoch_ns
        self.period_ns = round(1e9 / rate_hz)
        # Unsynchronised cameras: phases spread over one frame interval.
        self.phase_ns = camera * self.period_ns // max(len(world.cameras), 1)
        self.delay_ns = round(delay_s * 1e9)
        self.noise_px = noise_px
        self.rng = np.random.default_rng(seed * 1000 + camera)
        self.clock = clock
        self.frames = 0
        self.skipped = 0
        self.paused = False  # a test's "unplugged camera": frames are captured but nothing is delivered

    async def run(self, sink: KeypointSink) -> None:
        now = self.clock()
        k = (now - self.epoch_ns - self.phase_ns) // self.period_ns + 1
        while True:
            capture = self.epoch_ns + self.phase_ns + k * self.period_ns
            await asyncio.sleep(max(0.0, (capture + self.delay_ns - self.clock()) / 1e9))
            if not self.paused:
                dets = self.world.detections(self.camera, (capture - self.epoch_ns) / 1e9, self.rng, self.noise_px)
                sink(self.camera, capture, dets, self.clock())
                self.frames += 1
            # A detector that fell behind skips to the newest frame rather than queueing old ones.
            behind = (self.clock() - self.delay_ns - capture) // self.period_ns
            self.skipped += max(0, behind - 1) if behind > 1 else 0
            k += max(1, behind)

    def open_state(self) -> OpenState:
        return OpenState("open", "")  # nothing to open: the detections are computed

    def status(self) -> dict[str, Any]:
        return {"name": self.name, "kind": "synthetic", "frames": self.frames, "skipped": self.skipped,
                "paused": self.paused}  # fmt: skip
