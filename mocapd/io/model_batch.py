"""A fixed-batch-k copy of a batch-1 ONNX pose model, made in memory when a detector needs one.

The shipped exports (Ultralytics YOLO pose, batch 1) carry their batch size in two places: the first dimension
of the input and output, and the leading element of the constant shapes their ``Reshape`` nodes take. Setting
both to k gives a model that runs k canvases in one call; its outputs equal k batch-1 runs (bit for bit on the
CPU provider, tests/test_model_batch.py).

Why: on a GPU one yolo11n-pose inference at batch 1 is bound by kernel launches (5.5 ms on an H100), while four
canvases in one call cost 1.3-1.8 ms each (docs/detection.md, "GPU"). On a CPU a batch costs what its canvases
cost one by one, so the detector batches only on GPU providers unless told otherwise (``[detector] batch``).
Why fixed rather than a symbolic batch: a symbolic batch (leading shape 0, "copy from the input") ran whole
frames at 6.3 camera-frames/s on onnxruntime's CUDA provider on the H100 against 48.8 with the batch-1 model
(cause not isolated; cuDNN tuning per input shape is the likely one), so the detector keeps one fixed-size
session per batch size it meets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from google.protobuf.message import DecodeError
from onnx import numpy_helper

from mocapd.errors import ModelError


def _set_batch_dim(value_info: onnx.ValueInfoProto, where: str, k: int) -> None:
    dims = value_info.type.tensor_type.shape.dim
    if not dims:
        raise ModelError(f"{where} {value_info.name!r} has no shape: cannot change its batch")
    first = dims[0]
    if not first.HasField("dim_value") or first.dim_value != 1:
        raise ModelError(f"{where} {value_info.name!r} has batch {first.dim_value or first.dim_param!r}, expected 1")
    first.dim_value = k


def _shape_tensor(model: onnx.ModelProto, name: str) -> onnx.TensorProto | None:
    """The constant tensor called ``name`` (an initializer or a ``Constant`` node's value), or None."""
    found: onnx.TensorProto | None = None
    for init in model.graph.initializer:
        if init.name == name:
            found = init
    for node in model.graph.node:
        if node.op_type == "Constant" and node.output[0] == name:
            for attr in node.attribute:
                if attr.name == "value":
                    found = attr.t
    return found


def fixed_batch(model: onnx.ModelProto, k: int) -> onnx.ModelProto:
    """A copy of the batch-1 ``model`` that runs ``k`` images per call.

    Raises
    ------
    ModelError
        The model has not one input and one output with a leading batch of 1, or a ``Reshape`` takes a shape
        that is computed, has ``allowzero = 1``, or does not start with the batch of 1: its batch cannot be made
        changed by this rewrite (use ``[detector] batch = false``).
    """
    if k < 1:
        raise ModelError(f"batch size {k} < 1")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    graph = out.graph
    inits = {i.name for i in graph.initializer}
    inputs = [i for i in graph.input if i.name not in inits]
    if len(inputs) != 1 or len(graph.output) != 1:
        raise ModelError(f"expected one input and one output, got {len(inputs)} and {len(graph.output)}")
    _set_batch_dim(inputs[0], "input", k)
    _set_batch_dim(graph.output[0], "output", k)
    reshapes = [n for n in graph.node if n.op_type == "Reshape"]
    shape_names = {n.input[1] for n in reshapes}
    for node in graph.node:
        if node.op_type != "Reshape" and shape_names.intersection(node.input):
            raise ModelError(f"{node.op_type} {node.name!r} shares a Reshape's shape constant")
    done: set[str] = set()
    for node in reshapes:
        if any(a.name == "allowzero" and a.i == 1 for a in node.attribute):
            raise ModelError(f"Reshape {node.name!r} has allowzero = 1")
        if node.input[1] in done:  # one constant shared by several Reshapes: rewritten once
            continue
        tensor = _shape_tensor(out, node.input[1])
        if tensor is None:
            raise ModelError(f"Reshape {node.name!r} takes a computed shape ({node.input[1]!r})")
        done.add(node.input[1])
        shape = numpy_helper.to_array(tensor).copy()
        if shape.ndim != 1 or shape.size == 0 or shape[0] != 1:
            raise ModelError(f"Reshape {node.name!r} takes shape {shape.tolist()}, not a leading batch of 1")
        shape[0] = k
        tensor.CopyFrom(numpy_helper.from_array(shape.astype(np.int64), tensor.name))
    # Intermediate shapes recorded at export say batch 1; onnxruntime infers them again.
    del graph.value_info[:]
    return out


def load_model(path: Path) -> onnx.ModelProto:
    """The ONNX model at ``path``, checked once for :func:`fixed_batch` (so a model that cannot be batched fails
    when the detector loads, not in the middle of a run).

    Raises
    ------
    ModelError
        The file is not an ONNX model, or its batch cannot be changed.
    """
    try:
        model = onnx.load(str(path))
    except (OSError, DecodeError, ValueError) as exc:
        raise ModelError(f"cannot read {path} as an ONNX model: {exc}") from exc
    try:
        fixed_batch(model, 2)
    except ModelError as exc:
        raise ModelError(f"{path}: {exc}") from exc
    return model
