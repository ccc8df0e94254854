"""Synthetic ChArUco board views through a known camera: the ground truth of the
calibration's tests and demos.
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.calibration.board import BoardSpec
from schlieren.pipeline.calibration.projection import _distort_pixels, project_points

__all__ = ["BoardRenderer"]


class BoardRenderer:
    """Render a ChArUco board as seen by a known camera, for ground-truth tests.

    The printed board (:meth:`BoardSpec.texture`, white margin of one square) is sampled
    by exact inverse mapping: every output pixel is split into ``supersample**2``
    sub-pixels whose undistorted rays (distortion inverted numerically, once per
    camera) meet the board plane through a homography; the texture is read there with
    bicubic interpolation and the sub-pixels are averaged (area sampling, no aliasing).
    Optical blur (Gaussian) and sensor noise are then added and the image is
    quantised to uint8.

    Parameters
    ----------
    board : BoardSpec
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (k,)
    image_size : tuple of int
        ``(width, height)``.
    supersample : int
        Sub-pixels per pixel along each axis.
    pixels_per_square : int
        Texture resolution.
    """

    def __init__(self, board: BoardSpec, K, dist, image_size, *, supersample: int = 3,
                 pixels_per_square: int = 160):
        self.board = board
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64).ravel()
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.ss = int(supersample)
        self.pps = int(pixels_per_square)
        self.texture = board.texture(self.pps, 1).astype(np.float32) / 255.0
        W, H = self.image_size
        s = self.ss
        off = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(W)[:, None] + off[None, :]).ravel().astype(np.float32)
        v = (np.arange(H)[:, None] + off[None, :]).ravel().astype(np.float32)
        if np.any(self.dist != 0):
            # The undistortion map is smooth: solve it exactly on a coarse grid (step
            # 4 px, one cell of margin) and interpolate bicubically to the sub-pixels.
            step = 4.0
            uc = np.arange(-2 * step, W + 2 * step, step)
            vc = np.arange(-2 * step, H + 2 * step, step)
            ug, vg = np.meshgrid(uc, vc)
            coarse = self._undistort(np.stack([ug.ravel(), vg.ravel()], axis=1))
            coarse = coarse.reshape(len(vc), len(uc), 2).astype(np.float64)
            # (cv2.remap would quantise the positions to 1/32 cell: not accurate enough.)
            from scipy.interpolate import RectBivariateSpline  # here: loading the package costs every command 0.7 s

            xy = np.empty((len(v), len(u), 2), dtype=np.float32)
            for k in range(2):
                spline = RectBivariateSpline(vc, uc, coarse[..., k], kx=3, ky=3)
                xy[..., k] = spline(v.astype(np.float64), u.astype(np.float64))
            self._xy = xy
        else:
            Kinv = np.linalg.inv(self.K)
            uu, vv = np.meshgrid(u.astype(np.float64), v.astype(np.float64))
            xy = np.stack([uu, vv], axis=-1) @ Kinv[:2, :2].T + Kinv[:2, 2]
            self._xy = xy.astype(np.float32)

    def _undistort(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates of distorted pixel positions, shape (M, 2)."""
        Kinv = np.linalg.inv(self.K)
        if not np.any(self.dist != 0):
            return uv @ Kinv[:2, :2].T + Kinv[:2, 2]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        src = uv.reshape(-1, 1, 2)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            xy = cv2.undistortPointsIter(src, self.K, self.dist, None, None, crit)
        else:  # OpenCV 5 takes the criteria in undistortPoints
            xy = cv2.undistortPoints(src, self.K, self.dist, None, None, None, crit)
        xy = xy.reshape(-1, 2).astype(np.float64)
        # Newton polish on the forward model (closed-form 2x2 solve).
        d = np.zeros(8)
        d[: min(8, len(self.dist))] = self.dist[:8]
        fx, fy, cx, cy, sk = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], self.K[0, 1]
        h = 1e-7
        for _ in range(2):
            x, y = xy[:, 0], xy[:, 1]
            f0 = _distort_pixels(x, y, fx, fy, cx, cy, d, skew=sk)
            jx = (_distort_pixels(x + h, y, fx, fy, cx, cy, d, skew=sk) - f0) / h
            jy = (_distort_pixels(x, y + h, fx, fy, cx, cy, d, skew=sk) - f0) / h
            r = uv - f0
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            xy[:, 0] += (jy[:, 1] * r[:, 0] - jy[:, 0] * r[:, 1]) / det
            xy[:, 1] += (-jx[:, 1] * r[:, 0] + jx[:, 0] * r[:, 1]) / det
        return xy

    def render(self, R, t, *, blur_sigma: float = 0.7, noise_sigma: float = 2.0,
               black: float = 25.0, white: float = 230.0, surround: float = 110.0,
               rng: np.random.Generator | None = None) -> np.ndarray:
        """Image of the board at pose ``x_cam = R @ x_board + t``.

        Parameters
        ----------
        R : ndarray, shape (3, 3)
        t : ndarray, shape (3,)
            Metres.
        blur_sigma : float
            Gaussian optical blur, pixels.
        noise_sigma : float
            Additive Gaussian noise, grey levels.
        black, white, surround : float
            Grey levels of the printed black, the paper and what lies around the board.
        rng : numpy.random.Generator, optional
            Noise source (required when ``noise_sigma > 0``).

        Returns
        -------
        image : ndarray of uint8, shape (H, W)
        """
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).ravel()
        Hn = np.column_stack([R[:, 0], R[:, 1], t])  # board (X, Y, 1) -> normalised camera
        Hinv = np.linalg.inv(Hn)
        W, H = self.image_size
        s = self.ss
        sq = self.board.square_size
        nx, ny = self.board.squares
        # Only the pixels the paper can cover need sampling: bound its projected outline.
        r0, r1, c0, c1 = 0, H, 0, W
        e = np.linspace(0.0, 1.0, 50)
        X0, X1, Y0, Y1 = -sq, (nx + 1) * sq, -sq, (ny + 1) * sq
        edge = np.concatenate([np.stack([X0 + (X1 - X0) * e, np.full_like(e, Y0)], 1),
                               np.stack([X0 + (X1 - X0) * e, np.full_like(e, Y1)], 1),
                               np.stack([np.full_like(e, X0), Y0 + (Y1 - Y0) * e], 1),
                               np.stack([np.full_like(e, X1), Y0 + (Y1 - Y0) * e], 1)])
        Xc = np.column_stack([edge, np.zeros(len(edge))]) @ R.T + t
        if np.all(Xc[:, 2] <= 0):  # the paper lies wholly behind the camera
            r1 = r0
        elif np.all(Xc[:, 2] > 1e-6):
            uv = project_points(Xc, self.K, self.dist)
            if np.all(np.isfinite(uv)):
                c0 = int(np.clip(np.floor(uv[:, 0].min()) - 4, 0, W))
                c1 = int(np.clip(np.ceil(uv[:, 0].max()) + 5, 0, W))
                r0 = int(np.clip(np.floor(uv[:, 1].min()) - 4, 0, H))
                r1 = int(np.clip(np.ceil(uv[:, 1].max()) + 5, 0, H))
        img = np.full((H, W), np.float32(surround), dtype=np.float32)
        if r1 > r0 and c1 > c0:
            xy = self._xy[r0 * s:r1 * s, c0 * s:c1 * s]
            w = Hinv[2, 0] * xy[..., 0] + Hinv[2, 1] * xy[..., 1] + Hinv[2, 2]  # > 0: in front
            XY = cv2.perspectiveTransform(np.ascontiguousarray(xy).reshape(-1, 1, 2), Hinv)
            XY = XY.reshape(xy.shape)
            X, Y = XY[..., 0], XY[..., 1]
            inside = (w > 0) & (X >= X0) & (X <= X1) & (Y >= Y0) & (Y <= Y1)
            scale = np.float32(self.pps / sq)
            off = np.float32(self.pps - 0.5)
            mx = np.where(inside, X * scale + off, np.float32(-1.0))
            my = np.where(inside, Y * scale + off, np.float32(-1.0))
            tex = cv2.remap(self.texture, mx, my, interpolation=cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REPLICATE)
            np.clip(tex, 0.0, 1.0, out=tex)
            sub = np.where(inside, np.float32(black) + np.float32(white - black) * tex,
                           np.float32(surround))
            img[r0:r1, c0:c1] = sub.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        if noise_sigma > 0:
            if rng is None:
                raise ValueError("rng is required when noise_sigma > 0")
            img = img + rng.normal(0.0, noise_sigma, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
