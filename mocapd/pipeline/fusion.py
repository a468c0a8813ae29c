"""The learned fusion of seed 001 in the daemon (issue 30): the exported networks run with onnxruntime.

Per tracked person, every :data:`~mocapd.core.fusion_features.STRIDE`-th tick (20 Hz of the 60 Hz output),
:class:`FusionStage`

1. carves the person's two-channel PVH (:mod:`mocapd.core.pvh`) around the grid centre triangulated from their
   detections: the matte channel from each camera's foreground matte (a :class:`~mocapd.pipeline.mattes.MatteSource`:
   background subtraction on real frames, rendered proxies on the synthetic rig), the joint channel from the
   person's own keypoints in that camera (so another person inside the grid carves only the matte);
2. runs the PVH network (``fusion_cnn.onnx``) and, on the last f of these frames, the temporal graph
   (``fusion_temporal.onnx``: the vision LSTM, the solved-IMU LSTM and the 64-unit fusion layer);
3. for a suit wearer, feeds mocapd's IMU-only solve of the suit (a :class:`~mocapd.core.solver.PoseSolver` without
   cameras, every tick) whose joints are the solved-IMU stream.

The result (:class:`LearnedJoints`) enters the person's LM solve as soft 3D joint observations (``[fusion] mode =
"both"``, the E_J term), or replaces the cameras and IMUs in it (``"learned"``: the skeleton fitted to the learned
joints, prior and floor kept). The networks are trained here (``tools/train_fusion.py``, ~50 min on two cores)
into the cache (:func:`default_model_dir`), not kept in the repository (no model weights are committed);
``mocapd/data/fusion.json`` is the provenance of the reference training every published number comes from.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.fusion_features import JOINT_DIM, LOOK_BACK, N_JOINTS, STRIDE, imu_windows, vision_windows
from mocapd.core.imu import ImuMount
from mocapd.core.keypoints import TrackTargets
from mocapd.core.prior import PcaPrior
from mocapd.core.pvh import PvhGrid, carve, joint_map, joint_sigma, log_channels, person_centre, scaled_pixels
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.terms import CostOptions
from mocapd.errors import ModelError
from mocapd.io.model_cache import cache_dir
from mocapd.io.native_logs import quiet_session_options

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

CNN_FILE = "fusion_cnn.onnx"
TEMPORAL_FILE = "fusion_temporal.onnx"
RAW_IMU_FILE = "fusion_raw_imu.onnx"
PROVENANCE_FILE = "fusion.json"
Mode = Literal["solver", "learned", "both"]


def default_model_dir() -> Path:
    """Where ``tools/train_fusion.py`` writes the networks by default: ``<cache>/fusion``."""
    return cache_dir() / "fusion"


def reference_provenance() -> dict[str, Any]:
    """The reference training's provenance (``mocapd/data/fusion.json``: sources, recipe, file hashes, the CI
    recipe's reproduction check), the run docs/learned-fusion.md's numbers come from."""
    text = resources.files("mocapd").joinpath("data", PROVENANCE_FILE).read_text(encoding="utf-8")
    prov: dict[str, Any] = json.loads(text)
    return prov


def cnn_file(variant: str) -> str:
    """File of a PVH network variant: "both" (the daemon's), "matte" or "joints" (Table 6's single-channel ablation)."""
    return CNN_FILE if variant == "both" else CNN_FILE.replace(".onnx", f"_{variant}.onnx")


def available_variants(directory: Path | None = None) -> tuple[str, ...]:
    """The PVH network variants whose files are in ``directory`` (default: :func:`default_model_dir`)."""
    d = default_model_dir() if directory is None else Path(directory)
    return tuple(v for v in ("both", "matte", "joints") if (d / cnn_file(v)).is_file())


class FusionModels:
    """The exported networks of one training run, loaded into onnxruntime sessions.

    Parameters
    ----------
    directory : folder with the ONNX files and ``fusion.json`` (default: :func:`default_model_dir`).
    threads : onnxruntime intra-op threads per session (1: the daemon's other work keeps the second core).
    variants : PVH network variants to load (:func:`cnn_file`).
    raw_imu : also load the raw-IMU LSTM (Table 6).
    """

    def __init__(
        self,
        directory: Path | None = None,
        threads: int = 1,
        variants: tuple[str, ...] = ("both",),
        raw_imu: bool = False,
    ) -> None:
        self.directory = default_model_dir() if directory is None else Path(directory)
        prov = self.directory / PROVENANCE_FILE
        try:
            self.provenance: dict[str, Any] = json.loads(prov.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ModelError(
                f"learned fusion: cannot read {prov} ({exc}); train the networks with tools/train_fusion.py "
                f"--out {self.directory} (~50 min on two cores, docs/learned-fusion.md)"
            ) from exc
        recipe = self.provenance.get("recipe", {})
        self.grid = PvhGrid(
            int(recipe.get("grid_size", 30)),
            float(recipe.get("extent", 2.0)),
            int(recipe.get("supersample", 1)),
            int(recipe.get("scale", 8)),
        )
        self.look_back = int(recipe.get("look_back", LOOK_BACK))
        self.stride = int(recipe.get("stride", STRIDE))
        so = quiet_session_options(ort.SessionOptions())
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self._cnn = {v: self._session(cnn_file(v), so) for v in variants}
        self.variants = tuple(self._cnn)
        self._temporal = self._session(TEMPORAL_FILE, so)
        self._raw = self._session(RAW_IMU_FILE, so) if raw_imu else None

    def _session(self, name: str, so: ort.SessionOptions) -> ort.InferenceSession:
        path = self.directory / name
        if not path.is_file():
            raise ModelError(f"learned fusion: {path} is missing; train it with tools/train_fusion.py")
        try:
            return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors for a bad file
            raise ModelError(f"learned fusion: onnxruntime cannot load {path}: {exc}") from exc

    def cnn(self, pvh: F32, variant: str = "both") -> F32:
        """Joints relative to the grid centre (B, 63) of PVHs (B, C, S, S, S) in [0, 1]."""
        out = self._cnn[variant].run(None, {"pvh": np.ascontiguousarray(pvh, dtype=np.float32)})[0]
        return np.asarray(out, dtype=np.float32)

    def temporal(self, vision: F32, imu: F32, views: F32) -> tuple[F32, F32, F32]:
        """The vision LSTM's joints (rel. grid centre), the IMU LSTM's (rel. root) and the fused ones (rel. grid
        centre), each (B, 63), from windows (B, f, 63) and the views that see the person (B, 1)."""
        v, i, f = self._temporal.run(
            None,
            {
                "vision": np.ascontiguousarray(vision, dtype=np.float32),
                "imu": np.ascontiguousarray(imu, dtype=np.float32),
                "views": np.ascontiguousarray(views, dtype=np.float32),
            },
        )
        return np.asarray(v), np.asarray(i), np.asarray(f)

    def raw_imu(self, windows: F32) -> F32:
        """Raw-IMU LSTM: joints relative to the root (B, 63) from raw orientation windows (B, f, 91)."""
        if self._raw is None:
            raise ModelError("learned fusion: the raw-IMU network was not loaded (raw_imu=True)")
        return np.asarray(self._raw.run(None, {"raw_imu": np.ascontiguousarray(windows, dtype=np.float32)})[0])


@dataclass(frozen=True)
class LearnedJoints:
    """One person's learned joints at one learned frame (world, metres, (21, 3) each).

    ``fused`` is None without an IMU stream (no suit); ``joints`` is what enters the solve: the fused joints where
    there are IMUs, else the vision LSTM's."""

    vision: FloatArray
    fused: FloatArray | None
    views: int

    @property
    def joints(self) -> FloatArray:
        return self.vision if self.fused is None else self.fused


class PersonFusion:
    """One person's learned stream: the last f learned frames of both streams, in the training's windows."""

    def __init__(self, models: FusionModels) -> None:
        self.models = models
        f = models.look_back
        self._vision: deque[FloatArray] = deque(maxlen=f)
        self._centres: deque[FloatArray] = deque(maxlen=f)
        self._imu: deque[FloatArray] = deque(maxlen=f)
        self.last_ms: dict[str, float] = {}
        """Milliseconds of the last step's PVH network and temporal graph (for benchmarks and /status)."""

    def reset(self) -> None:
        self._vision.clear()
        self._centres.clear()
        self._imu.clear()

    def step(self, pvh: F32, centre: FloatArray, views: int, imu_joints: FloatArray | None) -> LearnedJoints:
        """One learned frame.

        Parameters
        ----------
        pvh : (2, S, S, S) in [0, 1]; centre : (3,) its grid centre; views : cameras that see the person.
        imu_joints : (21, 3) the IMU-only solve's joints, or None without a suit.
        """
        t0 = time.perf_counter()
        rel = self.models.cnn(pvh[None])[0].astype(np.float64).reshape(N_JOINTS, 3)
        t1 = time.perf_counter()
        _push(self._vision, rel + centre, self.models.look_back)
        _push(self._centres, np.asarray(centre, dtype=np.float64), self.models.look_back)
        hist_v = np.stack(self._vision)
        vis_win = vision_windows(hist_v, np.stack(self._centres), len(hist_v))[-1]
        if imu_joints is not None:
            _push(self._imu, np.asarray(imu_joints, dtype=np.float64), self.models.look_back)
            imu_win = imu_windows(np.stack(self._imu), len(self._imu))[-1]
        else:
            self._imu.clear()
            imu_win = np.zeros_like(vis_win)
        v, _, fused = self.models.temporal(
            vis_win[None].astype(np.float32), imu_win[None].astype(np.float32), np.array([[views]], dtype=np.float32)
        )
        self.last_ms = {"cnn": 1e3 * (t1 - t0), "temporal": 1e3 * (time.perf_counter() - t1)}
        c = np.asarray(centre, dtype=np.float64)
        vision = v[0].astype(np.float64).reshape(N_JOINTS, 3) + c
        out = fused[0].astype(np.float64).reshape(N_JOINTS, 3) + c if imu_joints is not None else None
        return LearnedJoints(vision, out, views)


def _push(buf: deque[FloatArray], x: FloatArray, f: int) -> None:
    """Append ``x``; a fresh buffer is filled with copies of it (the training's windows repeat the first frame)."""
    if not buf:
        buf.extend(x.copy() for _ in range(f - 1))
    buf.append(x)


@dataclass(frozen=True)
class FusionOptions:
    """``[fusion]``: what the learned fusion does in the daemon."""

    mode: Mode = "solver"
    """"solver": the LM solve alone (seed 003); "learned": the skeleton fitted to the learned joints (prior and
    floor kept, cameras and IMUs only through the networks); "both": the learned joints enter the LM solve as soft
    3D observations (E_J) on the frames the learned stream runs."""
    weight: float = 100.0
    """λ_J of the E_J term (1/m²)."""
    loss_scale: float = 1.0
    """Cauchy scale of E_J, in units of sqrt(λ_J) · metres."""
    model: str = "default"
    """"default" (:func:`default_model_dir`) or a folder with the files tools/train_fusion.py writes."""
    threads: int = 1
    """onnxruntime intra-op threads."""

    def cost(self, base: CostOptions) -> CostOptions:
        """``base`` with E_J's weight and loss."""
        from dataclasses import replace

        from mocapd.core.loss import CauchyLoss

        return replace(base, lambda_learned=self.weight, loss_learned=CauchyLoss(self.loss_scale))


@dataclass
class _Person:
    fusion: PersonFusion
    imu_solver: PoseSolver | None
    imu_joints: FloatArray | None
    centre: FloatArray | None
    last: LearnedJoints | None
    previous: LearnedJoints | None
    ticks: int


class FusionStage:
    """The learned stream of every tracked person (see the module docstring).

    Parameters
    ----------
    models : the loaded networks.
    cameras : the rig; mattes : per tick, camera → matte (h, w) at the grid's scale, or None where the camera has
        none (its matte channel then sits the hull out).
    prior, cost : for the IMU-only solves of suit wearers.
    """

    def __init__(
        self,
        models: FusionModels,
        cameras: list[Camera],
        targets: TrackTargets,
        prior: PcaPrior | None,
        cost: CostOptions | None = None,
    ) -> None:
        self.models = models
        self.cameras = cameras
        self.targets = targets
        self.prior = prior
        self.cost = cost if cost is not None else CostOptions()
        self.grid = models.grid
        self.people: dict[str, _Person] = {}
        self.counters = {"learned_frames": 0, "imu_solves": 0, "no_centre": 0}
        self.last_ms: dict[str, float] = {}
        """Milliseconds of the last step's parts: ``imu_solve``, and on learned frames ``pvh``, ``cnn``,
        ``temporal`` (mattes not included: they are made where the frames are)."""

    def _person(self, identity: str, skeleton: Skeleton, mounts: tuple[ImuMount, ...], start: FloatArray) -> _Person:
        p = self.people.get(identity)
        if p is None:
            solver = None
            if mounts:
                solver = PoseSolver(skeleton, [], self.targets, mounts, self.prior, self.cost)
                solver.reset(start)
            p = _Person(PersonFusion(self.models), solver, None, None, None, None, 0)
            self.people[identity] = p
        return p

    def forget(self, keep: set[str]) -> None:
        """Drop the state of people no longer tracked."""
        for identity in list(self.people):
            if identity not in keep:
                del self.people[identity]

    def step(
        self,
        identity: str,
        skeleton: Skeleton,
        start: FloatArray,
        kp: FloatArray,
        conf: FloatArray,
        mattes: Callable[[], list[F32 | None]],
        dt: float,
        imu: tuple[tuple[ImuMount, ...], Observations] | None = None,
    ) -> LearnedJoints | None:
        """One tick of one person: the IMU-only solve (suit wearers, every tick) and, on every ``stride``-th tick,
        the learned frame. Returns the learned joints on the ticks the learned stream runs, else None.

        Parameters
        ----------
        start : (66,) the pose the IMU-only solve starts from (the person's current solve).
        kp : (n_cams, 17, 2); conf : (n_cams, 17) the person's detections.
        mattes : gives every camera's matte for this tick (called only on learned frames).
        imu : the suit's mounts and this tick's IMU observations (orientations, accelerations, mask).
        """
        p = self._person(identity, skeleton, imu[0] if imu is not None else (), start)
        t0 = time.perf_counter()
        if p.imu_solver is not None and imu is not None:
            theta = p.imu_solver.solve(imu[1]).theta
            p.imu_joints = p.imu_solver.kin.forward(theta).positions
            self.counters["imu_solves"] += 1
        self.last_ms = {"imu_solve": 1e3 * (time.perf_counter() - t0)}
        p.ticks += 1
        if (p.ticks - 1) % self.models.stride:
            return None
        centre = person_centre(self.cameras, kp, conf, fallback=p.centre)
        if centre is None:
            self.counters["no_centre"] += 1
            return None
        p.centre = centre
        frame_mattes = mattes()
        t1 = time.perf_counter()
        pvh = self.pvh(centre, kp, conf, frame_mattes)
        self.last_ms["pvh"] = 1e3 * (time.perf_counter() - t1)
        views = int(np.count_nonzero(np.any(conf > 0, axis=1)))
        out = p.fusion.step(pvh, centre, views, p.imu_joints)
        self.last_ms.update(p.fusion.last_ms)
        p.previous, p.last = p.last, out
        self.counters["learned_frames"] += 1
        return out

    def pvh(self, centre: FloatArray, kp: FloatArray, conf: FloatArray, mattes: list[F32 | None]) -> F32:
        """The two-channel PVH (2, S, S, S) of one person."""
        g = self.grid
        imgs = []
        valid = np.zeros((len(self.cameras), 2), dtype=bool)
        for c, cam in enumerate(self.cameras):
            h, w = g.image_size(cam)
            m = mattes[c]
            seen = bool(np.any(conf[c] > 0))
            valid[c] = (m is not None, seen)
            jm = (
                joint_map(scaled_pixels(kp[c], g.scale), conf[c], (h, w), joint_sigma(cam, centre, g.scale))
                if seen
                else np.ones((h, w), np.float32)
            )
            imgs.append(log_channels(np.stack((m if m is not None else np.ones((h, w), np.float32), jm))))
        return carve(g, centre, self.cameras, imgs, valid)

    def extrapolated(self, identity: str) -> FloatArray | None:
        """The person's learned joints carried from their last learned frame to this tick at the velocity of the
        last two (what ``mode = "learned"`` fits between learned frames); None before the first."""
        p = self.people.get(identity)
        if p is None or p.last is None:
            return None
        if p.previous is None:
            return p.last.joints
        since = (p.ticks - 1) % self.models.stride
        step = (p.last.joints - p.previous.joints) / self.models.stride
        return np.asarray(p.last.joints + since * step)

    def status(self) -> dict[str, Any]:
        """Counters for /status."""
        return {
            **self.counters,
            "people": sorted(self.people),
            "rate_hz": round(60.0 / self.models.stride, 1),
            "model": str(self.models.directory),
        }


__all__ = [
    "CNN_FILE",
    "JOINT_DIM",
    "PROVENANCE_FILE",
    "RAW_IMU_FILE",
    "TEMPORAL_FILE",
    "FusionModels",
    "FusionOptions",
    "FusionStage",
    "LearnedJoints",
    "PersonFusion",
]
