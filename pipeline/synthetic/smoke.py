"""A small Boussinesq smoke simulation for the non-stationary plume phantom.

Stable-fluids style (Stam 1999; Fedkiw et al. 2001) on a coarse periodic cell-centred
grid with numpy/scipy only:

1. semi-Lagrangian advection of velocity and excess temperature (trilinear,
   midpoint back-trace);
2. a hot puffing source at the floor whose shape is perturbed by slowly drifting
   random azimuthal modes (breaks the symmetry so the rolled-up rings break up);
3. buoyancy ``g (1 - T_amb / T)`` on the vertical velocity;
4. vorticity confinement (restores the small-scale roll-up lost to numerical diffusion);
5. a sponge layer at the top and the sides of the domain (the domain is periodic;
   the sponge makes the wrap-around see still, ambient air);
6. a spectral pressure projection (the velocity is made exactly divergence free in
   Fourier space).

The simulation domain covers the phantom's grid with a lateral margin and a sponge
above. Only the excess temperature is kept, at every time step after the spin-up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy import ndimage

from schlieren.pipeline.geometry import Grid, Medium

__all__ = ["SmokeParams", "SmokeResult", "simulate", "upsample_matrices"]

G = 9.81


@dataclass(frozen=True)
class SmokeParams:
    """Parameters of :func:`simulate` (SI units).

    Attributes
    ----------
    cell : float
        Cell size (metres).
    dt : float
        Time step (seconds); also the spacing of the stored samples.
    source_temperature : float
        Kelvin at the source core.
    source_radius : float
        Radius of the hot source disk (metres).
    source_height : float
        Height of the source above the floor of the phantom grid (metres).
    source_velocity : float
        Upward inflow speed at the source (m/s).
    puff_frequency : float
        Frequency (Hz) of the source-strength modulation (puffing).
    puff_depth : float
        Relative modulation depth, 0..1.
    perturbation : float
        Relative amplitude of the random azimuthal source perturbations.
    vorticity : float
        Vorticity-confinement strength (dimensionless epsilon).
    margin : float
        Lateral margin of the simulation domain around the grid (metres).
    sponge : float
        Height of the damping layer above the grid (metres).
    """

    cell: float = 0.006
    dt: float = 1.0 / 240.0
    source_temperature: float = 600.0
    source_radius: float = 0.02
    source_height: float = 0.012
    source_velocity: float = 0.3
    puff_frequency: float = 8.0
    puff_depth: float = 0.8
    perturbation: float = 0.7
    vorticity: float = 6.0
    margin: float = 0.05
    sponge: float = 0.12


@dataclass(frozen=True)
class SmokeResult:
    """Output of :func:`simulate`.

    Attributes
    ----------
    excess : ndarray, shape (n_samples, Nz, Ny, Nx)
        Excess temperature ``T - T_amb`` (kelvin) at each sample time.
    times : ndarray, shape (n_samples,)
        Session times of the samples (seconds).
    origin : ndarray, shape (3,)
        World (x, y, z) of the centre of cell [0, 0, 0].
    cell : float
    """

    excess: np.ndarray
    times: np.ndarray
    origin: np.ndarray
    cell: float


@njit(cache=True, inline="always")
def _trilerp(f, z, y, x):
    nz, ny, nx = f.shape
    iz = int(np.floor(z))
    iy = int(np.floor(y))
    ix = int(np.floor(x))
    az = z - iz
    ay = y - iy
    ax = x - ix
    z0 = iz % nz
    y0 = iy % ny
    x0 = ix % nx
    z1 = (z0 + 1) % nz
    y1 = (y0 + 1) % ny
    x1 = (x0 + 1) % nx
    return ((1 - az) * ((1 - ay) * ((1 - ax) * f[z0, y0, x0] + ax * f[z0, y0, x1])
                        + ay * ((1 - ax) * f[z0, y1, x0] + ax * f[z0, y1, x1]))
            + az * ((1 - ay) * ((1 - ax) * f[z1, y0, x0] + ax * f[z1, y0, x1])
                    + ay * ((1 - ax) * f[z1, y1, x0] + ax * f[z1, y1, x1])))


@njit(cache=True, parallel=True)
def _advect(u, v, w, th, c):
    """Semi-Lagrangian advection of (u, v, w, th) by (u, v, w); ``c = dt / h``; midpoint back-trace."""
    nz, ny, nx = u.shape
    uo = np.empty_like(u)
    vo = np.empty_like(v)
    wo = np.empty_like(w)
    to = np.empty_like(th)
    for k in prange(nz):
        for j in range(ny):
            for i in range(nx):
                zm = k - 0.5 * c * w[k, j, i]
                ym = j - 0.5 * c * v[k, j, i]
                xm = i - 0.5 * c * u[k, j, i]
                zb = k - c * _trilerp(w, zm, ym, xm)
                yb = j - c * _trilerp(v, zm, ym, xm)
                xb = i - c * _trilerp(u, zm, ym, xm)
                uo[k, j, i] = _trilerp(u, zb, yb, xb)
                vo[k, j, i] = _trilerp(v, zb, yb, xb)
                wo[k, j, i] = _trilerp(w, zb, yb, xb)
                to[k, j, i] = _trilerp(th, zb, yb, xb)
    return uo, vo, wo, to


def simulate(grid: Grid, params: SmokeParams, *, medium: Medium = Medium(), t_first: float,
             n_samples: int, spinup: float, seed: int) -> SmokeResult:
    """Run the smoke simulation and return the excess temperature at the sample times.

    Parameters
    ----------
    grid : Grid
        The phantom's grid: the simulation covers it (plus margins).
    params : SmokeParams
    medium : Medium
        ``T_ambient`` sets the buoyancy.
    t_first : float
        Session time of the first stored sample (seconds).
    n_samples : int
        Number of samples stored, ``params.dt`` apart.
    spinup : float
        Seconds simulated before ``t_first``.
    seed : int
        Seeds the source perturbation.

    Returns
    -------
    SmokeResult
    """
    rng = np.random.default_rng(seed)
    h = params.cell
    dt = params.dt
    origin, (X, Y, Z) = _domain(grid, params)
    nz, ny, nx = X.shape
    src = _Source.at_floor(grid, params, X, Y, Z)
    damp = _sponge(grid, params, X, Y, Z)
    project = _spectral_projection(nx, ny, nz, h)

    u = np.zeros((nz, ny, nx))
    v = np.zeros_like(u)
    w = np.zeros_like(u)
    th = np.zeros_like(u)

    n_modes = 5
    amp = rng.normal(0.0, 1.0, n_modes)
    pha = rng.uniform(0, 2 * np.pi, n_modes)
    dT0 = params.source_temperature - medium.T_ambient

    n_spin = int(round(spinup / dt))
    total = n_spin + n_samples
    out = np.empty((n_samples, nz, ny, nx), dtype=np.float64)
    times = t_first + dt * np.arange(n_samples)
    for step in range(total):
        t = t_first + (step - n_spin) * dt
        # 1. advection (midpoint back-trace, trilinear, periodic)
        u, v, w, th = _advect(u, v, w, th, dt / h)
        # 2. source: puffing, perturbed hot disk with inflow
        amp = 0.9 * amp + np.sqrt(1 - 0.81) * rng.normal(0.0, 1.0, n_modes)
        pha = pha + rng.normal(0.0, 0.3, n_modes)
        src.heat(th, w, params, amp, pha, t, dT0)
        # 3. buoyancy
        w = w + dt * G * th / (medium.T_ambient + th)
        # 4. vorticity confinement
        if params.vorticity > 0:
            u, v, w = _confine_vorticity(u, v, w, params.vorticity * h * dt, h)
        # 5. sponge
        u, v, w, th = u * damp, v * damp, w * damp, th * damp
        # 6. projection
        u, v, w = project(u, v, w)
        th = np.maximum(th, 0.0)
        if step >= n_spin:
            out[step - n_spin] = th
    return SmokeResult(excess=out, times=times, origin=origin, cell=h)


def _domain(grid: Grid, params: SmokeParams):
    """World (x, y, z) of the centre of cell [0, 0, 0] and the cell centres' coordinates, each
    shape (Nz, Ny, Nx): the grid with a lateral margin, two cells below and the sponge above,
    an even number (at least 8) of cells along each axis."""
    h = params.cell
    lo = np.asarray(grid.vmin, dtype=np.float64) - np.array([params.margin, params.margin, 2 * h])
    hi = np.asarray(grid.vmax, dtype=np.float64) + np.array([params.margin, params.margin, params.sponge])
    n = np.maximum(np.ceil((hi - lo) / h).astype(int), 8)
    n += n % 2
    nx, ny, nz = (int(v) for v in n)
    origin = lo + 0.5 * h
    x = origin[0] + h * np.arange(nx)
    y = origin[1] + h * np.arange(ny)
    z = origin[2] + h * np.arange(nz)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    return origin, (X, Y, Z)


@dataclass(frozen=True)
class _Source:
    """The hot source: a disk at the grid centre, a few cells thick (the slab ``zsl`` of
    cells it covers, with each cell's azimuth, radius, vertical profile and mask)."""

    zsl: slice
    phi: np.ndarray
    rad: np.ndarray
    src_z: np.ndarray
    mask: np.ndarray

    @classmethod
    def at_floor(cls, grid: Grid, params: SmokeParams, X, Y, Z) -> "_Source":
        h = params.cell
        cx, cy = 0.5 * (grid.vmin[0] + grid.vmax[0]), 0.5 * (grid.vmin[1] + grid.vmax[1])
        zs = grid.vmin[2] + params.source_height
        rad = np.hypot(X - cx, Y - cy)
        phi = np.arctan2(Y - cy, X - cx)
        src_z = np.exp(-((Z - zs) / (1.0 * h)) ** 2)
        src_mask = (src_z > 0.05) & (rad < 1.5 * params.source_radius)
        kz = np.nonzero(src_mask.any(axis=(1, 2)))[0]
        zsl = slice(int(kz.min()), int(kz.max()) + 1)
        return cls(zsl, phi[zsl], rad[zsl], src_z[zsl], src_mask[zsl])

    def heat(self, th, w, params: SmokeParams, amp, pha, t: float, dT0: float) -> None:
        """Raise ``th`` and ``w`` (in place) to the puffing, perturbed source profile at time ``t``
        (azimuthal modes of amplitudes ``amp`` and phases ``pha``)."""
        zsl, ph_s, rad_s, srcz_s, m_s = self.zsl, self.phi, self.rad, self.src_z, self.mask
        n_modes = len(amp)
        az = 1.0 + params.perturbation * sum(amp[m] * np.cos((m + 1) * ph_s + pha[m]) for m in range(n_modes)) / np.sqrt(n_modes)
        puff = 1.0 + params.puff_depth * np.sin(2 * np.pi * params.puff_frequency * t)
        prof = np.exp(-(rad_s / params.source_radius) ** 4) * srcz_s * np.clip(az, 0.3, 1.3) / 1.3
        th[zsl] = np.where(m_s, np.maximum(th[zsl], dT0 * puff / (1 + params.puff_depth) * prof), th[zsl])
        w[zsl] = np.where(m_s, np.maximum(w[zsl], params.source_velocity * puff * prof), w[zsl])


def _sponge(grid: Grid, params: SmokeParams, X, Y, Z) -> np.ndarray:
    """Per-step damping factor: a rate (1/s) rising smoothly in the top layer and the lateral margins."""
    dt = params.dt
    cx, cy = 0.5 * (grid.vmin[0] + grid.vmax[0]), 0.5 * (grid.vmin[1] + grid.vmax[1])
    top = np.clip((Z - grid.vmax[2]) / params.sponge, 0.0, 1.0)
    side_x = np.clip((np.abs(X - cx) - (0.5 * (grid.vmax[0] - grid.vmin[0]) + 0.3 * params.margin))
                     / (0.6 * params.margin), 0.0, 1.0)
    side_y = np.clip((np.abs(Y - cy) - (0.5 * (grid.vmax[1] - grid.vmin[1]) + 0.3 * params.margin))
                     / (0.6 * params.margin), 0.0, 1.0)
    return np.exp(-dt * 60.0 * np.maximum(top, np.maximum(side_x, side_y)) ** 2)


def _spectral_projection(nx: int, ny: int, nz: int, h: float):
    """``project(u, v, w)``: the divergence-free part of a periodic velocity field (Fourier space)."""
    kx = 2 * np.pi * np.fft.fftfreq(nx, d=h)
    ky = 2 * np.pi * np.fft.fftfreq(ny, d=h)
    kz = 2 * np.pi * np.fft.rfftfreq(nz, d=h)
    KZ = kz[None, None, :]
    KY = ky[None, :, None]
    KX = kx[:, None, None]
    K2 = KX**2 + KY**2 + KZ**2
    K2[0, 0, 0] = 1.0

    def project(u, v, w):
        # FFT over (x, y, z) with arrays transposed to (x, y, z)
        uh = np.fft.rfftn(u.transpose(2, 1, 0))
        vh = np.fft.rfftn(v.transpose(2, 1, 0))
        wh = np.fft.rfftn(w.transpose(2, 1, 0))
        div = KX * uh + KY * vh + KZ * wh
        uh -= KX * div / K2
        vh -= KY * div / K2
        wh -= KZ * div / K2
        shp = (nx, ny, nz)
        return (np.fft.irfftn(uh, s=shp, axes=(0, 1, 2)).transpose(2, 1, 0), np.fft.irfftn(vh, s=shp, axes=(0, 1, 2)).transpose(2, 1, 0),
                np.fft.irfftn(wh, s=shp, axes=(0, 1, 2)).transpose(2, 1, 0))

    return project


def _confine_vorticity(u, v, w, eps: float, h: float):
    """Vorticity confinement (Fedkiw et al. 2001): ``u += eps (N x omega)``, N the unit gradient of |omega|."""
    dwdy, dwdx = np.gradient(w, h, axis=(1, 2))
    dvdz, dvdx = np.gradient(v, h, axis=(0, 2))
    dudz, dudy = np.gradient(u, h, axis=(0, 1))
    ox, oy, oz = dwdy - dvdz, dudz - dwdx, dvdx - dudy
    mag = np.sqrt(ox**2 + oy**2 + oz**2)
    gz_, gy_, gx_ = np.gradient(mag, h)
    gn = np.sqrt(gx_**2 + gy_**2 + gz_**2) + 1e-12
    Nx_, Ny_, Nz_ = gx_ / gn, gy_ / gn, gz_ / gn
    u = u + eps * (Ny_ * oz - Nz_ * oy)
    v = v + eps * (Nz_ * ox - Nx_ * oz)
    w = w + eps * (Nx_ * oy - Ny_ * ox)
    return u, v, w


def upsample_matrices(sim: SmokeResult, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Separable periodic cubic B-spline interpolation from the simulation to ``grid``.

    Returns
    -------
    Mz, My, Mx : ndarray, shapes (nz, Nz), (ny, Ny), (nx, Nx)
        ``fine = Mz @ coarse @ ...`` along each axis (apply with ``tensordot``).
    """
    mats = []
    axes = grid.axes()
    for ax, n_c in zip((2, 1, 0), sim.excess.shape[1:]):
        coord = (axes[ax] - sim.origin[ax]) / sim.cell
        M = np.empty((coord.size, n_c))
        eye = np.eye(n_c)
        for j in range(n_c):
            M[:, j] = ndimage.map_coordinates(eye[j], coord[None, :], order=3, mode="grid-wrap")
        mats.append(M)
    return mats[0], mats[1], mats[2]
