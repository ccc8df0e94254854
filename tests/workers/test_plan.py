"""The compiled task plan: topological order, dependency kinds, resume skipping."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schlieren.pipeline.stages import STAGES
from schlieren.workers.plan import Extents, make_plan, task_key

extents = st.builds(
    lambda c, f, margin_lo, margin_hi, block: Extents(
        camera=c, frame=f, raw_frame=f + margin_lo + margin_hi, raw_offset=margin_lo,
        warm_start_block=block),
    st.integers(1, 4), st.integers(1, 6), st.integers(0, 2), st.integers(0, 2), st.integers(1, 4))


@settings(max_examples=40, deadline=None)
@given(extents)
def test_every_dependency_comes_earlier_and_exists(ext):
    plan = make_plan(ext, "tok")
    seen = set()
    for t in plan.tasks:
        for d in t.deps:
            assert d in seen, (t.key, d)
        seen.add(t.key)
    # one task per index of the mapped dims
    sizes = {"camera": ext.camera, "frame": ext.frame, "raw_frame": ext.raw_frame}
    for s in STAGES:
        n = 1
        for d in s.over:
            n *= sizes[d]
        assert len([t for t in plan.tasks if t.stage == s.name]) == n


def _indices_of(task, stage):
    """Sorted (camera, frame) indices of ``task``'s dependencies on ``stage``."""
    return sorted(tuple(int(x) for x in d.split("-")[-2:]) for d in task.deps if d.startswith(stage + "-"))


@settings(max_examples=40, deadline=None)
@given(extents)
def test_resample_waits_for_raw_frames_within_the_halo(ext):
    plan = make_plan(ext, "tok")
    for t in plan.by_stage()["resample"]:
        c, k = t.index
        expect = [(c, j) for j in range(ext.raw_frame) if abs(j - ext.raw_offset - k) <= 2]
        assert _indices_of(t, "deflection") == expect
        assert task_key("clock", "tok", ()) in t.deps


@settings(max_examples=40, deadline=None)
@given(extents)
def test_only_margin_deflections_wait_for_the_clock(ext):
    """A raw frame outside the output range is processed only if an output instant needs
    it, which the clock decides; the others start at once."""
    plan = make_plan(ext, "tok")
    clock = task_key("clock", "tok", ())
    for t in plan.by_stage()["deflection"]:
        c, j = t.index
        margin = not ext.raw_offset <= j < ext.raw_offset + ext.frame
        assert (clock in t.deps) == margin, (t.index, ext)


@settings(max_examples=40, deadline=None)
@given(extents)
def test_masks_wait_for_the_threshold_and_the_potentials_they_read(ext):
    # the potential edges keep Dask from queueing masks as root tasks (stages.py)
    plan = make_plan(ext, "tok")
    for t in plan.by_stage()["mask"]:
        c, k = t.index
        assert _indices_of(t, "potential") == [(c, j) for j in range(ext.frame) if abs(j - k) <= 1]
        assert task_key("threshold", "tok", ()) in t.deps


