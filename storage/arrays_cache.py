"""Per-session derived arrays (the tomography geometry) saved as ``.npy`` files.

The projection geometry is computed once per session by one task and written beside
the result store, in ``<store>.cache/`` (outside the Zarr hierarchy, so that zarr and
xarray see only Zarr nodes in the store; ``schlieren clean STORE`` removes it); every tomography task maps the files read-only (``mmap_mode="r"``)
instead of receiving the matrix through the task graph (DASK-ZARR.md item 6).
The directory is written under a temporary name and renamed when complete, so a crash
never leaves a half-written cache that looks valid; its manifest records each file's size
and CRC-32C, which :func:`verify_arrays` checks (``schlieren verify``, and every worker
when it first maps the geometry).

A store on object storage (an fsspec URL) has no files to map: there the set is two
objects, ``arrays.pack`` (every ``.npy`` file, each starting at a multiple of 64 bytes)
and ``manifest.json`` (uploaded last: its presence means complete; it records each
member's offset, size and CRC-32C). One object per array would cost a request each on
upload and on every machine that stages them (17 for the geometry). Each machine that
loads the set stages one local copy (:func:`schlieren.storage.location.stage_folder`,
keyed by the URL and the manifest's version) and maps the arrays inside the pack
(``numpy.memmap`` at each member's data offset).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from schlieren.storage import location

#: The single data object of a set on object storage (see the module doc).
PACK = "arrays.pack"
_ALIGN = 64  # members start at multiples of this (the .npy header keeps the data aligned too)

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
        _pack(local)
        location.write_bytes(location.join(url, PACK), (local / PACK).read_bytes())
        location.write_bytes(location.join(url, "manifest.json"), (local / "manifest.json").read_bytes())
        location.adopt_staged_folder(url, local, complete_marker="manifest.json")
    finally:
        shutil.rmtree(local, ignore_errors=True)
    return url


def _pack(folder: Path) -> None:
    """Rewrite a set saved by :func:`save_arrays` in ``folder`` as :data:`PACK` plus its
    manifest (``pack``: member -> byte offset); the ``.npy`` files are removed."""
    meta = json.loads((folder / "manifest.json").read_text())
    offsets = {}
    with open(folder / PACK, "wb") as out:
        for name in meta["files"]:
            pad = -out.tell() % _ALIGN
            out.write(b"\0" * pad)
            offsets[name] = out.tell()
            with open(folder / name, "rb") as f:
                shutil.copyfileobj(f, out)
            os.remove(folder / name)
    meta["pack"] = {"file": PACK, "offsets": offsets}
    (folder / "manifest.json").write_text(json.dumps(meta))


def load_arrays(path: str | os.PathLike, *, mmap: bool = True) -> dict:
    """Read arrays saved by :func:`save_arrays` (memory-mapped read-only by default).

    From an object store the folder is first staged once per machine (see the module doc).
    """
    path = Path(location.stage_folder(path, complete_marker="manifest.json"))
    meta = json.loads((path / "manifest.json").read_text())
    out = dict(meta["scalars"])
    pack = meta.get("pack")
    for k in meta["arrays"]:
        if pack:
            out[k] = _from_pack(path / pack["file"], int(pack["offsets"][f"{k}.npy"]), mmap)
        else:
            out[k] = np.load(path / f"{k}.npy", mmap_mode="r" if mmap else None, allow_pickle=False)
    return out


def _from_pack(pack: Path, offset: int, mmap: bool) -> np.ndarray:
    """The ``.npy`` member of ``pack`` starting at byte ``offset`` (mapped read-only, or read)."""
    from numpy.lib import format as npy

    with open(pack, "rb") as f:
        f.seek(offset)
        version = npy.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = npy.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = npy.read_array_header_2_0(f)
        else:  # np.save writes 1.0 (2.0 for huge headers)
            raise ValueError(f"{pack}: .npy format {version} at byte {offset} is not read here")
        data = f.tell()
        if dtype.hasobject:
            raise ValueError(f"{pack}: object arrays are never stored")
        order = "F" if fortran else "C"
        if 0 in shape:  # nothing to map (memmap refuses empty maps)
            return np.zeros(shape, dtype=dtype, order=order)
        if mmap and shape:
            return np.memmap(pack, dtype=dtype, mode="r", offset=data, shape=shape, order=order)
        return np.fromfile(f, dtype=dtype, count=int(np.prod(shape))).reshape(shape, order=order)


def _file_crc(path: Path) -> dict:
    with open(path, "rb") as f:
        return _crc(f)


def _crc(f, size: int | None = None) -> dict:
    """Size and CRC-32C of the next ``size`` bytes of open file ``f`` (to its end if None)."""
    import google_crc32c

    crc = google_crc32c.Checksum()
    n = 0
    while size is None or n < size:
        block = f.read(1 << 22 if size is None else min(1 << 22, size - n))
        if not block:
            break
        crc.update(block)
        n += len(block)
    return {"size": n, "crc32c": int.from_bytes(crc.digest(), "big")}


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
    if meta.get("pack"):
        return _verify_pack(path / meta["pack"]["file"], meta["pack"]["offsets"], files, read)
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


def _verify_pack(pack: Path, offsets: dict, files: dict, read: bool) -> list[str]:
    """:func:`verify_arrays` of a packed set: each member's byte range, size and CRC-32C."""
    if not pack.is_file():
        return [f"{pack}: missing"]
    size = pack.stat().st_size
    problems = []
    with open(pack, "rb") as f:
        for name, want in files.items():
            start = int(offsets[name])
            if want is None:
                continue
            if start + want["size"] > size:
                problems.append(f"{pack}: member {name} ends at byte {start + want['size']}, the pack at {size} "
                                "(truncated?)")
            elif read:
                f.seek(start)
                if _crc(f, want["size"])["crc32c"] != want["crc32c"]:
                    problems.append(f"{pack}: member {name} fails its CRC-32C checksum")
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
