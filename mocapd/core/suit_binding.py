"""Which IMU suit belongs to which visually tracked person — found, kept, and used to repair identity swaps.

Seed 003's stated failure case is swapped identities after close interaction: the detection sorter follows 3D
proximity, so two people who pass close can exchange tracks. IMU suits cannot swap: a suit is strapped to one
person. Each suit's measured bone orientations predict where that person's limbs point; each visual track's
triangulated keypoints show where its limbs point. Comparing the two over a sliding window gives a cost for
every (suit, track) pair; the optimal assignment (Hungarian) pairs them, and a pairing that changes — with
enough evidence, for long enough — is a re-pairing: the track now follows the suit's wearer.

Limb directions are compared after the best rotation about the vertical per pair (closed form), so the binding
does not depend on the IMUs' heading alignment R_ig, the least reliable part of their calibration.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.keypoints import COCO17
from mocapd.core.rotations import quat_rotate
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

_KP = {name: i for i, (name, _, _) in enumerate(COCO17)}
# (bone carrying the IMU, child bone whose offset gives the limb axis, keypoint from, keypoint to)
LIMBS: tuple[tuple[str, str, str, str], ...] = (
    ("LeftUpperArm", "LeftLowerArm", "left_shoulder", "left_elbow"),
    ("LeftLowerArm", "LeftHand", "left_elbow", "left_wrist"),
    ("RightUpperArm", "RightLowerArm", "right_shoulder", "right_elbow"),
    ("RightLowerArm", "RightHand", "right_elbow", "right_wrist"),
    ("LeftUpperLeg", "LeftLowerLeg", "left_hip", "left_knee"),
    ("LeftLowerLeg", "LeftFoot", "left_knee", "left_ankle"),
    ("RightUpperLeg", "RightLowerLeg", "right_hip", "right_knee"),
    ("RightLowerLeg", "RightFoot", "right_knee", "right_ankle"),
)


@dataclass(frozen=True)
class BindingOptions:
    window_s: float = 2.0
    """Sliding window of evidence (seconds). A pairing also lasts while its suit and its track were each seen
    within it: a frame or a few without the wearer (a late detection on a loaded machine, an IMU sample held up)
    does not unpair them, so the identity ``suit:<id>`` does not flicker back to the track's."""
    min_samples: int = 20
    """Limb observations a (suit, track) pair needs in the window before it can be paired."""
    max_mean_angle_deg: float = 15.0
    """A pair whose mean limb-direction disagreement exceeds this is never paired (not the same person).

    Measured on synthetic gait (2 cm keypoint, 2° IMU noise): 7–8° for the wearer, 28–31° for other people.
    """
    switch_margin_deg: float = 5.0
    """A new assignment must beat the current one by this much (mean angle, summed over pairs) to re-pair."""
    switch_after_s: float = 0.5
    """... and keep doing so for this long."""


@dataclass(frozen=True)
class BindingEvent:
    t_ns: int
    kind: str  # "paired", "re-paired", "unpaired"
    suit: str
    track: int | None
    previous_track: int | None
    mean_angle_deg: float


_Sums = NDArray[np.float64]  # (4,): c, s, Σ a_y b_y, n — see yaw_aligned_cosine


@dataclass
class BindingState:
    """The current pairing as reported in status."""

    pairs: dict[str, int] = field(default_factory=dict)  # suit -> track
    confidence: dict[str, float] = field(default_factory=dict)  # suit -> [0, 1]
    mean_angle_deg: dict[str, float] = field(default_factory=dict)


def limb_axes(skeleton: Skeleton) -> FloatArray:
    """Unit limb axes in each limb bone's frame (the child's offset direction), shape (n_limbs, 3)."""
    ax = np.array([skeleton.offsets[BONE_INDEX[child]] for _, child, _, _ in LIMBS])
    return np.asarray(ax / np.linalg.norm(ax, axis=1, keepdims=True))


