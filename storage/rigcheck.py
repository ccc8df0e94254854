"""The files ``schlieren check`` reads: a camera's reference frames, a few frames of its
capture and its strobe window (:func:`camera_inputs`), the benchmark family's results
(:func:`family_cases`), and a fingerprint of a session folder that is being filled
(:func:`folder_state`, for ``--watch``). The checks themselves are pure
(:mod:`schlieren.pipeline.rigcheck`)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schlieren.pipeline.rigcheck.expect import FamilyCase
from schlieren.pipeline.sync.strobe import row_means
from schlieren.storage.errors import DroppedFrame
from schlieren.storage.readers.decoding import read_image
from schlieren.storage.readers.interlaced import InterlacedFields
from schlieren.storage.readers.kinds import frames_kind
from schlieren.storage.readers.opening import open_frames
from schlieren.storage.session.checks import frames_beside_strobe

__all__ = ["CameraInputs", "camera_inputs", "family_cases", "folder_state", "FAMILY_FILES"]

#: The family's results files read by :func:`family_cases` (relative to the results folder).
FAMILY_FILES = ("realistic.json", "realistic_bounds.json", "check_family.json")

#: At most this many reference frames are read. Enough: the sensor noise from 8 frames has
#: 7 degrees of freedom per pixel over some 10^5 pixels (a relative error of a few 1e-4),
#: their mean's noise is a few percent of a background's contrast, and the flow noise is
#: predicted for the reference the run averages from all its frames (``n_reference``).
MAX_REFERENCE_FRAMES = 8


@dataclass(frozen=True)
class CameraInputs:
    """What :func:`camera_inputs` read for one camera.

    Attributes
    ----------
    reference_frames : ndarray, shape (n, H, W), float32
        At most :data:`MAX_REFERENCE_FRAMES` of the reference's frames.
    n_reference : int
        Frames the reference holds (the run averages them all).
    frames : ndarray, shape (k, H, W), float32, or None
    frame_indices : tuple of int
    strobe_rows : ndarray, shape (F, H), or None
    full_scale : float
        255 for 8-bit frames, 65535 for 16-bit.
    n_frames : int
        Frames the camera holds now.
    """

    reference_frames: np.ndarray
    n_reference: int
    frames: np.ndarray | None
    frame_indices: tuple
    strobe_rows: np.ndarray | None
    full_scale: float
    n_frames: int


def _reference_frames(src) -> tuple[np.ndarray, int]:
    """At most :data:`MAX_REFERENCE_FRAMES` reference frames, and how many it holds."""
    kind = frames_kind(src.reference)
    if kind not in ("sequence", "glob", "folder", "tiff", "video"):  # one image file
        img, _ = read_image(src.reference, camera_name=src.name, field="reference")
        return img[None], 1
    fs = open_frames(src.reference, camera_name=src.name)
    if src.interlaced:
        fs = InterlacedFields(fs, src.interlaced)
    present = fs.present()
    return _stack(fs, present[:MAX_REFERENCE_FRAMES]), len(present)


def _stack(fs, indices) -> np.ndarray:
    """Frames ``indices`` of ``fs`` (float32), decoded one at a time into one array."""
    out = None
    for k, i in enumerate(indices):
        img = fs.read(i)
        if out is None:
            out = np.empty((len(indices),) + img.shape, np.float32)
        out[k] = img
    return out


def _spread(rng: tuple[int, int], k: int, skip) -> list[int]:
    a, b = rng
    cand = [i for i in range(a, b) if i not in skip]
    if len(cand) <= k:
        return cand
    return [cand[int(round(j * (len(cand) - 1) / max(k - 1, 1)))] for j in range(k)]


def _read(fs, indices, cache: dict) -> list[np.ndarray]:
    """Frames ``indices`` of ``fs`` (dropped ones skipped), each decoded once (``cache``)."""
    out = []
    for i in indices:
        if i not in cache:
            try:
                cache[i] = fs.read(i)
            except DroppedFrame:
                continue
        out.append(cache[i])
    return out


def camera_inputs(session, c: int, *, motion_frames: int = 3) -> CameraInputs:
    """Read camera ``c``'s reference frames, ``motion_frames`` frames spread over the
    frames to process (all frames beside the strobe window when the session gives none)
    and the strobe window's row means; each file decoded once."""
    src = session.sources[c]
    refs, n_ref = _reference_frames(src)
    fs = open_frames(src)
    n = len(fs)
    strobe = session.strobe_search
    rng = session.frames if session.frames is not None else frames_beside_strobe(n, strobe)
    rng = (min(rng[0], n), min(rng[1], n))
    skip = set(fs.dropped)
    idx = _spread(rng, motion_frames, skip)
    cache: dict = {}
    frames = _read(fs, idx, cache)
    rows = None
    if strobe is not None and strobe[1] <= n:
        rows = np.stack([row_means(f) for f in _read(fs, range(*strobe), cache)])
        rows = rows if len(rows) >= 3 else None
    full = 65535.0 if np.dtype(fs.raw_dtype).itemsize > 1 else 255.0  # known once a frame was read
    if hasattr(fs, "close"):
        fs.close()
    return CameraInputs(refs.astype(np.float32, copy=False), n_ref, np.stack(frames) if frames else None,
                        tuple(idx), rows, full, n)


def family_cases(results_dir: str | os.PathLike) -> tuple[list[FamilyCase], list[str]]:
    """The benchmark family's cases (``realistic.json``: each case's run; its bounds from
    ``realistic_bounds.json`` and its cameras' flow noise by LK window from
    ``check_family.json`` where present) and the files read; ``([], [])`` when the
    folder has none."""
    root = Path(results_dir)
    runs, bounds, read = {}, {}, []
    p = root / FAMILY_FILES[0]
    if p.is_file():
        runs = {c["case"]: c for c in json.loads(p.read_text(encoding="utf-8")).get("cases", [])}
        read.append(str(p))
    p = root / FAMILY_FILES[1]
    if p.is_file():
        bounds = json.loads(p.read_text(encoding="utf-8")).get("cases", {})
        read.append(str(p))
    noise = {}
    p = root / FAMILY_FILES[2]
    if p.is_file():
        noise = json.loads(p.read_text(encoding="utf-8")).get("cases", {})
        read.append(str(p))
    cases = []
    for name, c in runs.items():
        row = c.get("rows", {}).get("optical_flow")
        if not row:
            continue
        b = bounds.get(name, {}).get("rows", {}).get("consistent, run hull", {})
        bound = b.get("plume_db")
        fn = noise.get(name, {})
        cases.append(FamilyCase(name, int(c["cameras"]), tuple(c["size"]), bool(c.get("video")),
                                float(row["psnr"]), float(row["psnr_plume"]),
                                None if bound is None else float(bound), float(fn.get("noise", 1.5)),
                                tuple(sorted((int(w), float(v)) for w, v in fn.get("flow_noise", {}).items())),
                                int(fn.get("n_reference", 16))))
    return cases, read


def folder_state(folder: str | os.PathLike) -> tuple:
    """A fingerprint of every file under ``folder`` (relative path, size, modification
    time), sorted: it changes when a file arrives, grows or is rewritten."""
    root = Path(folder)
    out = []
    for dirpath, _, names in os.walk(root):
        for n in names:
            p = Path(dirpath) / n
            try:
                st = p.stat()
            except OSError:
                continue
            out.append((str(p.relative_to(root)), st.st_size, st.st_mtime_ns))
    return tuple(sorted(out))
