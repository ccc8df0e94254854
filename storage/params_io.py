"""Read a run-parameters file (YAML, safe loading only)."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.yaml_bounds import BoundedSafeLoader

__all__ = ["read_params", "write_params_text", "ParamsLoader"]


class ParamsLoader(BoundedSafeLoader):
    """SafeLoader reading numbers as YAML 1.2 does: ``1e-6`` is a float, not the text "1e-6";
    documents that aliases expand beyond a size are refused (:mod:`schlieren.storage.yaml_bounds`).

    PyYAML follows YAML 1.1, whose floats need a dot (``1.0e-6``); a user's ``tol: 1e-6``
    would otherwise reach the strict parameter check as text and be refused.
    """


ParamsLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                 |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                 |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                 |[-+]?\.(?:inf|Inf|INF)
                 |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def read_params(path: str | Path) -> dict:
    """Parameters as a nested dict; a missing, garbled or non-mapping file is a one-line error."""
    p = Path(path)
    try:
        data = yaml.load(p.read_text(), Loader=ParamsLoader)  # noqa: S506 - a SafeLoader subclass
    except FileNotFoundError:
        raise SchlierenInputError("parameters file not found", file=str(p)) from None
    except IsADirectoryError:
        raise SchlierenInputError("is a folder, not a parameters file", file=str(p)) from None
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
