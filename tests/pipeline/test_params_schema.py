"""The run-parameter schema: every field documented and bounded, strict validation, no drift of docs."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import yaml

from schlieren.pipeline.params import ParamsError, param, params_markdown, params_yaml, schema, validate
from schlieren.pipeline.stages import RunConfig, check_config, config_from_dict, config_to_dict

REPO = Path(__file__).resolve().parents[2]


def _groups():
    return [f for f in dataclasses.fields(RunConfig) if dataclasses.is_dataclass(f.default_factory)]


def test_every_parameter_has_meaning_unit_default_and_range():
    rows = schema(RunConfig)
    # every leaf field of every params dataclass is in the schema
    expected = {f.name for f in dataclasses.fields(RunConfig) if f not in _groups()}
    for g in _groups():
        expected |= {f"{g.name}.{h.name}" for h in dataclasses.fields(g.default_factory)}
    assert {r.path for r in rows} == expected
    for r in rows:
        assert r.meaning and r.description, r.path
        assert r.valid, r.path
        if {"int", "float"} & set(r.types):  # numbers are bounded both ways
            assert (r.spec.ge is not None or r.spec.gt is not None) and \
                   (r.spec.le is not None or r.spec.lt is not None), r.path


def test_a_field_without_metadata_or_meaning_fails_the_schema():
    @dataclasses.dataclass(frozen=True)
    class NewParams:
        """New stage.

        Attributes
        ----------
        a : int
            Documented and declared.
        b : float
            Documented, not declared.
        """

        a: int = param(1, unit="1", ge=0, le=5)
        b: float = 0.5

    @dataclasses.dataclass(frozen=True)
    class Cfg:
        new: NewParams = dataclasses.field(default_factory=NewParams)

    with pytest.raises(TypeError, match="NewParams.b has no schema"):
        schema(Cfg)

    @dataclasses.dataclass(frozen=True)
    class Undocumented:
        """No attributes section."""

        a: int = param(1, unit="1", ge=0, le=5)

    @dataclasses.dataclass(frozen=True)
    class Cfg2:
        new: Undocumented = dataclasses.field(default_factory=Undocumented)

    with pytest.raises(TypeError, match="Undocumented.a has no meaning"):
        schema(Cfg2)


def test_a_number_or_keyword_field_accepts_both():
    @dataclasses.dataclass(frozen=True)
    class AutoParams:
        """Auto.

        Attributes
        ----------
        window : int or "auto"
            Window edge, or chosen from the images.
        """

        window: int | str = param("auto", unit="px", ge=3, le=99, odd=True, choices=("auto",))

    @dataclasses.dataclass(frozen=True)
    class Cfg:
        flow: AutoParams = dataclasses.field(default_factory=AutoParams)

    assert validate(Cfg, {"flow": {"window": 7}}).flow.window == 7
    assert validate(Cfg, {"flow": {"window": "auto"}}).flow.window == "auto"
    with pytest.raises(ParamsError, match=r"flow.window: must be an odd integer in \[3, 99\] or one of 'auto'"):
        validate(Cfg, {"flow": {"window": "big"}})
    with pytest.raises(ParamsError):
        validate(Cfg, {"flow": {"window": 8}})


# the failures reported in issue 16 (item 3) and a few more
BAD = [
    ({"tomography": {"reg_weight": "abc"}}, "tomography.reg_weight"),
    ({"tomography": {"max_iter": -5}}, "tomography.max_iter"),
    ({"tomography": {"step": -0.25}}, "tomography.step"),
    ({"flow": {"texture_correction": "no"}}, "flow.texture_correction"),
    ({"flow": {"texture_correction": 1}}, "flow.texture_correction"),
    ({"flow": {"levels": 2.7}}, "flow.levels"),
    ({"flow": {"levels": "3"}}, "flow.levels"),
    ({"flow": {"levels": True}}, "flow.levels"),
    ({"flow": {"levels": 40}}, "flow.levels"),
    ({"tomography": {"max_iter": 10 ** 9}}, "tomography.max_iter"),
    ({"tomography": {"tol": 0}}, "tomography.tol"),
    ({"poisson": {"max_iter": 10 ** 9}}, "poisson.max_iter"),
    ({"flow": {"presmooth": math.nan}}, "flow.presmooth"),
    ({"tomography": {"reg_weight": math.inf}}, "tomography.reg_weight"),
    ({"flow": {"window": 4}}, "flow.window"),
    ({"flow": {"method": "magic"}}, "flow.method"),
    ({"flow": {"wndow": 5}}, "flow.wndow"),
    ({"flow": [1, 2]}, "flow"),
    ({"warm_start_block": 0}, "warm_start_block"),
    ({"bogus": 1}, "bogus"),
]


@pytest.mark.parametrize("data,field", BAD, ids=[b[1] + "=" + repr(b[0])[-14:] for b in BAD])
def test_bad_values_are_refused_naming_the_field(data, field):
    with pytest.raises(ParamsError) as info:
        config_from_dict(data)
    assert info.value.field == field
    assert str(info.value).startswith(field + ":")


def test_the_message_says_what_is_valid():
    with pytest.raises(ParamsError, match=r"must be an integer in \[1, 10000\] \(got -5\)"):
        config_from_dict({"tomography": {"max_iter": -5}})
    with pytest.raises(ParamsError, match="did you mean 'window'"):
        config_from_dict({"flow": {"wndow": 5}})
    with pytest.raises(ParamsError, match=r"and 1 more problem"):
        config_from_dict({"tomography": {"max_iter": 10 ** 9, "tol": 0}})


def test_numbers_are_kept_with_their_types():
    cfg = config_from_dict({"flow": {"alpha": 1, "window": 21}, "tomography": {"tol": 1e-3}})
    assert cfg.flow.alpha == 1.0 and type(cfg.flow.alpha) is float
    assert cfg.flow.window == 21 and type(cfg.flow.window) is int
    assert config_from_dict(config_to_dict(cfg)) == cfg


def test_configurations_built_in_python_are_checked_too():
    bad = dataclasses.replace(RunConfig(), tomography=dataclasses.replace(RunConfig().tomography, max_iter=-5))
    with pytest.raises(ParamsError, match="tomography.max_iter"):
        check_config(bad)
    assert check_config(RunConfig()) == RunConfig()


def test_the_printed_yaml_is_a_valid_params_file_of_the_defaults(tmp_path):
    from schlieren.storage.params_io import read_params

    text = params_yaml(RunConfig)
    p = tmp_path / "p.yaml"
    p.write_text(text)
    assert config_from_dict(read_params(p)) == RunConfig()
    # every parameter is printed with its meaning, unit, valid values and default
    for r in schema(RunConfig):
        assert f"valid: {r.valid}; default:" in text, r.path


def test_params_files_read_exponents_as_numbers(tmp_path):
    from schlieren.storage.params_io import read_params

    p = tmp_path / "p.yaml"
    p.write_text("tomography:\n  tol: 1e-3\n  max_iter: 40\npoisson:\n  tol: 1E-7\n")
    cfg = config_from_dict(read_params(p))
    assert cfg.tomography.tol == 1e-3 and cfg.poisson.tol == 1e-7 and cfg.tomography.max_iter == 40
    p.write_text("flow:\n  presmooth: .nan\n")
    with pytest.raises(ParamsError, match="flow.presmooth"):
        config_from_dict(read_params(p))


def test_docs_parameters_md_is_the_schema():
    doc = (REPO / "docs" / "parameters.md").read_text()
    assert doc == params_markdown(RunConfig), (
        "docs/parameters.md differs from the parameter schema: regenerate it with "
        "`schlieren params --format markdown > docs/parameters.md`")


def test_cli_params_prints_meaning_unit_default_and_range(capsys):
    from schlieren.workers.cli import main

    assert main(["params"]) == 0
    out = capsys.readouterr().out
    assert "# unit: px; valid: an odd integer in [3, 255]; default: 17\n  window: 17" in out
    assert yaml.safe_load(out)["tomography"]["max_iter"] == RunConfig().tomography.max_iter
