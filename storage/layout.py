"""The layout of the result store: every array's dims, shape, chunks, dtype and fill value.

:func:`result_layout` lists the SPEC section 2 arrays plus the internal ones of
``docs/design.md`` (one chunk per camera-frame for image arrays, one frame per chunk for
volumes) and the coordinate arrays that let ``xarray.open_zarr`` label the axes
(``frame``, ``camera``, ``x``, ``y``, ``z``, ``component``, ``axis``, ``stat``).

Region arithmetic for chunk-aligned writes lives here too (:func:`normalize_region`,
:func:`assert_aligned`): it is pure index arithmetic, property-tested with hypothesis.

Dimension names: SPEC names the last axis of both ``flow`` and ``gradient``
``component``, but xarray needs one size per dimension name in a dataset, so the
gradient's 3-vector axis is named ``axis`` (x, y, z) and the flow's 2-vector axis keeps
``component`` (u/x, v/y).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from schlieren.pipeline.capture import CAPTURE_STATS, MOTION_PARAMS
from schlieren.pipeline.frame_quality import QUALITY_NAMES
from schlieren.pipeline.geometry import Grid

__all__ = [
    "STORE_FORMAT",
    "ArraySpec",
    "AlignmentError",
    "result_layout",
    "SIGMA_OF",
    "with_uncertainty",
    "stage_markers",
    "marker_spec",
    "MARKER_GROUP",
    "normalize_region",
    "assert_aligned",
    "is_aligned",
    "chunk_grid_regions",
]

STORE_FORMAT = "schlieren-store/1"

#: The group holding the completion markers ``status/<stage>``.
MARKER_GROUP = "status"


class AlignmentError(ValueError):
    """A write region that is not a union of whole chunks (a programming error)."""


@dataclass(frozen=True, eq=False)
class ArraySpec:
    """Everything needed to create one array of the store.

    Attributes
    ----------
    name : str
        Path inside the group (``flow``, ``status/tomography``).
    dims : tuple of str
        Dimension names (stored as zarr ``dimension_names``).
    shape, chunks : tuple of int
    dtype : str
        numpy dtype string (``"float32"``, ``"bool"``, ``"str"`` for text coordinates).
    fill_value : scalar
        Explicit fill value (NaN for floats: an unwritten chunk reads as NaN, never 0).
    attrs : dict
        JSON attributes (``units``, ``long_name``, ``origin``/``voxel_size`` for volumes,
        ``coordinates: "time"`` so xarray attaches the time coordinate).
    data : ndarray, optional
        Values written when the store is created (static coordinates), else None.
    zstd_level : int
        The chunks' zstd level (:data:`FAST_ZSTD` for the float fields zstd cannot shrink).
    """

    name: str
    dims: tuple[str, ...]
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: str
    fill_value: Any
    attrs: dict = field(default_factory=dict)
    data: np.ndarray | None = None
    zstd_level: int = 3

    def __post_init__(self):
        object.__setattr__(self, "dims", tuple(self.dims))
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "chunks", tuple(int(c) for c in self.chunks))
        if not (len(self.dims) == len(self.shape) == len(self.chunks)):
            raise ValueError(f"{self.name}: dims {self.dims}, shape {self.shape} and chunks {self.chunks} "
                             "must have the same length")
        if any(c < 1 for c in self.chunks):
            raise ValueError(f"{self.name}: chunks must be positive, got {self.chunks}")

    @property
    def n_chunks(self) -> tuple[int, ...]:
        """Number of chunks along each dimension."""
        return tuple(-(-s // c) if s else 0 for s, c in zip(self.shape, self.chunks))


#: zstd level of the per camera-frame float fields (``flow_raw``, ``flow``, ``potential``: most
#: of a run's bytes, written once and read several times). Noisy float32 mantissas barely
#: compress, so the default level's time buys almost nothing; zstd's fastest level stores
#: them as they are, still framed and checksummed like every other chunk (docs/tuning.md,
#: "Chunk I/O and object storage").
FAST_ZSTD = -1


def _f32(name, dims, shape, chunks, attrs, fill=np.nan, dtype="float32", zstd_level: int = 3) -> ArraySpec:
    return ArraySpec(name, dims, shape, chunks, dtype, fill, attrs, zstd_level=zstd_level)


def result_layout(*, camera_names: Sequence[str], n_frames: int, flow_shape: tuple[int, int],
                  grid: Grid, first_frame: int = 0, n_raw: int | None = None,
                  raw_first: int | None = None, n_summary: int = 2001,
                  flow_factor: int | None = None, image_shape: tuple[int, int] | None = None,
                  row_knots: Sequence[float] | None = None,
                  per_frame_gradient: bool = False, reference_topup: bool = False) -> list[ArraySpec]:
    """Every array of a run's store (SPEC section 2 and docs/design.md).

    Parameters
    ----------
    camera_names : sequence of str
        In session order; also stored as the ``camera`` coordinate.
    n_frames : int
        Frames to process, ``B - A``.
    flow_shape : (int, int)
        ``(rows, cols)`` of the flow grid (``FlowGrid.shape``), the same for every camera.
    grid : Grid
        Reconstruction grid; volume arrays are ``grid.shape`` = (nz, ny, nx).
    first_frame : int
        Index ``A`` of the first processed frame (values of the ``frame`` coordinate).
    n_raw : int, optional
        Frames of ``flow_raw`` (dimension ``raw_frame``): the processed range plus the
        margin that rolling-shutter resampling reads. Defaults to ``n_frames``.
    raw_first : int, optional
        Capture index of ``flow_raw``'s first frame (values of the ``raw_frame``
        coordinate). Defaults to ``first_frame`` when ``n_raw`` is not given; without it
        and with a different ``n_raw``, no ``raw_frame`` coordinate is written.
    n_summary : int
        Length of each camera-frame's ``potential_summary`` (pixel count, then
        ``MaskParams.n_quantiles`` quantiles of the potential's magnitude).
    flow_factor : int, optional
        Image pixels per flow cell (``FlowGrid.factor``): with it the ``u`` and ``v``
        coordinates give the image position (pixels) of every flow cell's centre.
    image_shape : (int, int), optional
        ``(rows, columns)`` of the camera images: with it (and ``row_knots``), the capture
        corrections' arrays (:func:`_capture_arrays`).
    row_knots : sequence of float, optional
        Image rows of the knots of the photometric profiles
        (:func:`schlieren.pipeline.capture.row_knots`).
    per_frame_gradient : bool
        Also ``gradient_frame``, each frame's own tomographic solve, when a space-time stage
        computes ``gradient`` from it (``spacetime.window > 0``).
    reference_topup : bool
        Also each camera's reference, topped up from the capture (``capture.reference_topup``
        > 0; with ``image_shape``: :func:`_topup_arrays`).

    Returns
    -------
    list of ArraySpec
    """
    C, F = len(camera_names), int(n_frames)
    if C < 1 or F < 1:
        raise ValueError(f"need at least one camera and one frame, got {C} cameras and {F} frames")
    R = F if n_raw is None else int(n_raw)
    if R < 1:
        raise ValueError(f"n_raw must be positive, got {R}")
    if raw_first is None and R == F:
        raw_first = first_frame
    h, w = (int(s) for s in flow_shape)
    capture = [] if image_shape is None else _capture_arrays(C, R, image_shape, row_knots)
    if image_shape is not None and reference_topup:
        capture += _topup_arrays(C, image_shape)
    return (_coordinates(camera_names, F, R, first_frame, raw_first, grid, (h, w), flow_factor)
            + _camera_arrays(C, F, R, (h, w), n_summary) + capture + _volumes(F, grid)
            + (_per_frame_gradient(F, grid) if per_frame_gradient else []))


def _coordinates(camera_names: Sequence[str], F: int, R: int, first_frame: int, raw_first: int | None, grid: Grid,
                 flow_shape: tuple[int, int], flow_factor: int | None) -> list[ArraySpec]:
    """The coordinate arrays that label the axes (written with the template), and ``time``."""
    C = len(camera_names)
    h, w = flow_shape
    nz, ny, nx = grid.shape
    x, y, z = grid.axes()
    uv = []
    if flow_factor is not None:
        f = int(flow_factor)  # cell j averages pixels [f j, f j + f): centre f j + (f - 1) / 2
        for name, n, what in (("u", w, "column (image x)"), ("v", h, "row (image y)")):
            uv.append(ArraySpec(name, (name,), (n,), (n,), "float64", np.nan,
                                {"long_name": f"image {what} of the flow-cell centres", "units": "pixel",
                                 "flow_factor": f},
                                data=f * np.arange(n, dtype=np.float64) + (f - 1) / 2.0))
    return [
        ArraySpec("frame", ("frame",), (F,), (F,), "int64", -1,
                  {"long_name": "capture frame index (frame number in the cameras' recordings)", "units": "1"},
                  data=np.arange(first_frame, first_frame + F, dtype=np.int64)),
        *([ArraySpec("raw_frame", ("raw_frame",), (R,), (R,), "int64", -1,
                     {"long_name": "capture frame index of flow_raw", "units": "1"},
                     data=np.arange(raw_first, raw_first + R, dtype=np.int64))] if raw_first is not None else []),
        ArraySpec("camera", ("camera",), (C,), (C,), "str", "",
                  {"long_name": "camera name"}, data=np.asarray(list(camera_names), dtype=object)),
        ArraySpec("component", ("component",), (2,), (2,), "str", "",
                  {"long_name": "deflection component: u (image x, columns), v (image y, rows)"},
                  data=np.asarray(["u", "v"], dtype=object)),
        ArraySpec("axis", ("axis",), (3,), (3,), "str", "",
                  {"long_name": "world axis of the gradient component"},
                  data=np.asarray(["x", "y", "z"], dtype=object)),
        ArraySpec("quality", ("quality",), (len(QUALITY_NAMES),), (len(QUALITY_NAMES),), "str", "",
                  {"long_name": "entry of frame_quality"},
                  data=np.asarray(QUALITY_NAMES, dtype=object)),
        ArraySpec("x", ("x",), (nx,), (nx,), "float64", np.nan,
                  {"long_name": "world x of voxel centres", "units": "m", "axis": "X"}, data=x.astype(np.float64)),
        ArraySpec("y", ("y",), (ny,), (ny,), "float64", np.nan,
                  {"long_name": "world y of voxel centres", "units": "m", "axis": "Y"}, data=y.astype(np.float64)),
        ArraySpec("z", ("z",), (nz,), (nz,), "float64", np.nan,
                  {"long_name": "world z of voxel centres", "units": "m", "axis": "Z", "positive": "up"},
                  data=z.astype(np.float64)),
        *uv,
        ArraySpec("time", ("frame",), (F,), (F,), "float64", np.nan,
                  {"long_name": "session-clock time of each reconstructed frame", "units": "s",
                   "stage": "resample"}),
    ]


def _camera_arrays(C: int, F: int, R: int, flow_shape: tuple[int, int], n_summary: int) -> list[ArraySpec]:
    """The per-camera arrays: sync results, flow fields and their quality, potentials, masks,
    and the tomography's regularisation inputs."""
    h, w = flow_shape
    t = {"coordinates": "time"}  # xarray attaches the time coordinate to frame arrays
    cam: dict = {}  # camera names: the `camera` coordinate (a list attribute would not survive netCDF)
    return [
        _f32("time_offset", ("camera",), (C,), (1,),
             {"long_name": "session-clock time at which row 0 of frame 0 starts", "units": "s",
              "stage": "sync", **cam}, dtype="float64"),
        ArraySpec("flash_frames", ("camera", "bound"), (C, 2), (1, 2), "int64", -1,
                  {"long_name": "first and last capture frame lit by the sync flash (-1: none)",
                   "units": "1", "stage": "sync", **cam}),
        _f32("flow_raw", ("camera", "raw_frame", "v", "u", "component"), (C, R, h, w, 2), (1, 1, h, w, 2),
             {"long_name": "BOS deflection at each frame's own rolling-shutter times",
              "units": "pixel", "stage": "deflection", **cam}, zstd_level=FAST_ZSTD),
        _f32("frame_quality", ("camera", "raw_frame", "quality"), (C, R, len(QUALITY_NAMES)),
             (1, 1, len(QUALITY_NAMES)),
             {"long_name": "mean grey level, saturated fraction, mean absolute change from the previous "
                           "frame, flags (1 dark, 2 saturated, 4 frozen, 8 dropped: excluded from "
                           "resampling), standard deviation, minimum and maximum grey level",
              "units": "1", "stage": "deflection", **cam}),
        _f32("flow", ("camera", "frame", "v", "u", "component"), (C, F, h, w, 2), (1, 1, h, w, 2),
             {"long_name": "BOS deflection resampled to the output times", "units": "pixel",
              "stage": "resample", **cam, **t}, zstd_level=FAST_ZSTD),
        _f32("potential", ("camera", "frame", "v", "u"), (C, F, h, w), (1, 1, h, w),
             {"long_name": "2-D integral (potential) of the deflection field", "units": "pixel * flow cell",
              "stage": "potential", **cam, **t}, zstd_level=FAST_ZSTD),
        _f32("potential_summary", ("camera", "frame", "summary"), (C, F, int(n_summary)), (1, 1, int(n_summary)),
             {"long_name": "pixel count, then quantiles of the smoothed |potential| (mask threshold input)",
              "units": "pixel * flow cell", "stage": "potential", **cam, **t}, dtype="float64"),
        _f32("mask_threshold", ("scalar",), (1,), (1,),
             {"long_name": "flow-mask threshold on the potential", "units": "pixel * flow cell",
              "stage": "threshold"}, dtype="float64"),
        ArraySpec("mask", ("camera", "frame", "v", "u"), (C, F, h, w), (1, 1, h, w), "bool", False,
                  {"long_name": "conservative flow mask", "units": "1", "stage": "mask", **cam, **t}),
        _f32("reg_weight", ("scalar",), (1,), (1,),
             {"long_name": "tomography regularisation weight used for every frame", "units": "1",
              "stage": "regularisation"}, dtype="float64"),
        _f32("rhs_noise", ("axis",), (3,), (3,),
             {"long_name": "noise of the tomography right-hand side measured outside the masks (x, y, z)",
              "units": "1", "stage": "regularisation"}, dtype="float64"),
        _f32("flow_window", ("camera",), (C,), (C,),
             {"long_name": "width of the flow's image averaging modelled by the tomography per camera "
                           "(0 = cell-centre rays)", "units": "flow cell", "stage": "regularisation", **cam},
             dtype="float64"),
    ]


