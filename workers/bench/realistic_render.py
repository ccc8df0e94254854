"""Rendering the realistic family's sessions (``schlieren bench realistic``), cached in the work folder.

A case's flow (the CFD knots, simulated once and cached, :func:`cfd_flow`) is upsampled,
scaled so its deflections peak at the case's request (traced probes,
:func:`_solve_scale`), and rendered by :func:`schlieren.workers.synth.synthesize` with the
case's rig, format, texture, readout and lab effects (:func:`ensure_session`). A lab case
takes the scale its clean twin was rendered at, when that twin is in the work folder, so
the two captures differ by the lab effects alone.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.storage import bench_io
from schlieren.storage import synthetic_io as sio
from schlieren.workers.bench.realistic_cases import (BOX, CFD_KNOTS, CFD_T0, FLOWS, TEXTURES, VOXEL, Flow,
                                                     RealisticCase, clean_twin)

__all__ = ["cfd_flow", "ensure_session", "PEAK_TOL", "PROPORTIONAL_STEPS", "MAX_PROBES", "RENDER_TOL"]

log = logging.getLogger(__name__)

#: Scale calibration (:func:`_solve_scale`): the probed peak is accepted within this
#: relative tolerance of the request; the first ``PROPORTIONAL_STEPS`` steps assume
#: peak ~ scale, later ones are secant steps in log-log coordinates; at most
#: ``MAX_PROBES`` probes per solve.
PEAK_TOL = 0.02
PROPORTIONAL_STEPS = 3
MAX_PROBES = 12
#: The rendered truth's peak (what the results report) may miss the request by this much
#: before the probe target is corrected by the truth/probe ratio and the case re-rendered once.
RENDER_TOL = 0.03


def _grid(voxel: float) -> Grid:
    return Grid(BOX[0], BOX[1], voxel)


def cfd_flow(flow: Flow, cache_dir: Path, *, voxel: float = VOXEL, progress: Callable[[str], None] | None = None):
    """The flow's CFD knots on the ``voxel`` grid (simulated once, then read from the cache)."""
    from schlieren.pipeline.synthetic import cfd

    grid = _grid(voxel)
    params = flow.params()
    key = hashlib.sha1(json.dumps({"params": dataclasses.asdict(params), "seed": flow.seed, "knots": CFD_KNOTS,
                                   "t0": CFD_T0, "box": BOX, "voxel": voxel, "version": 1},
                                  sort_keys=True).encode()).hexdigest()[:12]
    path = Path(cache_dir) / f"cfd-{flow.name}-{key}.npz"
    t0 = time.perf_counter()

    def compute():
        if progress:
            progress(f"simulating {flow.name} with PhiFlow on a {'x'.join(map(str, grid.shape))} grid (cached "
                     f"afterwards in {path})")
        last = [0.0]

        def tick(step, total):
            if progress and time.perf_counter() - last[0] > 60:
                last[0] = time.perf_counter()
                progress(f"  {flow.name}: step {step}/{total} ({time.perf_counter() - t0:.0f} s)")

        r = cfd.simulate_cfd(grid, params, n_knots=CFD_KNOTS, t_first=CFD_T0, seed=flow.seed, progress=tick)
        return {"excess": r.excess, "knot_times": r.knot_times, "params": json.dumps(r.params)}

    arrays = bench_io.cached_arrays(path, compute)
    return cfd.CFDResult(grid=grid, knot_times=arrays["knot_times"], excess=arrays["excess"],
                         params=json.loads(str(arrays["params"])))


def _scaled(result, scale: float):
    from schlieren.pipeline.synthetic.cfd import CFDResult

    return CFDResult(grid=result.grid, knot_times=result.knot_times,
                     excess=(result.excess * np.float32(scale)).astype(np.float32), params=result.params)


def _factory(result, medium: Medium):
    from schlieren.pipeline.synthetic.cfd import cfd_phantom

    def make(fine, *, t_start, duration, seed, medium=medium, knot_dt=None):
        return cfd_phantom(result, medium=medium)

    return make


