"""The manifest's YAML read as plain data (``yaml.safe_load`` semantics, stricter).

A tag that would construct a Python object is refused, dates stay strings, a key
given twice is an error naming both lines, and a document whose aliases expand it beyond
a million values (a "billion laughs" bomb) is refused before it is built; every value must be JSON data (the manifest is
saved in the store's attributes).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.yaml_bounds import BoundedSafeLoader


class _ManifestLoader(BoundedSafeLoader):
    """SafeLoader that keeps dates as strings, refuses duplicate keys and documents that
    aliases expand beyond a size (:mod:`schlieren.storage.yaml_bounds`)."""


_ManifestLoader.yaml_implicit_resolvers = {
    ch: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:timestamp"]
    for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}


def _construct_mapping(loader, node, deep=False):
    loader.flatten_mapping(node)
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_ManifestLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_yaml(path: Path | str) -> Any:
    try:
        text = location.read_bytes(path).decode("utf-8")
    except UnicodeDecodeError:
        raise SessionError("the manifest is not UTF-8 text", file=str(path)) from None
    except OSError as exc:
        raise SessionError(f"cannot read the manifest ({exc.strerror or exc})", file=str(path)) from None
    try:
        return yaml.load(text, Loader=_ManifestLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.constructor.ConstructorError as exc:
        line = f" at line {exc.problem_mark.line + 1}" if exc.problem_mark else ""
        problem = str(exc.problem or exc)
        m = re.search(r"tag '([^']+)'", problem)
        if m and "constructor" in problem:
            tag = m.group(1).replace("tag:yaml.org,2002:", "!!")
            raise SessionError(
                f"YAML tag {tag}{line} is not allowed: the manifest must be plain data "
                "(mappings, lists, strings, numbers), not Python objects", file=str(path)) from None
        raise SessionError(f"invalid YAML{line}: {problem}", file=str(path)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise SessionError(f"not valid YAML{line}: {problem}", file=str(path)) from None


def check_plain(obj: Any, where: str, file: str) -> None:
    """Refuse values that JSON cannot hold (the manifest is saved in the store attrs)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                raise SessionError(f"field names must be text, got {k!r}", file=file, field=where or None)
            check_plain(v, f"{where}.{k}" if where else k, file)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            check_plain(v, f"{where}[{i}]", file)
    elif not (obj is None or isinstance(obj, (str, bool, int, float))):
        raise SessionError(f"value of type {type(obj).__name__} is not plain data", file=file,
                           field=where or None)
