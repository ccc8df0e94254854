"""Parameters of the tomography stage (one frozen dataclass; field names = kernel keywords)."""

from __future__ import annotations

from dataclasses import dataclass

from schlieren.pipeline.params import param

__all__ = ["TomoParams", "RefractivityParams"]


@dataclass(frozen=True)
class TomoParams:
    """Gradient-field tomography (paper sec. 5, eqs. 4-6).

    Attributes
    ----------
    step : float
        Ray-marching step for the line integrals of the basis functions, in voxels
        (midpoint rule). Part of the geometry content hash.
    prune : float
        Entries of a projection row below this fraction of the row's largest are dropped
        and the rest scaled so the row's sum (the ray's length through the basis) is
        kept (:func:`schlieren.pipeline.tomography.projection.prune_rows`): the nodes a ray
        only grazes. Part of the geometry content hash; 0 keeps every entry. At 0.05 the
        paper-scale session loses 17 % of its entries (1 % of the row sums) and its warm
        solves take 13-15 % less time (1.87 / 1.99 / 2.21 -> 1.63 / 1.70 / 1.88 s,
        single-threaded, the same 19 iterations); the realistic family's tune cases are
        unchanged to the reported digit (16-camera H.264 +0.01 dB). 0.1 cut another
        4-6 % of the time and lost 0.01-0.02 dB on every lossless tune case.
    ray_binning : int
        Flow cells per tomography ray along each image axis
        (:mod:`schlieren.pipeline.tomography.binning`): 1 = a ray per flow cell (the
        paper); ``b`` = one ray through the centre of each ``b x b`` block of cells,
        measuring the block's mean flow; 0 (default) chooses the largest ``b`` that leaves
        at least 1.25 rays per voxel edge at the box centre, so only flow grids finer than
        the voxels are binned (paper scale, 16 cameras at 1440x1080 with 2.5 mm voxels:
        2.7 cells per voxel edge, ``b = 2``; every realistic-family rig and Table 1 keep
        1). There it quarters the projection and the solve: paper-scale frame 1.18 ->
        0.56 s (benchmarks/tomography.py --speed), whole session 5.07 -> 3.46 s per time
        step on 2 workers, its phantom 51.92 -> 51.84 dB (the ray through a block's centre
        is not quite the mean of its cells' rays; docs/design.md). The chosen value is in
        the geometry receipt.
    hull_dilation : int
        Basis functions kept per frame: the hull dilated by this many voxels (3x3x3
        structuring element). 1 keeps every basis function whose support (radius one
        voxel) touches a hull voxel, as in the paper.
    prior : {"first-differences", "second-differences"}
        Smoothness term of the solve: the squared first differences of each gradient
        component between neighbouring basis functions (``L^T L``, the set's 7-point
        Laplacian; the paper's choice) or the squared Laplacian (``(L^T L)^2``, a
        curvature penalty that lets smooth ramps through; the default). On the realistic
        family, each with its discrepancy-chosen weight, second differences gave +0.29 to
        +0.35 dB on the 16-camera cases and 0 to +0.1 dB on the 8-camera ones, never less
        (means: tune +0.15 / +0.18, report +0.11 / +0.14 dB whole box / in plume).
    reg_weight : float
        Weight of the smoothness term (``prior``) restricted to the basis set,
        relative to the mean of ``diag(S^T S)`` (dimensionless; 0 = plain least squares,
        which semi-converges with noisy data). Used as given with ``reg_choice: fixed``;
        with ``discrepancy`` it is only the fallback when no noise can be measured.
    reg_choice : {"discrepancy", "fixed"}
        How the pipeline sets the weight: ``discrepancy`` measures the noise of the
        right-hand side on the rays outside every flow mask and picks, on the middle
        frame, the weight whose data residual matches it (Morozov's discrepancy
        principle, :func:`~schlieren.pipeline.tomography.reg_choice.choose_reg_weight`); the
        chosen weight is stored (``reg_weight`` array) and used for every frame.
        ``fixed`` uses ``reg_weight``.
    reg_tau : float
        Safety factor of the discrepancy principle: the residual target is ``reg_tau``
        times the measured noise level. Below 1 because the flow noise is spatially
        correlated (the LK window) and the solution fits part of it: on the realistic
        family's tune cases the residual at the error-minimising weight was 0.3-0.6 of the
        measured level, and 1 chose weights 5-10x too large (1.7 where 0.2 was best).
    curl_weight : float
        Weight of the integrability term ``||C x||^2`` (:func:`~schlieren.pipeline.
        tomography.regularisers.curl_normal`, the discrete curl of the gradient field), relative to
        the mean of ``diag(S^T S)`` like ``reg_weight``. A refractive-index gradient is
        curl-free; the limited views leave each component a large null space, and the
        coupling removes the part of it that is not a gradient. 0 solves the three
        components independently (the paper); > 0 couples them in one joint CG. The
        smoothness weight is chosen without it (``reg_choice``). On the realistic family
        3 gave +0.26 to +0.35 dB on the 8-camera PNG cases and +0.04 to +0.09 dB on the
        others, never less (tune: 1 and 10 no better).
    model_flow_window : bool
        Model the flow's image averaging in the data term (pipeline runs from optical flow):
        a measured deflection is the LK window's mean of the per-pixel deflections, smoothed
        and block-averaged to the flow grid, not the deflection of the ray through the cell
        centre; the solve fits ``W S x`` with ``W`` that averaging over neighbouring cells
        (:class:`~schlieren.pipeline.tomography.blur.MeasurementBlur`, its width from
        :func:`~schlieren.pipeline.flow.measurement_sigma`). Beyond the paper. On the
        realistic family: 16 cameras +1.4 to +1.6 dB whole box, +2.1 to +2.3 in plume;
        8-camera PNG +0.3 to +0.5 / +0.7 to +1.0; H.264 -0.05 to +0.03 / +0.1 to +0.2. On the
        smooth phantoms it loses (Table 1's optical-flow rows -0.15 to -1.3 dB, peak ratio 1.07;
        the tests' 4-camera blob -1.2 dB): the family, whose truth keeps its structure at the
        voxel, chose the default. The widths used are stored (``flow_window``).
    flow_window_space : {"volume", "image"}
        Where ``model_flow_window`` applies the averaging. ``image``: ``W S x`` with ``W`` each
        camera's Gaussian over its flow cells (exact for the cell grid, but one more pass over
        ``S`` and two image filters per iteration). ``volume`` (default): ``S G x`` with ``G``
        one Gaussian over the basis coefficients of the width the cameras' averaging has at
        the volume (:class:`~schlieren.pipeline.tomography.blur.VolumeBlur`,
        :func:`~schlieren.pipeline.tomography.blur.volume_sigma`; exact for parallel rays):
        the point-ray model's single fused pass plus two small volume filters. The
        smoothness weight is chosen with the image model either way (``reg_choice``: its
        misfit reaches the noise, the volume model's stays above it on 16 cameras). On the
        realistic family's tune cases ``volume`` gave +0.23 / +0.06 / +0.05 dB over ``image``
        (16 cameras / 8 / 8 H.264) at the same weight, at 0.6-0.8x its solve time.
    flow_window_scale : float
        Factor on the modelled flow averaging (``model_flow_window``): the stored
        ``flow_window`` widths are :func:`~schlieren.pipeline.flow.measurement_sigma` times
        this. Below 1 the solve deconvolves less than the formula's width, which is wider
        than the flow's real averaging (against the truth's deflections the flows are best
        described by a Gaussian of about 1.5 px where the formula gives 2.1-2.4 px). Chosen
        on the realistic family's tune cases (plume seed 1, frame 1 re-solved from the run's
        flows, mean in plume over the four tune cases): 0.8 23.76 dB, **0.9** 23.79, 1 23.68,
        1.2 and 1.4 lower (16 cameras: 0.9 +0.45 dB over 1, 8 cameras -0.08, H.264 +0.03 to
        +0.05); on the report cases 16 cameras +0.24 to +0.60, 8 cameras -0.05
        (``benchmarks/results/realistic_window_scale_rebased.md``). Table 1's optical-flow
        rows gain 0.4-1.2 dB at 0.9. Before the family was re-based on consistent renders its
        8-camera cases preferred 1.4 (the scale sharpened back what the old tracer smoothed;
        docs/realistic.md, "The flow-window scale").
    max_iter : int
        Iteration cap of the fused conjugate-gradient (CGLS-equivalent) solver.
    tol : float
        Stop when the normal-equation residual of every component has dropped by this
        factor relative to its initial value.
    discrepancy : float
        If > 0, also stop when the data residual of every component is below
        ``discrepancy * noise_rms * sqrt(m)`` (Morozov's discrepancy principle) with
        ``noise_rms`` passed to the solver; 0 disables it.
    n_ambient : float
        Refractive index of the surrounding air; the right-hand side is
        ``n_ambient * (d_out - d_in)`` (eq. 3 with ``d = n * unit direction``).
    """

    step: float = param(0.25, unit="voxels", gt=0, le=1)
    prune: float = param(0.05, unit="1", ge=0, lt=1)
    ray_binning: int = param(0, unit="flow cells", ge=0, le=16)
    hull_dilation: int = param(1, unit="voxels", ge=0, le=10)
    prior: str = param("second-differences", choices=("first-differences", "second-differences"))
    reg_weight: float = param(0.1, unit="1", ge=0, le=1e6)
    reg_choice: str = param("discrepancy", choices=("discrepancy", "fixed"))
    reg_tau: float = param(0.7, unit="1", gt=0, le=100)
    curl_weight: float = param(3.0, unit="1", ge=0, le=1e6)
    model_flow_window: bool = param(True)
    flow_window_space: str = param("volume", choices=("volume", "image"))
    flow_window_scale: float = param(0.9, unit="1", gt=0, le=10)
    max_iter: int = param(25, unit="1", ge=1, le=10000)
    tol: float = param(5e-3, unit="1", gt=0, lt=1)
    discrepancy: float = param(0.0, unit="1", ge=0, le=100)
    n_ambient: float = param(1.00029, unit="1", ge=1, le=3, note="Set from the session's medium.n_ambient at run time.")


@dataclass(frozen=True)
class RefractivityParams:
    """Direct refractivity reconstruction (beyond the paper): solve for ``r = n - 1``.

    Attributes
    ----------
    reg_weight : float
        First-difference smoothness of ``r`` relative to the mean diagonal of the data
        normal matrix (dimensionless).
    max_iter : int
        CGLS iteration cap.
    tol : float
        Relative normal-equation residual at which to stop.
    n_ambient : float
        Refractive index of the surrounding air (right-hand side scaling).
    """

    reg_weight: float = param(0.02, unit="1", ge=0, le=1e6)
    max_iter: int = param(150, unit="1", ge=1, le=100000)
    tol: float = param(1e-4, unit="1", gt=0, lt=1)
    n_ambient: float = param(1.00029, unit="1", ge=1, le=3, note="Set from the session's medium.n_ambient at run time.")
