"""Export reconstructed volumes for ParaView and other renderers.

Formats (one file set per frame; voxel centres are the sample points, so ``Origin`` is the
world position of voxel ``[0, 0, 0]``'s centre and ``Spacing`` the voxel size, metres):

* ``vti``: VTK XML ImageData (version 1.0, UInt64 headers), point data as one inline
  base64 ``binary`` DataArray (little endian), plus a ``.pvd`` collection whose
  ``timestep`` is the store's ``time`` (seconds), so ParaView plays the sequence in time.
* ``raw``: little-endian float32 ``.raw`` (x fastest, then y, then z; components fastest for
  the gradient), a MetaImage ``.mhd`` header per frame that ParaView/ITK/3D Slicer open
  directly, and one JSON sidecar describing every frame.
* ``nrrd``: NRRD with an attached header: ``space origin`` and ``space directions`` in
  world metres (``space units: "m"``), raw little-endian data.
* ``ome-zarr``: one multiscale OME-Zarr 0.5 image ``<quantity>.ome.zarr`` (Zarr v3) with
  every frame, axes ``t, [c,] z, y, x`` (seconds, metres), levels halved by 2x2x2 block
  means (block maxima for ``hull``) down to 8 voxels a side, scale and translation from the
  store's time and grid, written to the NGFF 0.5 specification that napari's OME-Zarr
  reader plugin and other NGFF viewers read (tested here against the specification's
  rules and the world coordinates, not with napari itself). Frames not complete yet are
  left at the fill value.

``hull`` (bool) is written as UInt8; ``gradient`` as a 3-component vector.

The VTK, MetaImage and NRRD files are written here, a few lines of header each, not
through a library: meshio writes neither VTK ImageData nor MetaImage; pyevtk writes
ImageData only with raw appended data (not well-formed XML); SimpleITK/ITK and VTK are
large compiled packages for a short text header; pynrrd cannot write the ``units:=``
key/value pair (it takes ``units`` for NRRD's per-axis field) and stamps every file with
the time it was written. The tests read the NRRD files back with pynrrd.
"""

from __future__ import annotations

import base64
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from schlieren.storage.errors import StoreError
from schlieren.storage.report.reader import first_frame, frame_range, open_result, volume_grid

__all__ = ["export", "ExportResult", "FORMATS", "QUANTITIES"]

log = logging.getLogger(__name__)

FORMATS = ("vti", "raw", "nrrd", "ome-zarr")
STAGE_OF = {"refractivity": "integrate", "density": "integrate", "temperature": "integrate",
            "gradient": "tomography", "hull": "hull", "refractivity_sigma": "uncertainty",
            "density_sigma": "uncertainty", "temperature_sigma": "uncertainty"}
QUANTITIES = {  # name -> (units, components)
    "refractivity": ("1", 1),
    "density": ("kg/m^3", 1),
    "temperature": ("K", 1),
    "gradient": ("1/m", 3),
    "hull": ("1", 1),
    "refractivity_sigma": ("1", 1),
    "density_sigma": ("kg/m^3", 1),
    "temperature_sigma": ("K", 1),
}


@dataclass(frozen=True)
class ExportResult:
    """What an export wrote.

    Attributes
    ----------
    entry_points : list of Path
        The files to open: the ``.pvd`` (vti), the ``.mhd`` headers (raw), the ``.nrrd`` files.
    files : list of Path
        Every file written.
    skipped : list of int
        Store frames left out because their stage is not complete (partial run).
    """

    entry_points: list[Path] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)


def _vtk_type(dtype: np.dtype) -> str:
    return {np.dtype("<f4"): "Float32", np.dtype("<f8"): "Float64", np.dtype("u1"): "UInt8"}[np.dtype(dtype)]


def _frame_values(arr, f: int, quantity: str) -> np.ndarray:
    v = np.asarray(arr[f])
    if quantity == "hull" or v.dtype == bool:
        return np.ascontiguousarray(v.astype(np.uint8))
    return np.ascontiguousarray(v.astype("<f4"))


