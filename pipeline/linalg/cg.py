"""Conjugate gradients, step by step: the one CG loop of the pipeline.

Every conjugate-gradient solve runs :class:`ConjugateGradient`: the tomography's
Jacobi-scaled regularised normal equations (paper sec. 5, eq. 5: three right-hand sides
sharing ``S``, fused float32 passes, :mod:`schlieren.pipeline.tomography.normal_equations`),
the direct refractivity solve's CGLS (:func:`~schlieren.pipeline.linalg.cgls.cgls`) and the
Poisson integration's preconditioned CG (eq. 8; the paper's Jacobi-preconditioned CG,
:func:`pcg`). The loop owns the scalars: the step lengths ``alpha`` and ``beta`` of each
column (each column of a multi-column solve is its own CG, unless its vectors couple
them), which columns are still active, the iteration count and the stop reason. What
differs between the problems is pluggable (:class:`CGVectors`): the operator product, the
preconditioner and the vector updates, each a kernel of its problem that fuses several
vector operations into one pass, and the measure the stopping rule compares.

PyLops-style (``optimization/basesolver.py``): :meth:`ConjugateGradient.setup`,
:meth:`~ConjugateGradient.step` and :meth:`~ConjugateGradient.run` with a callback, and a
named result (:class:`CGResult`).

Why not scipy's ``cg`` or PyLops' ``CG``: both iterate on one right-hand side with the
array library's vector operations (scipy: BLAS ``dot`` and ``axpy`` and a preconditioner;
PyLops: numpy, no preconditioner). The tomography's three components would then take
three solves with a pass over ``S`` each per iteration (or one ``S @ X`` at about five
passes' cost) instead of the one fused pass, the running ``S^T S x`` that its data
residual is tracked with has no place in their updates, and a threaded BLAS ``dot`` costs
more than a multigrid V-cycle at the Poisson sizes (:func:`pcg`). Their summation order
also differs from these kernels', so every result would change.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.linalg._cg_kernels import cg_direction, cg_update, dot

__all__ = ["CGVectors", "ConjugateGradient", "CGResult", "SerialVectors", "pcg"]


@dataclass(frozen=True)
class CGResult:
    """Receipt of a :class:`ConjugateGradient` run.

    Attributes
    ----------
    x : ndarray
        The iterate (for scaled systems the scaled unknowns; :meth:`CGVectors.solution`).
    iterations : int
        Iterations run.
    stop_reason : str
        ``"tol"`` (every column met its stopping rule), ``"max_iter"``, ``"breakdown"``
        (no active column had a positive curvature ``p . A p``) or the reason the vectors'
        :meth:`~CGVectors.early_stop` gave (e.g. ``"discrepancy"``).
    residual : ndarray, shape (k,)
        The stopping rule's measure per column when its column stopped (squared norms:
        ``r . r``; CGLS: the normal residual's), as :meth:`CGVectors.update` returns it.
    """

    x: np.ndarray
    iterations: int
    stop_reason: str
    residual: np.ndarray


class CGVectors(ABC):
    """The vectors of one CG run and the kernels that update them (the pluggable part).

    A subclass holds the iterate ``x``, the residual ``r``, the search direction ``p``,
    the operator's product ``q = A p`` and, with a preconditioner, ``z = M r``, each with
    ``k`` columns, and implements the vector steps of an iteration. Every per-column
    scalar passed in or returned is an array of shape (k,).
    """

    @abstractmethod
    def start(self) -> np.ndarray:
        """Compute the initial residual; returns the stopping rule's measure per column."""

    @abstractmethod
    def converged(self, measure: np.ndarray) -> np.ndarray:
        """Which columns meet the stopping rule (bool, shape (k,))."""

    def precondition(self, measure: np.ndarray) -> np.ndarray:
        """``z = M r``; returns ``r . z`` per column. Without a preconditioner (this
        default) ``z`` is ``r`` and ``r . z`` is the measure :meth:`update` returned."""
        return measure

    @abstractmethod
    def direction(self, beta: np.ndarray | None) -> None:
        """``p = z + beta p``; the first direction ``p = z`` when ``beta`` is None."""

    @abstractmethod
    def curvature(self) -> np.ndarray:
        """``q = A p``; returns ``p . q`` per column."""

    @abstractmethod
    def update(self, alpha: np.ndarray) -> np.ndarray:
        """``x += alpha p``, ``r -= alpha q``; returns the stopping rule's measure per column."""

    def early_stop(self) -> str | None:
        """Checked before every iteration: a stop reason (e.g. the discrepancy principle's)
        or None (this default) to go on."""
        return None

    def solution(self) -> np.ndarray:
        """The iterate ``x``."""
        return self.x


