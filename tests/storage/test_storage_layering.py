"""Layering: the storage modules never pull in dask or distributed, and import no cycle (STYLE.md)."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from graph_cycles import find_cycle

import schlieren.storage
from schlieren.storage.errors import SessionError
from schlieren.storage.session.checks import _check_range

STORAGE = Path(schlieren.storage.__file__).resolve().parent


def storage_modules() -> list[str]:
    """Every module and subpackage of ``schlieren.storage``, found by walking the package."""
    found = ["schlieren.storage"]
    for info in pkgutil.walk_packages([str(STORAGE)], prefix="schlieren.storage."):
        found.append(info.name)
    return sorted(found)


def test_the_module_list_is_found_not_written_down():
    mods = storage_modules()
    # one of each kind: a plain module, a subpackage, and a module inside a subpackage
    assert {"schlieren.storage.layout", "schlieren.storage.store", "schlieren.storage.readers.video"} <= set(mods)
    assert len(mods) == len(list(STORAGE.rglob("*.py")))


def test_storage_modules_do_not_import_dask():
    """Importing every storage module (one after another, in a fresh interpreter) loads neither
    dask nor distributed; the first module that would is named."""
    code = (
        "import importlib, sys\n"
        "bad = {}\n"
        f"for name in {storage_modules()!r}:\n"
        "    importlib.import_module(name)\n"
        "    got = sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'})\n"
        "    if got:\n"
        "        bad[name] = got\n"
        "        break\n"
        "print(bad or '')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _storage_imports(path: Path, known: set[str]) -> set[str]:
    """The storage modules that ``path`` imports anywhere (also inside functions and under
    ``if TYPE_CHECKING``): ``from a import b`` counts as ``a.b`` if that is a module, else ``a``."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in known)
        elif isinstance(node, ast.ImportFrom) and node.module:
            for a in node.names:
                full = f"{node.module}.{a.name}"
                if full in known:
                    out.add(full)
                elif node.module in known:
                    out.add(node.module)
    return out


def _module_files() -> dict[str, Path]:
    files = {}
    for p in STORAGE.rglob("*.py"):
        parts = list(p.relative_to(STORAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(["schlieren", "storage", *parts])] = p
    return files


def test_storage_modules_import_no_cycle():
    """No storage module imports, even lazily or for type checking only, a module that imports
    it back (e.g. the store and its integrity checks: integrity.scan_store takes any store with
    the methods it names, and never imports the store)."""
    files = _module_files()
    assert set(files) == set(storage_modules())
    graph = {name: _storage_imports(path, set(files)) - {name} for name, path in files.items()}
    assert "schlieren.storage.integrity" in graph["schlieren.storage.store.result_store"]  # the checker sees edges
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


@settings(max_examples=200, deadline=None)
@given(st.integers(-5, 30), st.integers(-5, 30), st.one_of(st.none(), st.integers(0, 25)))
def test_frame_range_check_matches_its_definition(a, b, n):
    valid = 0 <= a < b and (n is None or b <= n)
    if valid:
        _check_range((a, b), n, file="m.yaml", field="frames", what="frames")
    else:
        with pytest.raises(SessionError) as info:
            _check_range((a, b), n, file="m.yaml", field="frames", what="frames")
        assert info.value.field == "frames" and info.value.file == "m.yaml"
