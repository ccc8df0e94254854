"""The regularisation weight of the per-frame gradient solve (beyond the paper).

Morozov's discrepancy principle (:func:`choose_reg_weight`): the largest weight whose data
residual has fallen to the noise of the right-hand side, measured on the rays that see no
flow (:func:`rhs_noise`); :func:`rhs_snr` is the receipt of the signal the other rays carry.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.tomography.blur import MeasurementBlur
from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.solve import FrameSystem, _solve_restricted, frame_rhs, prepare_frame, valid_rays

__all__ = ["RegularisationChoice", "choose_reg_weight", "rhs_noise", "rhs_snr", "RUN_SMALLEST_WEIGHT"]

log = logging.getLogger(__name__)

#: Smallest weight the run's regularisation stage searches (``choose_reg_weight``'s
#: ``smallest``; the function's own default serves converged solves). The search solves
#: each weight to convergence, but a run's frames stop at ``tomography.max_iter`` CG
#: iterations, before fitting what a smaller weight would let in: below this weight the
#: run's volumes no longer change while the search's solves grow costly (docs/tuning.md,
#: "Tomography weight").
RUN_SMALLEST_WEIGHT = 2.0 ** -8


def rhs_noise(rhs: np.ndarray, quiet: np.ndarray) -> np.ndarray:
    """Robust RMS noise of each right-hand-side component over rays that see no flow.

    Parameters
    ----------
    rhs : ndarray, shape (C, h, w, 3)
        ``n_amb (d_out - d_in)`` of every ray (e.g. :func:`rhs_from_flows`).
    quiet : ndarray, shape (C, h, w) bool
        Rays whose true right-hand side is zero: outside every flow mask (their
        measurement is pure noise: sensor noise, compression, optical-flow error).

    Returns
    -------
    sigma : ndarray, shape (3,)
        ``1.4826 * MAD`` per world component (x, y, z); NaN where no quiet ray is finite.
    """
    b = np.asarray(rhs, dtype=np.float64).reshape(-1, 3)[np.asarray(quiet, bool).ravel()]
    b = b[np.isfinite(b).all(axis=1)]
    if b.shape[0] < 10:
        return np.full(3, np.nan)
    return 1.4826 * np.median(np.abs(b - np.median(b, axis=0)), axis=0)


def rhs_snr(rhs: np.ndarray, seen: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Signal-to-noise ratio of the rays that see the flow, per world component.

    ``sqrt(max(mean(b^2) - sigma^2, 0)) / sigma`` over the finite rays of ``seen`` (e.g.
    inside a flow mask), ``sigma`` from :func:`rhs_noise`: the RMS of the signal the rays
    carry, its noise removed, in units of the noise. A receipt (the regularisation stage
    logs and records it; the values on the realistic family: docs/tuning.md, "Tomography
    weight").

    Returns
    -------
    snr : ndarray, shape (3,)
        NaN where no seen ray is finite or the noise is not positive.
    """
    b = np.asarray(rhs, dtype=np.float64).reshape(-1, 3)[np.asarray(seen, bool).ravel()]
    b = b[np.isfinite(b).all(axis=1)]
    sigma = np.asarray(noise, dtype=np.float64).reshape(3)
    if b.shape[0] == 0:
        return np.full(3, np.nan)
    power = np.maximum(np.mean(b * b, axis=0) - sigma * sigma, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma > 0, np.sqrt(power) / sigma, np.nan)


@dataclass(frozen=True)
class RegularisationChoice:
    """Receipt of :func:`choose_reg_weight`.

    Attributes
    ----------
    reg_weight : float
        The chosen weight (the same units as :attr:`TomoParams.reg_weight`).
    target : float
        Discrepancy target ``tau^2 m sum_c sigma_c^2`` of the summed squared data residual.
    path : tuple of (float, float)
        ``(reg_weight, sum_c ||S x - b_c||^2 / target)`` of every weight tried, largest first.
    """

    reg_weight: float
    target: float
    path: tuple