def _capture_arrays(C: int, R: int, image_shape: tuple[int, int], row_knots) -> list[ArraySpec]:
    """The capture corrections (issue 33, :mod:`schlieren.pipeline.capture`): each camera's
    defective pixels, and each raw frame's background motion, gain and offset profiles and
    fit statistics, with the coordinates that label their small axes."""
    H, W = (int(v) for v in image_shape)
    knots = np.asarray([0.0] if row_knots is None else row_knots, np.float64)
    K = len(knots)
    cam: dict = {}
    return [
        ArraySpec("motion", ("motion",), (len(MOTION_PARAMS),), (len(MOTION_PARAMS),), "str", "",
                  {"long_name": "term of the background motion (docs/store.md)"},
                  data=np.asarray(MOTION_PARAMS, dtype=object)),
        ArraySpec("photometric_term", ("photometric_term",), (2,), (2,), "str", "",
                  {"long_name": "term of the photometric profile"}, data=np.asarray(["gain", "offset"], dtype=object)),
        ArraySpec("row_knot", ("row_knot",), (K,), (K,), "float64", np.nan,
                  {"long_name": "image row of each knot of the photometric profiles", "units": "pixel"}, data=knots),
        ArraySpec("capture_stat", ("capture_stat",), (len(CAPTURE_STATS),), (len(CAPTURE_STATS),), "str", "",
                  {"long_name": "entry of capture_fit"}, data=np.asarray(CAPTURE_STATS, dtype=object)),
        ArraySpec("defective_pixels", ("camera", "row", "column"), (C, H, W), (1, H, W), "uint8", 0,
                  {"long_name": "defective sensor pixels (1 hot, 2 dead, 4 stuck; bit sum), excluded from the flow",
                   "units": "1", "stage": "capture", **cam}),
        ArraySpec("presmooth", ("camera",), (C,), (1,), "float64", np.nan,
                  {"long_name": "Gaussian pre-smoothing of the camera's images before the flow (flow.presmooth; "
                                "with auto, chosen from the reference's sharpness)",
                   "units": "pixel", "stage": "capture"}),
        _f32("background_motion", ("camera", "raw_frame", "motion"), (C, R, len(MOTION_PARAMS)),
             (1, 1, len(MOTION_PARAMS)),
             {"long_name": "motion of the background against the reference (u, v: pixels at the image centre; "
                           "a, b, c, d: linear terms; g, h: projective terms, per pixel)",
              "units": "pixel", "stage": "deflection", **cam}, dtype="float64"),
        _f32("photometric", ("camera", "raw_frame", "photometric_term", "row_knot"), (C, R, 2, K), (1, 1, 2, K),
             {"long_name": "gain and offset (grey levels) of each frame against the reference at the knot rows",
              "units": "1", "stage": "deflection", **cam}),
        _f32("capture_fit", ("camera", "raw_frame", "capture_stat"), (C, R, len(CAPTURE_STATS)),
             (1, 1, len(CAPTURE_STATS)),
             {"long_name": "static fraction of the image, registration residual (grey levels), its samples, "
                           "motion the flow still showed (pixels), flags (1 motion removed, 2 gain and offset "
                           "removed, 4 measured on every pixel, 8 not converged)",
              "units": "1", "stage": "deflection", **cam}),
    ]


