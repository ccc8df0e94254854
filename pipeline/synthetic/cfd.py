"""Buoyant plumes and hot jets from a real CFD library (PhiFlow), for realistic benchmarks.

The project's own :mod:`~schlieren.pipeline.synthetic.smoke` phantom is simulated on a
coarse grid and upsampled with cubic B-splines: smooth, with structure several voxels
wide. Real flows have structure down to the reconstruction voxel. This module runs an
incompressible Boussinesq simulation with PhiFlow (Holl et al., ``phiflow`` on PyPI; an
optional dependency, extra ``bench``) *on the reconstruction grid itself*, so the truth
keeps every scale the grid can hold and nothing is smoothed by resampling:

1. MacCormack advection of the excess temperature (sharp fronts), semi-Lagrangian
   advection of the staggered velocity;
2. a hot source at the floor (``kind="plume"``: a disk of hot air with a slow inflow; a
   ``"jet"``: a narrow, fast, hot inflow) whose temperature and inflow are modulated
   by a smooth random field that drifts in time (it breaks the symmetry, so the plume
   meanders, rolls up and breaks into fine structure);
3. buoyancy ``g (T - T_amb) / T_amb`` (Boussinesq) on the vertical velocity;
4. pressure projection by conjugate gradients (walls at the sides and the floor, an
   open top).

The result is the excess temperature at fixed time knots; :func:`cfd_phantom` turns it
into a :class:`~schlieren.pipeline.synthetic.phantoms.Phantom` (refractivity by the
project's Gladstone-Dale model). Pure computation: no file I/O (the benchmark caches the
knots through :mod:`schlieren.storage`).

PhiFlow 3.4 with numpy 2.x casts the flat indices of its sparse-matrix tracer back to
int32, which overflows for grids above about 46k cells (the dense index space is the
square of the cell count); :func:`_patch_phiml_int64` keeps them int64.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.synthetic.phantoms import Phantom, refractivity_from_temperature

__all__ = ["CFDParams", "CFDResult", "simulate_cfd", "upsample_cfd", "cfd_phantom", "cfd_available", "KINDS"]

log = logging.getLogger(__name__)

G = 9.81
KINDS = ("plume", "jet")


@dataclass(frozen=True)
class CFDParams:
    """Parameters of :func:`simulate_cfd` (SI units).

    Attributes
    ----------
    kind : {"plume", "jet"}
        A buoyant plume above a hot disk, or a hot jet from a narrow nozzle.
    excess_temperature : float
        Kelvin above ambient at the source core. Sets the deflection strength: 25-60 K
        gives the 0.2-0.5 px peak deflections of a real BOS capture at 640-960 px.
    source_radius : float
        Radius of the source disk / nozzle (metres).
    source_height : float
        Height of the source centre above the floor of the grid (metres).
    inflow_velocity : float
        Upward speed imposed inside the source (m/s).
    dt : float
        Simulation time step and knot spacing (seconds).
    spinup : float
        Seconds simulated before the first knot.
    perturbation : float
        Relative amplitude of the random modulation of the source temperature and inflow.
    perturbation_scale : float
        Correlation length of that modulation (metres).
    perturbation_time : float
        Correlation time of that modulation (seconds).
    swirl : float
        Random horizontal inflow at the source, relative to ``inflow_velocity`` (or to
        0.2 m/s for a plume without inflow).
    cg_tolerance : float
        Relative tolerance of the pressure solve.
    """

    kind: str = "plume"
    excess_temperature: float = 40.0
    source_radius: float = 0.015
    source_height: float = 0.008
    inflow_velocity: float = 0.15
    dt: float = 1.0 / 120.0
    spinup: float = 0.7
    perturbation: float = 0.4
    perturbation_scale: float = 0.008
    perturbation_time: float = 0.05
    swirl: float = 0.5
    cg_tolerance: float = 1e-3

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"CFDParams.kind must be one of {KINDS}, got {self.kind!r}")
        if not (self.excess_temperature > 0 and self.dt > 0 and self.source_radius > 0):
            raise ValueError("CFDParams: excess_temperature, dt and source_radius must be positive")


@dataclass
class CFDResult:
    """Excess temperature at the knots of a simulation.

    Attributes
    ----------
    grid : Grid
        The simulation (= truth) grid.
    knot_times : ndarray, shape (K,)
        Session seconds of the knots.
    excess : ndarray, shape (K, nz, ny, nx) float32
        Kelvin above ambient (clipped at 0).
    params : dict
        The :class:`CFDParams` used, and the seed.
    """

    grid: Grid
    knot_times: np.ndarray
    excess: np.ndarray
    params: dict


def cfd_available() -> bool:
    """Whether PhiFlow can be imported (the optional ``bench`` extra)."""
    try:
        import phi  # noqa: F401
    except ImportError:
        return False
    return True


def _patch_phiml_int64() -> None:
    """Keep PhiFlow's raveled sparse indices int64 (numpy 2.x overflow, see module notes)."""
    from phiml.backend._numpy_backend import NumPyBackend

    if getattr(NumPyBackend, "_schlieren_int64", False):
        return

    def ravel_multi_index(self, multi_index, shape, mode="undefined"):
        mode = mode if isinstance(mode, int) else {"undefined": "raise", "periodic": "wrap", "clamp": "clip"}[mode]
        idx_first = np.transpose(multi_index, (-1,) + tuple(range(self.ndims(multi_index) - 1)))
        result = np.ravel_multi_index(idx_first, shape, mode="wrap" if isinstance(mode, int) else mode)
        if float(np.prod(np.asarray(shape, dtype=np.float64))) <= np.iinfo(np.int32).max:
            result = result.astype(multi_index.dtype)
        if isinstance(mode, int):
            outside = self.any((multi_index < 0) | (multi_index >= shape), -1)
            result = self.where(outside, mode, result)
        return result

    NumPyBackend.ravel_multi_index = ravel_multi_index
    NumPyBackend._schlieren_int64 = True


