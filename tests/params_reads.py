"""Which fields of the run's params classes the package's code reads while a block runs.

The dropped-field test (tests/workers/test_params_wiring.py) runs the tiny session inside
:func:`recording_reads`: a field no code of the package reads during a run (no task glue
passing it to a kernel, no kernel reading it from its params object) is declared for
nothing. Reads by the parameter machinery itself (validation, ``dataclasses``, the
generated ``__repr__``/``__eq__``) and by the code that only reports the run's derived
values do not count.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
from pathlib import Path


def params_classes() -> list[type]:
    """RunConfig and the params class of each of its groups."""
    from schlieren.pipeline.stages import RunConfig

    groups = [f.default_factory for f in dataclasses.fields(RunConfig)
              if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory)]
    return [RunConfig] + groups


def _roots() -> tuple[tuple[str, ...], tuple[str, ...]]:
    import schlieren.pipeline
    import schlieren.pipeline.overrides
    import schlieren.pipeline.params
    import schlieren.storage
    import schlieren.workers
    import schlieren.workers.overrides

    roots = tuple(str(Path(m.__file__).parent) + os.sep
                  for m in (schlieren.pipeline, schlieren.storage, schlieren.workers))
    skip = tuple(str(Path(m.__file__)) for m in (schlieren.pipeline.params, schlieren.pipeline.overrides,
                                                  schlieren.workers.overrides))
    return roots, skip


@contextlib.contextmanager
def recording_reads():
    """Yield a set that collects ``(class name, field)`` for every field read by the package's code."""
    roots, skip = _roots()
    reads: set[tuple[str, str]] = set()
    saved = {}
    for cls in params_classes():
        names = frozenset(f.name for f in dataclasses.fields(cls))

        def getattribute(self, name, _names=names, _cls=cls.__name__):
            if name in _names:
                where = sys._getframe(1).f_code.co_filename
                if where.startswith(roots) and where not in skip:
                    reads.add((_cls, name))
            return object.__getattribute__(self, name)

        saved[cls] = cls.__dict__.get("__getattribute__")
        cls.__getattribute__ = getattribute
    try:
        yield reads
    finally:
        for cls, old in saved.items():
            if old is None:
                del cls.__getattribute__
            else:
                cls.__getattribute__ = old
