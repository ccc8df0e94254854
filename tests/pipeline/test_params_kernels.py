"""Kernels take their parameters explicitly, and never keep a second copy of a default.

The rule: a kernel keyword fed by a params class defaults to that class's own value
(``window: int = FlowParams.window``, ``params: HullParams = HullParams()``), never to a
literal; no code binds parameters to kernels by their signatures.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
from pathlib import Path

from schlieren.pipeline.stages import RunConfig

REPO = Path(__file__).resolve().parents[2]


def _scopes() -> dict[Path, list[type]]:
    """Source files -> the params classes feeding their kernels: a class's whole package
    (``pipeline/flow/`` for FlowParams), or its own module when it sits directly in pipeline/."""
    out: dict[Path, list[type]] = {}
    for f in dataclasses.fields(RunConfig):
        cls = f.default_factory
        if cls is dataclasses.MISSING or not dataclasses.is_dataclass(cls):
            continue
        module = importlib.import_module(cls.__module__)
        path = Path(module.__file__)
        files = [path] if path.parent.name == "pipeline" else sorted(path.parent.glob("*.py"))
        for p in files:
            out.setdefault(p, []).append(cls)
    return out


def _defaults(fn: ast.FunctionDef):
    a = fn.args
    pos = a.posonlyargs + a.args
    yield from zip(pos[len(pos) - len(a.defaults):], a.defaults)
    yield from ((arg, d) for arg, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None)


def test_kernel_defaults_refer_to_the_params_classes():
    bad = []
    for path, classes in _scopes().items():
        names = {c.__name__: {f.name for f in dataclasses.fields(c)} for c in classes}
        fed = set().union(*names.values())
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for arg, d in _defaults(node):
                where = f"{path.relative_to(REPO)}:{node.lineno} {node.name}({arg.arg}={ast.unparse(d)})"
                if arg.arg == "params":
                    ok = isinstance(d, ast.Call) and isinstance(d.func, ast.Name) and d.func.id in names \
                        and not d.args and not d.keywords
                elif arg.arg in fed:
                    ok = isinstance(d, ast.Attribute) and d.attr == arg.arg and isinstance(d.value, ast.Name) \
                        and arg.arg in names.get(d.value.id, ())
                else:
                    continue
                if not ok:
                    bad.append(where)
    assert not bad, "kernel defaults copying a parameter default (refer to the params class):\n" + "\n".join(bad)


def test_defaults_are_the_classes_values():
    from schlieren.pipeline import flow, masks, poisson, sync

    assert flow.deflection_field.__kwdefaults__["window"] == flow.FlowParams().window
    assert masks.make_mask.__kwdefaults__["grow_factor"] == masks.MaskParams().grow_factor
    assert sync.field_motion.__kwdefaults__["finest_level"] == sync.ResampleParams().finest_level
    assert poisson.sign_constraint.__kwdefaults__["max_opposite"] == poisson.PoissonParams().sign_max_opposite


_BINDING = ("import inspect", "from inspect", "__signature__", "__code__.co_varnames", "kernel_kwargs",
            "field_kwargs")


def test_no_binding_by_signature():
    """No code of the package binds parameters to kernels by their names in a signature
    (``inspect.signature``, ``__code__``), nor keeps a drop list of fields a kernel lacks."""
    bad = [f"{p.relative_to(REPO)}: {word}" for root in ("pipeline", "storage", "workers")
           for p in sorted((REPO / root).rglob("*.py")) for word in _BINDING if word in p.read_text()]
    assert not bad, bad