class ConjugateGradient:
    """Conjugate gradients on :class:`CGVectors`, step by step.

    Column ``c`` takes the step ``alpha_c = rho_c / (p_c . A p_c)`` (``rho = r . z``; none
    where the curvature is not positive) and the new direction ``p_c = z_c + beta_c p_c``,
    ``beta_c = rho_c' / rho_c``, until its stopping rule holds; the run ends when every
    column has stopped, after ``max_iter`` iterations, when no active column has a positive
    curvature (``"breakdown"``) or when the vectors' :meth:`~CGVectors.early_stop` says so.

    Parameters
    ----------
    vectors : CGVectors
    max_iter : int

    Examples
    --------
    ``ConjugateGradient(vectors, max_iter=50).run()``, or ``setup()`` then ``step()``
    while it returns True.
    """

    def __init__(self, vectors: CGVectors, *, max_iter: int):
        self.vectors = vectors
        self.max_iter = int(max_iter)
        self.iterations = 0
        self.stop_reason = ""
        self.stopped = False
        self.active: np.ndarray | None = None  # columns still iterating
        self.rho: np.ndarray | None = None  # r . z of the active columns
        self.residual: np.ndarray | None = None  # the stopping measure of each column

    def setup(self) -> ConjugateGradient:
        """The initial residual, the columns that need iterating and the first direction."""
        v = self.vectors
        self.residual = v.start()
        self.active = ~np.asarray(v.converged(self.residual), dtype=bool)
        self.iterations = 0
        if self.active.any():
            self.stopped, self.stop_reason = False, "max_iter"  # until a step says otherwise
            self.rho = v.precondition(self.residual)
            v.direction(None)
        else:
            self.stopped, self.stop_reason = True, "tol"
        return self

    def _stop(self, reason: str) -> bool:
        self.stopped, self.stop_reason = True, reason
        return False

    def step(self) -> bool:
        """One iteration; returns whether the run goes on (False once it has stopped)."""
        if self.stopped:
            return False
        v = self.vectors
        active, rho = self.active, self.rho
        pq = v.curvature()
        if not np.any(active & (pq > 0)):
            return self._stop("breakdown")
        alpha = np.where(active & (pq > 0), rho / np.where(pq > 0, pq, 1.0), 0.0)
        measure = v.update(alpha)
        self.iterations += 1
        self.residual = np.where(active, measure, self.residual)
        self.active = active & ~np.asarray(v.converged(measure), dtype=bool)
        if not self.active.any():
            return self._stop("tol")
        rho_new = v.precondition(measure)
        beta = np.where(active, rho_new / np.where(rho > 0, rho, 1.0), 0.0)
        self.rho = np.where(active, rho_new, rho)
        v.direction(beta)
        if self.iterations >= self.max_iter:
            return self._stop("max_iter")
        return True

    def run(self, callback=None) -> CGResult:
        """Iterate to a stop (:meth:`setup` first if it has not run).

        ``callback(solver)`` after every iteration (e.g. progress, or the iterate
        ``solver.vectors.solution()``).
        """
        if self.active is None:
            self.setup()
        if self.iterations >= self.max_iter and not self.stopped:
            self._stop("max_iter")
        while not self.stopped:
            reason = self.vectors.early_stop()
            if reason is not None:
                self._stop(reason)
                break
            self.step()
            if callback is not None:
                callback(self)
        return self.result()

    def result(self) -> CGResult:
        return CGResult(x=self.vectors.solution(), iterations=self.iterations, stop_reason=self.stop_reason,
                        residual=np.asarray(self.residual))


class SerialVectors(CGVectors):
    """One column, an operator ``A @ p`` and a preconditioner, vector updates in serial
    numba kernels (:mod:`~schlieren.pipeline.linalg._cg_kernels`).

    Stopping rule: ``||f - A x|| <= tol ||f||`` (scipy's ``cg`` criterion with ``atol = 0``).

    Parameters
    ----------
    A : scipy.sparse matrix or any object with ``A @ v``, shape (n, n)
    f : ndarray, shape (n,)
    precond : callable
        ``precond(r) -> z``, a symmetric positive definite approximation of ``A^-1``.
    x0 : ndarray, shape (n,), optional
    tol : float
    """

    def __init__(self, A, f: np.ndarray, precond, *, x0: np.ndarray | None = None, tol: float):
        self.A = A
        self.f = np.ascontiguousarray(f, dtype=np.float64)
        self.precond = precond
        self.x0 = x0
        self.x = np.zeros_like(self.f) if x0 is None else np.array(x0, dtype=np.float64, copy=True)
        self.thresh2 = (tol * np.sqrt(dot(self.f, self.f))) ** 2

    def start(self) -> np.ndarray:
        self.r = self.f - self.A @ self.x if self.x0 is not None else self.f.copy()
        return np.array([dot(self.r, self.r)])

    def converged(self, measure: np.ndarray) -> np.ndarray:
        return measure <= self.thresh2

    def precondition(self, measure: np.ndarray) -> np.ndarray:
        self.z = np.ascontiguousarray(self.precond(self.r))
        return np.array([dot(self.r, self.z)])

    def direction(self, beta: np.ndarray | None) -> None:
        if beta is None:
            self.p = self.z.copy()
        else:
            cg_direction(self.p, self.z, beta[0])

    def curvature(self) -> np.ndarray:
        self.q = self.A @ self.p
        return np.array([dot(self.p, self.q)])

    def update(self, alpha: np.ndarray) -> np.ndarray:
        return np.array([cg_update(self.x, self.r, self.p, self.q, alpha[0])])


def pcg(A, f: np.ndarray, precond, *, x0: np.ndarray | None = None, tol: float,
        max_iter: int) -> tuple[np.ndarray, int]:
    """Preconditioned conjugate gradients for SPD ``A`` (the solver of "mg" and "jacobi_cg").

    Stops when ``||f - A u|| <= tol ||f||`` (scipy's ``cg`` criterion with ``atol = 0``).
    The vector operations are serial numba loops, not BLAS calls: on a small shared
    machine a multithreaded BLAS ``dot`` on a 10^5-vector costs milliseconds of thread
    wake-up, more than the multigrid V-cycle itself (docs/tuning.md, "Poisson"); the
    result is also independent of the BLAS thread count.

    Parameters
    ----------
    A : scipy.sparse.csr_matrix, shape (n, n)
    f : ndarray, shape (n,)
    precond : callable
        ``precond(r) -> z``, a symmetric positive definite approximation of ``A^-1``.
    x0 : ndarray, shape (n,), optional
    tol : float
    max_iter : int

    Returns
    -------
    u : ndarray, shape (n,)
    iterations : int
    """
    res = ConjugateGradient(SerialVectors(A, f, precond, x0=x0, tol=tol), max_iter=max_iter).run()
    return res.x, res.iterations
