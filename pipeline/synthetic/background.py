"""Wavelet Noise backgrounds (Cook and DeRose 2005), as the paper uses (sec. 4).

A noise *tile* is band-limited white noise: random coefficients ``R`` minus their
projection onto the next coarser quadratic B-spline space (least squares, computed
exactly on the periodic tile, separably along each axis): ``N = R - P R P^T``.
The pattern is evaluated *procedurally* at any point as a sum of quadratic B-splines
weighted by the tile coefficients, over several octaves (bands), so the renderer never
resamples an image: the background is exact at every sample position.

A :class:`Background` maps world points on a camera's background plane to grey levels:
Wavelet Noise by default, or a printed random dot pattern (:mod:`.dots`); a
:class:`Texture` chooses between them and sets their scale in camera pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from schlieren.pipeline.synthetic.dots import _dots_many, dot_params, dot_table

__all__ = ["wavelet_noise_tile", "Background", "make_background", "noise_values", "background_image", "Texture",
           "make_texture_background", "TEXTURE_KINDS"]

#: Background kinds: the renderer's kernel selects the pattern by the index in this tuple.
TEXTURE_KINDS = ("noise", "dots")


def _refinement_matrix(n: int) -> np.ndarray:
    """Periodic quadratic B-spline refinement ``U`` (n x n/2): coarse coefficients -> fine."""
    m = n // 2
    U = np.zeros((n, m))
    a = (0.25, 0.75, 0.75, 0.25)
    for k in range(m):
        for j, ak in zip((-1, 0, 1, 2), a):
            U[(2 * k + j) % n, k] += ak
    return U


def wavelet_noise_tile(n: int = 256, *, seed: int = 0) -> np.ndarray:
    """A periodic Wavelet Noise tile (Cook and DeRose 2005, sec. 3).

    Parameters
    ----------
    n : int
        Tile size (even; a power of two keeps the evaluation's wrap-around cheap).
    seed : int

    Returns
    -------
    tile : ndarray, shape (n, n) float64
        Coefficients whose B-spline evaluation has unit standard deviation and almost no
        energy below half the tile's Nyquist frequency.
    """
    if n % 2 or n & (n - 1):
        raise ValueError("tile size must be a power of two")
    rng = np.random.default_rng(seed)
    R = rng.normal(0.0, 1.0, (n, n))
    U = _refinement_matrix(n)
    P = U @ np.linalg.solve(U.T @ U, U.T)          # least-squares projection onto coarse splines
    N = R - P @ R @ P.T
    # normalise: unit standard deviation of the evaluated pattern
    pts = np.random.default_rng(seed + 1).uniform(0, n, (2, 20000))
    vals = _eval_band(N, pts[0], pts[1])
    return N / vals.std()


@njit(cache=True)
def _bspline2(t):
    # quadratic B-spline weights for offsets -1, 0, +1 around the nearest integer; t in [-0.5, 0.5)
    return 0.5 * (0.5 - t) ** 2, 0.75 - t * t, 0.5 * (0.5 + t) ** 2


@njit(cache=True)
def _noise_at(tile, x, y):
    n = tile.shape[0]
    mask = n - 1
    ix = int(np.floor(x + 0.5))
    iy = int(np.floor(y + 0.5))
    wx0, wx1, wx2 = _bspline2(x - ix)
    wy0, wy1, wy2 = _bspline2(y - iy)
    s = 0.0
    for jy in range(3):
        wy = wy0 if jy == 0 else (wy1 if jy == 1 else wy2)
        row = (iy + jy - 1) & mask
        acc = (wx0 * tile[row, (ix - 1) & mask] + wx1 * tile[row, ix & mask]
               + wx2 * tile[row, (ix + 1) & mask])
        s += wy * acc
    return s


@njit(cache=True)
def _eval_band(tile, x, y):
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        out[i] = _noise_at(tile, x[i], y[i])
    return out


@njit(cache=True)
def _pattern_value(tile, a, b, inv_spacing, offset_a, offset_b, weights):
    s = 0.0
    for k in range(inv_spacing.shape[0]):
        s += weights[k] * _noise_at(tile, a * inv_spacing[k] + offset_a[k], b * inv_spacing[k] + offset_b[k])
    return s


@njit(cache=True)
def _pattern_many(tile, a, b, inv_spacing, offset_a, offset_b, weights, out):
    for i in range(a.shape[0]):
        out[i] = _pattern_value(tile, a[i], b[i], inv_spacing, offset_a, offset_b, weights)


@dataclass(frozen=True, eq=False)
class Background:
    """A Wavelet Noise pattern (or a dot pattern, ``kind="dots"``) on a plane.

    Attributes
    ----------
    tile : ndarray, shape (n, n)
        :func:`wavelet_noise_tile` coefficients.
    spacing : float
        Coefficient spacing of the finest band (metres on the plane).
    bands : int
        Number of octaves; band ``k`` has spacing ``spacing * 2**k``.
    offsets : ndarray, shape (bands, 2)
        Per-band shifts in tile units (decorrelate the octaves and the cameras).
    mean, contrast : float
        Grey level = ``mean + contrast * pattern`` (pattern has unit standard deviation).
    point, e1, e2 : ndarray, shape (3,)
        Plane origin and in-plane orthonormal axes (world); plane coordinates
        ``a = (X - point) . e1``, ``b = (X - point) . e2``.
    kind : {"noise", "dots"}
        ``"dots"``: ``spacing`` is the dot pitch, ``bands`` is 1, ``dots`` the
        :func:`~schlieren.pipeline.synthetic.dots.dot_table` and ``dot_par`` its
        :func:`~schlieren.pipeline.synthetic.dots.dot_params` (``tile`` is unused).
    dots, dot_par : ndarray or None
    """

    tile: np.ndarray
    spacing: float
    bands: int
    offsets: np.ndarray
    mean: float
    contrast: float
    point: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    kind: str = "noise"
    dots: np.ndarray | None = None
    dot_par: np.ndarray | None = None

    @property
    def inv_spacing(self) -> np.ndarray:
        return 1.0 / (self.spacing * 2.0 ** np.arange(self.bands))

    @property
    def weights(self) -> np.ndarray:
        # equal energy per octave; the sum has unit standard deviation
        return np.full(self.bands, 1.0 / np.sqrt(self.bands))

    def kernel_args(self) -> tuple:
        """Arguments for the numba evaluation kernels (tile, inv_spacing, offsets a, b, weights)."""
        return (np.ascontiguousarray(self.tile), self.inv_spacing, np.ascontiguousarray(self.offsets[:, 0]),
                np.ascontiguousarray(self.offsets[:, 1]), self.weights)

    def texture_args(self) -> tuple:
        """The kernel's pattern selector: (kind index in :data:`TEXTURE_KINDS`, dot table, dot parameters)."""
        if self.kind == "dots":
            return 1, np.ascontiguousarray(self.dots), np.asarray(self.dot_par, dtype=np.float64)
        return 0, np.zeros((1, 1, 2)), np.zeros(4)

    def plane_coords(self, X: np.ndarray) -> np.ndarray:
        """Plane coordinates ``(a, b)`` (metres) of world points, shape (..., 2)."""
        d = np.asarray(X, dtype=np.float64) - self.point
        return np.stack([d @ self.e1, d @ self.e2], axis=-1)

    def values(self, ab: np.ndarray) -> np.ndarray:
        """Grey levels at plane coordinates ``ab`` (..., 2)."""
        return self.mean + self.contrast * noise_values(self, ab)


def noise_values(bg: Background, ab: np.ndarray) -> np.ndarray:
    """Unit-variance pattern values at plane coordinates ``ab`` (..., 2) (metres)."""
    ab = np.asarray(ab, dtype=np.float64)
    shp = ab.shape[:-1]
    flat = ab.reshape(-1, 2)
    out = np.empty(flat.shape[0])
    tile, inv, oa, ob, w = bg.kernel_args()
    if bg.kind == "dots":
        _, table, par = bg.texture_args()
        _dots_many(table, np.ascontiguousarray(flat[:, 0] * inv[0] + oa[0]),
                   np.ascontiguousarray(flat[:, 1] * inv[0] + ob[0]), par, out)
        return out.reshape(shp)
    _pattern_many(tile, np.ascontiguousarray(flat[:, 0]), np.ascontiguousarray(flat[:, 1]), inv, oa, ob, w, out)
    return out.reshape(shp)


def make_background(point: np.ndarray, normal: np.ndarray, *, spacing: float, tile: np.ndarray,
                    bands: int = 3, seed: int = 0, mean: float = 128.0, contrast: float = 40.0) -> Background:
    """A background pattern on the plane through ``point`` with ``normal``.

    Parameters
    ----------
    point, normal : ndarray, shape (3,)
        The plane (world metres); ``e1`` is horizontal, ``e2`` completes a right-handed
        in-plane frame.
    spacing : float
        Finest coefficient spacing (metres); about 1.5 camera pixels gives features a
        few pixels wide.
    tile : ndarray
        A :func:`wavelet_noise_tile` (shared by all cameras; ``seed`` shifts the pattern).
    bands : int
    seed : int
        Random per-band offsets (so different planes show different patterns).
    mean, contrast : float
        Grey levels (8-bit scale) of the mean and of one standard deviation.
    """
    e1, e2 = _plane_axes(normal)
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(0, tile.shape[0], (bands, 2))
    return Background(tile=tile, spacing=float(spacing), bands=int(bands), offsets=offsets, mean=float(mean),
                      contrast=float(contrast), point=np.asarray(point, dtype=np.float64), e1=e1, e2=e2)


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes: ``e1`` horizontal, ``e2`` completing a right-handed frame with the normal."""
    nrm = np.asarray(normal, dtype=np.float64)
    nrm = nrm / np.linalg.norm(nrm)
    up = np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, nrm)
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(np.array([1.0, 0.0, 0.0]), nrm)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(nrm, e1)


@dataclass(frozen=True)
class Texture:
    """What is printed on the background, scaled to the camera's pixels.

    Attributes
    ----------
    kind : {"noise", "dots"}
        Wavelet Noise (the paper's, sec. 4) or a random dot pattern (:mod:`.dots`).
    scale : float
        Noise: the finest band's coefficient spacing; dots: the dot pitch; in camera
        pixels at the background plane (the default noise, 1.5, gives features 2-3 px wide).
    bands : int
        Noise octaves (band ``k`` has spacing ``scale * 2**k``); dots ignore it.
    dot_diameter : float
        Dot diameter in units of the pitch.
    dot_edge : float
        Sigma of a dot's soft rim in units of the pitch.
    """

    kind: str = "noise"
    scale: float = 1.5
    bands: int = 3
    dot_diameter: float = 0.6
    dot_edge: float = 0.1

    def __post_init__(self):
        if self.kind not in TEXTURE_KINDS:
            raise ValueError(f"texture kind must be one of {TEXTURE_KINDS}, not {self.kind!r}")
        if not self.scale > 0 or self.bands < 1:
            raise ValueError("texture scale must be positive and bands at least 1")


def make_texture_background(point: np.ndarray, normal: np.ndarray, texture: Texture, *, pixel_footprint: float,
                            tile: np.ndarray | None = None, seed: int = 0, mean: float = 128.0,
                            contrast: float = 40.0) -> Background:
    """A :class:`Texture` on the plane through ``point`` with ``normal``.

    ``pixel_footprint`` is one camera pixel on the plane (metres); noise needs ``tile``
    (:func:`wavelet_noise_tile`); a dot pattern draws its own table from ``seed``.
    """
    spacing = texture.scale * float(pixel_footprint)
    if texture.kind == "noise":
        if tile is None:
            raise ValueError("a noise texture needs a wavelet noise tile")
        return make_background(point, normal, spacing=spacing, tile=tile, bands=texture.bands, seed=seed,
                               mean=mean, contrast=contrast)
    table = dot_table(seed=seed)
    e1, e2 = _plane_axes(normal)
    offsets = np.random.default_rng(seed).uniform(0, table.shape[0], (1, 2))
    return Background(tile=np.zeros((2, 2)), spacing=spacing, bands=1, offsets=offsets, mean=float(mean),
                      contrast=float(contrast), point=np.asarray(point, dtype=np.float64), e1=e1, e2=e2, kind="dots",
                      dots=table, dot_par=dot_params(table, diameter=texture.dot_diameter, edge=texture.dot_edge))


def background_image(bg: Background, width_px: int, height_px: int, *, pixel_size: float,
                     supersample: int = 2) -> np.ndarray:
    """The pattern as an image for printing: pixel ``(i, j)`` covers plane coordinates
    ``[j p, (j+1) p) x [i p, (i+1) p)`` with ``p = pixel_size`` (metres), area-averaged.

    Returns
    -------
    image : ndarray, shape (height_px, width_px) float64, grey levels clipped to [0, 255].
    """
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s
    out = np.empty((height_px, width_px))
    cols = (np.arange(width_px)[:, None] + off[None, :]).ravel() * pixel_size
    for r0 in range(0, height_px, 256):
        r1 = min(r0 + 256, height_px)
        rows = (np.arange(r0, r1)[:, None] + off[None, :]).ravel() * pixel_size
        B, A = np.meshgrid(rows, cols, indexing="ij")
        v = bg.values(np.stack([A, B], axis=-1))
        out[r0:r1] = v.reshape(r1 - r0, s, width_px, s).mean(axis=(1, 3))
    return np.clip(out, 0.0, 255.0)
