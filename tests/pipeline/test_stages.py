"""The stage table and the run configuration."""

import dataclasses

import pytest

from schlieren.pipeline import stages
from schlieren.pipeline.stages import STAGES, RunConfig, bind_medium, config_from_dict, config_to_dict


def test_config_round_trips_through_plain_dicts():
    cfg = RunConfig(reconstruction="direct", warm_start_block=2)
    assert config_from_dict(config_to_dict(cfg)) == cfg


def test_unknown_parameters_are_refused():
    with pytest.raises(ValueError, match="wndow"):
        config_from_dict({"flow": {"wndow": 5}})
    with pytest.raises(ValueError, match="bogus"):
        config_from_dict({"bogus": 1})
    with pytest.raises(ValueError):
        RunConfig(reconstruction="three-step")


def test_spacetime_needs_the_two_step_reconstruction():
    with pytest.raises(ValueError, match="spacetime.window"):
        config_from_dict({"reconstruction": "direct", "spacetime": {"window": 1}})
    assert config_from_dict({"spacetime": {"window": 1}}).spacetime.window == 1


def test_bind_medium_sets_every_n_ambient():
    cfg = bind_medium(RunConfig(), 1.0003)
    found = [getattr(cfg, f.name).n_ambient for f in dataclasses.fields(cfg)
             if dataclasses.is_dataclass(getattr(cfg, f.name))
             and hasattr(getattr(cfg, f.name), "n_ambient")]
    assert found and all(v == 1.0003 for v in found)


@pytest.mark.parametrize("optional", [(), ("spacetime",), ("uncertainty",), ("spacetime", "uncertainty")])
def test_table_is_consistent(optional):
    table = stages.stages_with(optional)
    names = [s.name for s in table]
    assert len(set(names)) == len(names)
    absent = {s.name for s in stages.OPTIONAL_STAGES} - set(names)  # a dependency on it is dropped without it
    produced = {"images"}
    for s in table:
        for dep, how in s.after:
            assert dep in names[: names.index(s.name) + (how == "chain")] or dep in absent, (s.name, dep)
            assert how in {"same", "all", "window", "neighbours", "chain", "block", "middle", "margin"}
        if s.params is not None:
            assert hasattr(RunConfig(), s.params), s.name
        produced |= set(s.outputs)
    # every stage's inputs are produced by an earlier stage (or are the frames); under a
    # space-time stage the tomography writes the per-frame gradient it reads
    seen = {"images"} | ({"gradient_frame"} if "spacetime" in optional else set())
    for s in table:
        # (flow_window: written by the regularisation task beside its reg_weight)
        assert set(s.inputs) <= seen | {"geometry", "flow_window"}, s.name
        seen |= set(s.outputs)
