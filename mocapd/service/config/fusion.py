"""The ``[fusion]`` section: the learned fusion of seed 001 beside the LM solve (issue 30, docs/learned-fusion.md)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field

from mocapd.service.config.schema import PathStr, Section

if TYPE_CHECKING:  # the fusion's module loads onnxruntime and the solver: imported for a default or its options
    from mocapd.pipeline.fusion import FusionOptions


def _fusion() -> FusionOptions:
    from mocapd.pipeline.fusion import FusionOptions

    return FusionOptions()


class FusionConfig(Section):
    """What the learned fusion does in the daemon."""

    mode: Literal["solver", "learned", "both"] = "solver"
    """"solver": the LM solve alone; "learned": the skeleton fitted to the learned joints alone; "both": the learned
    joints enter the LM solve as soft 3D observations (E_J) on the frames the learned stream runs."""
    weight: float = Field(default_factory=lambda: _fusion().weight, ge=0.0, le=1e6)
    """λ_J: weight of the learned joints in the solve (1/m²)."""
    loss_scale: float = Field(default_factory=lambda: _fusion().loss_scale, gt=0.0, le=1e6)
    """Cauchy scale of E_J in units of sqrt(λ_J) · metres (1 with λ_J = 100: errors past 10 cm count less)."""
    model: PathStr = Field("default", min_length=1)
    """"default" (the networks tools/train_fusion.py writes to the cache, ~/.cache/mocapd/fusion) or a folder it
    wrote."""
    threads: int = Field(1, ge=1, le=64)
    """onnxruntime threads of the networks."""

    def options(self) -> FusionOptions:
        from mocapd.pipeline.fusion import FusionOptions

        return self.build(FusionOptions)
