"""What a run made of a capture, beyond its score: how much the masks and the hull cover,
and how much the flow moves where nothing flows.

On a clean capture the masks cover the plume's footprint (a few percent of each image)
and the visual hull a tenth of the box; the flow where no ray crosses the flow is sensor
noise (hundredths of a pixel). A capture whose camera moved against its reference, or
whose lamp flickered, shows it here first: the flow carries the camera's motion
everywhere, the masks fill the images, and the hull fills the box (issue 33).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["capture_diagnostics", "QUIET_PX"]

#: A flow cell "has nothing flowing" where the truth's deflection stays below this (pixels)
#: in it and its neighbours (the truth is exactly 0 where a ray misses the flow).
QUIET_PX = 1e-3


def _quiet_cells(truth_defl: np.ndarray, truth_factor: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Store flow cells (v, u) whose truth cells, dilated by one, hold no deflection above
    :data:`QUIET_PX`; ``truth_defl`` (rows, cols, 2) on the truth's flow grid."""
    mag = np.hypot(truth_defl[..., 0], truth_defl[..., 1])
    busy = ndimage.maximum_filter(np.nan_to_num(mag, nan=np.inf), size=3, mode="nearest") >= QUIET_PX
    rows = np.clip((np.asarray(v) // truth_factor).astype(int), 0, busy.shape[0] - 1)
    cols = np.clip((np.asarray(u) // truth_factor).astype(int), 0, busy.shape[1] - 1)
    return ~busy[np.ix_(rows, cols)]


def capture_diagnostics(store_path, truth_path) -> dict:
    """Mask and hull fill fractions and the flow's magnitude where nothing flows.

    Returns
    -------
    dict
        ``mask_fill`` (mean over camera-frames of the masked fraction of flow cells),
        ``mask_fill_max``, ``hull_fill`` (mean over frames of the hull's fraction of the
        box's voxels), ``quiet_flow_median`` (median of ``|flow|`` over every camera-frame's
        cells where nothing flows, pixels), ``quiet_flow_p90_camera_frame`` (90th percentile
        over camera-frames of that median per camera-frame) and ``quiet_fraction``.
    """
    from schlieren.storage import synthetic_io as sio
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store_path, mode="r")
    out: dict = {}
    if "mask" in st:
        m = np.asarray(st.read("mask"), dtype=bool)
        fill = m.reshape(m.shape[0] * m.shape[1], -1).mean(axis=1)
        out["mask_fill"] = float(fill.mean())
        out["mask_fill_max"] = float(fill.max())
    if "hull" in st:
        h = np.asarray(st.read("hull"), dtype=bool)
        out["hull_fill"] = float(h.reshape(h.shape[0], -1).mean(axis=1).mean())
    if "flow" not in st:
        return out
    flow = np.asarray(st.read("flow"), dtype=np.float64)              # camera, frame, v, u, 2
    u = np.asarray(st.read("u"), dtype=np.float64)
    v = np.asarray(st.read("v"), dtype=np.float64)
    truth = sio.read_truth(truth_path)
    tf = int(truth.attrs.get("flow_factor", 3))
    tdef = np.asarray(truth.group["deflection"][...], dtype=np.float64)  # camera, frame, rows, cols, 2
    mags, medians, quiet_n, total = [], [], 0, 0
    for c in range(flow.shape[0]):
        for k in range(min(flow.shape[1], tdef.shape[1])):
            quiet = _quiet_cells(tdef[c, k], tf, u, v)
            mag = np.hypot(flow[c, k, ..., 0], flow[c, k, ..., 1])[quiet]
            mag = mag[np.isfinite(mag)]
            quiet_n += int(quiet.sum())
            total += quiet.size
            if mag.size:
                mags.append(mag)
                medians.append(float(np.median(mag)))
    if mags:
        out["quiet_flow_median"] = float(np.median(np.concatenate(mags)))
        out["quiet_flow_p90_camera_frame"] = float(np.percentile(medians, 90))
        out["quiet_fraction"] = quiet_n / max(total, 1)
    return out