def visual_directions(keypoints: FloatArray) -> FloatArray:
    """Limb directions from triangulated COCO-17 keypoints (17, 3) -> (n_limbs, 3), NaN where missing."""
    a = np.array([_KP[f] for _, _, f, _ in LIMBS])
    b = np.array([_KP[t] for _, _, _, t in LIMBS])
    d = keypoints[b] - keypoints[a]
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(np.where(n > 1e-6, d / np.where(n > 0, n, 1.0), np.nan))


def imu_directions(bone_orientations: dict[str, FloatArray], axes: FloatArray) -> FloatArray:
    """Limb directions predicted by measured global bone orientations (Eq. 8), shape (n_limbs, 3)."""
    q = np.array([bone_orientations.get(bone, (np.nan,) * 4) for bone, _, _, _ in LIMBS], dtype=np.float64)
    return np.asarray(quat_rotate(q, axes))


def pair_sums(imu: FloatArray, vis: FloatArray) -> _Sums:
    """Sufficient statistics of two direction sets for the yaw-aligned agreement (rows with NaN ignored).

    With a = IMU directions, b = visual ones, and R(ψ) the rotation by ψ about +Y, ``Σ b·R(ψ)a = cos ψ c +
    sin ψ s + Σ a_y b_y`` where ``c = Σ a_x b_x + a_z b_z`` and ``s = Σ a_z b_x - a_x b_z``: its maximum over ψ
    is ``sqrt(c² + s²) + Σ a_y b_y``, so a window of evidence reduces to four running sums.
    """
    return np.asarray(all_pair_sums(imu[None], vis[None])[0, 0])


def all_pair_sums(imu: FloatArray, vis: FloatArray) -> FloatArray:
    """:func:`pair_sums` of every (suit, track) pair at once: imu (S, L, 3), vis (T, L, 3) -> (S, T, 4)."""
    ok = np.all(np.isfinite(imu), axis=-1)[:, None] & np.all(np.isfinite(vis), axis=-1)[None]  # (S, T, L)
    a = np.nan_to_num(imu)[:, None]
    b = np.nan_to_num(vis)[None]
    c = np.sum(ok * (a[..., 0] * b[..., 0] + a[..., 2] * b[..., 2]), axis=-1)
    s = np.sum(ok * (a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]), axis=-1)
    y = np.sum(ok * (a[..., 1] * b[..., 1]), axis=-1)
    return np.stack((c, s, y, ok.sum(axis=-1).astype(np.float64)), axis=-1)


def yaw_aligned_cosine(sums: _Sums) -> float:
    """Mean cosine between the direction sets after the best rotation about +Y (NaN without samples)."""
    c, s, y, n = sums
    return float((np.hypot(c, s) + y) / n) if n > 0 else np.nan


def yaw_aligned_angle(imu: FloatArray, vis: FloatArray) -> tuple[float, int]:
    """The disagreement (deg) ``arccos`` of :func:`yaw_aligned_cosine`, and the sample count."""
    sums = pair_sums(imu, vis)
    return _angle(sums), int(sums[3])


def _angle(sums: _Sums) -> float:
    cos = yaw_aligned_cosine(sums)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))) if np.isfinite(cos) else np.inf