class _DriftingNoise:
    """A smooth random field on the source plane that decorrelates over ``tau`` seconds.

    Ornstein-Uhlenbeck in time of Gaussian-filtered white noise in space; unit RMS.
    """

    def __init__(self, shape: tuple[int, int], sigma_cells: float, tau: float, dt: float,
                 rng: np.random.Generator, channels: int = 1):
        from scipy import ndimage

        self._nd = ndimage
        self.shape = shape
        self.sigma = max(float(sigma_cells), 0.5)
        self.a = float(np.exp(-dt / max(tau, 1e-9)))
        self.rng = rng
        self.channels = channels
        self.state = np.stack([self._fresh() for _ in range(channels)])

    def _fresh(self) -> np.ndarray:
        f = self._nd.gaussian_filter(self.rng.standard_normal(self.shape), self.sigma, mode="wrap")
        return f / max(float(f.std()), 1e-12)

    def step(self) -> np.ndarray:
        b = np.sqrt(1.0 - self.a ** 2)
        self.state = self.a * self.state + b * np.stack([self._fresh() for _ in range(self.channels)])
        return self.state


def simulate_cfd(grid: Grid, params: CFDParams = CFDParams(), *, n_knots: int, t_first: float = 0.0,
                 seed: int = 0, medium: Medium = Medium(), progress=None) -> CFDResult:
    """Run the PhiFlow simulation on ``grid`` and return ``n_knots`` samples of the excess temperature.

    Parameters
    ----------
    grid : Grid
        Simulation grid (cell = voxel; its box is the domain: walls at the sides and
        the floor, open top).
    params : CFDParams
    n_knots : int
        Samples kept, one per ``params.dt`` after ``params.spinup`` seconds.
    t_first : float
        Session time of the first sample (seconds).
    seed : int
        Seeds the source modulation.
    medium : Medium
        Ambient temperature for the buoyancy.
    progress : callable, optional
        ``progress(step, total)`` after each time step.

    Returns
    -------
    CFDResult
    """
    try:
        from phi import flow as pf
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise ImportError("the realistic benchmark needs PhiFlow: pip install 'schlieren[bench]'") from exc
    _patch_phiml_int64()
    nz, ny, nx = grid.shape
    h = float(grid.voxel_size)
    src, profile = _source_shape(grid, params)
    flow = _Boussinesq(pf, grid, params, src, g_over_T=G / medium.T_ambient)
    rng = np.random.default_rng(seed)
    noise = _DriftingNoise((ny, nx), params.perturbation_scale / h, params.perturbation_time, params.dt, rng,
                           channels=3)
    n_spin = int(round(params.spinup / params.dt))
    total = n_spin + n_knots
    knots = np.empty((n_knots, nz, ny, nx), np.float32)
    for step in range(total):
        nse = noise.step()
        target = params.excess_temperature * profile * np.clip(1.0 + params.perturbation * nse[0], 0.0, None)
        flow.step(target, nse)
        if step >= n_spin:
            knots[step - n_spin] = np.maximum(flow.temp.values.numpy("z,y,x"), 0.0)
        if progress is not None:
            progress(step + 1, total)
    kt = t_first + params.dt * np.arange(n_knots)
    meta = asdict(params)
    meta["seed"] = int(seed)
    return CFDResult(grid=grid, knot_times=kt, excess=knots, params=meta)