def _topup_arrays(C: int, image_shape: tuple[int, int]) -> list[ArraySpec]:
    """The reference each camera's flows were measured against, with the capture frames averaged
    into it where its rays miss the volume (``capture.reference_topup``,
    :mod:`schlieren.pipeline.capture.topup`): written for every camera when the top-up is on."""
    H, W = (int(v) for v in image_shape)
    cam: dict = {}
    return [
        ArraySpec("reference_topup", ("camera",), (C,), (1,), "int32", 0,
                  {"long_name": "capture frames averaged into the camera's reference where its rays miss the volume "
                                "(capture.reference_topup; 0: the reference as recorded)",
                   "units": "frames", "stage": "capture", **cam}),
        _f32("reference", ("camera", "row", "column"), (C, H, W), (1, H, W),
             {"long_name": "the reference the camera's flows were measured against (NaN for interlaced cameras, "
                           "whose fields have their own)", "units": "grey level", "stage": "capture", **cam}),
        _f32("reference_count", ("camera", "row", "column"), (C, H, W), (1, H, W),
             {"long_name": "frames averaged at each pixel of the reference (its own frames as many as its measured "
                           "noise is worth, when topped up)", "units": "frames", "stage": "capture", **cam}),
    ]


def _volumes(F: int, grid: Grid) -> list[ArraySpec]:
    """The volume arrays, one frame per chunk, with the grid's ``origin`` and ``voxel_size``."""
    nz, ny, nx = grid.shape
    vol_attrs = grid.to_attrs()
    t = {"coordinates": "time"}  # xarray attaches the time coordinate to frame arrays
    return [
        ArraySpec("hull", ("frame", "z", "y", "x"), (F, nz, ny, nx), (1, nz, ny, nx), "bool", False,
                  {"long_name": "visual hull", "units": "1", "stage": "hull", **vol_attrs, **t}),
        _f32("gradient", ("frame", "z", "y", "x", "axis"), (F, nz, ny, nx, 3), (1, nz, ny, nx, 3),
             {"long_name": "gradient of the refractive index", "units": "m-1", "stage": "tomography",
              **vol_attrs, **t}),
        _f32("refractivity", ("frame", "z", "y", "x"), (F, nz, ny, nx), (1, nz, ny, nx),
             {"long_name": "refractivity n - 1 (refractive index minus one)", "units": "1", "stage": "integrate",
              **vol_attrs, **t}),
        _f32("density", ("frame", "z", "y", "x"), (F, nz, ny, nx), (1, nz, ny, nx),
             {"long_name": "density (Gladstone-Dale)", "standard_name": "air_density", "units": "kg m-3",
              "stage": "integrate",
              **vol_attrs, **t}),
        _f32("temperature", ("frame", "z", "y", "x"), (F, nz, ny, nx), (1, nz, ny, nx),
             {"long_name": "temperature (ideal gas at p_ambient)", "standard_name": "air_temperature", "units": "K",
              "stage": "integrate",
              **vol_attrs, **t}),
    ]


