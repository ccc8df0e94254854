"""The flow's pre-smoothing against the background's focus: the measurements behind
``flow.presmooth: auto`` (pipeline/flow/focus.py; benchmarks/results/realistic_focus.md).

Two parts, both printed as markdown tables:

* ``--cases``: per case of the realistic family (its rendered sessions under ``--realistic``),
  the blur :func:`~schlieren.pipeline.flow.reference_blur` measures on each camera's
  reference (the sensor noise from the reference frames) and the pre-smoothing
  :func:`~schlieren.pipeline.flow.auto_presmooth` chooses.
* ``--textures``: the family's textures rendered as its renderer renders them (3 x 3
  supersampled Wavelet Noise of three scales, printed dots), in focus and blurred, with a
  known smooth deflection field (0.25 px, 48 px period) and 8-bit noise (1.5 grey levels, a
  16-frame reference): the flow's RMS error against the field for fixed pre-smoothing widths
  (the ground truth of which width is best), the choice of ``auto``, and the choice of a
  self-calibration (the reference warped by a known field with exact cubic B-splines, the
  sensor noise added, the width with the least error kept), which misses what the rendered
  truth shows on sharp textures.

Usage::

    python benchmarks/presmooth_focus.py --cases plume1-16cam-640,plume1-16cam-640-lab --textures
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from scipy import ndimage

from schlieren.pipeline.flow import auto_presmooth, deflection_field, reference_blur, warp_image
from schlieren.pipeline.rigcheck import sensor_noise
from schlieren.pipeline.synthetic.background import (Texture, make_texture_background, noise_values,
                                                     wavelet_noise_tile)
from schlieren.storage.frames import open_frames
from schlieren.storage.session import load_session

WIDTHS = (0.0, 0.3, 0.45, 0.6, 0.9)
TEXTURES = {"noise 1.5 (family)": Texture(), "noise 1.0 (fine)": Texture(scale=1.0),
            "noise 3.0 (coarse)": Texture(scale=3.0), "dots 4.0": Texture(kind="dots", scale=4.0)}
SHAPE = (240, 320)


def case_table(root: str, cases: list[str]) -> str:
    lines = ["| case | cameras | reference blur px (min..max) | auto presmooth px |", "|---|---:|---|---|"]
    for case in cases:
        blur, chosen = [], []
        session = load_session(os.path.join(root, case, "session.yaml"), check_files=False)
        for src in session.sources:
            ref_src = open_frames(src.reference, camera_name=src.name)
            frames = np.stack([np.asarray(ref_src.read(i), np.float64) for i in ref_src.present()])
            dtype = ref_src.raw_dtype
            full = float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None
            noise = sensor_noise(frames, full_scale=full) if len(frames) >= 2 else 0.0
            ref = frames.mean(axis=0).astype(np.float32)
            blur.append(reference_blur(ref, noise=noise, n_frames=len(frames)))
            chosen.append(auto_presmooth(ref, noise=noise, n_frames=len(frames)))
        vals = sorted(set(round(p, 3) for p in chosen))
        lines.append(f"| {case} | {len(blur)} | {min(blur):.3f}..{max(blur):.3f} | "
                     f"{', '.join(f'{v:g}' for v in vals)} |")
    return "\n".join(lines)


def _field(shape, amp=0.25, lam=48.0, seed=7):
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    ph = np.random.default_rng(seed).uniform(0, 2 * np.pi, 4)
    u = amp * np.sin(2 * np.pi * x / lam + ph[0]) * np.cos(2 * np.pi * y / (1.3 * lam) + ph[1])
    v = amp * np.cos(2 * np.pi * x / (1.2 * lam) + ph[2]) * np.sin(2 * np.pi * y / lam + ph[3])
    return np.stack([u, v], -1).astype(np.float32)


def _render(bg, d=None, ss=3):
    off = (np.arange(ss) + 0.5) / ss - 0.5
    y, x = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    dx, dy = (0.0, 0.0) if d is None else (d[..., 0], d[..., 1])
    acc = sum(noise_values(bg, np.stack([x + ox + dx, y + oy + dy], -1)) for oy in off for ox in off)
    return 128.0 + 40.0 * acc / ss ** 2


def _error(ref, frame, d, p, b=12):
    e = (deflection_field(ref, frame, window=9, presmooth=p) - d)[b:-b, b:-b]
    return float(np.sqrt((e ** 2).sum(-1).mean()))


def texture_table(noise: float = 1.5, n_ref: int = 16) -> str:
    head = " / ".join(f"{p:g}" for p in WIDTHS)
    lines = [f"| texture | blur px | reference blur px | flow error px at presmooth {head} | best | auto | "
             "self-calibration errors (same widths) | self-calibration's choice |",
             "|---|---:|---:|---|---:|---|---|---:|"]
    tile = wavelet_noise_tile(128, seed=3)
    d = _field(SHAPE)
    for name, tex in TEXTURES.items():
        bg = make_texture_background(np.zeros(3), np.array([0, 0, 1.0]), tex, pixel_footprint=1.0, tile=tile, seed=5)
        ref0, frm0 = _render(bg), _render(bg, d)
        for blur in (0.0, 0.4, 0.7, 1.0):
            rng = np.random.default_rng(0)
            r0, f0 = ((ndimage.gaussian_filter(a, blur, mode="nearest") if blur else a) for a in (ref0, frm0))

            def sensor(a):
                return np.clip(np.round(a + rng.normal(0, noise, a.shape)), 0, 255)

            ref = np.mean([sensor(r0) for _ in range(n_ref)], 0).astype(np.float32)
            frm = sensor(f0).astype(np.float32)
            truth = {p: _error(ref, frm, d, p) for p in WIDTHS}
            # self-calibration: the reference itself warped by a known field, sensor noise added
            ds = _field(SHAPE, seed=1)
            srng = np.random.default_rng(1)
            sfrm = np.round(warp_image(ref, ds) + srng.normal(0, noise, ref.shape)).astype(np.float32)
            selfcal = {p: _error(ref, sfrm, ds, p) for p in WIDTHS}
            auto = auto_presmooth(ref, noise=noise, n_frames=n_ref)
            lines.append(f"| {name} | {blur:g} | {reference_blur(ref, noise=noise, n_frames=n_ref):.3f} | "
                         + " / ".join(f"{truth[p]:.4f}" for p in WIDTHS)
                         + f" | {min(truth, key=truth.get):g} | {auto:.2f} ({_error(ref, frm, d, auto):.4f}) | "
                         + " / ".join(f"{selfcal[p]:.4f}" for p in WIDTHS)
                         + f" | {min(selfcal, key=selfcal.get):g} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--realistic", default="/work/realistic", help="the realistic family's work folder")
    ap.add_argument("--cases", default="", help="comma-separated case names (their rendered sessions)")
    ap.add_argument("--textures", action="store_true", help="the rendered-texture table")
    a = ap.parse_args()
    if a.cases:
        print(case_table(a.realistic, [c for c in a.cases.split(",") if c]))
        print()
    if a.textures:
        print(texture_table())


if __name__ == "__main__":
    main()
