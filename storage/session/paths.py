"""Manifest paths resolved against the session folder and kept inside it (SPEC section 1).

Absolute paths, URLs, ``..`` escapes and symbolic links out of the folder are refused
unless ``allow_external_paths: true``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from schlieren.storage import location
from schlieren.storage.errors import SessionError


def resolve_path(spec: str, root: Path | str, *, allow_external: bool, file: str, camera: str, field: str) -> str:
    if location.is_url(spec):
        if not allow_external:
            raise SessionError(f"URL {spec!r} is not allowed (paths are relative to the session folder "
                               "unless allow_external_paths: true)", file=file, camera=camera, field=field)
        return location.normalize(spec)
    remote = location.is_url(str(root))  # a session on object storage: "/"-separated paths below it
    if not allow_external:
        if spec.startswith("~") or os.path.isabs(spec) or re.match(r"^[A-Za-z]:[\\/]", spec):
            raise SessionError(f"absolute path {spec!r} is not allowed (paths are relative to the "
                               "session folder unless allow_external_paths: true)",
                               file=file, camera=camera, field=field)
        norm = os.path.normpath(spec)
        if norm == ".." or norm.startswith(".." + os.sep) or norm.startswith("../"):
            raise SessionError(f"path {spec!r} escapes the session folder (set allow_external_paths: "
                               "true to allow it)", file=file, camera=camera, field=field)
        if remote:
            return location.join(str(root), norm.replace(os.sep, "/"))
        out = str(root / norm)
        # folders on the way (a pattern's folder) may be symbolic links out of the session
        existing = out
        while not os.path.lexists(existing) and os.path.dirname(existing) != existing:
            existing = os.path.dirname(existing)
        check_contained(existing, root, file=file, camera=camera, field=field, what=spec)
        return out
    spec = os.path.expanduser(spec)
    if os.path.isabs(spec):
        return spec
    return location.join(str(root), spec) if remote else os.path.normpath(str(root / spec))


def check_contained(path: str, root: Path, *, file: str, camera: str | None, field: str | None,
                     what: str | None = None) -> None:
    """Refuse ``path`` if, with every symbolic link resolved, it is not inside ``root``."""
    if location.is_url(str(path)) or location.is_url(str(root)):
        return  # object stores have no symbolic links
    real = os.path.realpath(path)
    base = os.path.realpath(root)
    if real != base and not real.startswith(base.rstrip(os.sep) + os.sep):
        raise SessionError(f"path {what or path!r} leads outside the session folder through a symbolic link "
                           f"(to {real}); set allow_external_paths: true to allow it", file=file, camera=camera,
                           field=field)