def export(store_path: str | os.PathLike, out_path: str | os.PathLike, *, format: str = "vti",
           quantity: str = "refractivity", frames=None, with_sigma: bool = True) -> ExportResult:
    """Write one volume quantity of a result store in a format other tools read.

    With ``with_sigma``, a quantity whose standard error the store holds (its
    ``ancillary_variables``, ``uncertainty.enabled``) is written with it: the same files for
    ``<quantity>_sigma`` beside the value's (its entry points follow the value's).

    Parameters
    ----------
    store_path : path
        The Zarr result store.
    out_path : path
        Output folder (created). Files are named ``<quantity>_<frame:05d>.<ext>`` with the
        capture frame index (the store's ``frame`` coordinate).
    format : {"vti", "raw", "nrrd", "ome-zarr"}
    quantity : {"refractivity", "density", "temperature", "gradient", "hull"}
    frames : (a, b), optional
        Half-open range of capture frames (default: all). Frames whose stage is not complete
        (``status/<stage>`` marker unset) are skipped and listed in the result.
    with_sigma : bool
        Also write the quantity's standard error when the store has it.

    Returns
    -------
    ExportResult

    Raises
    ------
    StoreError
        Unknown format or quantity, the quantity is not in the store, bad frame range, or no
        frame of the range is complete.
    """
    src = _open_source(store_path, format, quantity, frames)
    out = Path(out_path)
    out.mkdir(parents=True, exist_ok=True)
    sigma = src.arr.attrs.get("ancillary_variables") if with_sigma else None
    group = open_result(store_path) if sigma in QUANTITIES else None
    if group is not None and sigma in group and np.any(_done(group, sigma, src.arr.shape[0])[src.sel]):
        value = export(store_path, out, format=format, quantity=quantity, frames=frames, with_sigma=False)
        err = export(store_path, out, format=format, quantity=sigma, frames=frames, with_sigma=False)
        return ExportResult(entry_points=value.entry_points + err.entry_points, files=value.files + err.files,
                            skipped=value.skipped)
    if format == "ome-zarr":
        return _export_ome_zarr(out, src.arr, quantity, src.sel, src.done, src.first, src.times, src.origin, src.h,
                                src.ncomp, src.name)
    result, records, dtype_name = _export_frames(out, src, format)
    first, sel = src.first, src.sel
    if not records:
        raise StoreError(f"no frame of {quantity!r} in {first + sel.start}:{first + sel.stop} is complete yet", file=src.name,
                         field=quantity)
    if result.skipped:
        log.warning("%s: frames %s are not complete yet and were not exported", quantity,
                    ", ".join(map(str, result.skipped)))
    if format == "vti":
        pvd = out / f"{quantity}.pvd"
        _write_pvd(pvd, records)
        result.files.append(pvd)
        result.entry_points.insert(0, pvd)
    if format == "raw":
        side = out / f"{quantity}.json"
        _write_sidecar(side, src, dtype_name, records)
        result.files.append(side)
    log.info("exported %d frame(s) of %s as %s to %s", len(sel), quantity, format, out)
    return result


@dataclass(frozen=True)
class _Source:
    """The quantity to export: its array, where its samples lie, and the frames asked for."""

    name: str  # the store, as messages name it
    arr: Any
    quantity: str
    first: int  # capture index of the store's first frame
    sel: range  # store frames asked for
    times: np.ndarray | None
    done: np.ndarray  # store frames whose stage is complete
    origin: list[float]  # world x, y, z of the centre of voxel [0, 0, 0], metres
    h: float  # voxel size, metres
    shape: tuple[int, int, int]  # (nz, ny, nx)
    units: str
    ncomp: int


