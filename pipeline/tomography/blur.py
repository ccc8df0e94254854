"""The flow's image averaging in the data term (beyond the paper): ``W S x`` or ``S G x``.

A measured deflection is a weighted mean of the per-pixel deflections around its flow
cell, while a row of ``S`` is the single ray through the cell centre
(``TomoParams.model_flow_window``). :class:`MeasurementBlur` models the averaging in
image space (``W``, per camera over its flow cells), :class:`VolumeBlur` as a Gaussian
over the basis coefficients of the width the cameras' averaging has at the volume
(``G``, :func:`volume_sigma`; ``TomoParams.flow_window_space``).
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.tomography._restriction_kernels import _move3

__all__ = ["MeasurementBlur", "VolumeBlur", "volume_sigma"]


class MeasurementBlur:
    """The flow's image-space averaging, per camera, at flow-cell resolution: ``W``.

    A measured deflection is a weighted mean of the per-pixel deflections around the cell
    (the LK window, smoothing and block mean: :func:`schlieren.pipeline.flow.measurement_sigma`),
    while a row of ``S`` is the single ray through the cell centre. With ``W`` the data
    term becomes ``||W S x - b||^2``: ``W`` is a separable Gaussian over neighbouring cells
    of the same camera (``sigma`` in cells, taps out to ``ceil(2 sigma)``, at least one),
    zero-padded at the image border so that it is symmetric (``W^T = W``).

    Parameters
    ----------
    flow_shape : (C, h, w)
    sigmas : sequence of float
        Per camera, in flow cells; <= 0 leaves that camera's rays as they are.
    """

    def __init__(self, flow_shape, sigmas):
        self.flow_shape = tuple(int(v) for v in flow_shape)
        sig = np.asarray(sigmas, dtype=np.float64).reshape(-1)
        if len(sig) != self.flow_shape[0]:
            raise ValueError(f"one sigma per camera expected ({self.flow_shape[0]}), got {len(sig)}")
        self.sigmas = sig
        self.taps = []
        for v in sig:
            if v <= 0:
                self.taps.append(None)
                continue
            K = max(1, int(np.ceil(2.0 * v)))
            k = np.exp(-0.5 * (np.arange(-K, K + 1) / v) ** 2)
            self.taps.append((k / k.sum()).astype(np.float32))

    def apply(self, Y: np.ndarray) -> np.ndarray:
        """``W Y`` for ``Y`` of shape (C, h, w, k) (float32 result)."""
        import cv2

        Y = np.ascontiguousarray(Y, dtype=np.float32)
        out = np.empty_like(Y)
        for c, t in enumerate(self.taps):
            if t is None:
                out[c] = Y[c]
                continue
            for j in range(Y.shape[-1]):
                out[c, ..., j] = cv2.sepFilter2D(Y[c, ..., j], cv2.CV_32F, t, t, borderType=cv2.BORDER_CONSTANT)
        return out

    def restricted(self, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``(W Y)[rows]`` where ``Y`` is ``values`` (len(rows), k) on ``rows`` and zero
        elsewhere (float32)."""
        C, h, w = self.flow_shape
        k = values.shape[1]
        full = np.zeros((C * h * w, k), np.float32)
        full[rows] = values
        return self.apply(full.reshape(C, h, w, k)).reshape(-1, k)[rows]


def volume_sigma(cell_sigmas, cameras, grid, factor: int) -> float:
    """Width (voxels) of the volume Gaussian equivalent to the flow's per-camera image
    averaging: each camera's ``sigma`` (flow cells, :func:`~schlieren.pipeline.flow.measurement_sigma`
    over ``factor``) times ``factor`` pixels per cell times its pixel footprint at the box
    centre (metres per pixel), over the voxel size; the mean over the cameras with a
    width (0 if none has one).
    """
    from schlieren.pipeline.geometry import pixel_footprint

    sig = np.asarray(cell_sigmas, dtype=np.float64).reshape(-1)
    if len(sig) != len(cameras):
        raise ValueError(f"one width per camera expected ({len(cameras)}), got {len(sig)}")
    vals = [s * factor * pixel_footprint(cam, grid.center) / grid.voxel_size for s, cam in zip(sig, cameras) if s > 0]
    return float(np.mean(vals)) if vals else 0.0


class VolumeBlur:
    """``G``: a Gaussian over the basis coefficients (``sigma`` in voxels), restricted to the
    basis set (zero outside it on input and output, so ``G^T = G``).

    The flow's image-space averaging of a projection equals the projection of the volume
    averaged by a Gaussian of the same width at the volume (exact for parallel rays, the
    width scaled by depth for a pinhole), so ``W S x ~ S G x``: the data term keeps the
    single fused pass over ``S`` of the point-ray model (:meth:`RestrictedOperator.normal3`)
    and adds two cheap volume filters (taps out to ``ceil(2 sigma)``).
    """

    def __init__(self, inset: np.ndarray, sigma: float):
        self.sigma = float(sigma)
        if not self.sigma > 0:
            raise ValueError(f"VolumeBlur: sigma must be > 0 voxels, got {sigma}")
        K = max(1, int(np.ceil(2.0 * self.sigma)))
        k = np.exp(-0.5 * (np.arange(-K, K + 1) / self.sigma) ** 2)
        self.taps = (k / k.sum()).astype(np.float32)
        inset = np.asarray(inset, dtype=bool)
        nz = [np.flatnonzero(inset.any(axis=tuple(j for j in range(3) if j != i))) for i in range(3)]
        lo = [int(a[0]) if len(a) else 0 for a in nz]
        hi = [int(a[-1]) + 1 if len(a) else 0 for a in nz]
        self.box = tuple(slice(a, b) for a, b in zip(lo, hi))
        sub = inset[self.box]
        self.shape = sub.shape
        self.idx = np.flatnonzero(sub).astype(np.int64)
        # The set's box as one OpenCV image of nz * (ny + 2K) rows, nx columns and the 3
        # components as channels, K zero rows above and below each z-plane: one sepFilter2D
        # (zero borders) filters every plane along x and y without mixing planes, a second
        # one along z treats each plane as one row: faster than a point-by-point numba
        # filter (docs/tuning.md, "Speed").
        nzb, nyb, nxb = self.shape
        self._K = (len(self.taps) - 1) // 2
        self._rows = nyb + 2 * self._K
        z, r = np.divmod(self.idx, max(nyb * nxb, 1))
        y, xx = np.divmod(r, max(nxb, 1))
        self._pidx = ((z * self._rows + y + self._K) * nxb + xx).astype(np.int64)
        self._a = np.zeros((nzb * self._rows, nxb, 3), np.float32)  # zero off the set, always

    _ONE = np.ones(1, np.float32)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``G x`` for ``x`` of shape (n, 3) (float64 result)."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, 3)
        out = np.empty((len(self.idx), 3))
        if len(self.idx):
            _move3(x, self._a.reshape(-1, 3), self._pidx, True)
            xy = cv2.sepFilter2D(self._a, cv2.CV_32F, self.taps, self.taps, borderType=cv2.BORDER_CONSTANT)
            xyz = cv2.sepFilter2D(xy.reshape(self.shape[0], -1), cv2.CV_32F, self._ONE, self.taps,
                                  borderType=cv2.BORDER_CONSTANT)
            _move3(xyz.reshape(-1, 3), out, self._pidx, False)
        return out
