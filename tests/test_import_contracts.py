"""The layers' import contracts: pipeline <- storage <- workers, one way only (STYLE.md).

The contracts are declared in pyproject.toml (``[tool.importlinter]``) and checked by
import-linter. Its import graph (grimp) walks a package's folder, but the editable install
maps four separate folders into ``schlieren`` (``package-dir``), so the tests first lay out
the installed package tree (links to the source files, exactly the ``packages`` list) and
run the linter on it in a fresh interpreter. Two rules import-linter cannot state are
checked here on the same graph: the top-level package imports only the public API, and no
module of pipeline/ or storage/ reaches itself through runtime imports.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest
from graph_cycles import find_cycle

REPO = Path(__file__).resolve().parents[1]


def installed_tree(dest: Path) -> Path:
    """Lay out the package tree a regular install would make: one folder per entry of
    pyproject's ``packages``, holding links to that package's own ``.py`` files (its
    folder from ``package-dir``). Returns the folder to put on ``sys.path``."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = tool["package-dir"]
    for pkg in tool["packages"]:
        base = max((p for p in dirs if pkg == p or pkg.startswith(p + ".")), key=len)
        src = REPO / dirs[base] / Path(*pkg[len(base):].lstrip(".").split(".") if pkg != base else ())
        out = dest.joinpath(*pkg.split("."))
        out.mkdir(parents=True, exist_ok=True)
        for f in src.glob("*.py"):
            (out / f.name).symlink_to(f)
    return dest


def _run(tree: Path, code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=tree, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    return installed_tree(tmp_path_factory.mktemp("installed"))


def test_the_tree_is_the_installed_layout(tree):
    assert (tree / "schlieren" / "__init__.py").resolve() == REPO / "workers" / "toplevel" / "__init__.py"
    assert (tree / "schlieren" / "pipeline" / "tomography" / "solve.py").is_symlink()
    assert not (tree / "schlieren" / "workers" / "toplevel").exists()  # not a package of its own
    out = _run(tree, "import schlieren.pipeline.geometry as g; print(g.__file__)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().startswith(str(tree))


def test_import_linter_contracts_are_kept(tree):
    """pipeline/ imports nothing of storage/ or workers/ and never Dask, Zarr, fsspec or
    matplotlib; storage/ nothing of workers/ and never Dask; nothing inside imports the
    top-level package; no import cycle between siblings in pipeline/ and storage/."""
    out = _run(tree, f"""
        import sys
        from importlinter.cli import lint_imports
        sys.exit(lint_imports(config_filename={str(REPO / "pyproject.toml")!r}, no_cache=True, no_logo=True))
    """)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "4 kept, 0 broken" in out.stdout, out.stdout


def test_a_broken_contract_is_reported(tree, tmp_path):
    """The linter sees this tree's imports: a contract that does not hold fails."""
    cfg = tmp_path / "broken.toml"
    cfg.write_text('[tool.importlinter]\nroot_package = "schlieren"\n\n[[tool.importlinter.contracts]]\n'
                   'name = "workers never import pipeline (false)"\ntype = "forbidden"\n'
                   'source_modules = ["schlieren.workers"]\nforbidden_modules = ["schlieren.pipeline"]\n')
    out = _run(tree, f"""
        import sys
        from importlinter.cli import lint_imports
        sys.exit(lint_imports(config_filename={str(cfg)!r}, no_cache=True, no_logo=True))
    """)
    assert out.returncode == 1 and "BROKEN" in out.stdout, out.stdout + out.stderr


GRAPH = """
    import json, grimp
    g = grimp.build_graph("schlieren", cache_dir=None, exclude_type_checking_imports=True)
    inner = sorted(m for m in g.modules if m.startswith(("schlieren.pipeline", "schlieren.storage")))
    print(json.dumps({
        "top": sorted(g.find_modules_directly_imported_by("schlieren")),
        "edges": {m: sorted(n for n in g.find_modules_directly_imported_by(m) if n in inner) for m in inner},
    }))
"""


@pytest.fixture(scope="module")
def graph(tree) -> dict:
    out = _run(tree, GRAPH)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_top_level_package_imports_only_the_public_api(graph):
    assert graph["top"] == ["schlieren.workers.api"]


def test_the_cycle_finder_finds_cycles():
    assert find_cycle({"a": ["b"], "b": ["c"], "c": ["a"]}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": ["b"], "b": ["c"], "c": []}) is None


def test_no_module_of_pipeline_or_storage_imports_itself_back(graph):
    """Runtime imports (at module level or inside functions; not the annotation-only ones
    under ``if TYPE_CHECKING``) between any two modules, a package and its own modules
    included, which the sibling contract does not look at."""
    edges = graph["edges"]
    assert "schlieren.storage.integrity" in edges["schlieren.storage.store.result_store"]  # edges are seen
    found = find_cycle(edges)
    assert found is None, " -> ".join(found)
