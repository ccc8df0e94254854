"""OpenCV's dense inverse search (DIS, Kroeger et al. 2016) as a flow method."""

from __future__ import annotations

import cv2
import numpy as np


_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def _dis_flow(ref, frame, *, dis_preset):
    """OpenCV DIS (Kroeger et al. 2016). DIS needs 8-bit input: both images are scaled
    with one common linear map to 0..255 and rounded, which quantises the signal."""
    lo, hi = np.percentile(ref[::2, ::2], [0.1, 99.9])
    scale = 255.0 / max(float(hi - lo), 1e-12)
    r8 = np.clip((ref - lo) * scale, 0, 255).round().astype(np.uint8)
    f8 = np.clip((frame - lo) * scale, 0, 255).round().astype(np.uint8)
    dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[dis_preset])
    # calc(I0, I1) gives I0(x) ~= I1(x + flow): I0 = frame, I1 = reference.
    flow = dis.calc(f8, r8, None)
    return np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1])
