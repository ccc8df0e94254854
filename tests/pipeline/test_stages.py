"""The stage table and the run configuration."""

import dataclasses

import pytest

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


def test_bind_medium_sets_every_n_ambient():
    cfg = bind_medium(RunConfig(), 1.0003)
    found = [getattr(cfg, f.name).n_ambient for f in dataclasses.fields(cfg)
             if dataclasses.is_dataclass(getattr(cfg, f.name))
             and hasattr(getattr(cfg, f.name), "n_ambient")]
    assert found and all(v == 1.0003 for v in found)


def test_table_is_consistent():
    names = [s.name for s in STAGES]
    assert len(set(names)) == len(names)
    produced = {"images"}
    for s in STAGES:
        for dep, how in s.after:
            assert dep in names[: names.index(s.name) + (how == "chain")], (s.name, dep)
            assert how in {"same", "all", "window", "chain", "block", "middle", "margin"}
        if s.params is not None:
            assert hasattr(RunConfig(), s.params), s.name
        produced |= set(s.outputs)
    # every stage's inputs are produced by an earlier stage (or are the frames)
    seen = {"images"}
    for s in STAGES:
        assert set(s.inputs) <= seen | {"geometry"}, s.name
        seen |= set(s.outputs)
