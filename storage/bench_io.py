"""Files of ``schlieren bench``: estimate stores for scoring, the markdown/JSON results.

An *estimate store* is the smallest Zarr v3 group that
:func:`schlieren.storage.synthetic_io.read_store_refractivity` (and therefore
``schlieren evaluate``) accepts: ``refractivity`` (frame, z, y, x) with the grid's
``origin`` / ``voxel_size`` attributes (SPEC section 2) and ``time`` (frame,). The
benchmark writes one per reconstruction variant (exact d_out, approximate d_out, ...)
so that every row of the table is scored by the same code as a pipeline run.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import zarr

from schlieren.storage.synthetic_io import write_json

__all__ = ["write_estimate_store", "write_text", "write_json", "remove_tree", "cached_arrays"]

ESTIMATE_FORMAT = "schlieren-estimate/1"


def write_estimate_store(path: str | os.PathLike, refractivity: np.ndarray, times: np.ndarray, *,
                         origin, voxel_size: float, attrs: dict | None = None) -> Path:
    """Write ``refractivity`` and ``time`` into a new Zarr group at ``path`` (overwritten).

    Parameters
    ----------
    path : path
        Folder of the group (``.zarr``).
    refractivity : ndarray, shape (F, nz, ny, nx)
        ``n - 1`` per frame (stored as float32 like a result store).
    times : ndarray, shape (F,)
        Seconds, the instants of the frames.
    origin : sequence of 3 float
        Centre of voxel [0, 0, 0], metres (x, y, z).
    voxel_size : float
        Metres.
    attrs : dict, optional
        Extra JSON-able root attributes (e.g. which variant this is).

    Returns
    -------
    Path
    """
    vol = np.asarray(refractivity, dtype=np.float32)
    t = np.asarray(times, dtype=np.float64)
    if vol.ndim != 4 or t.shape != (vol.shape[0],):
        raise ValueError(f"expected refractivity (F, nz, ny, nx) and times (F,), got {vol.shape} and {t.shape}")
    p = Path(path)
    g = zarr.open_group(str(p), mode="w", zarr_format=3)
    g.attrs.update({"format": ESTIMATE_FORMAT, **(attrs or {})})
    a = g.create_array("refractivity", shape=vol.shape, chunks=(1,) + vol.shape[1:], dtype="float32",
                       fill_value=np.nan, dimension_names=["frame", "z", "y", "x"],
                       attributes={"origin": [float(v) for v in origin], "voxel_size": [float(voxel_size)] * 3,
                                   "units": "1 (n - 1)"})
    a[...] = vol
    ta = g.create_array("time", shape=t.shape, chunks=t.shape, dtype="float64", fill_value=np.nan,
                        dimension_names=["frame"], attributes={"units": "s"})
    ta[...] = t
    return p


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a UTF-8 text file (parent folders created)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text, encoding="utf-8")
    return p


def remove_tree(path: str | os.PathLike) -> None:
    """Delete a work folder of the benchmark (no error if it does not exist)."""
    import shutil

    shutil.rmtree(path, ignore_errors=True)


def cached_arrays(path: str | os.PathLike, compute) -> dict:
    """Arrays saved at ``path`` (``.npz``), or ``compute()``'s dict of arrays, saved there first.

    The write goes to a temporary file renamed into place, so a killed computation never
    leaves a partial cache behind. Values are converted with :func:`numpy.asarray`
    (scalars and strings become 0-d arrays).
    """
    p = Path(path)
    if p.exists():
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    arrays = {k: np.asarray(v) for k, v in compute().items()}
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + f".{os.getpid()}.partial")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, p)
    return arrays
