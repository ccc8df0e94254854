"""Layering: the storage modules never pull in dask or distributed (STYLE.md)."""

from __future__ import annotations

import subprocess
import sys

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from schlieren.storage.errors import SessionError
from schlieren.storage.session.checks import _check_range


def test_storage_modules_do_not_import_dask():
    code = (
        "import sys\n"
        "import schlieren.storage.session, schlieren.storage.frames\n"
        "import schlieren.storage.store, schlieren.storage.layout\n"
        "bad = sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


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