def _per_frame_gradient(F: int, grid: Grid) -> list[ArraySpec]:
    """``gradient_frame``: the per-frame solve a space-time stage averages into ``gradient``."""
    nz, ny, nx = grid.shape
    return [_f32("gradient_frame", ("frame", "z", "y", "x", "axis"), (F, nz, ny, nx, 3), (1, nz, ny, nx, 3),
                 {"long_name": "gradient of the refractive index, each frame solved alone", "units": "m-1",
                  "stage": "tomography", **grid.to_attrs(), "coordinates": "time"})]
#: The standard-error arrays of the optional ``uncertainty`` stage and the value array each
#: belongs to (docs/store.md).
SIGMA_OF = {"refractivity_sigma": "refractivity", "density_sigma": "density", "temperature_sigma": "temperature"}


def with_uncertainty(layout: list[ArraySpec]) -> list[ArraySpec]:
    """``layout`` with the standard errors of the optional ``uncertainty`` stage.

    Beside each of ``refractivity``, ``density`` and ``temperature`` a ``<name>_sigma``
    array of the same dims, chunks and grid attributes (CF conventions: ``standard_name``
    "<standard name> standard_error", the value's units), and the value's
    ``ancillary_variables`` attribute naming it, so that xarray users (and CF tools) find
    the standard error beside the value.
    """
    by_name = {a.name: a for a in layout}
    out = []
    for a in layout:
        sigma = next((s for s, v in SIGMA_OF.items() if v == a.name), None)
        out.append(a if sigma is None else dataclasses.replace(a, attrs={**a.attrs, "ancillary_variables": sigma}))
    for sigma, value in SIGMA_OF.items():
        v = by_name[value]
        attrs = {k: val for k, val in v.attrs.items() if k not in ("long_name", "standard_name", "stage")}
        attrs.update({"long_name": f"standard error of the {value} (one standard deviation)",
                      "standard_name": f"{v.attrs.get('standard_name', value)} standard_error",
                      "units": v.attrs.get("units", "1"), "stage": "uncertainty"})
        out.append(dataclasses.replace(v, name=sigma, attrs=attrs))
    return out


