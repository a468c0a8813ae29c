"""Training the default PCA pose prior (seed 000 §3.2.4): k-means with k = n/100, then PCA keeping 95 %.

All frames of the ``prior`` split (CMU only) at 60 Hz are retargeted onto the 21-bone skeleton; the pose vectors
without root translation and root rotation (θ̄, 60-D) are clustered so that common poses (standing, walking) do
not dominate, and PCA of the cluster centres gives ``(M, μ, σ)``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import scipy
from scipy.cluster.vq import kmeans2

from mocapd.core.prior import PcaPrior
from mocapd.eval.data import load_clip, load_splits

VARIANCE_KEPT = 0.95


def train(data_root: Path | None, out: Path, seed: int = 0, variance_kept: float = VARIANCE_KEPT) -> dict[str, Any]:
    """Train, write ``out`` (.npz) and its ``.json`` provenance sidecar; return the provenance."""
    splits = load_splits(data_root)
    files = splits["prior"]
    poses = []
    for f in files:
        poses.append(load_clip(f).theta[:, 6:])
    X = np.concatenate(poses)
    k = max(2, X.shape[0] // 100)
    centres, _ = kmeans2(X, k, seed=seed, minit="++", iter=30)
    prior = PcaPrior.fit(centres, variance_kept)
    out.parent.mkdir(parents=True, exist_ok=True)
    prior.save(out)
    full = PcaPrior.fit(centres, 1.0)
    kept = float(np.sum(prior.sigma**2) / np.sum(full.sigma**2))
    prov: dict[str, Any] = {
        "what": "PCA pose prior over θ̄ (θ without root translation and rotation), seed 000 §3.2.4",
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "source_files": [
            {"path": str(f.relative_to(f.parents[3] if "asfamc" in f.parts else f.parents[2])), "sha256": _sha(f)}
            for f in files
        ],
        "licence_of_sources": "CMU Graphics Lab Motion Capture Database: free for research and commercial use",
        "frames": int(X.shape[0]),
        "frame_rate_hz": 60.0,
        "k_means_k": int(k),
        "k_means_seed": seed,
        "variance_target": variance_kept,
        "variance_kept": round(kept, 4),
        "components": prior.n_components,
        "tool": "tools/train_prior.py",
        # Seeded k-means is reproducible bit for bit with the same libraries; tests/test_default_prior.py retrains
        # and compares, and names these versions when the result no longer matches.
        "libraries": {"numpy": np.__version__, "scipy": scipy.__version__},
    }
    out.with_suffix(".json").write_text(json.dumps(prov, indent=2) + "\n", encoding="utf-8")
    return prov


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
