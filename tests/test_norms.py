"""mocapd.core.norms.norms is np.linalg.norm along an axis, to the bit, on the shapes its callers pass."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.norms import norms


@pytest.mark.parametrize(("shape", "axis", "keepdims"), [((17, 2), -1, False), ((4, 9, 3), -1, True),
                                                         ((6, 2), 1, False), ((3, 5, 7, 4), -1, True)])  # fmt: skip
def test_norms_are_numpys_to_the_bit(shape: tuple[int, ...], axis: int, keepdims: bool) -> None:
    rng = np.random.default_rng(len(shape) * 10 + axis)
    for scale in (1e-9, 1.0, 1e3, 1e150):
        x = rng.normal(size=shape) * scale
        x.flat[::7] = 0.0
        got, want = norms(x, axis=axis, keepdims=keepdims), np.linalg.norm(x, axis=axis, keepdims=keepdims)
        assert got.shape == want.shape and np.array_equal(got, want)
    x = rng.normal(size=shape)
    x.flat[3] = np.nan
    assert np.array_equal(norms(x, axis=axis), np.linalg.norm(x, axis=axis), equal_nan=True)
