"""Loading the pose prior: the shipped default (``mocapd/data/prior_cmu.npz``) or a file.

The solver core does not read files; the service resolves ``[solver] prior`` with :func:`resolve_prior` and hands
the :class:`PcaPrior` to the solver. The default prior is trained from CMU motion only (its licence allows
shipping) by ``tools/train_prior.py``; ``prior_cmu.json`` beside it records its provenance.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

from mocapd.core.prior import PcaPrior
from mocapd.errors import ModelError

DEFAULT_PRIOR = "prior_cmu.npz"


def default_prior_path() -> Path:
    """Filesystem path of the shipped default prior."""
    return Path(str(resources.files("mocapd").joinpath("data", DEFAULT_PRIOR)))


def load_default_prior() -> PcaPrior:
    """The shipped CMU-trained PCA pose prior."""
    p = default_prior_path()
    if not p.exists():
        raise ModelError(f"the default pose prior {p} is missing; run tools/train_prior.py")
    return PcaPrior.load(p)


def default_prior_provenance() -> dict[str, Any]:
    """The provenance sidecar of the default prior (source files, date, variance kept, k)."""
    p = default_prior_path().with_suffix(".json")
    try:
        data: dict[str, Any] = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ModelError(f"cannot read the default prior's provenance {p}: {exc}") from exc
    return data


def resolve_prior(spec: str) -> PcaPrior | None:
    """``"default"`` → the shipped prior, ``"none"`` → no prior, anything else → a ``.npz`` path."""
    if spec == "default":
        return load_default_prior()
    if spec == "none":
        return None
    return PcaPrior.load(Path(spec))
