"""The bundle adjustment of the rig calibration: every camera's intrinsics, distortion and
pose and every board pose refined jointly by minimising the reprojection error of every
detected corner (Huber loss), with :func:`scipy.optimize.least_squares`.

:class:`_BundleProblem` packs the parameters and gives the residuals and their sparse,
block-structured Jacobian; :func:`_bundle_adjust` runs the solver.
"""

from __future__ import annotations

import numpy as np

# scipy.optimize, .sparse and .spatial are imported where used: every command that loads a
# session imports this module (the calibration checks), and they take 0.6 s to load
from schlieren.pipeline.calibration.projection import _distort_pixels, _pose_matrix


class _BundleProblem:
    """Parameter packing and residuals of the joint refinement.

    Parameters (in order): per camera ``fx fy cx cy dist[n_dist]``; per non-reference
    camera ``rvec tvec`` (camera <- reference); per view ``rvec tvec`` (reference <- board).
    """

    def __init__(self, names, ref, views, obs_cam, obs_view, obs_pts, obs_uv, n_dist):
        self.names, self.ref, self.views = list(names), ref, list(views)
        self.n_dist = n_dist
        self.n_intr = 4 + n_dist
        self.n_cam = len(self.names)
        self.free = [i for i, n in enumerate(self.names) if n != ref]
        self.ext_index = {ci: j for j, ci in enumerate(self.free)}
        self.view_index = {v: j for j, v in enumerate(self.views)}
        self.obs_cam, self.obs_pts, self.obs_uv = obs_cam, obs_pts, obs_uv
        self.obs_vidx = np.array([self.view_index[v] for v in obs_view], dtype=np.int64)
        self.o_ext = self.n_cam * self.n_intr
        self.o_view = self.o_ext + 6 * len(self.free)
        self.n_params = self.o_view + 6 * len(self.views)

    def pack(self, K, dist, T_cam_ref, T_ref_board) -> np.ndarray:
        from scipy.spatial.transform import Rotation
        x = np.zeros(self.n_params)
        for i, n in enumerate(self.names):
            o = i * self.n_intr
            x[o:o + 4] = K[n][0, 0], K[n][1, 1], K[n][0, 2], K[n][1, 2]
            x[o + 4:o + self.n_intr] = dist[n][: self.n_dist]
        for ci, j in self.ext_index.items():
            T = T_cam_ref[self.names[ci]]
            o = self.o_ext + 6 * j
            x[o:o + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[o + 3:o + 6] = T[:3, 3]
        for v, j in self.view_index.items():
            T = T_ref_board[v]
            o = self.o_view + 6 * j
            x[o:o + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[o + 3:o + 6] = T[:3, 3]
        return x

    def unpack(self, x):
        from scipy.spatial.transform import Rotation
        K, dist, T_cam_ref, T_ref_board = {}, {}, {}, {}
        for i, n in enumerate(self.names):
            o = i * self.n_intr
            fx, fy, cx, cy = x[o:o + 4]
            K[n] = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            dist[n] = x[o + 4:o + self.n_intr].copy()
            T_cam_ref[n] = np.eye(4)
        for ci, j in self.ext_index.items():
            o = self.o_ext + 6 * j
            R = Rotation.from_rotvec(x[o:o + 3]).as_matrix()
            T_cam_ref[self.names[ci]] = _pose_matrix(R, x[o + 3:o + 6])
        for v, j in self.view_index.items():
            o = self.o_view + 6 * j
            T_ref_board[v] = _pose_matrix(Rotation.from_rotvec(x[o:o + 3]).as_matrix(), x[o + 3:o + 6])
        return K, dist, T_cam_ref, T_ref_board

    def residuals(self, x) -> np.ndarray:
        from scipy.spatial.transform import Rotation
        intr = x[: self.o_ext].reshape(self.n_cam, self.n_intr)
        ext = np.zeros((self.n_cam, 6))
        if self.free:
            ext[self.free] = x[self.o_ext:self.o_view].reshape(-1, 6)
        vw = x[self.o_view:].reshape(-1, 6)
        Rc = Rotation.from_rotvec(ext[:, :3]).as_matrix()
        Rv = Rotation.from_rotvec(vw[:, :3]).as_matrix()
        c, v = self.obs_cam, self.obs_vidx
        X_ref = np.einsum("mij,mj->mi", Rv[v], self.obs_pts) + vw[v, 3:]
        X_cam = np.einsum("mij,mj->mi", Rc[c], X_ref) + ext[c, 3:]
        d = np.zeros((len(c), 8))
        d[:, : self.n_dist] = intr[c, 4:]
        z = X_cam[:, 2]
        uv = _distort_pixels(X_cam[:, 0] / z, X_cam[:, 1] / z, intr[c, 0], intr[c, 1],
                             intr[c, 2], intr[c, 3], d)
        return (uv - self.obs_uv).ravel()

    def jacobian(self, x):
        """Central-difference Jacobian of :meth:`residuals`, exploiting its block structure.

        Parameter ``k`` of every camera's intrinsics (or pose, or of every view's board
        pose) touches disjoint residual rows, so one pair of evaluations per parameter
        *kind* gives all of their columns: ``2 * (n_intr + 6 + 6)`` evaluations in all.
        """
        from scipy.sparse import coo_matrix
        m = len(self.obs_cam)
        obs = np.arange(m)
        free = np.array([self.ext_index.get(int(ci), -1) for ci in self.obs_cam], dtype=np.int64)
        groups = []
        for k in range(self.n_intr):
            groups.append((obs, self.obs_cam * self.n_intr + k))
        if self.free:
            for k in range(6):
                sel = free >= 0
                groups.append((obs[sel], self.o_ext + 6 * free[sel] + k))
        for k in range(6):
            groups.append((obs, self.o_view + 6 * self.obs_vidx + k))
        rows_all, cols_all, vals_all = [], [], []
        for o, cols in groups:
            ucols = np.unique(cols)
            h = 1e-6 * np.maximum(1.0, np.abs(x[ucols]))
            step = np.zeros_like(x)
            step[ucols] = h
            diff = (self.residuals(x + step) - self.residuals(x - step)).reshape(-1, 2)
            hh = 2.0 * step[cols]
            for c in (0, 1):
                rows_all.append(2 * o + c)
                cols_all.append(cols)
                vals_all.append(diff[o, c] / hh)
        J = coo_matrix((np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
                       shape=(2 * m, self.n_params))
        return J.tocsr()


def _huber(z: np.ndarray) -> np.ndarray:
    """scipy's ``"huber"`` loss with Gauss-Newton (IRLS) curvature, for ``least_squares(loss=...)``.

    ``rho(z) = z`` for ``z <= 1`` and ``2 sqrt(z) - 1`` above (``z = (r / f_scale)**2``), and
    ``rho'``, exactly as scipy's ``loss="huber"``, so the cost and its gradient are the same.
    Only ``rho''`` of the linear branch is given as 0 instead of ``-z**-1.5 / 2``: scipy then
    weights a residual's Jacobian row by ``sqrt(rho')`` (iteratively reweighted least squares)
    instead of zeroing it (its ``J_scale = rho' + 2 rho'' z`` is 0 there, clamped to machine
    epsilon, and the residual is multiplied by ``1 / sqrt(eps)``), which stalls the LSMR
    trust-region steps: with 3 % of the corners misdetected by 3-8 px the built-in loss had not
    converged after 300 iterations (camera rotations 0.6 degree off), this one converges in 6
    to the same minimum that the built-in loss reaches with dense exact steps.
    """
    rho = np.empty((3, z.size))
    big = z > 1.0
    sq = np.sqrt(z[big])
    rho[0] = z
    rho[0][big] = 2.0 * sq - 1.0
    rho[1] = 1.0
    rho[1][big] = 1.0 / sq
    rho[2] = 0.0
    return rho


def _bundle_adjust(prob: _BundleProblem, x0, *, robust_scale: float, max_iter: int):
    """Minimise the Huber cost of the reprojection errors with :func:`scipy.optimize.least_squares`.

    Trust-region reflective (``method="trf"``; scipy's ``"lm"`` takes no robust loss) with the
    Huber loss (:func:`_huber`) and ``f_scale=robust_scale``: each residual component ``r``
    (pixels) costs ``r**2`` below ``robust_scale`` and ``2 s |r| - s**2`` above. The Jacobian
    is :meth:`_BundleProblem.jacobian` (sparse); the trust-region steps are solved by LSMR on
    it (no dense SVD of the Jacobian, whose memory grows with the rig and which thrashes with
    multi-threaded BLAS on shared machines), to a tolerance tight enough that the steps equal
    the exact ones. ``x_scale="jac"`` scales the parameters as Marquardt's diagonal damping does.

    Returns
    -------
    x : ndarray
    info : dict
        ``iterations`` (Jacobian evaluations), ``status`` (scipy's message), ``cost``.
    """
    from scipy.optimize import least_squares
    res = least_squares(prob.residuals, np.asarray(x0, dtype=np.float64), jac=prob.jacobian, method="trf",
                        loss=_huber, f_scale=float(robust_scale), x_scale="jac", max_nfev=int(max_iter),
                        tr_solver="lsmr", tr_options={"atol": 1e-12, "btol": 1e-12,
                                                      "maxiter": max(1000, 10 * prob.n_params)})
    return res.x, {"iterations": int(res.njev), "status": res.message, "cost": float(res.cost)}
