"""The report's uncertainty section: each quantity's slices beside its standard error's, and
the temperature along the plume axis with its error bars (``uncertainty.enabled`` stores).

The standard errors are the ``<quantity>_sigma`` arrays of the optional ``uncertainty``
stage (docs/uncertainty.md). The plume axis is traced height by height: in each horizontal
slice the hottest voxel of the hull's largest connected part, the temperature there and its sigma, drawn with one
and two sigma bands.
"""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from schlieren.pipeline.geometry import Grid
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, fmt_number, html_img, html_table
from schlieren.workers.report._common import _figure
from schlieren.workers.report.figures import _new_figure
from schlieren.workers.report.volume_figures import MM, _draw_slice

__all__ = ["value_sigma_figure", "axis_profile", "axis_profile_figure", "uncertainty_section"]

_SPECS = (("refractivity", "refractivity n - 1", "10$^{-6}$", 1e6, "viridis"),
          ("temperature", "temperature", "K", 1.0, "inferno"),
          ("density", "density", "kg/m$^3$", 1.0, "cividis"))


def value_sigma_figure(value: np.ndarray, sigma: np.ndarray, grid: Grid, *, index, label: str, units: str,
                       cmap: str, title: str | None = None) -> Figure:
    """Three orthogonal slices of ``value`` (top) and of its standard error ``sigma`` (bottom)
    through the voxel ``index`` (iz, iy, ix), each row with its own colour bar; NaN voxels
    (``sigma`` outside the hull, where it is not an estimate) are drawn grey."""
    nx, ny, nz = grid.shape_xyz
    fig = _new_figure(15.0, 10.0)
    axes = fig.subplots(2, 3, width_ratios=[nx / ny, nx / nz, ny / nz])
    sigma_cmap = matplotlib.colormaps["magma"].with_extremes(bad="0.8")
    for row, (vol, lab, cm) in enumerate(((value, label, cmap), (sigma, f"sigma of the {label}", sigma_cmap))):
        finite = vol[np.isfinite(vol)]
        if not finite.size:
            lo, hi = 0.0, 1.0
        elif row == 0:  # the value's whole range, as the slices section
            lo, hi = float(finite.min()), float(finite.max())
        else:  # sigma from 0 to its 99.5th percentile in the hull (a few voxels at r ~ 0 have huge T sigmas)
            lo, hi = 0.0, float(np.percentile(finite, 99.5))
        im = None
        for ax, axis in zip(axes[row], ("z", "y", "x")):
            im = _draw_slice(fig, ax, vol, grid, axis=axis, index=int(index["zyx".index(axis)]), label=lab,
                             units=units, cmap=cm, vmin=lo, vmax=hi if hi > lo else lo + 1e-12, colorbar=False)
        fig.colorbar(im, ax=list(axes[row]), label=f"{lab} ({units})", shrink=0.9)
    if title:
        fig.suptitle(title)
    return fig


def axis_profile(temperature: np.ndarray, sigma: np.ndarray, hull: np.ndarray, grid: Grid):
    """The plume axis: per height with voxels of the hull's largest connected part, its hottest
    voxel's height (m), x and y (m), temperature and sigma (K). Stray hull pieces (a lone
    voxel a mask let through) are left out, so the axis stays on the plume. Returns a dict of
    arrays (empty arrays without a hull)."""
    from scipy import ndimage

    z_axis = grid.axes()[2]
    xs, ys = grid.axes()[0], grid.axes()[1]
    labels, n = ndimage.label(np.asarray(hull, dtype=bool))
    main = labels == (1 + int(np.argmax(np.bincount(labels.ravel())[1:]))) if n else np.zeros(hull.shape, bool)
    rows = []
    for k in range(temperature.shape[0]):
        t = np.where(main[k] & np.isfinite(temperature[k]) & np.isfinite(sigma[k]), temperature[k], -np.inf)
        if not np.isfinite(t).any():
            continue
        j, i = np.unravel_index(int(np.argmax(t)), t.shape)
        rows.append((z_axis[k], xs[i], ys[j], temperature[k, j, i], sigma[k, j, i]))
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 5)
    return {"z": a[:, 0], "x": a[:, 1], "y": a[:, 2], "temperature": a[:, 3], "sigma": a[:, 4]}