def _source_shape(grid: Grid, params: CFDParams) -> tuple[np.ndarray, np.ndarray]:
    """The source's occupancy (nz, ny, nx), a soft disk of cells, and its radial temperature
    profile (ny, nx), hotter in the core; on the cell centres, relative to the floor's centre."""
    nz, ny, nx = grid.shape
    h = float(grid.voxel_size)
    zc = (np.arange(nz) + 0.5) * h
    yc = (np.arange(ny) + 0.5) * h - 0.5 * ny * h
    xc = (np.arange(nx) + 0.5) * h - 0.5 * nx * h
    rr = np.hypot(yc[:, None], xc[None, :])
    radial = np.clip((params.source_radius - rr) / h + 0.5, 0.0, 1.0)          # (ny, nx), soft disk
    depth = max(params.source_radius if params.kind == "plume" else 2.0 * h, 2.0 * h)
    vertical = np.clip((depth - np.abs(zc - params.source_height)) / h + 0.5, 0.0, 1.0)  # (nz,)
    src = vertical[:, None, None] * radial[None]                                 # (nz, ny, nx)
    profile = np.exp(-(rr / max(params.source_radius, h)) ** 2)                    # core hotter
    return src, profile


class _Boussinesq:
    """The PhiFlow state (temperature, staggered velocity, pressure) on the grid's box and its
    time step: steps 1-4 of the module notes. Walls at the sides and the floor, open top."""

    def __init__(self, pf, grid: Grid, params: CFDParams, src: np.ndarray, *, g_over_T: float):
        self.pf, self.params, self.src, self.g_over_T = pf, params, src, g_over_T
        nz, ny, nx = grid.shape
        h = float(grid.voxel_size)
        self.shape = (nz, ny, nx)
        self.bounds = pf.Box(x=nx * h, y=ny * h, z=nz * h)
        self.res = dict(x=nx, y=ny, z=nz)
        vel_bc = {"x": 0, "y": 0, "z-": 0, "z+": pf.ZERO_GRADIENT}
        self.temp = pf.CenteredGrid(0, pf.ZERO_GRADIENT, bounds=self.bounds, **self.res)
        self.vel = pf.StaggeredGrid(0, vel_bc, bounds=self.bounds, **self.res)
        self.src_grid = self.as_grid(src)
        self.pressure = None
        self.swirl_speed = params.swirl * (params.inflow_velocity if params.inflow_velocity > 0 else 0.2)

    def as_grid(self, a: np.ndarray):
        # PhiFlow's spatial dims are ordered x, y, z; our arrays are (z, y, x)
        pf, math = self.pf, self.pf.math
        return pf.CenteredGrid(math.tensor(np.ascontiguousarray(np.transpose(a, (2, 1, 0)), dtype=np.float32),
                                           math.spatial("x,y,z")), pf.ZERO_GRADIENT, bounds=self.bounds, **self.res)

    def step(self, target: np.ndarray, nse: np.ndarray) -> None:
        """Advance one ``params.dt``: the source relaxes towards ``target`` (ny, nx) kelvin, and its
        inflow is modulated by the noise channels ``nse`` (3, ny, nx)."""
        pf, math, params = self.pf, self.pf.math, self.params
        nz, ny, nx = self.shape
        src, src_grid, swirl_speed = self.src, self.src_grid, self.swirl_speed
        temp, vel = self.temp, self.vel
        temp = pf.advect.mac_cormack(temp, vel, params.dt)
        # relax the source region towards its (fluctuating) target temperature
        temp = temp + src_grid * (self.as_grid(np.broadcast_to(target, (nz, ny, nx))) - temp) * 0.5
        w = params.inflow_velocity * (1.0 + params.perturbation * nse[0])
        inflow = np.stack([swirl_speed * nse[1], swirl_speed * nse[2], np.broadcast_to(w, (ny, nx))], axis=0)
        forcing = temp * pf.vec(x=0.0, y=0.0, z=self.g_over_T)
        vel = pf.advect.semi_lagrangian(vel, vel, params.dt) + pf.resample(forcing, to=vel) * params.dt
        if params.inflow_velocity > 0 or params.swirl > 0:
            # impose the inflow inside the source: v <- v + s (v_in - v)
            vin = pf.CenteredGrid(math.tensor(np.ascontiguousarray(
                (src[None] * inflow[:, None]).transpose(3, 2, 1, 0), dtype=np.float32),
                math.spatial("x,y,z"), math.channel(vector="x,y,z")), 0, bounds=self.bounds, **self.res)
            s_vel = pf.resample(src_grid, to=vel)
            vel = vel + s_vel * (pf.resample(vin, to=vel) - vel)
        vel, self.pressure = pf.fluid.make_incompressible(
            vel, (), pf.Solve("CG", params.cg_tolerance, params.cg_tolerance, max_iterations=500, x0=self.pressure,
                              rank_deficiency=0))
        self.temp, self.vel = temp, vel


