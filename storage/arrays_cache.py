"""Per-session derived arrays (the tomography geometry) saved as ``.npy`` files.

The projection geometry is computed once per session by one task and written beside
the result store, in ``<store>.cache/`` (outside the Zarr hierarchy, so that zarr and
xarray see only Zarr nodes in the store; ``schlieren clean STORE`` removes it); every tomography task maps the files read-only (``mmap_mode="r"``)
instead of receiving the matrix through the task graph (DASK-ZARR.md item 6).
The directory is written under a temporary name and renamed when complete, so a crash
never leaves a half-written cache that looks valid; its manifest records each file's size
and CRC-32C, which :func:`verify_arrays` checks (``schlieren verify``, and every worker
when it first maps the geometry).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

__all__ = ["cache_root", "cache_dir", "save_arrays", "load_arrays", "has_arrays", "remove_cache", "verify_arrays"]


def cache_root(store_path: str | os.PathLike) -> Path:
    """The cache folder of a store: ``<store>.cache`` beside it (``run.zarr.cache``)."""
    p = Path(os.fspath(store_path).rstrip("/\\"))
    return p.with_name(p.name + ".cache")


def cache_dir(store_path: str | os.PathLike, name: str, key: str) -> Path:
    """Folder for a cached set of arrays: ``<store>.cache/<name>-<key>``."""
    return cache_root(store_path) / f"{name}-{key}"


def remove_cache(store_path: str | os.PathLike) -> int:
    """Delete the store's cache folder (and a pre-0.2 ``<store>/_cache``); returns the bytes freed."""
    freed = 0
    for root in (cache_root(store_path), Path(store_path) / "_cache"):
        if root.is_dir():
            freed += sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
            shutil.rmtree(root)
    return freed


def has_arrays(path: str | os.PathLike) -> bool:
    return (Path(path) / "manifest.json").is_file()


def save_arrays(path: str | os.PathLike, arrays: dict) -> Path:
    """Write a dict of arrays (and JSON-able scalars) atomically as ``.npy`` files."""
    path = Path(path)
    if has_arrays(path):
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp"
    tmp.mkdir()
    meta = {"arrays": [], "scalars": {}, "files": {}}
    for k, v in arrays.items():
        if isinstance(v, np.ndarray):
            np.save(tmp / f"{k}.npy", v, allow_pickle=False)
            meta["arrays"].append(k)
            meta["files"][f"{k}.npy"] = _file_crc(tmp / f"{k}.npy")
        else:
            meta["scalars"][k] = v
    (tmp / "manifest.json").write_text(json.dumps(meta))
    try:
        os.replace(tmp, path)
    except OSError:  # another process finished first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def load_arrays(path: str | os.PathLike, *, mmap: bool = True) -> dict:
    """Read arrays saved by :func:`save_arrays` (memory-mapped read-only by default)."""
    path = Path(path)
    meta = json.loads((path / "manifest.json").read_text())
    out = dict(meta["scalars"])
    for k in meta["arrays"]:
        out[k] = np.load(path / f"{k}.npy", mmap_mode="r" if mmap else None, allow_pickle=False)
    return out


def _file_crc(path: Path) -> dict:
    import google_crc32c

    crc = google_crc32c.Checksum()
    size = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            crc.update(block)
            size += len(block)
    return {"size": size, "crc32c": int.from_bytes(crc.digest(), "big")}


def verify_arrays(path: str | os.PathLike, *, read: bool = True) -> list[str]:
    """Problems of a saved set of arrays (empty list: intact).

    Checks that every file listed in the manifest exists with its size and, with
    ``read``, its CRC-32C (sets saved before checksums were recorded: existence only).
    """
    path = Path(path)
    try:
        meta = json.loads((path / "manifest.json").read_text())
    except (OSError, ValueError) as exc:
        return [f"{path / 'manifest.json'}: unreadable ({exc})"]
    problems = []
    files = meta.get("files") or {f"{k}.npy": None for k in meta.get("arrays", [])}
    for name, want in files.items():
        f = path / name
        if not f.is_file():
            problems.append(f"{f}: missing")
            continue
        if want is None:
            continue
        if f.stat().st_size != want["size"]:
            problems.append(f"{f}: {f.stat().st_size} bytes, not {want['size']} (truncated?)")
        elif read and _file_crc(f)["crc32c"] != want["crc32c"]:
            problems.append(f"{f}: fails its CRC-32C checksum")
    return problems
