"""The store's root attributes as JSON: conversion, netCDF-safe encoding, fingerprints.

Nested values (mappings, lists of text or of mappings) and booleans are stored as JSON
text, listed in the root attribute ``json_attrs``, so that the attributes survive
``xarray.Dataset.to_netcdf``; :func:`decode_attrs` parses them back.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
from typing import Any, Mapping

import numpy as np


def to_json(obj: Any) -> Any:
    """Plain JSON data from numpy values, tuples, paths, dataclasses and datetimes.

    Non-finite floats become the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"``
    (JSON has no such numbers).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json(obj.tolist())
    if isinstance(obj, np.generic):
        return to_json(obj.item())
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        return "NaN" if math.isnan(obj) else ("Infinity" if obj > 0 else "-Infinity")
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    raise TypeError(f"cannot store a {type(obj).__name__} in the store attributes")


#: Root attribute listing (space-separated) the root attributes stored as JSON text.
JSON_ATTRS = "json_attrs"


def _flat(v: Any) -> bool:
    """A value netCDF can hold as an attribute: a number, text, or a flat list of numbers."""
    if isinstance(v, (str, int, float)) or v is None:
        return True
    return isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)


def encode_attrs(values: dict, encoded: set[str]) -> dict:
    """Nested values (mappings, lists of text or of mappings) and booleans as JSON text, so
    that the attributes survive ``xarray.Dataset.to_netcdf``; updates ``encoded``."""
    out = {}
    for k, v in values.items():
        if k == JSON_ATTRS:
            continue
        if _flat(v) and not isinstance(v, bool):
            encoded.discard(k)
            out[k] = v
        else:
            encoded.add(k)
            out[k] = json.dumps(v, separators=(",", ":"), allow_nan=False)
    out[JSON_ATTRS] = " ".join(sorted(encoded))
    return out


def decode_attrs(raw: Mapping[str, Any]) -> dict:
    """Root attributes as written: the JSON-text ones (listed in ``json_attrs``) parsed back."""
    d = dict(raw)
    for k in str(d.pop(JSON_ATTRS, "") or "").split():
        if isinstance(d.get(k), str):
            d[k] = json.loads(d[k])
    return d


def fingerprint(*parts: Any) -> str:
    """SHA-256 of the canonical JSON of ``parts`` (e.g. the manifest and the run config).

    Equal inputs give equal fingerprints across processes and machines; dict key order
    does not matter.
    """
    text = json.dumps(to_json(list(parts)), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def differences(old: Any, new: Any, where: str = "") -> list[str]:
    """Dotted names of the values that differ between two nested mappings, ``name: old -> new``.

    Lists of equal length are compared item by item (``cameras[2].K[0][0]``); long values
    are shown around their first difference, so that the two sides never read the same.
    """
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        out = []
        for k in list(old) + [k for k in new if k not in old]:
            out += differences(old.get(k), new.get(k), f"{where}.{k}" if where else str(k))
        return out
    if isinstance(old, (list, tuple)) and isinstance(new, (list, tuple)):
        if len(old) != len(new):
            return [f"{where}: {len(old)} items -> {len(new)} items"]
        out = []
        for i, (a, b) in enumerate(zip(old, new)):
            out += differences(a, b, f"{where}[{i}]")
        return out
    if old == new or to_json(old) == to_json(new):
        return []
    a, b = (json.dumps(to_json(v)) if v is not None else "(none)" for v in (old, new))
    return [f"{where}: {_around_difference(a, b)} -> {_around_difference(b, a)}"]


def _around_difference(text: str, other: str, width: int = 40, before: int = 15) -> str:
    """``text`` cut to about ``width`` characters around where it first differs from ``other``."""
    if len(text) <= width:
        return text
    i = next((k for k, (x, y) in enumerate(zip(text, other)) if x != y), min(len(text), len(other)))
    start = max(0, min(i - before, len(text) - width))
    end = start + width
    return ("..." if start else "") + text[start:end] + ("..." if end < len(text) else "")