def choose_reg_weight(geom: TomoGeometry, rhs_or_flows: np.ndarray, hull: np.ndarray, noise: np.ndarray, *,
                      params: TomoParams = TomoParams(), tau: float | None = None, largest: float = 4.0,
                      smallest: float = 1e-4, factor: float = 2.0, plateau: float = 0.02,
                      start: float = 0.125, blur: MeasurementBlur | None = None) -> RegularisationChoice:
    """Choose the regularisation weight of one frame by Morozov's discrepancy principle.

    The weights tried lie on the grid ``largest, largest / factor, ...`` down to
    ``smallest``; the result is the largest weight whose data residual has fallen to the
    noise: ``sum_c ||S x_c - b_c||^2 <= tau^2 m sum_c sigma_c^2`` (``m`` rays, ``sigma_c``
    the noise of component ``c``, e.g. from :func:`rhs_noise`), interpolated geometrically
    between the two grid weights around the crossing. Less regularisation would fit the
    noise; more would leave signal in the residual. The residual grows with the weight, so
    the search brackets the crossing from the grid weight nearest ``start``: upwards while
    the residual is below the target, downwards while it is above (each solve warm-started
    from the last, converged to ``tol`` = 1e-3, and started from the last one's ``S^T S x``
    without a setup pass). Where the residual crosses the target, that is the bracket a
    search down from ``largest`` finds, in fewer solves: ``start`` sits near the weights
    real data choose, and a cold solve at a large weight is the slowest (docs/tuning.md,
    "Tomography weight").

    If, going down, the residual levels off above the target (model error dominates, or the
    noise outside the masks understates the misfit inside), so that dividing the weight by
    ``factor`` lowers it by less than ``plateau`` (2 %), the search stops and returns the
    larger weight of that step (only steps below ``start`` are looked at; a residual that
    levels off above it is as level below): less regularisation no longer buys a better fit
    (e.g. noise-free renders, whose target lies far below the reachable misfit; docs/tuning.md,
    "Tomography weight"). ``smallest`` bounds the search.

    Parameters
    ----------
    geom, rhs_or_flows, hull :
        As for :func:`solve_gradient`.
    noise : ndarray, shape (3,)
        RMS noise of each right-hand-side component (dimensionless).
    params : TomoParams
        All but ``reg_weight`` / ``tol`` / ``max_iter`` are used.
    tau : float, optional
        Safety factor of the discrepancy principle (1 = the noise level exactly);
        default ``params.reg_tau``.
    largest, smallest, factor : float
        The grid of weights: ``largest``, ``largest / factor``, ... down to ``smallest``.
    plateau : float
        Stop when a step down lowers the residual by less than this fraction (see above); 0 never.
    start : float
        Where the search starts (snapped to the grid); only its cost depends on it.
    blur : MeasurementBlur, optional
        The data operator's image averaging, as for :func:`solve_gradient`.
        (The weight is chosen with the image-space model also for volume solves: the
        volume model's misfit levels off above the discrepancy target.)

    Returns
    -------
    RegularisationChoice
    """
    tau = float(params.reg_tau if tau is None else tau)
    # The smoothness weight is chosen without the curl term: with it, the discrepancy
    # principle trades smoothness for integrability and chooses far too small a weight
    # (docs/tuning.md, "Curl coupling"); the curl term is then added on top.
    params = dataclasses.replace(params, curl_weight=0.0)
    noise = _checked_search(noise, largest, smallest, factor, start)
    data = np.asarray(rhs_or_flows)
    rows = valid_rays(data)
    sys_ = prepare_frame(geom, hull, dilation=params.hull_dilation, rows=rows, prior=params.prior)
    op = sys_.op
    if op.n == 0 or op.m == 0:
        return RegularisationChoice(reg_weight=float(params.reg_weight), target=0.0, path=())
    b = frame_rhs(geom, data, op.rows, n_ambient=params.n_ambient)
    target = tau ** 2 * op.m * float(np.sum(noise ** 2))
    search = _WeightSearch(sys_, b, params, blur, target, largest, factor)
    last = int(np.floor(np.log(largest / smallest) / np.log(factor) + 1e-9))  # grid index of the smallest
    j = int(np.clip(np.round(np.log(largest / start) / np.log(factor)), 0, last))
    return search.result(search.bracket(j, last, plateau))


