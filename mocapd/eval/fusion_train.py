"""Training the learned fusion of seed 001 (issue 30) through the simulator, with PyTorch (the ``[train]`` extra).

Nothing in the daemon imports this module: it trains, validates and exports ONNX files that the daemon runs with
onnxruntime (:mod:`mocapd.pipeline.fusion`). ``tools/train_fusion.py`` is its command line.

The recipe (:class:`FusionRecipe`; seeded, every number in the provenance file):

1. **PVH network** (seed 001 §3.1, Table 1's layer pattern: conv 5³/2, conv 3³, conv 3³, max-pool 2, conv 3³,
   max-pool 2, three dense layers) on two-channel 30³ PVHs of simulated frames: CMU clips of the training split
   (:func:`~mocapd.eval.fusion_data.training_clips`) cut into in-volume windows, each pass turned by a random yaw
   about the vertical (the seed's augmentation) and moved in the volume, seen by 8 or by 4 adjacent ring cameras,
   with the accuracy harness's realistic detections and a simulated background subtraction. L2 loss on the joints
   relative to the grid centre (Eq. 1).
2. **Temporal stage**: fresh simulated passes of the same clips through the trained PVH network give per-frame
   vision joints; mocapd's IMU-only solve of the 6- and 13-IMU sets gives the solved-IMU joints. An LSTM per
   stream (two layers, look-back f = 5, §3.5) and one on the raw IMU orientations (Table 6's "raw IMU-LSTM") are
   trained on those windows.
3. **Fusion layer** (64 units, §3.6) on the two LSTMs' outputs (frozen), RMSprop at 1e-4 as the seed.

Adapted where the 2-core CPU requires it (measured; docs/learned-fusion.md): the layer widths are a quarter of
Table 1's (Table 1's network costs 33 ms per person-frame in onnxruntime here and ~280 ms per training sample), the
LSTMs have 128 cells instead of 1024, and the LSTMs predict a correction to their window's newest estimate
(a residual connection).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import sys
import time
import tomllib
import warnings
import zlib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from mocapd.core.fusion_features import (
    JOINT_DIM,
    LOOK_BACK,
    MAX_VIEWS,
    STRIDE,
    feature_windows,
    fusion_input,
    imu_windows,
    vision_windows,
)
from mocapd.core.pvh import PvhGrid
from mocapd.core.retarget import Retargeted
from mocapd.core.terms import CostOptions
from mocapd.errors import ConfigError
from mocapd.eval.data import load_clip
from mocapd.eval.fusion_data import (
    RAW_IMU_FEATURES,
    VisionInputs,
    random_rig,
    raw_imu,
    rig_vision,
    rotate_clip,
    sequence_vision,
    solved_imu,
    training_clips,
)
from mocapd.eval.harness import Sequence, make_sequence, windows
from mocapd.eval.simulate import DetectionNoise, ImuNoise
from mocapd.io.prior import load_default_prior
from mocapd.pipeline.fusion import PROVENANCE_FILE, RAW_IMU_FILE, TEMPORAL_FILE, cnn_file
from mocapd.sim.silhouettes import MatteNoise

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

CHANNEL_SETS: dict[str, tuple[int, ...]] = {"both": (0, 1), "matte": (0,), "joints": (1,)}
"""PVH channels each network variant reads (the shipped one reads both; the others are Table 6's ablation)."""


@dataclass(frozen=True)
class FusionRecipe:
    """Every setting of a training run (written into the provenance)."""

    seed: int = 0
    threads: int = 1
    """torch threads (1: on a shared 2-core machine a second thread mostly waits at barriers for the other)."""
    grid_size: int = 30
    extent: float = 2.0
    supersample: int = 1
    scale: int = 8
    widths: tuple[int, int, int, int] = (16, 24, 24, 32)
    fc: int = 256
    cnn_passes: int = 4
    """Simulated passes over the training clips for the PVH network (alternating camera counts)."""
    cnn_stride: int = 2
    """Every how many frames a PVH sample is taken (60 Hz motion: neighbours are near-duplicates)."""
    cnn_epochs: int = 4
    cnn_batch: int = 32
    cnn_lr: float = 1e-3
    lr_drop: float = 0.7
    """Fraction of the epochs after which the learning rate is divided by 5 (1: never)."""
    optimizer: str = "adam"
    """"adam" or "rmsprop" (seed 001: RMSprop) for the PVH network and the LSTMs."""
    camera_counts: tuple[int, ...] = (8, 4)
    shift_m: float = 0.75
    """Largest shift (x and z, metres) of a window in the volume."""
    stream_passes: int = 2
    look_back: int = LOOK_BACK
    stride: int = STRIDE
    """Frames (at 60 Hz) between two of the learned stream's: its rate is 60 / stride Hz."""
    lstm_hidden: int = 128
    lstm_layers: int = 2
    lstm_residual: bool = True
    lstm_dropout: float = 0.2
    """Dropout between the LSTM layers (the LSTMs overfit the few thousand training windows without it)."""
    lstm_keep_best: bool = True
    """The LSTMs and the fusion layer keep their weights of the epoch with the lowest validation error (the CMU
    clip of the development split) instead of the last epoch's."""
    lstm_epochs: int = 25
    lstm_batch: int = 64
    lstm_lr: float = 1e-3
    fusion_hidden: int = 64
    fusion_epochs: int = 40
    fusion_lr: float = 1e-4
    fusion_residual: bool = True
    imu_sets: tuple[int, ...] = (6, 13)
    max_frames: int | None = None
    """Cap per window (the CI recipe)."""
    max_windows: int | None = None
    """Cap on training windows (the CI recipe)."""
    max_clips: int | None = None
    """Cap on the clips read for training and for validation (the CI recipe)."""

    @classmethod
    def tiny(cls) -> FusionRecipe:
        """Seconds on the CI machine: a few dozen frames, one epoch each; checks the pipeline, not accuracy."""
        return cls(
            threads=1,
            widths=(4, 4, 4, 4),
            fc=16,
            cnn_passes=1,
            cnn_stride=4,
            cnn_epochs=1,
            cnn_batch=8,
            camera_counts=(4,),
            stream_passes=1,
            lstm_hidden=8,
            lstm_layers=1,
            lstm_epochs=1,
            fusion_epochs=1,
            imu_sets=(6,),
            max_frames=48,
            max_windows=1,
            max_clips=1,
        )

    @classmethod
    def from_toml(cls, path: Path) -> FusionRecipe:
        """A recipe from a TOML file: keys are the field names; missing keys keep the defaults."""
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read the training recipe: {exc}") from exc
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"{path}: unknown recipe keys {unknown}; known: {sorted(known)}")
        tuples = {k: tuple(v) for k, v in data.items() if isinstance(v, list)}
        return replace(cls(), **{**data, **tuples})

    @property
    def grid(self) -> PvhGrid:
        return PvhGrid(self.grid_size, self.extent, self.supersample, self.scale)