def _open_source(store_path, format: str, quantity: str, frames) -> _Source:
    """Check the request and open the quantity's array (one-line StoreErrors)."""
    if format not in FORMATS:
        raise StoreError(f"unknown export format {format!r} (choose from {', '.join(FORMATS)})", field="format")
    if quantity not in QUANTITIES:
        raise StoreError(f"cannot export {quantity!r} (choose from {', '.join(QUANTITIES)})", field="quantity")
    group = open_result(store_path)
    if quantity not in group:
        raise StoreError(f"the store has no {quantity!r} array (partial run?)", file=str(store_path),
                         field=quantity)
    arr = group[quantity]
    grid = volume_grid(arr)
    first = first_frame(group)
    sel = frame_range(frames, int(arr.shape[0]), first)
    times = np.asarray(group["time"][:], dtype=np.float64) if "time" in group else None
    units, ncomp = QUANTITIES[quantity]
    done = _done(group, quantity, int(arr.shape[0]))
    return _Source(str(store_path), arr, quantity, first, sel, times, done, [float(v) for v in grid.origin],
                   float(grid.voxel_size), tuple(grid.shape), units, ncomp)


def _done(group, quantity: str, n: int) -> np.ndarray:
    """Store frames whose stage (``STAGE_OF``) is complete (every frame without markers)."""
    try:
        return np.asarray(group[f"status/{STAGE_OF[quantity]}"][...]).reshape(-1) == 1
    except KeyError:  # a store without completion markers: take every frame
        return np.ones(n, bool)


def _export_frames(out: Path, src: _Source, format: str) -> tuple[ExportResult, list[dict], str]:
    """One file set per complete frame (vti, raw + mhd, or nrrd): the result, a record per
    frame written (capture index, time, file) and the samples' dtype name."""
    arr, quantity, first, times = src.arr, src.quantity, src.first, src.times
    origin, h, ncomp, units = src.origin, src.h, src.ncomp, src.units
    result = ExportResult()
    records = []
    dtype_name = ""
    for f in src.sel:
        if not src.done[f]:
            result.skipped.append(first + f)
            continue
        data = _frame_values(arr, f, quantity)
        dtype_name = {"<f4": "float32", "|u1": "uint8"}[data.dtype.str]
        t = None if times is None else float(times[f])
        stem = f"{quantity}_{first + f:05d}"
        if format == "vti":
            path = out / f"{stem}.vti"
            _write_vti(path, data, quantity, origin, h, ncomp)
            result.files.append(path)
        elif format == "raw":
            raw = out / f"{stem}.raw"
            data.tofile(raw)
            mhd = out / f"{stem}.mhd"
            _write_mhd(mhd, raw.name, data, origin, h, ncomp)
            result.files.extend([raw, mhd])
            result.entry_points.append(mhd)
        else:
            path = out / f"{stem}.nrrd"
            _write_nrrd(path, data, quantity, units, origin, h, ncomp, first + f, t)
            result.files.append(path)
            result.entry_points.append(path)
        records.append({"frame": first + f, "time": t, "file": result.files[-1].name if format != "raw" else f"{stem}.raw"})
    return result, records, dtype_name


def _write_sidecar(path: Path, src: _Source, dtype_name: str, records: list[dict]) -> None:
    """The raw export's JSON description of every frame written."""
    nz, ny, nx = src.shape
    quantity, units, ncomp, origin, h = src.quantity, src.units, src.ncomp, src.origin, src.h
    path.write_text(json.dumps({
        "quantity": quantity, "units": units, "dtype": dtype_name,
        "byte_order": "little", "order": "x fastest, then y, then z" + (", components fastest" if ncomp > 1 else ""),
        "shape_zyx": [nz, ny, nx], "components": ncomp,
        "origin_xyz_m": origin, "spacing_xyz_m": [h, h, h],
        "origin_is": "centre of voxel [0, 0, 0]",
        "frames": records,
    }, indent=2), encoding="utf-8")


