"""Property tests of region arithmetic: normalize_region, is_aligned / assert_aligned.

Oracles are brute force: numpy indexing for the region a given index selects, and an
element-wise enumeration of chunks for alignment.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import zarr
from hypothesis import given, settings
from hypothesis import strategies as st

from schlieren.storage.layout import (
    AlignmentError,
    ArraySpec,
    assert_aligned,
    chunk_grid_regions,
    is_aligned,
    normalize_region,
)


@st.composite
def shapes_chunks_regions(draw, max_dims=3, max_len=9):
    nd = draw(st.integers(1, max_dims))
    shape = tuple(draw(st.integers(1, max_len)) for _ in range(nd))
    chunks = tuple(draw(st.integers(1, n + 2)) for n in shape)
    region = []
    for n in shape:
        a = draw(st.integers(0, n))
        b = draw(st.integers(a, n))
        region.append(slice(a, b))
    return shape, chunks, tuple(region)


def oracle_aligned(shape, chunks, region) -> bool:
    """Brute force: every chunk touching the region lies inside it, and it is non-empty."""
    inside = np.zeros(shape, dtype=bool)
    inside[region] = True
    if not inside.any():
        return False
    counts = [-(-n // c) for n, c in zip(shape, chunks)]
    for idx in itertools.product(*(range(k) for k in counts)):
        box = tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(idx, chunks, shape))
        part = inside[box]
        if part.any() and not part.all():
            return False
    return True


@settings(max_examples=300, deadline=None)
@given(shapes_chunks_regions())
def test_is_aligned_matches_brute_force(scr):
    shape, chunks, region = scr
    assert is_aligned(region, shape, chunks) == oracle_aligned(shape, chunks, region)


@settings(max_examples=200, deadline=None)
@given(shapes_chunks_regions())
def test_assert_aligned_raises_exactly_when_misaligned(scr):
    shape, chunks, region = scr
    spec = ArraySpec("a", tuple(f"d{k}" for k in range(len(shape))), shape, chunks, "float32", np.nan)
    if oracle_aligned(shape, chunks, region):
        assert assert_aligned(region, spec) == region
    else:
        with pytest.raises(AlignmentError):
            assert_aligned(region, spec)


@st.composite
def shapes_and_indices(draw):
    nd = draw(st.integers(1, 4))
    shape = tuple(draw(st.integers(1, 6)) for _ in range(nd))
    k = draw(st.integers(0, nd))
    index = []
    for n in shape[:k]:
        if draw(st.booleans()):
            index.append(draw(st.integers(0, n - 1)))
        else:
            a = draw(st.one_of(st.none(), st.integers(-n - 2, n + 2)))
            b = draw(st.one_of(st.none(), st.integers(-n - 2, n + 2)))
            index.append(slice(a, b))
    return shape, tuple(index)


@settings(max_examples=300, deadline=None)
@given(shapes_and_indices())
def test_normalize_region_selects_what_numpy_selects(si):
    shape, index = si
    a = np.arange(int(np.prod(shape))).reshape(shape)
    region = normalize_region(index, shape)
    assert len(region) == len(shape)
    # ints become length-1 slices: same elements as numpy's basic indexing
    np.testing.assert_array_equal(np.sort(a[region], axis=None), np.sort(a[index], axis=None))
    for sl, n in zip(region, shape):
        assert 0 <= sl.start <= sl.stop <= n and sl.step is None


def test_normalize_region_rejects_bad_indices():
    with pytest.raises(IndexError):
        normalize_region((5,), (3,))
    with pytest.raises(IndexError):
        normalize_region((-1,), (3,))
    with pytest.raises(IndexError):
        normalize_region((slice(0, 3, 2),), (3,))
    with pytest.raises(IndexError):
        normalize_region((0, 0), (3,))
    with pytest.raises(IndexError):
        normalize_region((1.5,), (3,))


def test_empty_region_is_not_aligned():
    spec = ArraySpec("a", ("x",), (4,), (2,), "float32", np.nan)
    with pytest.raises(AlignmentError):
        assert_aligned(slice(2, 2), spec)


def test_sharded_arrays_align_to_shards():
    arr = zarr.create_array(zarr.storage.MemoryStore(), shape=(8, 8), chunks=(2, 2), shards=(4, 8),
                            dtype="float32", fill_value=np.nan)
    assert_aligned((slice(0, 4),), arr)  # one whole shard
    with pytest.raises(AlignmentError):
        assert_aligned((slice(0, 2),), arr)  # whole chunks but half a shard


def test_chunk_grid_regions_tile_the_array():
    spec = ArraySpec("a", ("x", "y"), (5, 4), (2, 3), "float32", np.nan)
    regions = chunk_grid_regions(spec)
    cover = np.zeros(spec.shape, dtype=int)
    for r in regions:
        assert is_aligned(r, spec.shape, spec.chunks)
        cover[r] += 1
    assert len(regions) == 3 * 2 and np.all(cover == 1)


@settings(max_examples=25, deadline=None)
@given(shapes_chunks_regions(max_dims=2, max_len=7), st.integers(0, 2**31 - 1))
def test_store_writes_change_exactly_their_region_or_nothing(scr, seed):
    """Through ResultStore.write on a real zarr array: aligned writes land, others are refused."""
    from schlieren.storage.store import ResultStore

    shape, chunks, region = scr
    spec = ArraySpec("a", tuple(f"d{k}" for k in range(len(shape))), shape, chunks, "float64", np.nan)
    store = ResultStore.create(zarr.storage.MemoryStore(), [spec], attrs={}, markers={})
    data = np.random.default_rng(seed).normal(size=tuple(s.stop - s.start for s in region))
    expected = np.full(shape, np.nan)
    if oracle_aligned(shape, chunks, region):
        store.write("a", region, data)
        expected[region] = data
    else:
        with pytest.raises(AlignmentError):
            store.write("a", region, data)
    np.testing.assert_array_equal(store.read("a"), expected)
