"""The Euclidean norm along an axis, as :func:`numpy.linalg.norm` takes it, without its Python layer.

``np.linalg.norm(x, axis=a)`` of a real float array is ``sqrt(add.reduce(x * x, axis=a))``: the same products, summed
in the same order, the same square root. Its wrapper (argument checks, dtype and order dispatch) costs a few
microseconds a call, several times the arithmetic on the small arrays of a person solve, which runs on the event loop
every tick (issue 39). Same floats, to the bit: tests/test_norms.py, and the bitwise tests of its callers.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def norms(x: FloatArray, axis: int = -1, keepdims: bool = False) -> FloatArray:
    """``np.linalg.norm(x, axis=axis, keepdims=keepdims)`` of a real float array ``x``, bit for bit."""
    squares = x * x
    total = np.add.reduce(squares, axis=axis, keepdims=True) if keepdims else np.add.reduce(squares, axis=axis)
    out: FloatArray = np.sqrt(total)
    return out