def _quick_flow(grid: Grid):
    """A tiny analytic stand-in for the CFD (tests): a tilted hot Gaussian wisp, static."""
    from schlieren.pipeline.synthetic.cfd import CFDResult

    z, y, x = np.meshgrid(*[a for a in grid.axes()[::-1]], indexing="ij")
    cx = 0.01 * np.sin(z / 0.05)
    blob = 40.0 * np.exp(-(((x - cx) ** 2 + y ** 2) / (2 * 0.012 ** 2)) - ((z - 0.12) ** 2) / (2 * 0.05 ** 2))
    kt = CFD_T0 + np.arange(CFD_KNOTS) / 120.0
    return CFDResult(grid=grid, knot_times=kt, excess=np.broadcast_to(blob.astype(np.float32),
                                                                      (CFD_KNOTS,) + grid.shape).copy(),
                     params={"kind": "quick"})


def _render(case: RealisticCase, d: Path, result, *, voxel: float):
    from schlieren.pipeline.synthetic.lab import LAB_PRESETS
    from schlieren.workers.synth import synthesize

    extra = {}  # only what a case sets: the family's first renders were made without these arguments
    if case.lab is not None:
        extra["lab"] = LAB_PRESETS[case.lab]
    if case.texture is not None:
        extra["texture"] = TEXTURES[case.texture]
    if case.line_time is not None:
        extra["line_time"] = case.line_time
    return synthesize(d, cameras=case.cameras, ring="half", phantom=_factory(result, Medium()), frames=case.frames,
                      size=tuple(case.size), flow_factor=3, seed=FLOWS[case.flow].seed, noise=case.noise,
                      video=case.video is not None, video_codec=case.video or "ffv1",
                      video_bits_per_pixel=case.bits_per_pixel, distortion=case.distortion, voxel_size=voxel,
                      recon_voxel=voxel, reference_frames=case.reference_frames, knot_dt=1.0 / 120.0,
                      name=f"realistic-{case.name}", manifest_voxel=case.manifest_voxel, **extra)


def _peak_deflection(truth_path) -> float:
    t = sio.read_truth(truth_path)
    d = np.asarray(t.group["deflection"][...], dtype=np.float64)
    return float(np.percentile(np.hypot(d[..., 0], d[..., 1]), 99.9))


def _probe_peak(case: RealisticCase, result) -> float:
    """99.9th percentile of the flow's deflection magnitude (pixels) in the case's rig.

    Point rays traced on the flow lattice at the middle processed frame, without rendering
    images. The truth's peak (:func:`_peak_deflection`, pixel means over the flow-grid
    cells of every processed frame) is what the results report; the two agree within a
    couple of percent for the CFD flows, less closely for a flow only a few lattice cells wide.
    """
    from schlieren.pipeline.synthetic import render as R
    from schlieren.pipeline.synthetic.rig import make_rig
    from schlieren.pipeline.synthetic.tracer import active_box, field_stack
    from schlieren.workers.synth import DISTORTION, FIRST_FRAME

    grid = result.grid
    rig = make_rig(case.cameras, ring="half", grid=grid, radius=2.5, image_size=tuple(case.size),
                   background_distance=2.5, distortion=DISTORTION if case.distortion else None, seed=FLOWS[case.flow].seed)
    t = (FIRST_FRAME + 0.5 * case.frames) / 60.0
    j = int(np.clip(np.searchsorted(result.knot_times, t), 1, len(result.knot_times) - 1))
    from schlieren.pipeline.synthetic.phantoms import refractivity_from_temperature

    med = Medium()
    vols = [refractivity_from_temperature(med.T_ambient + result.excess[i].astype(np.float64), med)
            for i in (j - 1, j)]
    fields = field_stack(vols, grid)
    box = active_box(fields, grid, tol=1e-5)
    lattice = R.make_lattice(tuple(case.size), 3)
    mags = []
    for cam in rig:
        tr = R.trace_lattice(cam, lattice, fields, result.knot_times[j - 1:j + 1], grid, frame=None, time=t,
                             frame_rate=60.0, n_ambient=med.n_ambient, clip_box=box)
        mags.append(np.hypot(tr.delta[..., 0], tr.delta[..., 1]).ravel())
    return float(np.percentile(np.concatenate(mags), 99.9))


