"""workers/tasks/: every stage of the stage table has its task, taking the stage's index."""

import inspect

from schlieren.pipeline.stages import OPTIONAL_STAGES, STAGES
from schlieren.workers.tasks import STAGE_TASKS


def test_every_declared_stage_has_a_task_taking_its_index():
    assert set(STAGE_TASKS) == {s.name for s in STAGES + OPTIONAL_STAGES}
    for s in STAGES + OPTIONAL_STAGES:
        params = list(inspect.signature(STAGE_TASKS[s.name]).parameters)
        assert params[0] == "ctx" and len(params) == 1 + len(s.over), (s.name, params, s.over)