def stage_markers() -> dict[str, tuple[str, ...]]:
    """Completion markers of the stages of ``pipeline/stages.py``, as dimension names.

    Pass to :meth:`ResultStore.create` (``markers=``); sizes come from the layout; ``()``
    is a single (0-d) marker for stages that run once.
    """
    return {
        "sync": ("camera",),
        "clock": (),
        "capture": ("camera",),
        "deflection": ("camera", "raw_frame"),
        "resample": ("camera", "frame"),
        "potential": ("camera", "frame"),
        "threshold": (),
        "mask": ("camera", "frame"),
        "geometry": (),
        "regularisation": (),
        "hull": ("frame",),
        "tomography": ("frame",),
        "integrate": ("frame",),
    }


def marker_spec(stage: str, dims_or_shape, sizes: dict[str, int]) -> ArraySpec:
    """The completion marker ``status/<stage>`` (uint8, one chunk per index) of a stage whose
    marker has the dims ``dims_or_shape`` (sizes from ``sizes``, the layout's) or that shape."""
    entries = tuple(dims_or_shape)
    if entries and all(isinstance(d, str) for d in entries):
        missing = [d for d in entries if d not in sizes]
        if missing:
            raise ValueError(f"marker {stage}: unknown dimension(s) {missing}; the layout has {sorted(sizes)}")
        dims = entries
        shape = tuple(sizes[d] for d in entries)
    elif not all(isinstance(d, (int, np.integer)) and not isinstance(d, bool) for d in entries):
        raise ValueError(f"marker {stage}: give dimension names or a shape of ints, got {entries!r}")
    else:
        shape = tuple(int(s) for s in entries)
        dims = tuple(f"{stage}_{k}" for k in range(len(shape)))
    return ArraySpec(f"{MARKER_GROUP}/{stage}", dims, shape, (1,) * len(shape), "uint8", 0,
                     {"long_name": f"completion of stage {stage} (1 = done)", "stage": stage})