def _solve_scale(probe: Callable[[float], float], target: float, probes: list[tuple[float, float]]
                 ) -> tuple[float, float, bool]:
    """Excess-temperature scale whose probed peak is within :data:`PEAK_TOL` of ``target``.

    ``probe(scale)`` is the peak deflection (px) of the flow scaled by ``scale``;
    ``probes`` the ``(scale, peak)`` pairs probed so far (appended to; empty: start at
    scale 1). The deflection is not linear in the temperature excess: the refractivity goes
    as 1 / T, so the deflection saturates as the excess grows. The first
    :data:`PROPORTIONAL_STEPS` steps assume peak ~ scale (enough for the CFD flows, which
    need a scale near 1); after that each step follows the local power law between the
    last two probes (a secant step on log peak against log scale), which converges where a
    weak flow must be scaled far into the saturated regime.

    Returns ``(scale, peak, converged)``: the accepted scale and its probed peak, or,
    after :data:`MAX_PROBES` probes without convergence, the probe closest to ``target``.
    """
    def accepted(peak):
        return peak <= 0 or abs(peak / target - 1.0) < PEAK_TOL

    if not probes:
        probes.append((1.0, probe(1.0)))
    for n in range(MAX_PROBES):
        scale, peak = probes[-1]
        if accepted(peak):
            return scale, peak, True
        if n == MAX_PROBES - 1:
            break
        slope = 1.0
        if len(probes) > PROPORTIONAL_STEPS:
            (s0, p0), (s1, p1) = probes[-2], probes[-1]
            if p0 > 0 and abs(np.log(s1 / s0)) > 1e-9:
                slope = float(np.log(p1 / p0) / np.log(s1 / s0))
            # a slope near zero (or negative) would step off to an absurd scale: bound it
            slope = min(max(slope, 0.1), 1.0) if np.isfinite(slope) else 1.0
        scale *= (target / peak) ** (1.0 / slope)
        probes.append((scale, probe(scale)))
    scale, peak = min((sp for sp in probes if sp[1] > 0), key=lambda sp: abs(np.log(sp[1] / target)))
    return scale, peak, False


def ensure_session(case: RealisticCase, work: Path, *, progress: Callable[[str], None] | None = None) -> dict:
    """Render ``case`` into ``work/<name>`` unless a session with the same content key is there.

    The flow's temperature excess is scaled so the deflections peak at
    :attr:`RealisticCase.peak_px` (traced probes, :func:`_probe_peak` and
    :func:`_solve_scale`). The reported peak is the rendered truth's
    (:func:`_peak_deflection`); if it misses the request by more than :data:`RENDER_TOL`
    (the probe and the truth measure differently), the probe target is corrected by their
    ratio and the case is rendered once more.
    """
    say = progress or (lambda m: log.info("%s", m))
    d = Path(work) / case.name
    stamp = d / "case.json"
    key = case.key()
    if stamp.exists():
        info = json.loads(stamp.read_text())
        if info.get("key") == key and (d / "session.yaml").exists() and (d / "truth.zarr").exists():
            return info
    bench_io.remove_tree(d)
    t0 = time.perf_counter()
    syn, scale, peak = _render_at_peak(case, d, _flow_knots(case, work, say), say, known=_known_scale(case, work))
    info = {"key": key, "case": dataclasses.asdict(case), "session": str(syn.session), "truth": str(syn.truth),
            "scale": scale, "peak_px": peak, "render_seconds": time.perf_counter() - t0}
    bench_io.write_json(stamp, info)
    say(f"{case.name}: rendered ({info['render_seconds']:.0f} s, peak deflection {peak:.3f} px)")
    return info


def _flow_knots(case: RealisticCase, work: Path, say: Callable[[str], None]):
    """The case's flow (the CFD knots, or the quick cases' analytic stand-in), upsampled
    ``case.upsample`` times."""
    from schlieren.pipeline.synthetic.cfd import upsample_cfd

    if case.name.startswith("quick"):
        knots = _quick_flow(_grid(case.voxel))
    else:
        knots = cfd_flow(FLOWS[case.flow], Path(work) / "_cfd", voxel=case.voxel, progress=say)
    return upsample_cfd(knots, case.upsample)


