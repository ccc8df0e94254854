"""schlieren: time-resolved 3D Background Oriented Schlieren tomography.

The Python API (docs/api.md)::

    import schlieren

    ds = schlieren.run("session/", "result.zarr", workers=2)   # -> xarray.Dataset
    ds = schlieren.open("result.zarr")
    schlieren.synth, schlieren.evaluate, schlieren.report, schlieren.export
    schlieren.__version__

This folder (``workers/toplevel/``) is installed as the top-level ``schlieren`` package
(``package-dir`` in pyproject.toml), beside ``schlieren.pipeline``, ``schlieren.storage``
and ``schlieren.workers``. It only re-exports :mod:`schlieren.workers.api`, lazily, so
``import schlieren`` stays cheap (no Dask, no zarr) until a function is used.
"""

from __future__ import annotations

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("schlieren")
except _metadata.PackageNotFoundError:  # pragma: no cover - running from an uninstalled tree
    __version__ = "0+unknown"

__all__ = ["run", "open", "synth", "evaluate", "report", "export", "load_params", "RunFailed",
           "__version__"]


def __getattr__(name: str):
    if name in __all__:
        from schlieren.workers import api

        return getattr(api, name)
    raise AttributeError(f"module 'schlieren' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