# --------------------------------------------------------------------------------------
# regions
# --------------------------------------------------------------------------------------
def normalize_region(index, shape: Sequence[int]) -> tuple[slice, ...]:
    """Turn an index (ints and unit-step slices, trailing dims omitted) into slices.

    Parameters
    ----------
    index : int, slice or tuple of them
        Non-negative ints pick one position; ``slice(a, b)`` with step 1 or None.
        Missing trailing dimensions mean the whole extent.
    shape : sequence of int

    Returns
    -------
    tuple of slice
        One ``slice(start, stop)`` per dimension, clipped to ``shape``.
    """
    if not isinstance(index, tuple):
        index = (index,)
    shape = tuple(int(s) for s in shape)
    if len(index) > len(shape):
        raise IndexError(f"index {index} has more entries than the {len(shape)} dimensions")
    out = []
    for k, (ix, n) in enumerate(zip(index + (slice(None),) * (len(shape) - len(index)), shape)):
        if isinstance(ix, slice):
            if ix.step not in (None, 1):
                raise IndexError(f"dimension {k}: only unit steps are allowed, got {ix}")
            start, stop, _ = ix.indices(n)
            out.append(slice(start, max(start, stop)))
        elif isinstance(ix, (int, np.integer)) and not isinstance(ix, bool):
            i = int(ix)
            if not 0 <= i < n:
                raise IndexError(f"dimension {k}: index {i} is outside [0, {n})")
            out.append(slice(i, i + 1))
        else:
            raise IndexError(f"dimension {k}: expected an int or a slice, got {ix!r}")
    return tuple(out)


