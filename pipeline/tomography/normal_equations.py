"""A frame's regularised normal equations as conjugate-gradient vectors (paper sec. 5, eq. 5).

The three gradient components at once, Jacobi-scaled:

    P (N + mu^2 R + mu_c^2 C^T C) P z = P S^T b,   x = P z,

with ``N`` the data term's normal operator (``S^T S``, or its blurred form
``G S^T S G`` / ``S^T W^T W S``: :func:`data_term`), ``R`` the smoothness term and
``C^T C`` the curl coupling (:mod:`~schlieren.pipeline.tomography.regularisers`) and ``P``
the inverse square root of the diagonal. :class:`NormalVectors3` plugs them into the
shared loop (:class:`~schlieren.pipeline.linalg.cg.ConjugateGradient`): an iteration is one
fused pass over ``S`` (the normal product) and three serial numba kernels
(:mod:`~schlieren.pipeline.tomography._normal_kernels`), and the data residual
``||S x - b||`` is tracked from ``||b||^2 - 2 x^T S^T b + x^T S^T S x`` without extra
passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from schlieren.pipeline.linalg.cg import CGVectors
from schlieren.pipeline.tomography._normal_kernels import _cg_apply, _cg_direction3, _cg_update3
from schlieren.pipeline.tomography._restriction_kernels import matvec3
from schlieren.pipeline.tomography.regularisers import SquaredLaplacian, apply_regulariser, curl_normal

if TYPE_CHECKING:
    from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
    from schlieren.pipeline.tomography.params import TomoParams
    from schlieren.pipeline.tomography.solve import FrameSystem

__all__ = ["DataTerm", "data_term", "NormalVectors3", "normal_vectors"]


@dataclass(frozen=True)
class DataTerm:
    """The data term of a frame's normal equations.

    Attributes
    ----------
    normal : callable
        ``v (n, 3) -> N v``, the data term's normal operator.
    colsumsq : ndarray, shape (n,)
        ``diag(S^T S)`` (the Jacobi scaling and the weights keep it for every model).
    Stb, StSx0 : ndarray, shape (n, 3)
        The model's ``S^T b`` and its normal operator on the warm start (zero without one).
    """

    normal: Callable
    colsumsq: np.ndarray
    Stb: np.ndarray
    StSx0: np.ndarray


def data_term(sys_: FrameSystem, b: np.ndarray, x_warm: np.ndarray | None, products=None, *,
              blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None) -> DataTerm:
    """The data term of the model in use: point rays, ``S G`` (``volume``) or ``W S`` (``blur``).

    One pass over ``S`` gives ``diag(S^T S)``, ``S^T b`` and the warm start's ``S^T S x0``
    (:meth:`~schlieren.pipeline.tomography.restriction.RestrictedOperator.setup_products`),
    or it was already done while restricting: ``products``.
    """
    op = sys_.op
    if volume is not None:
        # data operator S G (VolumeBlur): G^T S^T S G as two volume filters around the fused
        # pass; products (from the restriction or computed here) are S^T b and S^T S G x0,
        # G^T applied below; the Jacobi scaling keeps diag(S^T S) (G averages neighbours)
        def normal(v):
            return volume.apply(op.normal3(volume.apply(v)))
        if products is None:
            products = op.setup_products(b, volume.apply(x_warm) if x_warm is not None else None)
        colsumsq = products[0]
        Stb = volume.apply(products[1])
        StSx0 = volume.apply(products[2]) if x_warm is not None else products[2]
    elif blur is None:
        normal = op.normal3
        colsumsq, Stb, StSx0 = products if products is not None else op.setup_products(b, x_warm)
    else:
        # data operator W S (MeasurementBlur): S^T W^T W S x as two passes over S and two
        # image-space filters; the Jacobi scaling and mu keep diag(S^T S) (W only averages
        # neighbouring rays of a camera, which cross a voxel alike)
        rows = op.rows

        def normal(v):  # float32 passes, as op.normal3
            Sv = op.matvec3_f32(v)
            return op.rmatvec3_f32(blur.restricted(rows, blur.restricted(rows, Sv)))

        if products is not None:  # S^T (W b) and S^T W^T W S x0 (``state`` of a previous solve)
            colsumsq, Stb, StSx0 = products
        else:
            colsumsq = sys_.colsumsq
            Stb = op.rmatvec3(blur.restricted(rows, b).astype(np.float64))
            StSx0 = normal(x_warm) if x_warm is not None else np.zeros((op.n, 3))
    return DataTerm(normal, colsumsq, Stb, StSx0)


def normal_vectors(sys_: FrameSystem, b: np.ndarray, params: TomoParams, data: DataTerm,
                   x_warm: np.ndarray | None, noise_rms: float | None) -> NormalVectors3:
    """The weights ``mu^2 = reg_weight mean(diag(S^T S))`` and ``mu_c^2`` (``curl_weight``),
    the Jacobi scaling and the discrepancy stop of a frame's system (``sys_.CtC`` is built
    here when the curl term first needs it)."""
    colsumsq = data.colsumsq
    mu2 = params.reg_weight * float(np.mean(colsumsq))
    LtL = sys_.LtL
    diag = colsumsq + mu2 * LtL.diagonal()
    # Curl coupling (TomoParams.curl_weight): one joint CG over the three components.
    muc2 = params.curl_weight * float(np.mean(colsumsq)) if params.curl_weight > 0 else 0.0
    CtC = None
    if muc2 > 0:
        CtC = sys_.CtC if sys_.CtC is not None else curl_normal(sys_.inset)
        sys_.CtC = CtC
        diag = diag + muc2 * CtC.diagonal3().mean(axis=1)
    P = (1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)))[:, None]
    stop = None
    if params.discrepancy > 0 and noise_rms is not None:
        stop = params.discrepancy * noise_rms * np.sqrt(sys_.op.m)
    return NormalVectors3(data, P, b, x_warm, LtL, mu2, CtC, muc2, tol=params.tol, stop=stop)


class NormalVectors3(CGVectors):
    """The CG vectors of ``P (N + mu^2 R + mu_c^2 C^T C) P z = P S^T b``, three columns.

    The vector work of an iteration runs in three fused serial kernels: ``x = P p`` with
    the new direction; ``q = P (S^T S x + mu^2 R x)`` with ``p . q``; the updates with
    ``r . r``, which also keep ``S^T S x`` (``StSx``) for the data residual. Without the
    curl term each column is its own CG; with it one CG over all three (its residual and
    reference summed over the components). Stops a column when ``||r|| <= tol ||P S^T b||``,
    or all of them once the data residual is at ``stop`` (the discrepancy principle).
    """

    def __init__(self, data: DataTerm, P: np.ndarray, b: np.ndarray, x_warm: np.ndarray | None, R, mu2: float,
                 curl, muc2: float, *, tol: float, stop: float | None = None):
        self.normal = data.normal
        self.Stb, self.StSx0 = data.Stb, data.StSx0
        self.P = P
        self.P1 = np.ascontiguousarray(P[:, 0])
        self.bb = np.einsum("ij,ij->j", b, b)
        self.x_warm = x_warm
        self.R, self.mu2 = R, mu2
        self.curl, self.muc2 = curl, muc2
        self.tol, self.stop = tol, stop
        # (L^T L)^2 x as M (M x): the inner product into ``Mx``, the outer one fused in _cg_apply
        self.squared = isinstance(R, SquaredLaplacian) and mu2 > 0
        self.M = R.M if isinstance(R, SquaredLaplacian) else R

    def _curl_term(self, v, out=None):
        return self.curl.apply3(v, self.muc2, out)

    def start(self) -> np.ndarray:
        P = self.P
        self.rhs = rhs = P * self.Stb
        if self.x_warm is not None:
            x_warm = self.x_warm
            self.z = x_warm / P
            self.StSx = self.StSx0
            Nz = P * (self.StSx0 + (self.mu2 * apply_regulariser(self.R, x_warm) if self.mu2 > 0 else 0.0)
                      + (self._curl_term(x_warm) if self.curl is not None else 0.0))
        else:
            n = P.shape[0]
            self.z = np.zeros((n, 3))
            self.StSx, Nz = np.zeros((n, 3)), np.zeros((n, 3))
        self.r = rhs - Nz
        rr = np.einsum("ij,ij->j", self.r, self.r)
        ref = np.sqrt(np.einsum("ij,ij->j", rhs, rhs))
        if self.curl is not None:  # coupled: one CG, its residual and reference over all components
            rr = np.full(3, rr.sum())
            ref = np.full(3, np.sqrt(np.sum(ref ** 2)))
        self.ref = ref
        return rr

    def converged(self, rr: np.ndarray) -> np.ndarray:
        return ~(np.sqrt(rr) > self.tol * self.ref)

    def direction(self, beta: np.ndarray | None) -> None:
        if beta is None:
            self.p = self.r.copy()
            self.x = self.P * self.p
            self.q = np.empty_like(self.p)
            self.Mx = np.empty_like(self.p) if self.squared else self.x
        else:
            _cg_direction3(self.p, self.r, beta, self.P1, self.x)

    def curvature(self) -> np.ndarray:
        x, M = self.x, self.M
        Sp = self.Sp = self.normal(x)
        d = self._curl_term(x, Sp.copy()) if self.curl is not None else Sp
        if self.squared:
            matvec3(M.indptr, M.indices, M.data, x, self.Mx)
        pq = _cg_apply(self.P1, d, M.indptr, M.indices, M.data, float(self.mu2), self.Mx if self.squared else x,
                       self.p, self.q)
        if self.curl is not None:
            pq = np.full(3, pq.sum())
        return pq

    def update(self, alpha: np.ndarray) -> np.ndarray:
        rr = _cg_update3(self.z, self.StSx, self.r, self.p, self.q, self.Sp, alpha)
        if self.curl is not None:
            rr = np.full(3, rr.sum())
        return rr

    def data_residual(self) -> np.ndarray:
        """``||S x - b||`` per component, from ``||b||^2 - 2 x^T S^T b + x^T S^T S x``."""
        x = self.P * self.z
        val = self.bb - 2 * np.einsum("ij,ij->j", x, self.Stb) + np.einsum("ij,ij->j", x, self.StSx)
        return np.sqrt(np.maximum(val, 0.0))

    def early_stop(self) -> str | None:
        if self.stop is not None and np.all(self.data_residual() <= self.stop):
            return "discrepancy"
        return None

    def solution(self) -> np.ndarray:
        return self.z
