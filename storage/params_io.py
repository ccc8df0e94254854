"""Read a run-parameters file (YAML, safe loading only)."""

from __future__ import annotations

from pathlib import Path

import yaml

from schlieren.storage.errors import SchlierenInputError

__all__ = ["read_params", "write_params_text"]


def read_params(path: str | Path) -> dict:
    """Parameters as a nested dict; a missing, garbled or non-mapping file is a one-line error."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except FileNotFoundError:
        raise SchlierenInputError("parameters file not found", file=str(p)) from None
    except yaml.YAMLError as exc:
        raise SchlierenInputError(f"not valid YAML ({str(exc).splitlines()[0]})", file=str(p)) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise SchlierenInputError("expected a mapping of stage -> parameters", file=str(p))
    return data


def write_params_text(path: str | Path, text: str) -> Path:
    """Write a parameters file; refuses to overwrite an existing one."""
    p = Path(path)
    if p.exists():
        raise SchlierenInputError("exists already; not overwriting it", file=str(p))
    p.write_text(text)
    return p
