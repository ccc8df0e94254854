"""Refractive-index phantoms over time, with known ground truth (paper sec. 6).

Every phantom is a temperature field ``T(x, t)`` turned into refractivity
``r = n - 1`` by the project's Gladstone-Dale model at ambient pressure
(``docs/design.md``): ``r = r_amb * T_amb / T`` with ``r_amb = n_ambient - 1``.

A phantom is *defined* by its values at a set of time knots on its own fine grid,
linearly interpolated in time between them (constant before the first and after the
last knot). This makes the truth exactly reproducible: the renderer, the stored
ground truth and ``evaluate`` all use the same piecewise-linear-in-time field.

Three families:

* :func:`gaussian_blob` - an analytic hot Gaussian blob (optionally drifting).
* :func:`tealight_plumes` - three laminar plumes above tea lights (similarity
  solution of a point-source plume: width ~ height, excess temperature ~ height^-5/3),
  with an optional slow sway.
* :func:`buoyant_plume` - a non-stationary buoyant hot plume from a small Boussinesq
  smoke simulation (:mod:`schlieren.pipeline.synthetic.smoke`): a puffing source whose
  head rolls up into vortex rings that break up while rising.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence

import numpy as np

from schlieren.pipeline.geometry import Grid, Medium

__all__ = [
    "Phantom",
    "refractivity_from_temperature",
    "temperature_from_refractivity",
    "gaussian_blob",
    "tealight_plumes",
    "buoyant_plume",
    "make_phantom",
]

log = logging.getLogger(__name__)


def refractivity_from_temperature(T: np.ndarray, medium: Medium) -> np.ndarray:
    """Refractivity ``n - 1`` of air at temperature ``T`` (kelvin), ambient pressure.

    Gladstone-Dale with the ideal-gas law at constant pressure:
    ``r = r_amb * T_amb / T`` (``docs/design.md``, physics conventions).
    """
    return medium.refractivity_ambient * medium.T_ambient / np.asarray(T, dtype=np.float64)


def temperature_from_refractivity(r: np.ndarray, medium: Medium) -> np.ndarray:
    """Inverse of :func:`refractivity_from_temperature` (kelvin)."""
    return medium.T_ambient * medium.refractivity_ambient / np.asarray(r, dtype=np.float64)


class Phantom:
    """A refractivity field on a fine grid, piecewise linear in time.

    Parameters
    ----------
    grid : Grid
        The phantom's own (fine) grid; volumes have shape ``grid.shape`` = (nz, ny, nx).
    knot_times : sequence of float
        Increasing session times (seconds) at which the field is defined.
    knot_volume : callable
        ``knot_volume(i) -> ndarray (nz, ny, nx)`` float64 refractivity at knot ``i``.
    medium : Medium
    name : str
    cache_size : int
        How many knot volumes to keep in memory.

    Notes
    -----
    ``refractivity(t)`` interpolates linearly between the two knots around ``t`` and is
    constant outside ``[knot_times[0], knot_times[-1]]``. Outside the flow the value is
    ``medium.n_ambient - 1``.
    """

    def __init__(self, grid: Grid, knot_times: Sequence[float], knot_volume: Callable[[int], np.ndarray],
                 *, medium: Medium = Medium(), name: str = "phantom", cache_size: int = 8):
        self.grid = grid
        self.knot_times = np.asarray(knot_times, dtype=np.float64).ravel()
        if self.knot_times.size == 0 or np.any(np.diff(self.knot_times) <= 0):
            raise ValueError("knot_times must be a non-empty increasing sequence")
        self._knot_volume = knot_volume
        self.medium = medium
        self.name = name
        # the cache_size knots used last, per phantom (a shape error is raised, never cached); the
        # loader holds no reference to the phantom, so dropping it frees the volumes at once
        self._cached_knot = functools.lru_cache(maxsize=max(int(cache_size), 0))(
            functools.partial(_load_knot, knot_volume, grid.shape))

    @property
    def r_ambient(self) -> float:
        return self.medium.refractivity_ambient

    @property
    def n_knots(self) -> int:
        return int(self.knot_times.size)

    def knot_refractivity(self, i: int) -> np.ndarray:
        """Refractivity at knot ``i``, shape (nz, ny, nx) float64 (read-only view)."""
        return self._cached_knot(int(i))

    def bracket(self, t: float) -> tuple[int, int, float]:
        """Knots ``(i0, i1)`` around ``t`` and the weight ``w`` of ``i1`` (``r = (1-w) r0 + w r1``)."""
        kt = self.knot_times
        if kt.size == 1 or t <= kt[0]:
            return 0, 0, 0.0
        if t >= kt[-1]:
            return kt.size - 1, kt.size - 1, 0.0
        i1 = int(np.searchsorted(kt, t, side="right"))
        i0 = i1 - 1
        w = (t - kt[i0]) / (kt[i1] - kt[i0])
        return i0, i1, float(w)

    def refractivity(self, t: float) -> np.ndarray:
        """Refractivity ``n - 1`` at session time ``t`` (seconds), shape (nz, ny, nx) float64."""
        i0, i1, w = self.bracket(float(t))
        r0 = self.knot_refractivity(i0)
        if w == 0.0 or i0 == i1:
            return r0.copy()
        r1 = self.knot_refractivity(i1)
        return (1.0 - w) * r0 + w * r1

    def knots_covering(self, t0: float, t1: float) -> np.ndarray:
        """Indices of the knots needed to evaluate the field anywhere in ``[t0, t1]``."""
        kt = self.knot_times
        lo = max(int(np.searchsorted(kt, t0, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(kt, t1, side="left")), kt.size - 1)
        return np.arange(lo, max(hi, lo) + 1)

    def temperature(self, t: float) -> np.ndarray:
        """Temperature (kelvin) at time ``t``, shape (nz, ny, nx)."""
        return temperature_from_refractivity(self.refractivity(t), self.medium)


def _load_knot(knot_volume: Callable[[int], np.ndarray], shape: tuple, i: int) -> np.ndarray:
    vol = np.asarray(knot_volume(i), dtype=np.float64)
    if vol.shape != shape:
        raise ValueError(f"knot volume shape {vol.shape} != grid shape {shape}")
    vol.setflags(write=False)
    return vol


# --------------------------------------------------------------------------------------
# analytic phantoms
# --------------------------------------------------------------------------------------

def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def gaussian_blob(grid: Grid, *, centre: Sequence[float] | None = None, sigma: float = 0.015,
                  peak_temperature: float = 400.0, medium: Medium = Medium(),
                  velocity: Sequence[float] = (0.0, 0.0, 0.0),
                  knot_times: Sequence[float] = (0.0,)) -> Phantom:
    """A hot Gaussian blob of temperature.

    ``T(x, t) = T_amb + (T_peak - T_amb) exp(-|x - c - v t|^2 / (2 sigma^2))``.

    Parameters
    ----------
    grid : Grid
    centre : (3,) float, optional
        Blob centre at t = 0 (metres, world x, y, z); default the grid centre.
    sigma : float
        Standard deviation of the blob (metres).
    peak_temperature : float
        Kelvin at the centre.
    velocity : (3,) float
        Drift velocity (m/s); zero gives a stationary phantom.
    knot_times : sequence of float
        Time knots (seconds); a single knot is enough for a stationary blob.
    """
    c0 = grid.center if centre is None else np.asarray(centre, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    kt = np.asarray(knot_times, dtype=np.float64)
    x, y, z = grid.axes()

    def knot(i: int) -> np.ndarray:
        c = c0 + v * kt[i]
        gz = np.exp(-((z - c[2]) ** 2) / (2 * sigma**2))[:, None, None]
        gy = np.exp(-((y - c[1]) ** 2) / (2 * sigma**2))[None, :, None]
        gx = np.exp(-((x - c[0]) ** 2) / (2 * sigma**2))[None, None, :]
        T = medium.T_ambient + (peak_temperature - medium.T_ambient) * (gz * gy * gx)
        return refractivity_from_temperature(T, medium)

    return Phantom(grid, kt, knot, medium=medium, name="blob")


def tealight_plumes(grid: Grid, *, medium: Medium = Medium(),
                    sources: Sequence[Sequence[float]] | None = None,
                    source_temperature: float = 560.0, source_radius: float = 0.004,
                    virtual_origin: float = 0.012, flame_height: float = 0.03,
                    sway_amplitude: float = 0.002, sway_frequency: float = 0.7,
                    knot_times: Sequence[float] = (0.0,), seed: int = 0) -> Phantom:
    """Three laminar hot plumes above tea lights (paper Fig. 8, bottom row).

    Each plume follows the similarity form of a laminar point-source plume: a Gaussian
    cross-section of width ``s(h) = s0 * (h + h0) / h0`` and a centreline excess
    temperature ``dT(h) = dT0 * ((h + h0) / h0) ** (-5/3)`` at height ``h`` above the
    flame tip, which itself fades in smoothly over ``flame_height``. An optional sway
    moves each plume sideways in proportion to the height (a slow laminar wobble).

    Parameters
    ----------
    sources : sequence of (x, y, z), optional
        Flame tips (metres); default three tea lights 4 cm apart near the box floor.
    source_temperature : float
        Kelvin on the axis at the flame tip (350-600 K is realistic).
    source_radius : float
        Gaussian width ``s0`` at the flame tip (metres).
    virtual_origin : float
        ``h0`` (metres), distance of the virtual point source below the tip.
    flame_height : float
        Height (metres) over which the plume fades in below the tip.
    sway_amplitude : float
        Lateral displacement (metres) of each plume at the top of the box; it grows
        linearly with the height above the flame tip.
    sway_frequency : float
        Hz.
    knot_times : sequence of float
        Time knots (seconds). One knot (default) gives a stationary field.
    seed : int
        Seeds the sway phases.
    """
    c = grid.center
    zmin = grid.vmin[2]
    if sources is None:
        zs = zmin + 0.03
        sources = [(c[0] - 0.035, c[1] - 0.012, zs), (c[0] + 0.035, c[1] - 0.012, zs),
                   (c[0], c[1] + 0.025, zs)]
    src = np.asarray(sources, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0, 2 * np.pi, size=(len(src), 2))
    kt = np.asarray(knot_times, dtype=np.float64)
    x, y, z = grid.axes()
    height = grid.vmax[2] - grid.vmin[2]
    dT0 = source_temperature - medium.T_ambient

    def knot(i: int) -> np.ndarray:
        t = kt[i]
        dT = np.zeros(grid.shape)
        for k, s in enumerate(src):
            h = z - s[2]                                   # (nz,)
            a = (np.maximum(h, 0.0) + virtual_origin) / virtual_origin
            width = source_radius * a
            centre_dT = dT0 * a ** (-5.0 / 3.0) * _smoothstep((h + flame_height) / flame_height)
            sway = sway_amplitude * np.maximum(h, 0.0) / height
            sx = s[0] + sway * np.sin(2 * np.pi * sway_frequency * t + phases[k, 0])
            sy = s[1] + sway * np.sin(2 * np.pi * sway_frequency * t + phases[k, 1])
            dx2 = (x[None, None, :] - sx[:, None, None]) ** 2
            dy2 = (y[None, :, None] - sy[:, None, None]) ** 2
            dT += centre_dT[:, None, None] * np.exp(-(dx2 + dy2) / (2 * width[:, None, None] ** 2))
        return refractivity_from_temperature(medium.T_ambient + dT, medium)

    return Phantom(grid, kt, knot, medium=medium, name="tealights")


def buoyant_plume(grid: Grid, *, duration: float, seed: int = 0, medium: Medium = Medium(),
                  t_start: float = 0.0, knot_dt: float = 1.0 / 240.0, spinup: float = 0.35,
                  sim_cell: float | None = None, source_temperature: float = 600.0,
                  source_radius: float = 0.02, source_velocity: float = 0.3,
                  puff_frequency: float = 8.0, puff_depth: float = 0.8, perturbation: float = 0.7,
                  vorticity: float = 6.0) -> Phantom:
    """A non-stationary buoyant hot plume from a coarse Boussinesq smoke simulation.

    The simulation (:func:`schlieren.pipeline.synthetic.smoke.simulate`) runs from
    ``t_start - spinup`` with semi-Lagrangian advection, buoyancy ``g (1 - T_amb/T)``,
    vorticity confinement and a spectral pressure projection; a puffing, randomly
    perturbed hot source at the floor of the box makes a head that rolls up and
    breaks up. The coarse temperature is sampled every ``knot_dt`` over
    ``[t_start, t_start + duration]`` and upsampled to ``grid`` with periodic cubic
    B-spline interpolation when a knot is requested.

    Parameters
    ----------
    grid : Grid
        The fine grid of the phantom.
    duration : float
        Seconds covered by the knots.
    seed : int
        Seeds the source perturbations.
    t_start : float
        Session time of the first knot (seconds; may be negative).
    knot_dt : float
        Seconds between stored time knots (= the simulation time step).
    spinup : float
        Seconds simulated before ``t_start``.
    sim_cell : float, optional
        Cell size of the simulation (metres); default ``4 * grid.voxel_size`` or 6 mm,
        whichever is smaller.
    source_temperature : float
        Kelvin of the hot core at the source (350-600 K is realistic).
    source_radius, source_velocity, puff_frequency, puff_depth, perturbation, vorticity :
        Source disk radius (m), inflow speed (m/s), puffing frequency (Hz) and relative
        depth, relative amplitude of the random azimuthal source perturbations, and the
        vorticity-confinement strength.
    """
    from schlieren.pipeline.synthetic.smoke import SmokeParams, simulate, upsample_matrices

    cell = float(sim_cell) if sim_cell is not None else min(4 * grid.voxel_size, 0.006)
    params = SmokeParams(cell=cell, dt=knot_dt, source_temperature=source_temperature,
                         source_radius=source_radius, source_velocity=source_velocity,
                         puff_frequency=puff_frequency, puff_depth=puff_depth, perturbation=perturbation,
                         vorticity=vorticity)
    n_knots = int(np.ceil(duration / knot_dt - 1e-9)) + 1
    kt = t_start + knot_dt * np.arange(n_knots)
    sim = simulate(grid, params, medium=medium, t_first=t_start, n_samples=n_knots,
                   spinup=spinup, seed=seed)
    Mz, My, Mx = upsample_matrices(sim, grid)

    def knot(i: int) -> np.ndarray:
        dT = sim.excess[i]
        f = np.tensordot(Mz, dT, axes=(1, 0))                  # (nz, Ny, Nx)
        f = np.tensordot(f, My, axes=(1, 1))                   # (nz, Nx, ny)
        f = np.tensordot(f, Mx, axes=(1, 1))                   # (nz, ny, nx)
        f = np.maximum(f, 0.0)
        return refractivity_from_temperature(medium.T_ambient + f, medium)

    log.info("buoyant plume: %d knots, sim grid %s, cell %.4f m", n_knots, sim.excess.shape[1:], cell)
    return Phantom(grid, kt, knot, medium=medium, name="plume")


def make_phantom(kind: str, grid: Grid, *, t_start: float, duration: float, seed: int = 0,
                 medium: Medium = Medium(), knot_dt: float = 1.0 / 240.0) -> Phantom:
    """Build a phantom by name for a capture window ``[t_start, t_start + duration]``.

    ``kind`` is ``"blob"`` (stationary Gaussian), ``"tealights"`` (three laminar plumes
    with a slow sway) or ``"plume"`` (buoyant smoke simulation).
    """
    n = int(np.ceil(duration / knot_dt - 1e-9)) + 1
    kt = t_start + knot_dt * np.arange(n)
    if kind == "blob":
        c = grid.center
        return gaussian_blob(grid, centre=(c[0], c[1], c[2]),
                             sigma=0.1 * min(np.subtract(grid.vmax, grid.vmin)),
                             peak_temperature=450.0, medium=medium)
    if kind == "tealights":
        return tealight_plumes(grid, medium=medium, knot_times=kt, seed=seed)
    if kind == "plume":
        return buoyant_plume(grid, duration=duration, seed=seed, medium=medium, t_start=t_start,
                             knot_dt=knot_dt)
    raise ValueError(f"unknown phantom {kind!r} (blob, tealights, plume)")