def _checked_search(noise, largest: float, smallest: float, factor: float, start: float) -> np.ndarray:
    """:func:`choose_reg_weight`'s noise (3,) and grid, checked."""
    noise = np.asarray(noise, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(noise)) or not noise.any():
        raise ValueError(f"the noise estimate must be finite and positive, got {noise}")
    if not (largest > 0 and factor > 1 and 0 < smallest <= largest and start > 0):
        raise ValueError(f"need largest >= smallest > 0, factor > 1 and start > 0, got largest {largest}, "
                         f"smallest {smallest}, factor {factor}, start {start}")
    return noise


class _WeightSearch:
    """:func:`choose_reg_weight`'s search: the grid ``largest / factor^j`` of weights, the
    converged solve at each weight tried (warm-started from the last) and its residual ratio
    to the discrepancy target."""

    def __init__(self, sys_: FrameSystem, b: np.ndarray, params: TomoParams, blur: MeasurementBlur | None,
                 target: float, largest: float, factor: float):
        self.sys_, self.b, self.params, self.blur = sys_, b, params, blur
        self.bb = float(np.einsum("ij,ij->", b, b))
        self.target, self.largest, self.factor = target, largest, factor
        self.ratios: dict[int, float] = {}
        self.carry: dict = {}

    def weight(self, j: int) -> float:
        return float(self.largest / self.factor ** j)

    def ratio(self, j: int) -> float:
        """Solve at grid weight ``j``; ``sum_c ||S x_c - b_c||^2 / target``."""
        sys_, b, carry = self.sys_, self.b, self.carry
        p = dataclasses.replace(self.params, reg_weight=self.weight(j), max_iter=200, tol=1e-3, discrepancy=0.0)
        x0 = None
        if carry:  # the previous solve's result, exactly (float64), and its S^T S x: no setup pass
            x0 = np.zeros(sys_.inset.shape + (3,))
            x0[sys_.inset] = carry["x"]
        _x, _it, _reason, rel, _t = _solve_restricted(sys_, b, p, x0, None, products=carry.get("products"),
                                                      blur=self.blur, state=carry)
        res2 = (float(np.sum((rel * np.sqrt(np.maximum(np.einsum("ij,ij->j", b, b), 1e-300))) ** 2))
                if self.bb > 0 else 0.0)
        self.ratios[j] = res2 / self.target if self.target > 0 else 0.0
        return self.ratios[j]

    def crossing(self, j: int) -> float:
        """The weight where the residual crosses the target, interpolated geometrically
        between grid weight ``j - 1`` (above the target) and ``j`` (at or below it)."""
        r0, r1 = self.ratios[j - 1], self.ratios[j]
        t = np.log(r0) / (np.log(r0) - np.log(r1)) if r0 > 0 and r1 > 0 and r0 != r1 else 1.0
        mu0, mu1 = self.weight(j - 1), self.weight(j)
        return float(np.exp(np.log(mu0) + np.clip(t, 0.0, 1.0) * (np.log(mu1) - np.log(mu0))))

    def bracket(self, j: int, last: int, plateau: float) -> float:
        """The chosen weight: from grid weight ``j``, upwards while the residual is below the
        target, downwards while it is above (down to grid weight ``last``, or to a plateau)."""
        ratios, weight = self.ratios, self.weight
        if self.ratio(j) <= 1.0:  # upwards to the first weight above the target
            while j > 0:
                if self.ratio(j - 1) > 1.0:
                    return self.crossing(j)
                j -= 1
            return weight(0)
        while j < last:  # downwards to the first weight at or below the target
            if self.ratio(j + 1) <= 1.0:
                return self.crossing(j + 1)
            j += 1
            if ratios[j] > (1.0 - plateau) * ratios[j - 1]:
                log.info("regularisation: the data residual levels off %.3gx above the discrepancy target "
                         "(%.3g -> %.3g from weight %.3g to %.3g); taking %.3g", ratios[j], ratios[j - 1],
                         ratios[j], weight(j - 1), weight(j), weight(j - 1))
                return weight(j - 1)
        return weight(j)

    def result(self, mu: float) -> RegularisationChoice:
        path = tuple((self.weight(j), self.ratios[j]) for j in sorted(self.ratios))
        return RegularisationChoice(reg_weight=float(mu), target=self.target, path=path)