def _known_scale(case: RealisticCase, work: Path) -> tuple[str, float] | None:
    """``(case name, scale)`` of a case rendered in ``work`` whose deflections are this
    case's (same flow, rig, peak and grid; the lab effects, the texture, the format and the
    readout aside), preferring the clean twin; None if there is none."""
    from schlieren.workers.bench.realistic_cases import BITRATE_CASES, CASES, QUICK_CASES

    same = ("flow", "cameras", "size", "distortion", "peak_px", "frames", "upsample", "voxel")
    twin = clean_twin(case)
    pool = ([twin] if twin is not None else []) + [c for c in CASES + QUICK_CASES + BITRATE_CASES
                                                   if c.name != case.name and c is not twin]
    for c in pool:
        if any(getattr(c, k) != getattr(case, k) for k in same):
            continue
        stamp = Path(work) / c.name / "case.json"
        if stamp.exists():
            info = json.loads(stamp.read_text())
            if info.get("key") == c.key() and "scale" in info:
                return c.name, float(info["scale"])
    return None


def _render_at_peak(case: RealisticCase, d: Path, base, say: Callable[[str], None],
                    known: tuple[str, float] | None = None):
    """Render ``case`` into ``d`` with the flow ``base`` scaled to the requested peak
    deflection (re-rendered once if the truth misses it, see :func:`ensure_session`):
    ``(SynthResult, scale, truth's peak)``. ``known`` (:func:`_known_scale`) is tried first:
    kept if the rendered truth's peak is within :data:`RENDER_TOL` of the request."""
    if known is not None:
        syn = _render(case, d, _scaled(base, known[1]), voxel=case.voxel)
        peak = _peak_deflection(syn.truth)
        if peak > 0 and abs(peak / case.peak_px - 1.0) <= RENDER_TOL:
            say(f"{case.name}: excess temperature x {known[1]:.3f}, as {known[0]} was rendered")
            return syn, known[1], peak
        say(f"{case.name}: {known[0]}'s scale gives a peak of {peak:.3f} px; solving for its own")
        bench_io.remove_tree(d)
    def probe(scale: float) -> float:
        return _probe_peak(case, _scaled(base, scale))

    def warn_unconverged(target: float, peak: float):
        say(f"{case.name}: the scale did not converge in {MAX_PROBES} probes (probed peak {peak:.3f} px for "
            f"{target:.3f} px); using the closest")

    probes: list[tuple[float, float]] = []
    scale, probed, ok = _solve_scale(probe, case.peak_px, probes)
    if not ok:
        warn_unconverged(case.peak_px, probed)
    say(f"{case.name}: unscaled peak deflection {probes[0][1]:.3f} px -> excess temperature x {scale:.3f} "
        f"({len(probes)} probes)")
    syn = _render(case, d, _scaled(base, scale), voxel=case.voxel)
    peak = _peak_deflection(syn.truth)
    if peak > 0 and probed > 0 and abs(peak / case.peak_px - 1.0) > RENDER_TOL:
        # calibrate the probe against the truth: their ratio hardly depends on the scale
        target = case.peak_px * probed / peak
        say(f"{case.name}: rendered peak {peak:.3f} px (probed {probed:.3f} px); re-solving for a probed "
            f"{target:.3f} px")
        probes.remove((scale, probed))  # the accepted point is where the new solve steps from
        probes.append((scale, probed))
        n0 = len(probes)
        scale, probed, ok = _solve_scale(probe, target, probes)
        if not ok:
            warn_unconverged(target, probed)
        say(f"{case.name}: excess temperature x {scale:.3f} ({len(probes) - n0} more probes)")
        bench_io.remove_tree(d)
        syn = _render(case, d, _scaled(base, scale), voxel=case.voxel)
        peak = _peak_deflection(syn.truth)
    return syn, scale, peak