@settings(max_examples=30, deadline=None)
@given(extents)
def test_regularisation_waits_for_the_middle_frames_masks_only(ext):
    """It chooses the weight on the middle frame (tasks.regularisation reads those masks):
    every camera's mask of that frame and the geometry, no other mask."""
    plan = make_plan(ext, "tok")
    (t,) = plan.by_stage()["regularisation"]
    assert _indices_of(t, "mask") == [(c, ext.frame // 2) for c in range(ext.camera)]
    assert task_key("geometry", "tok", ()) in t.deps


@settings(max_examples=30, deadline=None)
@given(extents)
def test_tomography_chain_follows_warm_start_blocks(ext):
    plan = make_plan(ext, "tok")
    for t in plan.by_stage()["tomography"]:
        (k,) = t.index
        prev = task_key("tomography", "tok", (k - 1,))
        assert (prev in t.deps) == (k % ext.warm_start_block != 0)


def test_completed_tasks_are_skipped_and_their_edges_dropped():
    ext = Extents(camera=2, frame=3, raw_frame=5, raw_offset=1, warm_start_block=2)
    full = make_plan(ext, "tok")
    done = {("deflection", (0, j)) for j in range(5)} | {("sync", (0,)), ("sync", (1,))}
    plan = make_plan(ext, "tok", done=lambda s, i: (s, i) in done)
    assert plan.skipped == len(done)
    assert len(plan.tasks) == len(full.tasks) - len(done)
    keys = {t.key for t in plan.tasks}
    for t in plan.tasks:
        assert set(t.deps) <= keys


def test_critical_path_priorities_are_upward_ranks():
    """rank = own cost + the highest rank among the tasks waiting for it (checked by a
    brute-force longest path), so chained solves start early and leaves rank lowest."""
    from schlieren.workers.plan import critical_path_priorities

    ext = Extents(camera=2, frame=6, raw_frame=8, raw_offset=1, warm_start_block=3)
    plan = make_plan(ext, "tok")
    costs = {s.name: s.cost for s in STAGES}
    rank = critical_path_priorities(plan)
    stage_of = {t.key: t.stage for t in plan.tasks}
    succ = {t.key: [] for t in plan.tasks}
    for t in plan.tasks:
        for d in t.deps:
            succ[d].append(t.key)

    def longest(key):  # brute force over every path to the end
        return costs[stage_of[key]] + max((longest(s) for s in succ[key]), default=0.0)

    for t in plan.tasks:
        assert abs(rank[t.key] - longest(t.key)) < 1e-9, t.key
    tomo = {t.index[0]: rank[t.key] for t in plan.by_stage()["tomography"]}
    # within a warm-start block the chain's head outranks its tail; heads of blocks tie
    assert tomo[0] > tomo[1] > tomo[2] and tomo[3] > tomo[4] > tomo[5]
    assert abs(tomo[0] - tomo[3]) < 1e-9
    hull = {t.index[0]: rank[t.key] for t in plan.by_stage()["hull"]}
    # a block's first solve waits for every hull of the block (the shared restriction)
    tomo_deps = {t.index[0]: t.deps for t in plan.by_stage()["tomography"]}
    hull_key = {t.index[0]: t.key for t in plan.by_stage()["hull"]}
    assert {hull_key[i] for i in range(3)} <= set(tomo_deps[0]) and hull_key[3] not in tomo_deps[0]
    assert {hull_key[i] for i in range(3, 6)} <= set(tomo_deps[4])
    assert hull[0] == hull[2] > tomo[0] and hull[3] == hull[5]
    assert rank[plan.by_stage()["geometry"][0].key] > max(hull.values())


def test_chain_first_priorities_lift_each_chain_to_its_head():
    """A block's later solves outrank every other block's first solve (so a worker carries the
    block it holds on), keep their order inside the chain, and nothing else changes."""
    from schlieren.workers.plan import CHAIN_STEP, chain_first_priorities, critical_path_priorities

    ext = Extents(camera=2, frame=10, raw_frame=12, raw_offset=1, warm_start_block=4)
    plan = make_plan(ext, "tok")
    rank = critical_path_priorities(plan)
    prio = chain_first_priorities(plan, rank)
    tomo = {t.index[0]: t.key for t in plan.by_stage()["tomography"]}
    p = {k: prio[key] for k, key in tomo.items()}
    heads = (0, 4, 8)
    for h in heads:
        chain = [k for k in range(h, min(h + 4, 10))]
        assert [p[k] for k in chain] == sorted(p[k] for k in chain)  # order kept
        for k in chain[1:]:
            assert p[k] == pytest.approx(rank[tomo[h]] + CHAIN_STEP * (k - h))
            assert all(p[k] > p[o] for o in heads if o != h and rank[tomo[o]] <= rank[tomo[h]])
    assert rank[tomo[1]] < rank[tomo[4]] < p[1]  # by rank alone the next block's head went first
    others = [t.key for t in plan.tasks if t.stage != "tomography"]
    assert all(prio[k] == rank[k] for k in others)


@settings(max_examples=40, deadline=None)
@given(extents, st.integers(1, 5), st.integers(1, 5))
def test_batched_tasks_cover_every_index_once_and_keep_every_dependency(ext, image_per_task, flow_per_task):
    """Blocks of frames of one camera: each (stage, index) is in exactly one task, every
    per-index dependency becomes an edge to the task holding it (or is inside the task),
    edges point backwards, and only the batched stages are grouped (one size for all, or
    one for the image stages and another for the flow-grid stages)."""
    sizes = {s.name: (flow_per_task if s.grid == "flow" else image_per_task) for s in STAGES if s.batch}
    plan = make_plan(ext, "tok", frames_per_task=image_per_task if image_per_task == flow_per_task else sizes)
    unit = make_plan(ext, "tok")
    owner = {}
    for t in plan.tasks:
        for i in t.indices:
            assert (t.stage, i) not in owner
            owner[(t.stage, i)] = t.key
        st_ = next(s for s in STAGES if s.name == t.stage)
        if st_.batch:
            per_task = sizes[t.stage]
            assert len(t.indices) <= per_task
            assert len({i[0] for i in t.indices}) == 1  # one camera
            assert len({i[1] // per_task for i in t.indices}) == 1  # one fixed block
        else:
            assert t.indices == (t.index,)
    assert set(owner) == {(t.stage, t.index) for t in unit.tasks}
    unit_deps = {(t.stage, t.index): t.deps for t in unit.tasks}
    key_of_unit = {t.key: (t.stage, t.index) for t in unit.tasks}
    seen = set()
    for t in plan.tasks:
        need = {owner[key_of_unit[d]] for i in t.indices for d in unit_deps[(t.stage, i)]} - {t.key}
        assert set(t.deps) == need
        assert set(t.deps) <= seen
        seen.add(t.key)


def test_a_resumed_plan_batches_only_the_missing_frames():
    ext = Extents(camera=2, frame=7, raw_frame=9, raw_offset=1, warm_start_block=2)
    done = {("mask", (0, k)) for k in (0, 1, 2, 5)} | {("mask", (1, k)) for k in range(4)}
    plan = make_plan(ext, "tok", done=lambda s, i: (s, i) in done, frames_per_task=4)
    masks = {t.key: t.indices for t in plan.by_stage()["mask"]}
    assert masks == {task_key("mask", "tok", (0, 0)): ((0, 3),),
                     task_key("mask", "tok", (0, 4)): ((0, 4), (0, 6)),
                     task_key("mask", "tok", (1, 4)): ((1, 4), (1, 5), (1, 6))}
    assert plan.skipped == len(done)


def test_default_frames_per_task_follows_the_image_size():
    from schlieren.workers.run import MAX_FRAMES_PER_TASK, default_frames_per_task

    assert default_frames_per_task((480, 360)) == 8
    assert default_frames_per_task((960, 720)) == 4
    assert default_frames_per_task((1440, 1080)) == 2
    assert default_frames_per_task((2560, 1440)) == 1
    assert default_frames_per_task((4096, 3072)) == 1
    assert default_frames_per_task((32, 24)) == MAX_FRAMES_PER_TASK
    # with the flow grid: its stages batch by flow cells (480 x 360 at factor 3: 4 frames)
    sizes = default_frames_per_task((1440, 1080), 3)
    assert sizes == {"deflection": 2, "resample": 4, "potential": 4, "mask": 4}
    assert default_frames_per_task((480, 360), 3) == dict.fromkeys(sizes, MAX_FRAMES_PER_TASK)
    assert default_frames_per_task((4096, 3072), 3)["deflection"] == 1


def test_batch_sizes_are_checked():
    from schlieren.workers.plan import batch_sizes

    assert batch_sizes(3) == dict.fromkeys(["deflection", "resample", "potential", "mask"], 3)
    assert batch_sizes({"mask": 2})["mask"] == 2 and batch_sizes({"mask": 2})["resample"] == 1
    with pytest.raises(ValueError, match="not batched"):
        batch_sizes({"tomography": 2})
    with pytest.raises(ValueError, match="at least 1"):
        batch_sizes({"mask": 0})
    with pytest.raises(ValueError, match="at least 1"):
        make_plan(Extents(camera=1, frame=2, raw_frame=2, raw_offset=0), "t", frames_per_task=0)


def _deps_oracle(st, index, ext):
    """The former quadratic scan: every index of the dependency stage tested against the rule."""
    from schlieren.workers.plan import _STAGE, _indices

    labels = dict(zip(st.over, index))
    out = []
    for dep_name, how in st.after:
        dep = _STAGE[dep_name]
        for i in _indices(dep, ext):
            dl = dict(zip(dep.over, i))
            if how == "all":
                out.append((dep_name, i))
            elif how == "same" and all(labels[d] == dl[d] for d in dl.keys() & labels.keys()):
                out.append((dep_name, i))
            elif how == "window" and dl.get("camera", labels.get("camera")) == labels.get("camera"):
                f = dl["raw_frame"] - ext.raw_offset if "raw_frame" in dl else dl["frame"]
                if abs(f - labels["frame"]) <= st.frame_halo:
                    out.append((dep_name, i))
            elif how == "margin":
                if not 0 <= labels["raw_frame"] - ext.raw_offset < ext.frame:
                    out.append((dep_name, i))
            elif how == "middle":
                if dl["frame"] == ext.frame // 2:
                    out.append((dep_name, i))
            elif how == "block":
                B = max(ext.warm_start_block, 1)
                if dl["frame"] // B == labels["frame"] // B:
                    out.append((dep_name, i))
        if how == "chain" and labels["frame"] % max(ext.warm_start_block, 1) != 0:
            out.append((dep_name, (labels["frame"] - 1,)))
    return sorted(out)


@pytest.mark.parametrize("ext", [Extents(camera=3, frame=7, raw_frame=11, raw_offset=2, warm_start_block=4),
                                 Extents(camera=1, frame=1, raw_frame=5, raw_offset=2, warm_start_block=1),
                                 Extents(camera=4, frame=9, raw_frame=9, raw_offset=0, warm_start_block=3)])
def test_direct_dependencies_equal_the_exhaustive_scan(ext):
    """The linear dependency construction gives exactly the edges of the exhaustive scan."""
    from schlieren.workers.plan import _deps, _indices

    for st in STAGES:
        for index in _indices(st, ext):
            assert sorted(_deps(st, index, ext)) == _deps_oracle(st, index, ext), (st.name, index)