def _write_vti(path: Path, data: np.ndarray, name: str, origin, h: float, ncomp: int) -> None:
    nz, ny, nx = data.shape[:3]
    payload = data.tobytes(order="C")
    block = base64.b64encode(np.uint64(len(payload)).astype("<u8").tobytes() + payload).decode("ascii")
    extent = f"0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"
    attr = f'Vectors={quoteattr(name)}' if ncomp > 1 else f'Scalars={quoteattr(name)}'
    text = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
        f'  <ImageData WholeExtent="{extent}" Origin="{origin[0]!r} {origin[1]!r} {origin[2]!r}" '
        f'Spacing="{h!r} {h!r} {h!r}">\n'
        f'    <Piece Extent="{extent}">\n'
        f'      <PointData {attr}>\n'
        f'        <DataArray type="{_vtk_type(data.dtype)}" Name={quoteattr(name)} '
        f'NumberOfComponents="{ncomp}" format="binary">\n'
        f'{block}\n'
        '        </DataArray>\n'
        '      </PointData>\n'
        '      <CellData/>\n'
        '    </Piece>\n'
        '  </ImageData>\n'
        '</VTKFile>\n')
    path.write_text(text, encoding="ascii")


def _write_pvd(path: Path, records: list[dict]) -> None:
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', '  <Collection>']
    for r in records:
        t = r["time"] if r["time"] is not None else float(r["frame"])
        lines.append(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(r["file"])}/>')
    lines += ['  </Collection>', '</VTKFile>', '']
    path.write_text("\n".join(lines), encoding="utf-8")


def _write_mhd(path: Path, raw_name: str, data: np.ndarray, origin, h: float, ncomp: int) -> None:
    nz, ny, nx = data.shape[:3]
    etype = {np.dtype("<f4"): "MET_FLOAT", np.dtype("u1"): "MET_UCHAR"}[data.dtype]
    lines = ["ObjectType = Image", "NDims = 3", "BinaryData = True", "BinaryDataByteOrderMSB = False",
             "CompressedData = False", "TransformMatrix = 1 0 0 0 1 0 0 0 1",
             f"Offset = {origin[0]!r} {origin[1]!r} {origin[2]!r}", "CenterOfRotation = 0 0 0",
             f"ElementSpacing = {h!r} {h!r} {h!r}", f"DimSize = {nx} {ny} {nz}"]
    if ncomp > 1:
        lines.append(f"ElementNumberOfChannels = {ncomp}")
    lines += [f"ElementType = {etype}", f"ElementDataFile = {raw_name}", ""]
    path.write_text("\n".join(lines), encoding="ascii")


def _write_nrrd(path: Path, data: np.ndarray, name: str, units: str, origin, h: float, ncomp: int,
                frame: int, t: float | None) -> None:
    nz, ny, nx = data.shape[:3]
    ntype = {np.dtype("<f4"): "float", np.dtype("u1"): "uint8"}[data.dtype]
    dirs = f"({h!r},0,0) (0,{h!r},0) (0,0,{h!r})"
    if ncomp > 1:
        head = ["dimension: 4", f"sizes: {ncomp} {nx} {ny} {nz}", f"space directions: none {dirs}",
                "kinds: vector domain domain domain"]
    else:
        head = ["dimension: 3", f"sizes: {nx} {ny} {nz}", f"space directions: {dirs}",
                "kinds: domain domain domain"]
    lines = ["NRRD0004", f"# schlieren export: {name}, store frame {frame}", f"type: {ntype}",
             "space dimension: 3", *head, "endian: little", "encoding: raw",
             f"space origin: ({origin[0]!r},{origin[1]!r},{origin[2]!r})", 'space units: "m" "m" "m"',
             f"content: {name}", f"frame:={frame}", f"units:={units}"]
    if t is not None:
        lines.append(f"time:={t!r}")
    header = ("\n".join(lines) + "\n\n").encode("ascii")
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(data.tobytes(order="C"))