def axis_profile_figure(profile: dict, *, title: str | None = None) -> Figure:
    """The temperature along the plume axis with one and two sigma bands (height on the y axis)."""
    fig = _new_figure(6.0, 7.0)
    ax = fig.add_subplot()
    z = profile["z"] * MM
    T, s = profile["temperature"], profile["sigma"]
    ax.fill_betweenx(z, T - 2 * s, T + 2 * s, color="tab:red", alpha=0.15, lw=0, label="2 sigma")
    ax.fill_betweenx(z, T - s, T + s, color="tab:red", alpha=0.35, lw=0, label="1 sigma")
    ax.plot(T, z, color="tab:red", lw=1.5, label="hottest voxel of each height")
    ax.set_xlabel("temperature (K)")
    ax.set_ylabel("height z (mm)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    return fig


def uncertainty_section(page: ReportPage, rd: ReportReader, grid: Grid, writer: ReportWriter, shown, times):
    """The section (nothing when the store has no standard errors)."""
    if shown is None or not rd.has("refractivity_sigma"):
        return
    r = rd.volume("refractivity", shown)
    if r is None or rd.volume("refractivity_sigma", shown) is None:
        page.add("Uncertainty", "<p class='missing'>The standard errors of this frame are not computed yet.</p>",
                 "uncertainty")
        return
    index = np.unravel_index(np.nanargmin(r), r.shape)  # the hottest voxel, as the slices
    tstamp = f", t = {fmt_number(times[shown], 6)} s" if times is not None and np.isfinite(times[shown]) else ""
    cap = rd.capture_index(shown)
    parts, rows = [], []
    hull = rd.volume("hull", shown)
    hull = hull.astype(bool) if hull is not None else np.isfinite(r)
    for key, label, units, factor, cmap in _SPECS:
        v, s = rd.volume(key, shown), rd.volume(f"{key}_sigma", shown)
        if v is None or s is None:
            continue
        if key == "temperature":
            v, s = np.where(r > 0, v, np.nan), np.where(r > 0, s, np.nan)
        s = np.where(hull, s, np.nan)  # outside the hull: the ambient constraint, not an estimate
        fig = value_sigma_figure(v * factor, s * factor, grid, index=index, label=label, units=units, cmap=cmap,
                                 title=f"{label} and its standard error, frame {cap}{tstamp}")
        parts.append(html_img(_figure(writer, f"uncertainty_{key}.png", fig), f"{key} and its standard error"))
        inside = s[hull & np.isfinite(s)] * factor
        if inside.size:
            rows.append([label, units.replace("$", "").replace("^{", "^").replace("}", ""),
                         fmt_number(float(np.median(inside))), fmt_number(float(np.percentile(inside, 95)))])
    T, sT = rd.volume("temperature", shown), rd.volume("temperature_sigma", shown)
    if T is not None and sT is not None:
        prof = axis_profile(np.where(r > 0, T, np.nan), sT, hull, grid)
        if prof["z"].size:
            fig = axis_profile_figure(prof, title=f"plume axis, frame {cap}")
            parts.append(html_img(_figure(writer, "uncertainty_axis.png", fig), "temperature along the plume axis",
                                  "The temperature of the hottest voxel at each height of the hull's largest "
                                  "connected part, with its one and two sigma bands."))
    body = ("<p>Standard error of every voxel (one sigma; <code>uncertainty.enabled</code>, docs/uncertainty.md): "
            "the flows' measured noise propagated through the tomography and the integration, plus the "
            "integration's boundary sensitivity and the estimate's fine structure, scaled on the realistic family. "
            "Zero in the store outside the visual hull, drawn grey: the hull's ambient constraint is not an "
            "estimate, and flow every mask missed is not covered. With space-time reconstruction on, the noise term "
            "is the per-frame solve's (the window's average has less noise: the sigma is then conservative).</p>"
            + html_table(["quantity", "units", "median sigma in the hull", "95th percentile"], rows, "num")
            + "\n".join(parts))
    page.add("Uncertainty", body, "uncertainty")