class SuitBinder:
    """Keeps the suit ↔ track pairing from a sliding window of limb directions.

    Parameters
    ----------
    skeleton : Skeleton
        Gives the limb axes in the bone frames.
    options : BindingOptions
    names : sequence of str, optional
        The keypoint names of the tracks' keypoints, in order (default: COCO-17). Any format that has the
        COCO-17 keypoints among its own (Body25, Halpe-26) works: they are picked out by name.
    """

    def __init__(
        self, skeleton: Skeleton, options: BindingOptions | None = None, names: Sequence[str] | None = None
    ) -> None:
        self.options = options if options is not None else BindingOptions()
        self._axes = limb_axes(skeleton)
        self._n_kp = len(COCO17) if names is None else len(names)
        self._coco: NDArray[np.intp] | None = None
        if names is not None:
            missing = [n for n in _KP if n not in names]
            if missing:
                raise InputError(f"suit binding: the keypoint set lacks the COCO-17 keypoints {missing}")
            self._coco = np.array([list(names).index(n) for n in _KP], dtype=np.intp)
        # Per frame, its contribution to each (suit, track) pair's sums; and the window's totals.
        self._frames: deque[tuple[int, dict[tuple[str, int], _Sums]]] = deque()
        self._totals: dict[tuple[str, int], _Sums] = {}
        self.state = BindingState()
        self._challenger: dict[str, int] | None = None
        self._challenger_since = 0
        self._track_seen: dict[int, int] = {}  # last time (ns) each track / suit was given to update()
        self._suit_seen: dict[str, int] = {}

    def update(
        self, t_ns: int, tracks: dict[int, FloatArray], suits: dict[str, dict[str, FloatArray]]
    ) -> list[BindingEvent]:
        """Add one frame of evidence and update the pairing.

        Parameters
        ----------
        tracks : track id -> triangulated keypoints (n_kp, 3) (NaN rows allowed) of tracks seen now, in the
            order of ``names`` (COCO-17 by default).
        suits : suit id -> {bone name: measured global bone orientation (4,)} of suits streaming now.
        """
        for k, kp in tracks.items():
            if np.asarray(kp).shape != (self._n_kp, 3):
                raise InputError(f"suit binding: track {k} keypoints must have shape ({self._n_kp}, 3)")
        track_ids, suit_ids = list(tracks), list(suits)
        self._track_seen.update(dict.fromkeys(track_ids, t_ns))
        self._suit_seen.update(dict.fromkeys(suit_ids, t_ns))
        frame: dict[tuple[str, int], _Sums] = {}
        if track_ids and suit_ids:
            pick = self._coco
            vis = np.stack([
                visual_directions(np.asarray(tracks[k] if pick is None else tracks[k][pick], dtype=np.float64))
                for k in track_ids
            ])  # fmt: skip
            imu = np.stack([imu_directions(suits[s], self._axes) for s in suit_ids])
            sums = all_pair_sums(imu, vis)
            # Only pairs with a limb seen by both: a zero-count entry would be pruned from the totals below while
            # still in this frame, and its removal at the end of the window would find nothing to subtract from.
            frame = {(s, k): sums[i, j] for i, s in enumerate(suit_ids) for j, k in enumerate(track_ids)
                     if sums[i, j, 3] > 0}  # fmt: skip
        self._frames.append((t_ns, frame))
        for key, v in frame.items():
            self._totals[key] = self._totals.get(key, np.zeros(4)) + v
        while self._frames and t_ns - self._frames[0][0] > self.options.window_s * 1e9:
            for key, v in self._frames.popleft()[1].items():
                self._totals[key] = self._totals[key] - v
        self._totals = {key: v for key, v in self._totals.items() if v[3] > 0.5}
        return self._decide(t_ns, sorted(tracks), sorted(suits))

    def cost_matrix(self, suit_ids: list[str], track_ids: list[int]) -> tuple[FloatArray, NDArray[np.int64]]:
        """Yaw-aligned limb disagreement (deg) and sample count per (suit, track) over the window."""
        cost = np.full((len(suit_ids), len(track_ids)), np.inf)
        count = np.zeros((len(suit_ids), len(track_ids)), dtype=np.int64)
        for i, s in enumerate(suit_ids):
            for j, k in enumerate(track_ids):
                sums = self._totals.get((s, k))
                if sums is not None:
                    cost[i, j], count[i, j] = _angle(sums), round(float(sums[3]))
        return cost, count

    def _decide(self, t_ns: int, track_ids: list[int], suit_ids: list[str]) -> list[BindingEvent]:
        o = self.options
        events: list[BindingEvent] = []
        cost, count = self.cost_matrix(suit_ids, track_ids)
        usable = (count >= o.min_samples) & (cost <= o.max_mean_angle_deg)
        big = 1e6
        proposal: dict[str, int] = {}
        angles: dict[str, float] = {}
        if cost.size:
            rows, cols = linear_sum_assignment(np.where(usable, cost, big))
            for r, c in zip(rows, cols, strict=True):
                if usable[r, c]:
                    proposal[suit_ids[r]] = track_ids[c]
                    angles[suit_ids[r]] = float(cost[r, c])
        # Pairs whose suit or track has not been seen for a whole window (track released, suit unplugged) are
        # unpaired; the others hold, seen in this frame or not.
        window_ns = o.window_s * 1e9

        def recent(seen: int | None) -> bool:
            return seen is not None and t_ns - seen <= window_ns

        held = {
            s: k
            for s, k in self.state.pairs.items()
            if recent(self._suit_seen.get(s)) and recent(self._track_seen.get(k))
        }
        for s, k in list(self.state.pairs.items()):
            if s not in held:
                events.append(BindingEvent(t_ns, "unpaired", s, None, k, np.nan))
        self._track_seen = {k: t for k, t in self._track_seen.items() if t_ns - t <= window_ns}
        self._suit_seen = {s: t for s, t in self._suit_seen.items() if t_ns - t <= window_ns}
        new_pairs = dict(held)
        for s, k in proposal.items():  # first pairings need no challenge period
            if s not in new_pairs and k not in new_pairs.values():
                new_pairs[s] = k
                events.append(BindingEvent(t_ns, "paired", s, k, None, angles[s]))
        seen_now = {s: k for s, k in new_pairs.items() if s in suit_ids and k in track_ids}
        if self._better(proposal, seen_now, cost, suit_ids, track_ids):
            if self._challenger != proposal:
                self._challenger, self._challenger_since = dict(proposal), t_ns
            elif t_ns - self._challenger_since >= o.switch_after_s * 1e9:
                for s, k in proposal.items():
                    if new_pairs.get(s) != k:
                        events.append(BindingEvent(t_ns, "re-paired", s, k, new_pairs.get(s), angles[s]))
                new_pairs = {s: k for s, k in new_pairs.items() if s in proposal or k not in proposal.values()}
                new_pairs.update(proposal)
                self._challenger = None
        else:
            self._challenger = None
        self.state.pairs = new_pairs
        # Pairs not seen in this frame keep the figures of the last frame they were seen in.
        seen_now = {s: k for s, k in new_pairs.items() if s in suit_ids and k in track_ids}
        angle = {s: float(cost[suit_ids.index(s), track_ids.index(k)]) for s, k in seen_now.items()}
        confidence = self._confidence(seen_now, cost, suit_ids, track_ids)
        self.state.mean_angle_deg = {s: angle.get(s, self.state.mean_angle_deg.get(s, np.nan)) for s in new_pairs}
        self.state.confidence = {s: confidence.get(s, self.state.confidence.get(s, 0.0)) for s in new_pairs}
        return events

    def _better(self, proposal: dict[str, int], current: dict[str, int], cost: FloatArray, suit_ids: list[str],
                track_ids: list[int]) -> bool:  # fmt: skip
        """Does the proposal beat the current pairing by the margin (on the suits both pair)?"""
        if proposal == current or not proposal:
            return False
        suits = [s for s in proposal if s in current]
        if not suits:
            return False

        def total(pairs: dict[str, int]) -> float:
            return float(sum(cost[suit_ids.index(s), track_ids.index(pairs[s])] for s in suits))

        return total(proposal) + self.options.switch_margin_deg <= total(current)

    def _confidence(self, pairs: dict[str, int], cost: FloatArray, suit_ids: list[str],
                    track_ids: list[int]) -> dict[str, float]:  # fmt: skip
        """Per suit, how clearly its track beats the runner-up: 1 - best/second (1 when there is no rival)."""
        out = {}
        for s, k in pairs.items():
            row = cost[suit_ids.index(s)]
            best = row[track_ids.index(k)]
            others = np.delete(row, track_ids.index(k))
            second = float(np.min(others)) if others.size else np.inf
            out[s] = float(np.clip(1.0 - best / second, 0.0, 1.0)) if np.isfinite(second) and second > 0 else 1.0
        return out
