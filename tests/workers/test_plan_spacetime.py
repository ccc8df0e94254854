"""The space-time stage in the plan: present only with a window, fed by the per-frame
solves of its window, and feeding the integration."""

import dataclasses

from hypothesis import given, settings
from hypothesis import strategies as st

from schlieren.pipeline.spacetime import window_frames
from schlieren.pipeline.spacetime import SpaceTimeParams
from schlieren.pipeline.stages import STAGES, RunConfig, run_stages
from schlieren.workers.plan import Extents, make_plan, task_key

extents = st.builds(
    lambda c, f, block, window: Extents(camera=c, frame=f, raw_frame=f + 2, raw_offset=1, warm_start_block=block,
                                        spacetime_window=window),
    st.integers(1, 3), st.integers(1, 8), st.integers(1, 4), st.integers(0, 3))


def test_run_stages_add_the_spacetime_stage_before_the_integration():
    assert run_stages(RunConfig()) == STAGES
    names = [s.name for s in run_stages(RunConfig(spacetime=SpaceTimeParams(window=2)))]
    assert names.index("tomography") < names.index("spacetime") == names.index("integrate") - 1
    both = RunConfig(spacetime=SpaceTimeParams(window=2), uncertainty=dataclasses.replace(
        RunConfig().uncertainty, enabled=True))
    names = [s.name for s in run_stages(both)]
    assert names.index("spacetime") == names.index("integrate") - 1 and names[-1] == "uncertainty"


@settings(max_examples=40, deadline=None)
@given(extents)
def test_spacetime_tasks_wait_for_their_window_and_feed_the_integration(ext):
    plan = make_plan(ext, "tok")
    seen = set()
    for t in plan.tasks:
        assert all(d in seen for d in t.deps), (t.key, t.deps)
        seen.add(t.key)
    by = plan.by_stage()
    spacetime = by.get("spacetime", [])
    if ext.spacetime_window == 0:
        assert not spacetime
        for t in by["integrate"]:
            assert not any(d.startswith("spacetime-") for d in t.deps)
        return
    assert [t.index for t in spacetime] == [(k,) for k in range(ext.frame)]
    for t in spacetime:
        (k,) = t.index
        tomo = sorted(int(d.split("-")[-1]) for d in t.deps if d.startswith("tomography-"))
        assert tomo == list(window_frames(k, ext.frame, ext.spacetime_window))
    for t in by["integrate"]:
        assert task_key("spacetime", "tok", t.index) in t.deps


def test_spacetime_tasks_go_into_the_solves_resource_graph():
    """Dask gets one graph per resource request, each after the graphs it depends on: the
    space-time tasks (between the solves and the integrations) ask for the same TOMO slot."""
    from schlieren.workers.graph import plan_graphs

    plan = make_plan(Extents(camera=2, frame=5, raw_frame=7, raw_offset=1, warm_start_block=2,
                             spacetime_window=1), "tok")
    for have in (set(), {"TOMO"}):
        graphs = plan_graphs("store.zarr", plan, have)
        assert sum(len(g) for _, g in graphs) == len(plan.tasks)