# ------------------------------------------------------------------------------------------------ networks
class PvhNet(nn.Module):
    """Seed 001 Table 1's 3D convnet: PVH (B, C, S, S, S) in [0, 1] -> joints relative to the grid centre (B, 63)."""

    def __init__(self, in_ch: int, widths: tuple[int, int, int, int], fc: int, size: int) -> None:
        super().__init__()
        w1, w2, w3, w4 = widths
        self.features = nn.Sequential(
            nn.Conv3d(in_ch, w1, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv3d(w1, w2, 3, padding=1),
            nn.ReLU(),
            nn.Conv3d(w2, w3, 3, padding=1),
            nn.ReLU(),
            nn.MaxPool3d(2),
            nn.Conv3d(w3, w4, 3, padding=1),
            nn.ReLU(),
            nn.MaxPool3d(2),
            nn.Flatten(),
        )
        with torch.no_grad():
            n = int(self.features(torch.zeros(1, in_ch, size, size, size)).shape[1])
        self.head = nn.Sequential(nn.Linear(n, fc), nn.ReLU(), nn.Linear(fc, fc), nn.ReLU(), nn.Linear(fc, JOINT_DIM))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.head(self.features(x))
        return out


class JointLstm(nn.Module):
    """Seed 001 §3.5: LSTM layers over a window (B, f, n_in) -> the current frame's joints (B, 63).

    With ``residual`` the output is a correction added to the window's newest estimate (its first 63 inputs)."""

    def __init__(self, n_in: int, hidden: int, layers: int, residual: bool, dropout: float = 0.0) -> None:
        super().__init__()
        self.lstm = nn.LSTM(n_in, hidden, layers, batch_first=True, dropout=dropout if layers > 1 else 0.0)
        self.out = nn.Linear(hidden, JOINT_DIM)
        self.residual = residual

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.lstm(x)
        y: torch.Tensor = self.out(h[:, -1])
        if self.residual:
            y = y + x[:, -1, :JOINT_DIM]
        return y


class FusionLayer(nn.Module):
    """Seed 001 §3.6: a 64-unit dense layer over both streams (:func:`~mocapd.core.fusion_features.fusion_input`).

    With ``residual`` it predicts a correction to the mean of the two streams."""

    def __init__(self, hidden: int, residual: bool) -> None:
        super().__init__()
        self.fc1 = nn.Linear(2 * JOINT_DIM + 1, hidden)
        self.fc2 = nn.Linear(hidden, JOINT_DIM)
        self.residual = residual

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y: torch.Tensor = self.fc2(torch.relu(self.fc1(x)))
        if self.residual:
            y = y + 0.5 * (x[:, :JOINT_DIM] + x[:, JOINT_DIM : 2 * JOINT_DIM])
        return y


class TemporalStack(nn.Module):
    """The exported temporal graph: both LSTMs and the fusion layer.

    Inputs: ``vision`` (B, f, 63), ``imu`` (B, f, 63), ``views`` (B, 1). Outputs: the vision LSTM's joints
    (rel. grid centre), the IMU LSTM's (rel. root), the fused joints (rel. grid centre), each (B, 63)."""

    def __init__(self, vision: JointLstm, imu: JointLstm, fusion: FusionLayer) -> None:
        super().__init__()
        self.vision = vision
        self.imu = imu
        self.fusion = fusion

    def forward(
        self, vision: torch.Tensor, imu: torch.Tensor, views: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        v = self.vision(vision)
        i = self.imu(imu)
        b = v.shape[0]
        vr = v.reshape(b, -1, 3)
        ir = i.reshape(b, -1, 3)
        on_root = (ir - ir[:, :1] + vr[:, :1]).reshape(b, JOINT_DIM)
        fused = self.fusion(torch.cat((v, on_root, views / MAX_VIEWS), dim=1))
        return v, i, fused


# ------------------------------------------------------------------------------------------------ training
def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _seed(*parts: object) -> int:
    return zlib.crc32(":".join(str(p) for p in parts).encode())


def _optimizer(name: str, params: Any, lr: float) -> torch.optim.Optimizer:
    if name == "adam":
        return torch.optim.Adam(params, lr=lr)
    if name == "rmsprop":
        return torch.optim.RMSprop(params, lr=lr)
    raise ConfigError(f"optimizer must be 'adam' or 'rmsprop', got {name!r}")


def predict(model: nn.Module, inputs: list[NDArray[Any]], batch: int = 256, scale: float = 1.0) -> F32:
    """Model outputs for numpy inputs (first axis = samples), in evaluation mode, in batches."""
    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, inputs[0].shape[0], batch):
            xs = [torch.from_numpy(np.ascontiguousarray(x[i : i + batch], dtype=np.float32)) for x in inputs]
            if scale != 1.0:
                xs = [x * scale for x in xs]
            out.append(model(*xs).numpy())
    return np.concatenate(out) if out else np.zeros((0, JOINT_DIM), dtype=np.float32)


def fit(
    model: nn.Module,
    x: NDArray[Any],
    y: F32,
    *,
    epochs: int,
    batch: int,
    lr: float,
    optimizer: str,
    seed: int,
    name: str,
    x_scale: float = 1.0,
    val: tuple[NDArray[Any], F32] | None = None,
    lr_drop: float = 1.0,
    keep_best: bool = False,
) -> list[dict[str, float]]:
    """Minimise the mean squared joint error (seed 001 Eq. 1) with shuffled minibatches; per-epoch joint errors.

    ``x`` may be uint8 (PVHs): batches are converted and multiplied by ``x_scale`` on the fly. After the fraction
    ``lr_drop`` of the epochs the learning rate is divided by 5. With ``keep_best`` (and ``val``) the model ends
    with the weights of its best validation epoch (marked ``"kept"`` in the history)."""
    gen = torch.Generator().manual_seed(seed)
    opt = _optimizer(optimizer, model.parameters(), lr)
    history: list[dict[str, float]] = []
    best: tuple[float, int, dict[str, torch.Tensor]] | None = None
    n = x.shape[0]
    for epoch in range(epochs):
        if epoch == int(np.ceil(lr_drop * epochs)) and epoch > 0:
            for g in opt.param_groups:
                g["lr"] = lr / 5.0
        model.train()
        t0 = time.perf_counter()
        order = torch.randperm(n, generator=gen).numpy()
        total = 0.0
        for i in range(0, n, batch):
            idx = np.sort(order[i : i + batch])
            xb = torch.from_numpy(np.ascontiguousarray(x[idx], dtype=np.float32))
            if x_scale != 1.0:
                xb = xb * x_scale
            yb = torch.from_numpy(y[idx])
            opt.zero_grad()
            loss = torch.mean((model(xb) - yb) ** 2) * 3.0  # per joint: sum over x, y, z
            loss.backward()  # type: ignore[no-untyped-call]
            opt.step()
            total += float(loss.detach()) * len(idx)
        row = {"epoch": epoch + 1, "train_rms_mm": round(1e3 * float(np.sqrt(total / max(n, 1))), 2)}
        if val is not None:
            row["val_mean_mm"] = round(mean_joint_error_mm(predict(model, [val[0]], scale=x_scale), val[1]), 2)
        row["seconds"] = round(time.perf_counter() - t0, 1)
        history.append(row)
        _log(f"{name} epoch {epoch + 1}/{epochs}: {row}")
        if keep_best and val is not None and (best is None or row["val_mean_mm"] < best[0]):
            best = (row["val_mean_mm"], epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
    if best is not None:
        model.load_state_dict(best[2])
        history[best[1]]["kept"] = 1.0
    return history


def mean_joint_error_mm(pred: NDArray[Any], truth: NDArray[Any]) -> float:
    """Mean Euclidean joint error (mm) of flat (n, 63) joint vectors."""
    d = (np.asarray(pred, dtype=np.float64) - truth).reshape(len(truth), -1, 3)
    return float(1e3 * np.mean(np.linalg.norm(d, axis=-1))) if len(truth) else float("nan")


@dataclass
class _Stream:
    """One simulated pass of a window through every input the temporal stage reads."""

    seq: Sequence
    vision: VisionInputs
    solved: dict[int, FloatArray]
    raw: dict[int, FloatArray]


def _windows(files: tuple[Path, ...], recipe: FusionRecipe) -> list[Retargeted]:
    out: list[Retargeted] = []
    for f in files[: recipe.max_clips]:
        for w in windows(load_clip(f)):
            n = recipe.max_frames
            out.append(
                w
                if n is None or w.n_frames <= n
                else replace(
                    w,
                    theta=w.theta[:n],
                    positions=w.positions[:n],
                    rotations=w.rotations[:n],
                    source_positions=w.source_positions[:n],
                )
            )
    return out[: recipe.max_windows] if recipe.max_windows is not None else out


def _augmented(clip: Retargeted, recipe: FusionRecipe, *key: object) -> Sequence:
    rng = np.random.default_rng(_seed(recipe.seed, "aug", clip.name, *key))
    aug = rotate_clip(clip, float(rng.uniform(0, 2 * np.pi)), rng.uniform(-recipe.shift_m, recipe.shift_m, 2))
    return make_sequence(aug, _seed(recipe.seed, "sensors", clip.name, *key), DetectionNoise(), ImuNoise())


def _vision(
    seq: Sequence,
    n_cams: int,
    recipe: FusionRecipe,
    tag: str,
    p: int,
    rng: np.random.Generator,
    frames: NDArray[np.intp] | None = None,
) -> VisionInputs:
    """Training passes see a random rig (:func:`~mocapd.eval.fusion_data.random_rig`); validation the harness's
    ring (its first ``n_cams`` cameras), as the evaluation does."""
    if tag.startswith("val"):
        return sequence_vision(seq, n_cams, recipe.grid, MatteNoise(), _seed(recipe.seed, tag, p), 0, frames)
    return rig_vision(seq, random_rig(rng, n_cams), recipe.grid, MatteNoise(), rng, frames)


def pvh_dataset(clips: list[Retargeted], recipe: FusionRecipe, passes: int, tag: str) -> tuple[NDArray[np.uint8], F32]:
    """PVH samples (n, 2, S, S, S) uint8 and their targets (n, 63): joints relative to the grid centre."""
    xs, ys = [], []
    for p in range(passes):
        n_cams = recipe.camera_counts[p % len(recipe.camera_counts)]
        for clip in clips:
            seq = _augmented(clip, recipe, tag, p)
            rng = np.random.default_rng(_seed(recipe.seed, tag, "frames", clip.name, p))
            frames = np.arange(int(rng.integers(0, recipe.cnn_stride)), seq.clip.n_frames, recipe.cnn_stride)
            vi = _vision(seq, n_cams, recipe, tag, p, rng, frames)
            xs.append(vi.pvh)
            ys.append((seq.clip.positions[frames] - vi.centre[:, None, :]).reshape(len(frames), JOINT_DIM))
        _log(f"{tag} PVH pass {p + 1}/{passes}: {sum(len(x) for x in xs)} samples")
    return np.concatenate(xs), np.concatenate(ys).astype(np.float32)


def stream_passes(
    clips: list[Retargeted], recipe: FusionRecipe, passes: int, tag: str, cnn: nn.Module
) -> list[tuple[_Stream, FloatArray]]:
    """Simulated passes with the PVH network's per-frame world joints (n, 21, 3)."""
    prior = load_default_prior()
    cost = CostOptions()
    out = []
    for p in range(passes):
        n_cams = recipe.camera_counts[p % len(recipe.camera_counts)]
        for clip in clips:
            seq = _augmented(clip, recipe, tag, p)
            vi = _vision(
                seq, n_cams, recipe, tag, p, np.random.default_rng(_seed(recipe.seed, tag, "rig", clip.name, p))
            )
            rel = predict(cnn, [vi.pvh], scale=1.0 / 255.0).reshape(-1, 21, 3)
            solved = {n: solved_imu(seq, n, prior, cost) for n in recipe.imu_sets}
            raw = {n: raw_imu(seq, n) for n in recipe.imu_sets}
            out.append((_Stream(seq, vi, solved, raw), rel + vi.centre[:, None, :]))
        _log(f"{tag} stream pass {p + 1}/{passes}: {sum(s.seq.clip.n_frames for s, _ in out)} frames")
    return out


def _temporal_arrays(
    streams: list[tuple[_Stream, FloatArray]], look_back: int, stride: int
) -> dict[str, tuple[list[FloatArray], F32]]:
    """Training arrays of each temporal model: inputs and targets."""
    xv, yv, views, xi, xr, yi, ycentre, cset = [], [], [], [], [], [], [], []
    offset = 0  # row of each stream's first frame in the concatenated vision arrays
    for s, vis in streams:
        truth = s.seq.clip.positions
        c = s.vision.centre
        xv.append(vision_windows(vis, c, look_back, stride))
        yv.append((truth - c[:, None]).reshape(len(c), JOINT_DIM))
        for n in s.solved:
            xi.append(imu_windows(s.solved[n], look_back, stride))
            xr.append(feature_windows(s.raw[n], look_back, stride))
            yi.append((truth - truth[:, :1]).reshape(len(c), JOINT_DIM))
            ycentre.append((truth - c[:, None]).reshape(len(c), JOINT_DIM))
            views.append(s.vision.views)
            cset.append(offset + np.arange(len(c)))
        offset += len(c)
    f32 = np.float32
    return {
        "vision": ([np.concatenate(xv)], np.concatenate(yv).astype(f32)),
        "imu": ([np.concatenate(xi)], np.concatenate(yi).astype(f32)),
        "raw_imu": ([np.concatenate(xr)], np.concatenate(yi).astype(f32)),
        "fusion_targets": ([np.concatenate(views), np.concatenate(cset)], np.concatenate(ycentre).astype(f32)),
    }


def _export(
    model: nn.Module, args: tuple[torch.Tensor, ...], path: Path, inputs: list[str], outputs: list[str]
) -> None:
    model.eval()
    axes = {n: {0: "batch"} for n in [*inputs, *outputs]}
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of torch.export (which needs onnxscript); it exports
        # these layers exactly, and the export is checked against onnxruntime below.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            args,
            str(path),
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )


def _check_export(path: Path, model: nn.Module, args: tuple[torch.Tensor, ...], names: list[str]) -> float:
    """Largest difference between onnxruntime's and torch's outputs on ``args``."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {n: a.numpy() for n, a in zip(names, args, strict=True)})
    with torch.no_grad():
        want = model(*args)
    want = want if isinstance(want, tuple) else (want,)
    return max(float(np.max(np.abs(g - w.numpy()))) for g, w in zip(got, want, strict=True))


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cnn_key(recipe: FusionRecipe) -> str:
    """Hash of the recipe fields the PVH networks depend on (their checkpoints' names)."""
    d = asdict(recipe)
    for k in list(d):
        if k.startswith(("lstm_", "fusion_", "stream_")) or k in ("look_back", "stride", "imu_sets", "threads"):
            del d[k]
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


MAX_ROOT_OFFSET = 0.4
"""A training sample whose grid centre is further than this (m) from the person's root missed the person (the hips
were not triangulated right): its PVH is empty or cut, its target metres off; one such sample outweighs thousands of
good ones in the L2 loss."""


def _grid_holds_person(y: F32) -> NDArray[np.bool_]:
    """Which samples' targets (joints relative to the grid centre, (n, 63)) have the root within
    :data:`MAX_ROOT_OFFSET` of the centre."""
    return np.asarray(np.linalg.norm(y[:, :3], axis=1) <= MAX_ROOT_OFFSET)


def _data_key(recipe: FusionRecipe) -> str:
    """Hash of the recipe fields the PVH training samples depend on."""
    d = asdict(recipe)
    keep = ("seed", "grid_size", "extent", "supersample", "scale", "cnn_passes", "cnn_stride", "camera_counts",
            "shift_m", "max_frames", "max_windows", "max_clips")  # fmt: skip
    return hashlib.sha256(json.dumps({k: d[k] for k in keep}, sort_keys=True).encode()).hexdigest()[:12]


def _cached_data(work_dir: Path | None, key: str) -> tuple[NDArray[np.uint8], F32, NDArray[np.uint8], F32] | None:
    """The PVH samples of an earlier run of the same recipe (``--work``), or None."""
    p = None if work_dir is None else work_dir / f"pvh_data_{key}.npz"
    if p is None or not p.is_file():
        return None
    d = np.load(p)
    _log(f"PVH samples from {p}")
    return d["x"], d["y"], d["xv"], d["yv"]


def _load_checkpoint(work_dir: Path | None, variant: str, key: str) -> dict[str, Any] | None:
    p = None if work_dir is None else work_dir / f"cnn_{variant}_{key}.pt"
    if p is None or not p.is_file():
        return None
    ckpt: dict[str, Any] = torch.load(p, weights_only=True)
    return ckpt


def train(
    recipe: FusionRecipe,
    out_dir: Path,
    data_root: Path | None = None,
    ablation: bool = False,
    work_dir: Path | None = None,
) -> dict[str, Any]:
    """Run the whole recipe; writes the ONNX files and the provenance JSON into ``out_dir``; returns it.

    ``work_dir``: the PVH networks are saved there as they finish and taken from there when a checkpoint of the
    same recipe exists (the temporal stages can be re-run without the hours of the PVH networks)."""
    t_start = time.perf_counter()
    torch.manual_seed(recipe.seed)
    torch.set_num_threads(recipe.threads)
    out_dir.mkdir(parents=True, exist_ok=True)
    train_files, val_files = training_clips(data_root)
    train_clips = _windows(train_files, recipe)
    val_clips = _windows(val_files, recipe)
    times: dict[str, float] = {}
    history: dict[str, Any] = {}
    _log(f"training windows {len(train_clips)} ({sum(c.n_frames for c in train_clips)} frames), "
         f"validation {len(val_clips)}")  # fmt: skip

    size = recipe.grid_size
    variants = ("both", "matte", "joints") if ablation else ("both",)
    key = _cnn_key(recipe)
    cnns: dict[str, PvhNet] = {}
    done = {v: _load_checkpoint(work_dir, v, key) for v in variants} if work_dir is not None else {}
    n_samples = 0
    data: tuple[NDArray[np.uint8], F32, NDArray[np.uint8], F32] | None = None
    for variant in variants:
        ch = CHANNEL_SETS[variant]
        sl = slice(ch[0], ch[-1] + 1)  # a view of the samples, not a copy
        torch.manual_seed(_seed(recipe.seed, "cnn", variant))
        net = PvhNet(len(ch), recipe.widths, recipe.fc, size)
        ckpt = done.get(variant)
        if ckpt is not None:
            net.load_state_dict(ckpt["state"])
            history[f"cnn_{variant}"] = ckpt["history"]
            times[f"cnn_{variant}_train_s"] = ckpt["seconds"]
            n_samples = ckpt["samples"]
            cnns[variant] = net
            _log(f"PVH net ({variant}): from the checkpoint in {work_dir}")
            continue
        if data is None:
            t0 = time.perf_counter()
            data = _cached_data(work_dir, _data_key(recipe))
            if data is None:
                data = (
                    *pvh_dataset(train_clips, recipe, recipe.cnn_passes, "train"),
                    *pvh_dataset(val_clips, recipe, len(recipe.camera_counts), "val"),
                )
                if work_dir is not None:
                    work_dir.mkdir(parents=True, exist_ok=True)
                    np.savez(
                        work_dir / f"pvh_data_{_data_key(recipe)}.npz", x=data[0], y=data[1], xv=data[2], yv=data[3]
                    )
            times["pvh_data_s"] = time.perf_counter() - t0
        x, y, xv, yv = data
        keep = _grid_holds_person(y)
        if not np.all(keep):
            _log(f"{int((~keep).sum())} of {len(keep)} PVH samples dropped: their grid missed the person")
            x, y = x[keep], y[keep]
            data = (x, y, xv, yv)
        n_samples = int(x.shape[0])
        t0 = time.perf_counter()
        history[f"cnn_{variant}"] = fit(
            net,
            x[:, sl],
            y,
            epochs=recipe.cnn_epochs,
            batch=recipe.cnn_batch,
            lr=recipe.cnn_lr,
            optimizer=recipe.optimizer,
            seed=_seed(recipe.seed, "cnn-batches", variant),
            name=f"PVH net ({variant})",
            x_scale=1.0 / 255.0,
            val=(xv[:, sl], yv),
            lr_drop=recipe.lr_drop,
        )
        times[f"cnn_{variant}_train_s"] = time.perf_counter() - t0
        cnns[variant] = net
        if work_dir is not None:
            work_dir.mkdir(parents=True, exist_ok=True)
            torch.save(
                {"state": net.state_dict(), "history": history[f"cnn_{variant}"], "samples": n_samples,
                 "seconds": times[f"cnn_{variant}_train_s"], "key": key},
                work_dir / f"cnn_{variant}_{key}.pt",
            )  # fmt: skip
    del data

    t0 = time.perf_counter()
    streams = stream_passes(train_clips, recipe, recipe.stream_passes, "stream", cnns["both"])
    val_streams = stream_passes(val_clips, recipe, len(recipe.camera_counts), "val-stream", cnns["both"])
    times["stream_data_s"] = time.perf_counter() - t0
    arr = _temporal_arrays(streams, recipe.look_back, recipe.stride)
    varr = _temporal_arrays(val_streams, recipe.look_back, recipe.stride)
    lstms: dict[str, JointLstm] = {}
    t0 = time.perf_counter()
    for name, n_in in (("vision", JOINT_DIM), ("imu", JOINT_DIM), ("raw_imu", RAW_IMU_FEATURES)):
        torch.manual_seed(_seed(recipe.seed, "lstm", name))
        m = JointLstm(
            n_in,
            recipe.lstm_hidden,
            recipe.lstm_layers,
            recipe.lstm_residual and name != "raw_imu",
            recipe.lstm_dropout,
        )
        history[f"lstm_{name}"] = fit(
            m,
            arr[name][0][0],
            arr[name][1],
            epochs=recipe.lstm_epochs,
            batch=recipe.lstm_batch,
            lr=recipe.lstm_lr,
            optimizer=recipe.optimizer,
            seed=_seed(recipe.seed, "lstm-batches", name),
            name=f"LSTM ({name})",
            val=(varr[name][0][0], varr[name][1]),
            lr_drop=recipe.lr_drop,
            keep_best=recipe.lstm_keep_best,
        )
        lstms[name] = m
    times["lstm_train_s"] = time.perf_counter() - t0

    def fusion_arrays(a: dict[str, tuple[list[FloatArray], F32]]) -> tuple[FloatArray, F32]:
        v = predict(lstms["vision"], a["vision"][0]).reshape(-1, 21, 3).astype(np.float64)
        i = predict(lstms["imu"], a["imu"][0]).reshape(-1, 21, 3).astype(np.float64)
        views, which = a["fusion_targets"][0]
        return fusion_input(v[which.astype(np.intp)], i, views), a["fusion_targets"][1]

    fx, fy = fusion_arrays(arr)
    fvx, fvy = fusion_arrays(varr)
    torch.manual_seed(_seed(recipe.seed, "fusion"))
    fusion = FusionLayer(recipe.fusion_hidden, recipe.fusion_residual)
    t0 = time.perf_counter()
    history["fusion"] = fit(
        fusion,
        fx,
        fy,
        epochs=recipe.fusion_epochs,
        batch=recipe.lstm_batch,
        lr=recipe.fusion_lr,
        optimizer="rmsprop",
        seed=_seed(recipe.seed, "fusion-batches"),
        name="fusion layer",
        val=(fvx, fvy),
        keep_best=recipe.lstm_keep_best,
    )
    times["fusion_train_s"] = time.perf_counter() - t0
    mean_val = mean_joint_error_mm(0.5 * (fvx[:, :JOINT_DIM] + fvx[:, JOINT_DIM : 2 * JOINT_DIM]), fvy)

    # -- export and check ---------------------------------------------------------------------------------
    files: dict[str, str] = {}
    checks: dict[str, float] = {}
    for variant, net in cnns.items():
        name = cnn_file(variant)
        args = (torch.rand(2, len(CHANNEL_SETS[variant]), size, size, size),)
        _export(net, args, out_dir / name, ["pvh"], ["joints"])
        checks[name] = _check_export(out_dir / name, net, args, ["pvh"])
        files[name] = _sha(out_dir / name)
    stack = TemporalStack(lstms["vision"], lstms["imu"], fusion)
    f = recipe.look_back
    targs = (torch.randn(2, f, JOINT_DIM) * 0.3, torch.randn(2, f, JOINT_DIM) * 0.3, torch.full((2, 1), 6.0))
    _export(stack, targs, out_dir / TEMPORAL_FILE, ["vision", "imu", "views"], ["vision_lstm", "imu_lstm", "fused"])
    checks[TEMPORAL_FILE] = _check_export(out_dir / TEMPORAL_FILE, stack, targs, ["vision", "imu", "views"])
    rargs = (torch.randn(2, f, RAW_IMU_FEATURES),)
    _export(lstms["raw_imu"], rargs, out_dir / RAW_IMU_FILE, ["raw_imu"], ["joints"])
    checks[RAW_IMU_FILE] = _check_export(out_dir / RAW_IMU_FILE, lstms["raw_imu"], rargs, ["raw_imu"])
    for name in (TEMPORAL_FILE, RAW_IMU_FILE):
        files[name] = _sha(out_dir / name)

    import onnx
    import onnxruntime

    prov: dict[str, Any] = {
        "what": "learned fusion of seed 001 (PVH 3D convnet, LSTMs, solved-IMU stream, 64-unit fusion layer)",
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "tool": "tools/train_fusion.py",
        "recipe": asdict(recipe),
        "ablation_networks": ablation,
        "source_files": [
            {
                "path": str(p.relative_to(p.parents[3] if "asfamc" in p.parts else p.parents[2])),
                "sha256": _sha(p),
                "use": "train" if p in train_files else "validation",
            }
            for p in (*train_files, *val_files)
        ],
        "licence_of_sources": "CMU Graphics Lab Motion Capture Database: free for research and commercial use",
        "training_windows": len(train_clips),
        "training_frames": sum(c.n_frames for c in train_clips),
        "pvh_samples": n_samples,
        "cnn_checkpoint_key": key,
        "simulation": {
            "detections": asdict(DetectionNoise()),
            "imus": asdict(ImuNoise()),
            "mattes": asdict(MatteNoise()),
            "prior": "default (mocapd/data/prior_cmu.npz)",
            "cost": "CostOptions() (the shipped weights)",
        },
        "history": history,
        "validation_mean_mm": {
            **{k: _kept(v).get("val_mean_mm") for k, v in history.items() if k.startswith("cnn_")},
            **{k: _kept(v).get("val_mean_mm") for k, v in history.items() if k.startswith("lstm_")},
            "mean_of_streams": round(mean_val, 2),
            "fusion": _kept(history["fusion"]).get("val_mean_mm"),
        },
        "onnx_max_abs_diff_vs_torch": checks,
        "files": files,
        "wall_s": {**{k: round(v, 1) for k, v in times.items()}, "total": round(time.perf_counter() - t_start, 1)},
        "libraries": {
            "torch": torch.__version__,
            "numpy": np.__version__,
            "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__,
        },
        "threads": recipe.threads,
    }
    if recipe != FusionRecipe.tiny():
        prov["reproduction_check"] = reproduction_check(data_root)
    (out_dir / PROVENANCE_FILE).write_text(json.dumps(prov, indent=2) + "\n", encoding="utf-8")
    return prov


def _kept(history: list[dict[str, float]]) -> dict[str, float]:
    """The epoch whose weights a network kept (the best validation epoch, else the last)."""
    return next((h for h in history if h.get("kept")), history[-1])


def reproduction_check(data_root: Path | None = None) -> dict[str, Any]:
    """The validation errors of the CI recipe (:meth:`FusionRecipe.tiny`, all five networks) run now.

    Retraining the reference networks takes most of an hour on the 2-core CPU; this runs every stage of the same
    code on a few dozen frames in seconds. Recorded in the reference run's provenance (mocapd/data/fusion.json), it
    lets a test rerun it and find the recipe's code (or a library under it) changed since they were trained."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        tiny = train(FusionRecipe.tiny(), Path(tmp), data_root, ablation=True)
    return {"recipe": "FusionRecipe.tiny(), ablation=True", "validation_mean_mm": tiny["validation_mean_mm"]}