def upsample_cfd(result: CFDResult, factor: int) -> CFDResult:
    """The simulation's knots cubic-B-spline upsampled ``factor`` times in space.

    A curved-ray renderer differentiates the field it traces with central differences on
    its own grid, which attenuates structure near that grid's scale (by sin(kh)/(kh): to
    0.64 at a wavelength of four cells), while a truth scored by interpolating the same
    knots keeps it: the rendered data would not carry what the score asks for. Tracing
    and scoring the field upsampled here makes the two the same continuous field (the
    spline through the CFD knots) sampled finely enough for the differences to keep the
    CFD grid's structure (0.89 of a four-cell wave's gradient for ``factor`` 2, the
    spline's own interpolation included, against 0.64).

    Cell-centred grids on the same box: knot ``i`` of the coarse grid sits at
    ``(i + 1/2) h``, and the fine grid's voxels at ``(j + 1/2) h / factor``
    (``scipy.ndimage.zoom`` with ``grid_mode=True``); the faces extend the field as
    constant (``mode="nearest"``). The excess is not clipped at 0 again: the spline under-
    and overshoots a little near sharp edges, and clipping would add a kink, structure finer
    than the simulation's grid holds, which the rendered data would then have to carry
    (the pipeline scores lower against a clipped truth: docs/tuning.md, "Synthetic truth").
    """
    from scipy import ndimage

    factor = int(factor)
    if factor < 1:
        raise ValueError(f"upsampling factor must be a positive integer, got {factor}")
    if factor == 1:
        return result
    g = result.grid
    fine = Grid(g.vmin, g.vmax, g.voxel_size / factor)
    want = tuple(factor * n for n in g.shape)
    if tuple(fine.shape) != want:
        raise ValueError(f"the box does not hold a whole number of {fine.voxel_size} m voxels: grid "
                         f"{fine.shape}, upsampled knots {want}")
    ex = np.empty((len(result.excess),) + want, dtype=np.float32)
    for k, e in enumerate(result.excess):
        ex[k] = ndimage.zoom(np.asarray(e, dtype=np.float64), factor, order=3, mode="nearest", grid_mode=True)
    meta = dict(result.params)
    meta["upsample"] = factor
    return CFDResult(grid=fine, knot_times=result.knot_times, excess=ex, params=meta)


def cfd_phantom(result: CFDResult, *, medium: Medium = Medium(), name: str | None = None) -> Phantom:
    """The simulation as a :class:`Phantom` on its own grid (refractivity by Gladstone-Dale)."""
    excess = result.excess

    def knot(i: int) -> np.ndarray:
        return refractivity_from_temperature(medium.T_ambient + excess[i].astype(np.float64), medium)

    return Phantom(result.grid, result.knot_times, knot, medium=medium,
                   name=name or f"cfd-{result.params.get('kind', 'plume')}")