def _write_unit(array) -> tuple[int, ...]:
    shards = getattr(array, "shards", None)
    return tuple(shards) if shards else tuple(array.chunks)


def is_aligned(region: tuple[slice, ...], shape: Sequence[int], chunks: Sequence[int]) -> bool:
    """True if ``region`` (normalised slices) is a non-empty union of whole chunks.

    The last chunk along a dimension may be partial (it ends at the array's edge).
    """
    for sl, n, c in zip(region, shape, chunks):
        start, stop = sl.start, sl.stop
        if stop <= start:
            return False
        if start % c != 0:
            return False
        if stop != n and stop % c != 0:
            return False
    return len(region) == len(shape)


def assert_aligned(region, array) -> tuple[slice, ...]:
    """Check that a write region covers whole chunks (whole shards if sharded).

    Parameters
    ----------
    region : index (ints/slices) or tuple of slices
    array : object with ``shape`` and ``chunks`` (and optionally ``shards``)
        A zarr array or an :class:`ArraySpec`.

    Returns
    -------
    tuple of slice
        The normalised region.

    Raises
    ------
    AlignmentError
        If the region is empty or cuts a chunk: concurrent partial-chunk writes lose data.
    """
    shape = tuple(array.shape)
    reg = normalize_region(region, shape)
    unit = _write_unit(array)
    if not is_aligned(reg, shape, unit):
        name = getattr(array, "name", None) or getattr(array, "path", "") or "array"
        raise AlignmentError(
            f"{name}: region {[(s.start, s.stop) for s in reg]} is not a union of whole chunks "
            f"{unit} of shape {shape}: partial-chunk writes are refused")
    return reg


def chunk_grid_regions(spec) -> list[tuple[slice, ...]]:
    """Every chunk's region of an array (``spec`` with ``shape`` and ``chunks``), in C order."""
    shape, chunks = tuple(spec.shape), tuple(spec.chunks)
    counts = [-(-s // c) for s, c in zip(shape, chunks)]
    out = []
    for idx in np.ndindex(*counts):
        out.append(tuple(slice(i * c, min((i + 1) * c, s)) for i, c, s in zip(idx, chunks, shape)))
    return out

