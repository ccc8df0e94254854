"""Parameters of the deflection stage and the rules read off them.

:class:`FlowParams` (one frozen dataclass; field names = the kernels' keyword names),
:data:`METHODS`, when the finest LK level is solved per flow cell
(:func:`uses_cell_solve`) and the LK window a reconstruction voxel asks for
(:func:`window_for_voxel`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from schlieren.pipeline.params import param

__all__ = ["METHODS", "FlowParams", "CELL_SOLVE_MIN_CELLS", "uses_cell_solve", "window_for_voxel"]


METHODS = ("lk", "hs", "dis", "correlation")


@dataclass(frozen=True)
class FlowParams:
    """Parameters of the deflection stage (field names = keyword names of the kernels).

    Attributes
    ----------
    method : {"lk", "hs", "dis", "correlation"}
        Flow method (paper sec. 4 uses Lucas-Kanade).
    window : int
        LK integration window edge (full-resolution pixels, odd).
    window_type : {"box", "gaussian"}
        LK window weights: uniform box of size ``window`` or a Gaussian with
        sigma = ``window / 4`` truncated at the same size.
    levels : int
        Pyramid levels (1 = full resolution only). Each level halves the image.
    iterations : int
        Warping iterations on each coarser pyramid level (LK and HS).
    fine_iterations : int
        Warping iterations on the full-resolution level (LK and HS). Each LK step
        re-linearises every pixel around its own warp, so with a converged coarse level
        one full-resolution step reaches the accuracy of several (and costs the most); on
        the buoyant-plume phantom a second one even raised the error (0.015 -> 0.018 px).
    presmooth : float
        Gaussian sigma (pixels) applied to both images before the flow; 0 disables.
    regularisation : float
        LK Tikhonov weight ``lambda = regularisation * mean(trace T) / 2`` added to the
        structure tensor ``T``: pulls the flow of textureless windows towards zero.
    gradient : {"frame", "symmetric", "reference"}
        LK image gradient ``g``: the frame's (Scharr; structure tensor filtered once per
        level), the mean of the frame's and the warped reference's, or the warped
        reference's alone (exact B-spline derivative at ``q + d_q``; structure tensor
        re-filtered every iteration). Sensor noise in ``g`` biases LK towards zero
        (errors in variables: ``T`` gains the noise energy); a reference averaged over
        many frames has almost none.
    alpha : float
        Horn-Schunck smoothness weight (in units of the normalised image gradient).
    inner_iterations : int
        Horn-Schunck Jacobi iterations per warp.
    dis_preset : {"ultrafast", "fast", "medium"}
        OpenCV DIS preset.
    corr_window : int
        Cross-correlation interrogation window edge (pixels, even).
    corr_step : int
        Spacing of the interrogation windows (pixels); 16 with 32-pixel windows is the
        classic 50 % overlap.
    corr_taper : bool
        Hann-taper the interrogation windows (reduces edge effects; the classic top-hat
        window is ``False``).
    outlier_threshold : float
        Normalised median test threshold (Westerweel & Scarano 2005), applied on the
        flow grid (see :func:`deflection_stage`); 0 disables.
    outlier_epsilon : float
        Noise floor of the normalised median test, pixels.
    smoothing_sigma : float
        Gaussian smoothing of the flow, in full-resolution pixels (applied on the flow
        grid as ``smoothing_sigma / factor``); 0 disables.
    adaptive_sigma : float
        Structure-adaptive smoothing (see :func:`deflection_stage`): the larger Gaussian
        sigma, full-resolution pixels, used where the flow is smooth; 0 disables (the
        default: on the realistic family it cost 1.2 dB at 640x480 and its lower flow
        noise made the tomography weight chosen from the noise less reliable; the
        former default 9 px suits strong, smooth flows).
    adaptive_threshold : float
        Deviation between the large- and the ``smoothing_sigma``-smoothed flow, in units
        of its lower quartile over the image (a robust noise scale), at which the large
        scale is ``1 / e``-weighted.
    texture_correction : bool
        LK only, in :func:`deflection_stage`: remove the first-order bias of the
        texture-weighted window average where the deflection varies inside the window
        (see :func:`deflection_stage`).
    factor : int
        Area-downsampling factor to the flow grid (rows = H // factor, cols = W // factor);
        with ``auto_factor`` (the default) the largest factor a run may take.
    auto_factor : bool
        In a run: the flow grid's factor is the largest up to ``factor`` that leaves at least
        :data:`~schlieren.pipeline.tomography.binning.MIN_CELLS_PER_VOXEL` (1) flow cell per
        voxel edge at the volume (:func:`~schlieren.pipeline.tomography.binning.
        auto_flow_factor`: one sample per edge is the Nyquist rate of the linear basis).
        Rigs whose voxels span few pixels then get a finer flow grid: the realistic family
        (0.7-0.9 cells per voxel at factor 3, 2.0-2.6 pixels per voxel) takes 2, the paper's
        scale (2.7 cells at 3) keeps 3. Measured on the family (whole box / in plume, factor 3
        -> auto): tune plume1 16 cameras 43.43 / 28.72 -> 44.12 / 29.32, 8 cameras 41.77 /
        27.00 -> 42.48 / 27.61; see docs/realistic.md for every case. False: ``factor`` as
        given. The run logs and stores the factor it took (``run.flow_factor``).
    invalid_check : bool
        In :func:`deflection_stage`: find pixels that cannot carry a deflection
        (:func:`invalid_pixels`: non-finite, clipped black/white runs, textureless), give
        them zero weight in the flow (LK, HS) and return NaN on the flow-grid cells they
        dominate, instead of garbage that spreads over the window.
    texture_threshold : float
        A pixel is textureless where the local standard deviation of the image (7x7) is
        below this fraction of its median over the image.
    window_per_voxel : float
        When > 0, the pipeline sets each camera's LK window (and the support of its
        invalid-pixel check) to this many times the reconstruction voxel's footprint in
        that camera's pixels (:func:`window_for_voxel`: odd, 5 to 25 px), overriding
        ``window``: the flow then resolves what the voxels can hold, at any image size and
        voxel. Chosen on the realistic family's tune cases: 9 px at 640x480 and 11 px at
        960x720 (2.0 and 2.6 px voxels) beat 13 and 17 px; at the paper's 9 px voxels it
        gives 25 px. 0 uses ``window``.
    ici_gamma : float
        LK only (frame gradient): > 0 chooses the window per pixel by the intersection
        of confidence intervals (:func:`_lk_ici`), among odd windows from
        ``ici_min_window`` to ``window`` growing by about 1.4x; the interval half-width
        is ``ici_gamma`` predicted standard deviations (from the measured image noise).
        0 uses ``window`` everywhere. The texture correction is not applied to ICI flow.
    ici_min_window : int
        Smallest window of the ICI ladder, pixels.
    cell_solve : {"auto", "on", "off"}
        LK (frame gradient, no ICI), ``factor`` > 1, in :func:`deflection_stage`: solve
        the full-resolution level once per flow cell (window sums over the cell's pixels,
        :func:`_lk_cells`) instead of at every pixel and then averaging the cell: LK at
        the cell's centre with the window linear inside each cell, at a fraction of the
        cost (the finest level's window filtering was most of the stage; at paper scale
        deflection tasks 21 % faster, flow error in the plume 3 % lower, the phantom
        -0.07 dB). ``auto``: where the window spans at least
        :data:`CELL_SOLVE_MIN_CELLS` cells (``window >= 5 factor``: paper-scale images),
        where the cell steps are fine against the window; ``on`` / ``off``: always / never.
    """

    method: str = param("lk", unit="", choices=METHODS)
    window: int = param(17, unit="px", ge=3, le=255, odd=True)
    window_type: str = param("gaussian", choices=("box", "gaussian"))
    levels: int = param(3, unit="1", ge=1, le=8)
    iterations: int = param(2, unit="1", ge=1, le=50)
    fine_iterations: int = param(1, unit="1", ge=1, le=50)
    presmooth: float = param(0.6, unit="px", ge=0, le=20)
    regularisation: float = param(1e-3, unit="1", ge=0, le=1e3)
    gradient: str = param("frame", choices=("frame", "symmetric", "reference"))
    alpha: float = param(0.3, unit="1", gt=0, le=1e3)
    inner_iterations: int = param(30, unit="1", ge=1, le=1000)
    dis_preset: str = param("medium", choices=("ultrafast", "fast", "medium"))
    corr_window: int = param(32, unit="px", ge=8, le=512, even=True)
    corr_step: int = param(16, unit="px", ge=1, le=512)
    corr_taper: bool = param(False)
    outlier_threshold: float = param(3.0, unit="1", ge=0, le=100)
    outlier_epsilon: float = param(0.01, unit="px", ge=0, le=10)
    smoothing_sigma: float = param(0.5, unit="px", ge=0, le=100)
    adaptive_sigma: float = param(0.0, unit="px", ge=0, le=200)
    adaptive_threshold: float = param(3.0, unit="1", gt=0, le=100)
    texture_correction: bool = param(True)
    factor: int = param(3, unit="px per flow cell", ge=1, le=32)
    auto_factor: bool = param(True)
    invalid_check: bool = param(True)
    texture_threshold: float = param(0.1, unit="1", ge=0, le=1)
    window_per_voxel: float = param(3.8, unit="1", ge=0, le=50)
    ici_gamma: float = param(0.0, unit="1", ge=0, le=10)
    ici_min_window: int = param(5, unit="px", ge=3, le=255, odd=True)
    cell_solve: str = param("auto", choices=("auto", "on", "off"))

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"FlowParams.method must be one of {METHODS}, got {self.method!r}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"FlowParams.window must be odd and >= 3, got {self.window}")
        if self.levels < 1 or self.iterations < 1 or self.fine_iterations < 1:
            raise ValueError("FlowParams.levels, iterations and fine_iterations must be >= 1")
        if self.gradient not in ("frame", "symmetric", "reference"):
            raise ValueError("FlowParams.gradient must be 'frame', 'symmetric' or 'reference', "
                             f"got {self.gradient!r}")
        if self.factor < 1:
            raise ValueError(f"FlowParams.factor must be >= 1, got {self.factor}")

    def reference_kwargs(self) -> dict:
        """Keyword arguments of :func:`prepare_reference` taken from these parameters."""
        return {"presmooth": self.presmooth, "levels": self.levels}

    def field_kwargs(self) -> dict:
        """Keyword arguments of :func:`deflection_field` taken from these parameters."""
        d = asdict(self)
        for k in ("outlier_threshold", "outlier_epsilon", "smoothing_sigma", "adaptive_sigma",
                  "adaptive_threshold", "texture_correction", "factor", "auto_factor", "invalid_check",
                  "texture_threshold", "window_per_voxel", "cell_solve"):
            d.pop(k)
        return d


#: ``FlowParams.cell_solve = "auto"`` solves per cell when the LK window spans at least this
#: many flow cells (``window >= CELL_SOLVE_MIN_CELLS * factor``).
CELL_SOLVE_MIN_CELLS = 5


def uses_cell_solve(params: FlowParams) -> bool:
    """Whether :func:`deflection_stage` solves the finest LK level per flow cell (:func:`_lk_cells`)."""
    if params.cell_solve == "off" or params.method != "lk" or params.gradient != "frame" \
            or params.ici_gamma > 0 or params.factor <= 1:
        return False
    return params.cell_solve == "on" or params.window >= CELL_SOLVE_MIN_CELLS * params.factor


def window_for_voxel(px_per_voxel: float, window_per_voxel: float, *, smallest: int = 5,
                     largest: int = 25) -> int:
    """The odd LK window (pixels) spanning ``window_per_voxel`` voxel footprints."""
    w = int(round(window_per_voxel * px_per_voxel))
    w = min(max(w, smallest), largest)
    return w if w % 2 else w + 1
