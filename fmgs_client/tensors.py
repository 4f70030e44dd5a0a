"""Moved: the tensor codec lives in fmgs_wire.tensors (shared with the server)."""

from fmgs_wire.tensors import TensorError, from_tensor, join, row_chunks, to_tensor

__all__ = ["TensorError", "from_tensor", "join", "row_chunks", "to_tensor"]
