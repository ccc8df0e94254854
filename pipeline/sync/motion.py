"""The motion between two flow fields of one camera (paper sec. 4: successive fields are
warped along it to an instant between them): dense pyramidal Lucas-Kanade over the
fields' channels (:func:`field_motion`), and a per-process LRU of the motions of recent
frame pairs keyed by the fields' contents (:func:`cached_field_motion`).
"""

from __future__ import annotations

import hashlib
import threading

import cachetools
import cv2
import numpy as np

from schlieren.pipeline.flow.splines import prolong_flow, spline_coefficients, warp_coefficients

from .params import ResampleParams

__all__ = ["field_digest", "cached_field_motion", "field_motion"]


#: Motions between frame pairs recently computed in this process, keyed by the two
#: fields' contents and the parameters: successive output instants of a rolling-shutter
#: camera share a frame pair, so a task (or the next task of the camera on this worker)
#: finds the motion of the pair it shares with the previous instant here. Keyed by
#: content, so a hit returns exactly what :func:`field_motion` would.
_MOTION_CACHE = cachetools.LRUCache(maxsize=8)


def _digest(a: np.ndarray) -> bytes:
    # SHA-256, not BLAKE2b: it runs on the CPU's SHA extensions, and a resampled frame
    # takes four digests (docs/tuning.md, "Speed")
    a = np.ascontiguousarray(a, dtype=np.float32)
    return hashlib.sha256(memoryview(a).cast("B")).digest() + repr(a.shape).encode()


def field_digest(field: np.ndarray) -> bytes:
    """The motion cache's key of one flow field (its contents and shape): pass it to
    :func:`cached_field_motion` / :func:`resample_flow` where the caller has it already."""
    return _digest(field)


def _motion_key(source: np.ndarray, target: np.ndarray, *, digests: tuple[bytes, bytes] | None = None,
                **kwargs) -> tuple:
    """The motion cache's key: both fields' digests (``digests`` if the caller kept them)
    and the parameters."""
    ds, dt = digests if digests is not None else (_digest(source), _digest(target))
    return ds, dt, tuple(sorted(kwargs.items()))


@cachetools.cached(_MOTION_CACHE, key=_motion_key, lock=threading.Lock())
def _remembered_motion(source: np.ndarray, target: np.ndarray, *, digests=None, **kwargs) -> np.ndarray:
    # ``digests`` only feeds the key (:func:`_motion_key`)
    return field_motion(source, target, **kwargs)


def cached_field_motion(source: np.ndarray, target: np.ndarray, *, digests: tuple[bytes, bytes] | None = None,
                        **kwargs) -> np.ndarray:
    """:func:`field_motion`, remembered for the last few frame pairs of this process.

    ``digests``: :func:`field_digest` of ``source`` and ``target`` if the caller kept them
    (the resampling of neighbouring instants meets each raw field several times)."""
    return _remembered_motion(source, target, digests=digests, **kwargs).copy()


def field_motion(source: np.ndarray, target: np.ndarray, *, window: int = ResampleParams.window,
                 levels: int = ResampleParams.levels, iterations: int = ResampleParams.iterations,
                 regularisation: float = ResampleParams.regularisation,
                 finest_level: int = ResampleParams.finest_level) -> np.ndarray:
    """Motion ``m`` between two multi-channel fields: ``source(p) ~= target(p + m(p))``.

    Dense pyramidal Lucas-Kanade summing the structure tensors of all channels (here the
    u and v flow components), with a Tikhonov term so that regions without structure get
    zero motion. Used between successive flow fields of one camera (paper sec. 4).

    Parameters
    ----------
    source, target : ndarray, shape (h, w, C)
    window, levels, iterations, regularisation : int, int, int, float
        As in :class:`~.params.ResampleParams`.
    finest_level : int
        Finest pyramid level estimated (0: the fields' own grid); below it the motion is
        only prolonged to the fields' grid.

    Returns
    -------
    m : ndarray, shape (h, w, 2), float32 (component 0 = columns, 1 = rows)
    """
    src = np.asarray(source, np.float32)
    tgt = np.asarray(target, np.float32)
    if src.ndim == 2:
        src, tgt = src[..., None], tgt[..., None]
    C = src.shape[-1]
    # per level: lists of 2-D channel images (fine first)
    pyr_s = [[np.ascontiguousarray(src[..., k]) for k in range(C)]]
    pyr_t = [[np.ascontiguousarray(tgt[..., k]) for k in range(C)]]
    for _ in range(levels - 1):
        if min(pyr_s[-1][0].shape) < 2 * window:
            break
        pyr_s.append([cv2.pyrDown(a) for a in pyr_s[-1]])
        pyr_t.append([cv2.pyrDown(a) for a in pyr_t[-1]])
    h, w = pyr_s[-1][0].shape
    mu = np.zeros((h, w), np.float32)
    mv = np.zeros((h, w), np.float32)
    taps = np.full(window, 1.0 / window, np.float32)

    def box(a):
        return cv2.sepFilter2D(a, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REFLECT)

    stop = min(finest_level, len(pyr_s) - 1)
    for lev in range(len(pyr_s) - 1, stop - 1, -1):
        s_ch, t_ch = pyr_s[lev], pyr_t[lev]
        h, w = s_ch[0].shape
        if mu.shape != (h, w):
            mu, mv = prolong_flow(mu, mv, (h, w))
        gx = [cv2.Scharr(a, cv2.CV_32F, 1, 0, scale=1 / 32) for a in s_ch]
        gy = [cv2.Scharr(a, cv2.CV_32F, 0, 1, scale=1 / 32) for a in s_ch]
        sxx = box(sum(g * g for g in gx))
        sxy = box(sum(a * b for a, b in zip(gx, gy)))
        syy = box(sum(g * g for g in gy))
        lam = np.float32(regularisation * float(np.percentile((sxx + syy)[::2, ::2], 99)) + 1e-12)
        pxx = sxx + lam
        pyy = syy + lam
        det = pxx * pyy - sxy * sxy
        coefs = [spline_coefficients(a) for a in t_ch]
        for _ in range(iterations):
            disp = np.stack([mu, mv], -1)
            bx = np.zeros((h, w), np.float32)
            by = np.zeros((h, w), np.float32)
            for k in range(C):
                # linearised around each cell's own warp (as in pipeline.flow LK)
                e = s_ch[k] - warp_coefficients(coefs[k], disp) + gx[k] * mu + gy[k] * mv
                bx += gx[k] * e
                by += gy[k] * e
            bx = box(bx)
            by = box(by)
            mu = ((pyy * bx - sxy * by) / det).astype(np.float32)
            mv = ((pxx * by - sxy * bx) / det).astype(np.float32)
    for lev in range(stop - 1, -1, -1):  # levels below ``finest``: the motion prolonged only
        mu, mv = prolong_flow(mu, mv, pyr_s[lev][0].shape)
    return np.stack([mu, mv], -1)
