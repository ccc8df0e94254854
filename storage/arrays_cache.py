"""Per-session derived arrays (the tomography geometry) saved as ``.npy`` files.

The projection geometry is computed once per session by one task and written beside
the result store, in ``<store>.cache/`` (outside the Zarr hierarchy, so that zarr and
xarray see only Zarr nodes in the store; ``schlieren clean STORE`` removes it); every tomography task maps the files read-only (``mmap_mode="r"``)
instead of receiving the matrix through the task graph (DASK-ZARR.md item 6).
The directory is written under a temporary name and renamed when complete, so a crash
never leaves a half-written cache that looks valid; its manifest records each file's size
and CRC-32C, which :func:`verify_arrays` checks (``schlieren verify``, and every worker
when it first maps the geometry).

A store on object storage (an fsspec URL) has no files to map: the folder's files are
uploaded there with ``manifest.json`` last (its presence means complete), and each
machine that loads them stages one local copy (:func:`schlieren.storage.location.stage_folder`,
keyed by the URL and the manifest's version) and maps that.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from schlieren.storage import location

__all__ = ["cache_root", "cache_dir", "save_arrays", "load_arrays", "has_arrays", "remove_cache", "verify_arrays",
           "remove_arrays"]


def cache_root(store_path: str | os.PathLike) -> Path | str:
    """The cache folder of a store: ``<store>.cache`` beside it (``run.zarr.cache``; a URL
    beside a store on object storage)."""
    loc = location.normalize(store_path)
    if location.is_url(loc):
        return loc + ".cache"
    p = Path(loc.rstrip("/\\"))
    return p.with_name(p.name + ".cache")


def cache_dir(store_path: str | os.PathLike, name: str, key: str) -> Path | str:
    """Folder for a cached set of arrays: ``<store>.cache/<name>-<key>``."""
    root = cache_root(store_path)
    return location.join(root, f"{name}-{key}") if isinstance(root, str) else root / f"{name}-{key}"


def remove_cache(store_path: str | os.PathLike) -> int:
    """Delete the store's cache folder (and a pre-0.2 ``<store>/_cache``); returns the bytes freed."""
    loc = location.normalize(store_path)
    if location.is_url(loc):
        return location.remove_tree(cache_root(loc)) + location.remove_tree(location.join(loc, "_cache"))
    freed = 0
    for root in (cache_root(store_path), Path(store_path) / "_cache"):
        if root.is_dir():
            freed += sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
            shutil.rmtree(root)
    return freed


def has_arrays(path: str | os.PathLike) -> bool:
    if location.is_url(location.normalize(path)):
        return location.isfile(location.join(path, "manifest.json"))
    return (Path(path) / "manifest.json").is_file()


def save_arrays(path: str | os.PathLike, arrays: dict) -> Path | str:
    """Write a dict of arrays (and JSON-able scalars) atomically as ``.npy`` files."""
    if location.is_url(location.normalize(path)):
        return _upload_arrays(location.normalize(path), arrays)
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


def _upload_arrays(url: str, arrays: dict) -> str:
    """:func:`save_arrays` to an object store: written locally, uploaded, ``manifest.json`` last."""
    if has_arrays(url):
        return url
    local = location.local_cache_dir("upload") / f"{location.basename(url)}.{uuid.uuid4().hex}"
    try:
        save_arrays(local, arrays)
        files = {location.join(url, f.name): f.read_bytes() for f in local.iterdir() if f.name != "manifest.json"}
        location.write_many(files)
        location.write_bytes(location.join(url, "manifest.json"), (local / "manifest.json").read_bytes())
        location.adopt_staged_folder(url, local, complete_marker="manifest.json")
    finally:
        shutil.rmtree(local, ignore_errors=True)
    return url


def load_arrays(path: str | os.PathLike, *, mmap: bool = True) -> dict:
    """Read arrays saved by :func:`save_arrays` (memory-mapped read-only by default).

    From an object store the folder is first staged once per machine (see the module doc).
    """
    path = Path(location.stage_folder(path, complete_marker="manifest.json"))
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
    if location.is_url(location.normalize(path)):  # an object store: check the staged copy
        try:
            path = location.stage_folder(path, complete_marker="manifest.json")
        except (OSError, ValueError) as exc:
            return [f"{path}: cannot be fetched ({exc})"]
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


def remove_arrays(path: str | os.PathLike) -> None:
    """Delete one saved set (a damaged one, rebuilt by its stage); its manifest goes first,
    so a half-deleted set never looks complete."""
    loc = location.normalize(path)
    if location.is_url(loc):
        try:
            location.remove(location.join(loc, "manifest.json"))
        except FileNotFoundError:
            pass
        location.remove_tree(loc)
        return
    p = Path(loc)
    if not p.exists():
        return
    trash = p.parent / f".{p.name}.{uuid.uuid4().hex}.trash"
    os.replace(p, trash)
    shutil.rmtree(trash, ignore_errors=True)
