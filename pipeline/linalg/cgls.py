"""CGLS: conjugate gradients on ``min sum_k ||A_k x - b_k||^2`` through ``A`` and ``A^T``.

The least-squares form of CG (Hestenes and Stiefel's CGLS): the residual is kept in the
data space and the normal residual ``s = A^T r`` plays the preconditioned residual of
:class:`~schlieren.pipeline.linalg.cg.ConjugateGradient`, whose loop runs it. Used by the
direct refractivity solve (:mod:`schlieren.pipeline.tomography.direct`), whose stacked
operator (the projection of a gradient plus a smoothness term) is given as callables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.linalg.cg import CGVectors, ConjugateGradient

__all__ = ["cgls", "CGLSResult", "CGLSVectors"]


@dataclass
class CGLSResult:
    x: np.ndarray
    iterations: int
    stop_reason: str
    data_residual: np.ndarray  # ||S x - b|| per column
    rhs_norm: np.ndarray


class CGLSVectors(CGVectors):
    """The vectors of :func:`cgls` (numpy operations; the operator's callables dominate).

    ``r`` is the list of data-space residual blocks ``b_k - A_k x``, ``s = A^T r`` the
    normal residual (the measure: ``s . s``; stopping rule ``||s|| <= tol ||A^T b||``), ``q``
    the blocks of ``A p``.
    """

    def __init__(self, A, AT, b_parts, x0, *, tol: float, n_data_parts: int = 1,
                 stop_data_norm: np.ndarray | None = None):
        self.A, self.AT, self.b_parts = A, AT, b_parts
        self.x = np.array(x0, dtype=np.float64, copy=True)
        self.tol = tol
        self.n_data_parts = n_data_parts
        self.stop_data_norm = stop_data_norm

    def start(self) -> np.ndarray:
        Ax = self.A(self.x)
        self.r = [b - a for b, a in zip(self.b_parts, Ax)]
        self.s = self.AT(self.r)
        gamma = np.einsum("ij,ij->j", self.s, self.s)
        if np.any(self.x):
            # Warm start: measure convergence against ||A^T b|| (the cold-start reference),
            # not against the (already small) initial normal residual.
            sb = self.AT(self.b_parts)
            gamma0 = np.einsum("ij,ij->j", sb, sb)
        else:
            gamma0 = gamma.copy()
        self.gamma0 = gamma0
        return gamma

    def converged(self, gamma: np.ndarray) -> np.ndarray:
        return ~((gamma > 0) & (np.sqrt(gamma) > self.tol * np.sqrt(self.gamma0)))

    def direction(self, beta: np.ndarray | None) -> None:
        self.p = self.s.copy() if beta is None else self.s + beta * self.p

    def curvature(self) -> np.ndarray:
        self.q = self.A(self.p)
        return sum(np.einsum("ij,ij->j", qi, qi) for qi in self.q)

    def update(self, alpha: np.ndarray) -> np.ndarray:
        self.x += alpha * self.p
        for ri, qi in zip(self.r, self.q):
            ri -= alpha * qi
        self.s = self.AT(self.r)
        return np.einsum("ij,ij->j", self.s, self.s)

    def data_residual(self) -> np.ndarray:
        """``||A x - b||`` over the data blocks, per column."""
        return np.sqrt(sum(np.einsum("ij,ij->j", ri, ri) for ri in self.r[:self.n_data_parts]))

    def early_stop(self) -> str | None:
        if self.stop_data_norm is not None and np.all(self.data_residual() <= self.stop_data_norm):
            return "discrepancy"
        return None


def cgls(A, AT, b_parts: list[np.ndarray], x0: np.ndarray, *, max_iter: int, tol: float,
         n_data_parts: int = 1, stop_data_norm: np.ndarray | None = None, callback=None
         ) -> CGLSResult:
    """CGLS for ``min sum_k ||A_k x - b_k||^2`` on several independent columns at once.

    Parameters
    ----------
    A : callable
        ``A(x) -> list of arrays`` (the stacked operator applied to x of shape (n, k)).
    AT : callable
        ``AT(list of arrays) -> (n, k)``, the adjoint.
    b_parts : list of ndarray
        Right-hand side blocks, each shape (m_i, k).
    x0 : ndarray, shape (n, k)
        Initial guess.
    max_iter : int
    tol : float
        Stop when ``||A^T r|| <= tol * ||A^T b||`` for every column.
    n_data_parts : int
        The first ``n_data_parts`` blocks form the data term (for the residual report
        and the discrepancy stop).
    stop_data_norm : ndarray, shape (k,), optional
        Discrepancy principle: stop when the data residual of every column is below it.
    callback : callable, optional
        ``callback(iteration, x)`` after every iteration.

    Notes
    -----
    Each column has its own step lengths, so this is exactly ``k`` independent CGLS
    runs sharing the operator passes (PyLops-style step-wise loop).
    """
    vec = CGLSVectors(A, AT, b_parts, x0, tol=tol, n_data_parts=n_data_parts, stop_data_norm=stop_data_norm)
    rhs_norm = np.sqrt(sum(np.einsum("ij,ij->j", b, b) for b in b_parts[:n_data_parts]))
    each = None if callback is None else (lambda solver: callback(solver.iterations, vec.x))
    res = ConjugateGradient(vec, max_iter=max_iter).run(each)
    return CGLSResult(x=res.x, iterations=res.iterations, stop_reason=res.stop_reason,
                      data_residual=vec.data_residual(), rhs_norm=rhs_norm)
