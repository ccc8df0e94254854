"""The run-parameter declarations: every field with its help, unit and bounds; strict validation
(of ``--params`` and of construction); generated docstrings; no drift of the docs."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from schlieren.pipeline.params import ParamsError, param, parameters, schema, validate
from schlieren.pipeline.params_text import params_markdown, params_yaml
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
        if {"int", "float"} & set(r.types):  # numbers are bounded both ways and have a unit
            assert (r.spec.ge is not None or r.spec.gt is not None) and \
                   (r.spec.le is not None or r.spec.lt is not None), r.path
            assert r.unit, r.path


def _sentences(text: str) -> int:
    return len([s for s in re.split(r"(?<=[.!?])\s+(?=[A-Z`(])", text.strip()) if s])


def test_help_says_what_and_why_in_two_sentences_without_history():
    for r in schema(RunConfig):
        assert r.spec.help.endswith("."), r.path
        for text in (r.spec.help, r.spec.derived):
            assert len(text) <= 330, (r.path, len(text))
            assert _sentences(text) <= 2, (r.path, text)
            # measurement history (dB figures, timings, "was X") lives in the linked results
            assert not re.search(r"\bdB\b|\(was |\bms\b| -> |\d{4}-\d\d-\d\d", text), (r.path, text)
        for path in r.spec.see:
            assert (REPO / path).is_file(), (r.path, path)


def test_tuned_parameters_and_the_tuning_pages_entries_match():
    """``tuned=True`` links the parameter's entry on the tuning page (a heading of its dotted
    name under "Run parameters"), and every such entry belongs to a tuned parameter."""
    tuning = (REPO / "docs" / "tuning.md").read_text()
    entries = set(re.findall(r"^### `([\w.]+)`$", tuning.split("\n## Run parameters\n", 1)[1], re.M))
    tuned = {r.path for r in schema(RunConfig) if r.spec.tuned}
    assert tuned and tuned == entries, (sorted(tuned - entries), sorted(entries - tuned))
    doc = params_markdown(RunConfig)
    for path in tuned:  # the link's anchor is GitHub's for the heading
        assert f"(tuning.md#{path.replace('.', '')})" in doc, path


def test_a_field_without_metadata_or_help_fails_the_schema():
    @dataclasses.dataclass(frozen=True)
    class NewParams:
        """New stage."""

        a: int = param(1, unit="1", ge=0, le=5, help="Declared.")
        b: float = 0.5

    @dataclasses.dataclass(frozen=True)
    class Cfg:
        new: NewParams = dataclasses.field(default_factory=NewParams)

    with pytest.raises(TypeError, match="NewParams.b has no schema"):
        schema(Cfg)

    @dataclasses.dataclass(frozen=True)
    class Undocumented:
        """No help."""

        a: int = param(1, unit="1", ge=0, le=5)

    @dataclasses.dataclass(frozen=True)
    class Cfg2:
        new: Undocumented = dataclasses.field(default_factory=Undocumented)

    with pytest.raises(TypeError, match="Undocumented.a has no meaning"):
        schema(Cfg2)


def test_a_params_class_is_checked_where_it_is_declared():
    with pytest.raises(TypeError, match="Late.a has no meaning"):
        @parameters
        class Late:
            """No help."""

            a: int = param(1, unit="1", ge=0, le=5)
    with pytest.raises(TypeError, match="Attributes section is generated"):
        @parameters
        class HandWritten:
            """Hand-written.

            Attributes
            ----------
            a : int
                A second description.
            """

            a: int = param(1, unit="1", ge=0, le=5, help="The first.")
    with pytest.raises(TypeError, match="not in __post_init__"):
        @parameters
        class Checked:
            """Checks of its own."""

            a: int = param(1, unit="1", ge=0, le=5, help="A.")

            def __post_init__(self):
                pass
    with pytest.raises(TypeError, match=r"the default 9 is not an integer in \[0, 5\]"):
        @parameters
        class Outside:
            """Default out of range."""

            a: int = param(9, unit="1", ge=0, le=5, help="A.")


def test_construction_validates_through_the_schema():
    from schlieren.pipeline.flow import FlowParams
    from schlieren.pipeline.masks import MaskParams

    with pytest.raises(ParamsError, match=r"^FlowParams.window: must be an odd integer in \[3, 255\] \(got 10\)$"):
        FlowParams(window=10)
    with pytest.raises(ValueError, match="FlowParams.gradient: must be one of 'frame'"):
        FlowParams(gradient="central")
    with pytest.raises(ValueError, match=r"MaskParams.percentile: must be a finite number in \(0, 100\)"):
        MaskParams(percentile=100.0)
    with pytest.raises(ValueError, match="RunConfig.reconstruction"):
        RunConfig(reconstruction="three-step")
    with pytest.raises(ValueError, match="RunConfig.flow: must be a FlowParams"):
        RunConfig(flow=MaskParams())
    with pytest.raises(ParamsError, match=r"TomoParams.max_iter: .*\(and 1 more problem\)"):
        dataclasses.replace(RunConfig().tomography, max_iter=-5, tol=0)
    # numbers of numpy's types count as numbers, and keep their type
    p = FlowParams(window=np.int64(9), presmooth=np.float32(0.5))
    assert p.window == 9 and type(p.window) is np.int64


def test_a_number_or_keyword_field_accepts_both():
    @parameters
    class AutoParams:
        """Auto."""

        window: int | str = param("auto", unit="px", ge=3, le=99, odd=True, choices=("auto",),
                                  help="Window edge, or chosen from the images.")

    @dataclasses.dataclass(frozen=True)
    class Cfg:
        flow: AutoParams = dataclasses.field(default_factory=AutoParams)

    assert validate(Cfg, {"flow": {"window": 7}}).flow.window == 7
    assert validate(Cfg, {"flow": {"window": "auto"}}).flow.window == "auto"
    with pytest.raises(ParamsError, match=r"flow.window: must be an odd integer in \[3, 99\] or one of 'auto'"):
        validate(Cfg, {"flow": {"window": "big"}})
    with pytest.raises(ParamsError):
        validate(Cfg, {"flow": {"window": 8}})
    assert 'window : int or {"auto"}\n' in AutoParams.__doc__


def test_docstrings_are_generated_from_the_declarations():
    from schlieren.pipeline.flow import FlowParams

    doc = FlowParams.__doc__
    assert doc.startswith("Parameters of the deflection stage")
    assert '\nAttributes\n----------\nmethod : {"lk", "hs", "dis", "correlation"}\n' in doc
    assert "window : int\n    Edge of the Lucas-Kanade integration window" in doc
    assert "Derived by the run: with `window_per_voxel` > 0" in doc
    assert "flow : FlowParams\n" in RunConfig.__doc__


def test_derived_parameters_say_so_and_from_what():
    derived = {r.path for r in schema(RunConfig) if r.spec.derived}
    assert derived == {"flow.window", "flow.factor", "flow.presmooth", "tomography.ray_binning",
                       "tomography.reg_weight", "tomography.n_ambient", "direct.n_ambient"}
    text, md = params_yaml(RunConfig), params_markdown(RunConfig)
    assert text.count("Derived by the run:") == len(derived)
    assert "*Derived by the run*: with `window_per_voxel` > 0" in md


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
    with pytest.raises(ParamsError, match="TomoParams.max_iter"):
        dataclasses.replace(RunConfig().tomography, max_iter=-5)
    # one changed behind the construction's back is still refused by the run's check
    tomo = RunConfig().tomography
    object.__setattr__(tomo, "max_iter", -5)
    with pytest.raises(ParamsError, match="tomography.max_iter"):
        check_config(dataclasses.replace(RunConfig(), tomography=tomo))
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
