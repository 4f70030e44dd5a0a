"""Fixed sparse linear maps (CSR) with a precomputed transpose, differentiable in the dense operand.

Used where a linear map never changes during training: the blending weights of a view over frozen
geometry, and the hash-grid interpolation at fixed points. Both products are CSR x dense, which is
fast on CPU and CUDA and needs no sorting in the backward pass.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch


class SparseMatrix(NamedTuple):
    """A [R, C] sparse matrix held as CSR together with its [C, R] transpose."""

    csr: torch.Tensor
    """[R, C] sparse CSR."""
    csr_t: torch.Tensor
    """[C, R] sparse CSR of the transpose."""

    @classmethod
    def from_coo(
        cls, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]
    ) -> SparseMatrix:
        """From coordinates (duplicates are summed)."""
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, shape, check_invariants=True)
            coo = coo.coalesce()
            coo_t = torch.sparse_coo_tensor(
                coo.indices().flip(0), coo.values(), (shape[1], shape[0]), check_invariants=True
            )
            return cls(coo.to_sparse_csr(), coo_t.coalesce().to_sparse_csr())

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.csr.shape)

    def nnz(self) -> int:
        return int(self.csr.values().numel())

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> SparseMatrix:
        return SparseMatrix(
            self.csr.to(device=device, dtype=dtype), self.csr_t.to(device=device, dtype=dtype)
        )

    def matmul(self, x: torch.Tensor) -> torch.Tensor:
        """[R, D] = A @ x for x [C, D]; the gradient in x is A^T @ g."""
        return _SparseMatmul.apply(self.csr, self.csr_t, x)

    def dense(self) -> torch.Tensor:
        """[R, C] dense copy (for tests)."""
        return self.csr.to_dense()


class _SparseMatmul(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: torch.Tensor, a_t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(a_t)
        return a.to(x.dtype) @ x

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (a_t,) = ctx.saved_tensors
        return None, None, a_t.to(g.dtype) @ g
