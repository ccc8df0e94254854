"""Per-frame gradient tomography: hull restriction, regularised fused CGLS (paper sec. 5).

Least squares ``S n_{x,y,z} = n_amb (d_out - d_in)_{x,y,z}`` (eq. 5) for the three
components at once, restricted to the basis functions whose support touches the visual
hull and to the rays that hit them. Plain LSQR/CGLS semi-converges on noisy deflections,
so the normal equations are regularised with a smoothness term on the basis set built
from first differences ``L`` (differences to the zero-valued basis functions outside the
set included, so the gradient fades to zero at the hull boundary):

    min ||S x - b||^2 + mu^2 x^T R x + mu_c^2 ||C x||^2,
    mu^2 = reg_weight * mean(diag(S^T S)),   mu_c^2 = curl_weight * mean(diag(S^T S)),

with ``R = L^T L`` (``prior: first-differences``, the paper's) or ``R = (L^T L)^2``
(``second-differences``, the default: a curvature penalty, see ``TomoParams.prior``) and
``C`` the discrete curl of the gradient field (:func:`curl_normal`; beyond the paper, which
solves the components independently: ``curl_weight: 0``). From optical flow the data term is
``||S G x - b||^2`` with ``G`` the flow's image averaging moved to the volume (a Gaussian
over the basis coefficients, :class:`VolumeBlur`; ``TomoParams.model_flow_window``, beyond
the paper, whose rows are the cell-centre rays) or ``||W S x - b||^2`` with ``W`` the same
averaging in image space (:class:`MeasurementBlur`, ``flow_window_space: image``),

solved by conjugate gradients on the Jacobi-scaled normal equations (the CGLS iteration;
one fused pass over ``S`` per iteration applies ``S^T S`` to the three components),
stopped when the normal residual has dropped by ``tol`` or, optionally, by the
discrepancy principle. Warm start from the previous frame's gradient (on the full grid).
Why regularise: on noisy deflections plain CG on eq. 5 semi-converges (its error grows
with the iterations), while the regularised solve is stable at its tolerance stop, at a
small cost on noise-free data (benchmarks/results/tomography.md; docs/tuning.md,
"Tomography"). The weight a run uses is chosen from the data
(:mod:`~schlieren.pipeline.tomography.reg_choice`); ``TomoParams.reg_weight`` is the
fixed fallback.

Modules: the regularisers (:mod:`~schlieren.pipeline.tomography.regularisers`), the flow's
averaging in the data term (:mod:`~schlieren.pipeline.tomography.blur`), the normal
equations as CG vectors (:mod:`~schlieren.pipeline.tomography.normal_equations`, run by the
shared :class:`~schlieren.pipeline.linalg.cg.ConjugateGradient`) and the weight's choice
(:mod:`~schlieren.pipeline.tomography.reg_choice`); here the per-frame drivers.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from schlieren.pipeline.linalg.cg import ConjugateGradient
from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography.normal_equations import data_term, normal_vectors
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.rays import rhs_from_d_out, rhs_from_flows
from schlieren.pipeline.tomography.regularisers import CurlNormal, SquaredLaplacian, curl_normal, regulariser
from schlieren.pipeline.tomography.restriction import (
    RestrictedOperator,
    SubsetOperator,
    restrict_with_setup,
    shared_restriction,
)

__all__ = ["SolveInfo", "solve_gradient", "solve_gradient_d_out", "basis_set", "prepare_frame", "FrameSystem",
           "finite_rhs", "frame_rhs", "valid_rays", "block_support"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SolveInfo:
    """Receipt of one tomographic solve.

    Attributes
    ----------
    iterations : int
        Conjugate-gradient iterations run (CGLS-equivalent).
    residual : float
        Largest relative data residual ``||S x - b|| / ||b||`` over the components.
    residual_components : tuple of float
        The same per component (x, y, z).
    n_unknowns : int
        Basis functions per component.
    n_rays : int
        Rays (rows) used.
    nnz : int
        Non-zeros of the restricted matrix.
    stop_reason : str
        ``"tol"``, ``"discrepancy"``, ``"max_iter"`` or ``"empty"``.
    setup_seconds, solve_seconds : float
        Restriction / right-hand side time and iteration time.
    restriction : str
        ``"frame"`` (restricted for this frame), ``"shared-built"`` / ``"shared-kept"``
        (selected inside a shared restriction built by this call / kept from an earlier
        one, ``solve_gradient``'s ``support``) or ``"given"`` (``system``).
    """

    iterations: int
    residual: float
    residual_components: tuple = field(default=())
    n_unknowns: int = 0
    n_rays: int = 0
    nnz: int = 0
    stop_reason: str = ""
    setup_seconds: float = 0.0
    solve_seconds: float = 0.0
    restriction: str = ""


def basis_set(hull: np.ndarray, dilation: int) -> np.ndarray:
    """Basis functions kept for a hull: the hull dilated by ``dilation`` voxels (3x3x3)."""
    hull = np.asarray(hull, dtype=bool)
    if dilation <= 0:
        return hull.copy()
    return ndi.binary_dilation(hull, structure=np.ones((3, 3, 3), bool), iterations=dilation)


@dataclass
class FrameSystem:
    """The per-frame restricted system (also used by the direct refractivity solve)."""

    op: RestrictedOperator
    inset: np.ndarray  # (nz, ny, nx) bool: kept basis functions
    LtL: sp.csr_matrix | SquaredLaplacian  # smoothness term's normal matrix on the set (regulariser)
    _colsumsq: np.ndarray | None = None  # diag(S^T S), shape (n,); computed on first use
    CtC: CurlNormal | None = None  # curl_normal(inset) when TomoParams.curl_weight > 0

    @property
    def n(self) -> int:
        return self.op.n

    @property
    def colsumsq(self) -> np.ndarray:
        """``diag(S^T S)``, shape (n,) (the gradient solve gets it from its fused setup pass)."""
        if self._colsumsq is None:
            self._colsumsq = self.op.column_sumsq()
        return self._colsumsq


def valid_rays(data: np.ndarray) -> np.ndarray | None:
    """Flat indices of the rays whose measurement (last axis) is finite, or None if all are.

    The flow stage returns NaN where the images cannot carry a deflection (dead,
    clipped or textureless regions): those rays are left out of the system rather than
    read as "no deflection".
    """
    data = np.asarray(data)
    # the channel sum is finite exactly when every channel is (NaN and inf propagate; the
    # values are deflections in pixels or O(1e-3) right-hand sides, far from overflow),
    # and far cheaper than isfinite().all(axis=-1) over a trailing axis of 2 or 3
    total = data[..., 0].copy()
    for k in range(1, data.shape[-1]):
        total += data[..., k]
    ok = np.isfinite(total).ravel()
    return None if ok.all() else np.flatnonzero(ok)


def prepare_frame(geom: TomoGeometry, hull: np.ndarray, *, dilation: int,
                  rows: np.ndarray | None = None, prior: str = TomoParams.prior,
                  curl: bool = False) -> FrameSystem:
    """Restrict the session's projection to a frame's hull (basis functions and rays;
    ``rows``: only these rays, e.g. :func:`valid_rays`; ``curl``: also build
    :func:`curl_normal` for ``TomoParams.curl_weight``)."""
    hull = np.asarray(hull, dtype=bool)
    if hull.shape != geom.grid.shape:
        raise ValueError(f"hull shape {hull.shape} does not match the grid {geom.grid.shape}")
    inset = basis_set(hull, dilation)
    flat = inset.ravel()
    colmap = np.full(flat.size, -1, np.int32)
    n = int(flat.sum())
    colmap[flat] = np.arange(n, dtype=np.int32)
    op = RestrictedOperator.from_full(geom.S, np.arange(geom.S.shape[0]) if rows is None else rows, colmap, n)
    return FrameSystem(op=op, inset=inset, LtL=regulariser(inset, prior),
                       CtC=curl_normal(inset) if curl else None)


def finite_rhs(b: np.ndarray) -> np.ndarray:
    """Zero (and report) non-finite right-hand sides that are left (invalid deflections are
    dropped before, :func:`valid_rays`; this only guards the arithmetic)."""
    bad = ~np.isfinite(b)
    if bad.any():
        log.warning("%d non-finite right-hand-side value(s) replaced by 0", int(bad.sum()))
        b = np.where(bad, 0.0, b)
    return b


def frame_rhs(geom: TomoGeometry, data: np.ndarray, rows: np.ndarray, *, n_ambient: float) -> np.ndarray:
    """The right-hand side ``n_amb (d_out - d_in)`` of the rays ``rows``, shape (len(rows), 3),
    from deflections ``data`` (C, h, w, 2) (:func:`rhs_from_flows`) or right-hand sides
    (C, h, w, 3); non-finite values zeroed (:func:`finite_rhs`)."""
    if data.shape[-1] == 2:
        b = rhs_from_flows(geom, data, n_ambient=n_ambient, rays=rows)
    else:
        b = np.asarray(data, dtype=np.float64).reshape(-1, 3)[rows]
    return finite_rhs(b)


def _scatter(inset: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros(inset.shape + (values.shape[1],), np.float32)
    out[inset] = values
    return out


def solve_gradient(geom: TomoGeometry, rhs_or_flows: np.ndarray, hull: np.ndarray, *,
                   params: TomoParams = TomoParams(), x0: np.ndarray | None = None,
                   noise_rms: float | None = None, system: FrameSystem | None = None,
                   blur: MeasurementBlur | None = None,
                   volume_blur: float = 0.0, support: np.ndarray | None = None) -> tuple[np.ndarray, SolveInfo]:
    """Reconstruct the refractive-index gradient of one frame (paper sec. 5, eq. 5).

    Parameters
    ----------
    geom : TomoGeometry
        Per-session geometry (:func:`build_geometry`).
    rhs_or_flows : ndarray, shape (C, h, w, 2) or (C, h, w, 3)
        Either deflections ``delta`` (pixels; converted with :func:`approximate_d_out`) or
        the right-hand side ``n_amb * (d_out - d_in)`` (dimensionless, e.g. from exact
        exit directions via :func:`rhs_from_d_out`).
    hull : ndarray, shape (nz, ny, nx) bool
        Visual hull of the frame.
    params : TomoParams
    x0 : ndarray, shape (nz, ny, nx, 3), optional
        Warm start (previous frame's gradient, 1/m).
    noise_rms : float, optional
        RMS noise of one right-hand-side component, for the discrepancy stop.
    system : FrameSystem, optional
        A restriction already prepared for this hull (reuse across calls).
    blur : MeasurementBlur, optional
        Model the flow's image-space averaging (``W S x = b``; :class:`MeasurementBlur`);
        None: each measurement is the ray through its cell centre.
    volume_blur : float
        Or model it in the volume (``S G x = b``, :class:`VolumeBlur` of this sigma in
        voxels, :func:`volume_sigma`): the same fit at the cost of the point-ray model's
        single pass over ``S`` per iteration. 0: off.
    support : ndarray, shape (nz, ny, nx) bool, optional
        Basis functions shared by several frames, a superset of this frame's set (e.g.
        :func:`block_support` of a warm-start block): the projection is restricted to it
        once per thread and the frame's system selected inside it (:class:`SubsetOperator`;
        the same system, its products cost a pass over the shared restriction). Without a
        ``blur`` only; ignored with ``system``.

    Returns
    -------
    gradient : ndarray, shape (nz, ny, nx, 3) float32
        ``grad n`` in 1/m, component 0 = x; zero outside the basis set.
    info : SolveInfo
    """
    t0 = time.perf_counter()
    data = np.asarray(rhs_or_flows)
    if data.shape[:-1] != tuple(geom.flow_shape) or data.shape[-1] not in (2, 3):
        raise ValueError(f"expected shape {tuple(geom.flow_shape)} + (2,) or (3,), got {data.shape}")

    def rhs(rows):
        return frame_rhs(geom, data, rows, n_ambient=params.n_ambient)

    if blur is not None and volume_blur > 0:
        raise ValueError("solve_gradient: give either blur (image space) or volume_blur, not both")
    if system is not None:
        sys_, b_k, products, how = system, None, None, "given"
        G = VolumeBlur(sys_.inset, volume_blur) if volume_blur > 0 and sys_.inset.any() else None
    else:
        sys_, b_k, products, how, G = _restrict_frame(geom, data, hull, params, x0, rhs, blur, volume_blur, support)
    op = sys_.op
    if op.n == 0 or op.m == 0:
        info = SolveInfo(iterations=0, residual=0.0, residual_components=(0.0, 0.0, 0.0),
                         stop_reason="empty", setup_seconds=time.perf_counter() - t0, restriction=how)
        return np.zeros(geom.grid.shape + (3,), np.float32), info
    b = b_k if products is not None else rhs(op.rows)
    if blur is not None:
        products = None  # S^T b and the warm start's product go through W (_solve_restricted)
    x, it, reason, res, t_solve = _solve_restricted(sys_, b, params, x0, noise_rms, products, blur=blur, volume=G)
    t1 = time.perf_counter()
    grad = _scatter(sys_.inset, x)
    info = SolveInfo(iterations=it, residual=float(np.max(res)), residual_components=tuple(map(float, res)),
                     n_unknowns=op.n, n_rays=op.m, nnz=op.nnz, stop_reason=reason,
                     setup_seconds=t1 - t0 - t_solve, solve_seconds=t_solve, restriction=how)
    log.debug("solve_gradient: %s", info)
    return grad, info


def _restrict_frame(geom: TomoGeometry, data: np.ndarray, hull: np.ndarray, params: TomoParams, x0, rhs,
                    blur: MeasurementBlur | None, volume_blur: float, support: np.ndarray | None):
    """:func:`solve_gradient`'s frame system: the restriction fused with the solver's setup
    pass (diag(S^T S), S^T b, S^T S x0), inside the shared restriction of ``support`` if given.

    Returns
    -------
    sys_ : FrameSystem
    b : ndarray, shape (op.m, 3)
        ``rhs(op.rows)``.
    products : tuple
        The setup products (:meth:`RestrictedOperator.setup_products`).
    how : str
        :attr:`SolveInfo.restriction`.
    G : VolumeBlur or None
        The volume model's blur (``volume_blur > 0``).
    """
    hull = np.asarray(hull, dtype=bool)
    if hull.shape != geom.grid.shape:
        raise ValueError(f"hull shape {hull.shape} does not match the grid {geom.grid.shape}")
    inset = basis_set(hull, params.hull_dilation)
    flat = inset.ravel()
    n = int(flat.sum())
    colmap = np.full(flat.size, -1, np.int32)
    colmap[flat] = np.arange(n, dtype=np.int32)
    x_warm = _warm(x0, inset)
    G = VolumeBlur(inset, volume_blur) if volume_blur > 0 and inset.any() else None
    if G is not None and x_warm is not None:  # the unknowns are G's input: S^T S G x0
        x_warm = G.apply(x_warm)
    if support is not None and blur is None:
        op, b_k, products, how = _subset_system(geom, inset, support, valid_rays(data), rhs, x_warm)
    else:
        how = "frame"
        op, b_k, products = restrict_with_setup(geom.S, colmap, n, rhs, x_warm if blur is None else None,
                                                reuse_buffers=True, rows=valid_rays(data))
    sys_ = FrameSystem(op=op, inset=inset, LtL=regulariser(inset, params.prior), _colsumsq=products[0],
                       CtC=curl_normal(inset) if params.curl_weight > 0 else None)
    return sys_, b_k, products, how, G


def block_support(hulls, dilation: int) -> np.ndarray:
    """The union of several frames' basis sets (:func:`basis_set`), e.g. a warm-start
    block's: the shared restriction of :func:`solve_gradient`'s ``support``."""
    out = None
    for h in hulls:
        s = basis_set(h, dilation)
        out = s if out is None else (out | s)
    if out is None:
        raise ValueError("block_support needs at least one hull")
    return out


def _subset_system(geom: TomoGeometry, inset: np.ndarray, support: np.ndarray, valid: np.ndarray | None,
                   rhs=None, x_warm: np.ndarray | None = None):
    """The frame's system (basis set ``inset``, rays ``valid``) inside the restriction of
    the projection to ``support`` (built once per thread and support), with its right-hand
    side ``rhs(rows)`` and setup products (:meth:`SubsetOperator.setup_products`, fused with
    the restriction when this call builds it).

    Returns
    -------
    op : SubsetOperator
    b : ndarray (op.m, 3) or None (without ``rhs``)
    products : tuple or None
    how : str
        ``"shared-built"`` or ``"shared-kept"`` (:attr:`SolveInfo.restriction`).
    """
    support = np.asarray(support, dtype=bool)
    if support.shape != inset.shape:
        raise ValueError(f"support shape {support.shape} does not match the grid {inset.shape}")
    if np.any(inset & ~support):
        raise ValueError("support must contain the frame's basis set (the dilated hull)")
    digest = hashlib.blake2b(np.packbits(support).tobytes(), digest_size=16).hexdigest()
    sel = np.flatnonzero(inset.ravel()[support.ravel()])
    flag = None
    if valid is not None:
        flag = np.zeros(geom.S.shape[0], bool)
        flag[valid] = True
    x_sup = None
    if x_warm is not None:
        x_sup = np.zeros((int(support.sum()), 3))
        x_sup[sel] = x_warm
    rhs_valid = rhs
    if rhs is not None and flag is not None:
        def rhs_valid(rows):  # the support's rays include invalid ones: never evaluated
            out = np.zeros((len(rows), 3))
            ok = flag[rows]
            out[ok] = rhs(rows[ok])
            return out
    base, fused = shared_restriction(geom.S, support, (geom.key, geom.S.shape, geom.S.nnz, digest),
                                     rhs=rhs_valid, x=x_sup, valid=flag)
    op = SubsetOperator(base, sel, None if flag is None else flag[base.rows])
    how = "shared-kept" if fused is None else "shared-built"
    if rhs is None:
        return op, None, None, how
    if fused is not None:  # products over the support's rows: keep the frame's rows and columns
        b_all, prods = fused
        return op, b_all[op._live_idx], tuple(p[sel] for p in prods), how
    b = rhs(op.rows)
    return op, b, op.setup_products(b, x_warm), how


def _warm(x0, inset):
    """Warm start restricted to the basis set (None for no or an all-zero warm start)."""
    if x0 is not None and np.any(x0):
        return np.asarray(x0, dtype=np.float64)[inset]
    return None


class RestrictedSolve(NamedTuple):
    """Result of :func:`_solve_restricted`."""

    x: np.ndarray  # (n, 3) float64 over the basis set
    iterations: int
    stop_reason: str
    residual: np.ndarray  # (3,) relative data residual ||S x - b|| / ||b|| per component
    seconds: float  # setup products and iterations


def _solve_restricted(sys_: FrameSystem, b: np.ndarray, params: TomoParams, x0, noise_rms, products=None,
                      blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None,
                      state: dict | None = None) -> RestrictedSolve:
    """Jacobi-scaled CG on the regularised normal equations, three columns at once.

    ``P (S^T S + mu^2 L^T L) P z = P S^T b``, ``x = P z``. Mathematically the CGLS
    iteration; the normal operator is applied by a fused kernel that reads each row of
    ``S`` once per iteration (half the memory traffic of a forward plus an adjoint
    product), and ``diag(S^T S)``, ``S^T b`` and the warm start's ``S^T S x0`` come from
    one more shared pass (:meth:`RestrictedOperator.setup_products`, or fused with the
    restriction: ``products``). The data residual ``||S x - b||`` is tracked from
    ``||b||^2 - 2 x^T S^T b + x^T S^T S x`` without extra passes.

    ``state`` (a dict; not with ``volume``) receives ``products`` for a next solve of the
    same system and data warm-started from this one's result ``x`` (also stored there, as
    float64 over the basis set): ``diag(S^T S)``, ``S^T b`` and ``S^T S x``, the last kept up
    to date by the iteration itself, so that solve needs no setup pass.
    """
    t = time.perf_counter()
    if state is not None and volume is not None:
        raise ValueError("state is not kept for volume-blurred solves")
    x_warm = _warm(x0, sys_.inset)
    data = data_term(sys_, b, x_warm, products, blur=blur, volume=volume)
    if sys_._colsumsq is None:
        sys_._colsumsq = data.colsumsq
    vec = normal_vectors(sys_, b, params, data, x_warm, noise_rms)
    res = ConjugateGradient(vec, max_iter=params.max_iter).run()
    x = vec.P * res.x
    rel = vec.data_residual() / np.sqrt(np.where(vec.bb > 0, vec.bb, 1.0))
    if state is not None:
        state.update(products=(data.colsumsq, data.Stb, vec.StSx), x=x)
    return RestrictedSolve(x, res.iterations, res.stop_reason, rel, time.perf_counter() - t)


def solve_gradient_d_out(geom: TomoGeometry, d_out: np.ndarray, hull: np.ndarray, *,
                         params: TomoParams = TomoParams(), x0: np.ndarray | None = None,
                         noise_rms: float | None = None) -> tuple[np.ndarray, SolveInfo]:
    """:func:`solve_gradient` from exit directions (exact ones from a ray tracer).

    Parameters
    ----------
    d_out : ndarray, shape (C, h, w, 3)
        Unit exit directions (world).
    """
    rhs = rhs_from_d_out(geom, d_out, n_ambient=params.n_ambient)
    return solve_gradient(geom, rhs, hull, params=params, x0=x0, noise_rms=noise_rms)