def _halve(v: np.ndarray, quantity: str) -> np.ndarray:
    """2x2x2 block means (maxima for the hull) of ``v`` (z, y, x[, c]); odd edges dropped."""
    nz, ny, nx = (d // 2 for d in v.shape[:3])
    b = v[:2 * nz, :2 * ny, :2 * nx].reshape(nz, 2, ny, 2, nx, 2, *v.shape[3:])
    return b.max(axis=(1, 3, 5)) if quantity == "hull" else b.mean(axis=(1, 3, 5), dtype=np.float64).astype(v.dtype)


def _export_ome_zarr(out: Path, arr, quantity: str, sel: range, done: np.ndarray, first: int, times,
                     origin, h: float, ncomp: int, store_name: str) -> ExportResult:
    """Every frame of ``sel`` as one multiscale OME-Zarr 0.5 image (see the module docstring)."""
    import zarr

    result = ExportResult()
    todo = [f for f in sel if done[f]]
    result.skipped.extend(first + f for f in sel if not done[f])
    if not todo:
        raise StoreError(f"no frame of {quantity!r} in {first + sel.start}:{first + sel.stop} is complete yet",
                         file=store_name, field=quantity)
    shape = tuple(int(d) for d in arr.shape[1:4])
    levels = [shape]
    while min(levels[-1]) // 2 >= 8 and len(levels) < 8:
        levels.append(tuple(d // 2 for d in levels[-1]))
    units, _ = QUANTITIES[quantity]
    dt = float(np.median(np.diff(times[list(sel)]))) if times is not None and len(sel) > 1 else 1.0
    t0 = float(times[sel.start]) if times is not None else 0.0
    axes = [{"name": "t", "type": "time", "unit": "second"}]
    if ncomp > 1:
        axes.append({"name": "c", "type": "channel"})
    axes += [{"name": n, "type": "space", "unit": "meter"} for n in ("z", "y", "x")]
    datasets = []
    for k in range(len(levels)):
        step = h * 2 ** k
        # a level-k voxel is the mean of 2^k voxels: its centre sits half its width minus half a voxel further
        centre = [o + 0.5 * (step - h) for o in (origin[2], origin[1], origin[0])]
        lead = [dt] + ([1.0] if ncomp > 1 else [])
        shift = [t0] + ([0.0] if ncomp > 1 else [])
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": lead + [step] * 3},
            {"type": "translation", "translation": shift + centre}]})
    path = out / f"{quantity}.ome.zarr"
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "name": quantity, "axes": axes, "datasets": datasets,
        "type": "max (2x2x2 blocks)" if quantity == "hull" else "mean (2x2x2 blocks)",
        "metadata": {"units": units, "source": store_name,
                     "frames": [first + f for f in sel], "frames_not_complete": result.skipped}}]}
    dtype = np.uint8 if quantity == "hull" else np.float32
    fill = 0 if quantity == "hull" else float("nan")
    arrays = []
    for k, lv in enumerate(levels):
        full = (len(sel),) + ((ncomp,) if ncomp > 1 else ()) + lv
        chunks = (1,) + ((ncomp,) if ncomp > 1 else ()) + tuple(min(d, 64) for d in lv)
        arrays.append(root.create_array(str(k), shape=full, chunks=chunks, dtype=dtype, fill_value=fill,
                                        dimension_names=[a["name"] for a in axes]))
    for f in todo:
        v = _frame_values(arr, f, quantity)  # (z, y, x[, c])
        for k, a in enumerate(arrays):
            if k:
                v = _halve(v, quantity)
            a[f - sel.start] = np.moveaxis(v, -1, 0) if ncomp > 1 else v
    result.files.append(path)
    result.entry_points.append(path)
    if result.skipped:
        log.warning("%s: frames %s are not complete yet and were left at the fill value", quantity,
                    ", ".join(map(str, result.skipped)))
    log.info("exported %d frame(s) of %s as OME-Zarr (%d levels) to %s", len(todo), quantity, len(levels), path)
    return result
