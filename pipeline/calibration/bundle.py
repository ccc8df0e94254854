"""The bundle adjustment of the rig calibration: every camera's intrinsics, distortion and
pose and every board pose refined jointly by minimising the reprojection error of every
detected corner (Huber loss).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

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

    def jacobian(self, x, dense: bool = True):
        """Central-difference Jacobian of :meth:`residuals`, exploiting its block structure.

        Parameter ``k`` of every camera's intrinsics (or pose, or of every view's board
        pose) touches disjoint residual rows, so one pair of evaluations per parameter
        *kind* gives all of their columns: ``2 * (n_intr + 6 + 6)`` evaluations in all.
        """
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
        return J.toarray() if dense else J.tocsr()


def _levenberg_marquardt(prob: "_BundleProblem", x0, *, robust_scale: float, max_iter: int):
    """Levenberg-Marquardt on the Huber cost of the 2-D reprojection errors.

    Each observation's error ``e = |(du, dv)|`` costs ``e**2`` below ``robust_scale``
    and ``2 s e - s**2`` above (iteratively reweighted normal equations). The normal
    matrix is formed from the sparse Jacobian (no multi-threaded dense SVD, which
    thrashes on shared machines), damped by Marquardt's diagonal scaling.

    Returns
    -------
    x : ndarray
    info : dict
        ``iterations``, ``status``, ``cost``.
    """
    s = robust_scale

    def cost_and_weights(x):
        e = np.linalg.norm(prob.residuals(x).reshape(-1, 2), axis=1)
        big = e > s
        cost = np.where(big, 2 * s * e - s * s, e * e).sum()
        w = np.where(big, s / np.maximum(e, 1e-300), 1.0)
        return cost, w

    x = np.asarray(x0, dtype=np.float64).copy()
    cost, w = cost_and_weights(x)
    lam = 1e-3
    status = "maximum iterations reached"
    it = 0
    for it in range(1, max_iter + 1):
        r = prob.residuals(x)
        J = prob.jacobian(x, dense=False)
        sw = np.sqrt(np.repeat(w, 2))
        Jw = J.multiply(sw[:, None]).tocsr()
        A = (Jw.T @ Jw).toarray()
        g = Jw.T @ (sw * r)
        diag = np.maximum(np.diag(A).copy(), 1e-12)
        improved = False
        while lam < 1e12:
            try:
                dx = -np.linalg.solve(A + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            new_cost, new_w = cost_and_weights(x + dx)
            if np.isfinite(new_cost) and new_cost < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            status = "converged (no further decrease)"
            break
        rel = (cost - new_cost) / max(cost, 1e-300)
        x = x + dx
        cost, w = new_cost, new_w
        lam = max(lam / 10.0, 1e-12)
        if rel < 1e-10 or np.linalg.norm(dx) < 1e-12 * (np.linalg.norm(x) + 1e-12):
            status = "converged"
            break
    return x, {"iterations": it, "status": status, "cost": float(cost)}
