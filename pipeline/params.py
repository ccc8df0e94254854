"""The run-parameter schema: meaning, unit, default and valid range of every parameter.

Every field of a stage's frozen params dataclass (``FlowParams``, ``TomoParams``, ... and
the run-level fields of :class:`~schlieren.pipeline.stages.RunConfig`) declares its unit
and valid values next to its default with :func:`param`::

    @dataclass(frozen=True)
    class FlowParams:
        window: int = param(17, unit="px", ge=3, le=255, odd=True)
        window_type: str = param("gaussian", choices=("box", "gaussian"))
        # a number or a keyword: annotate the union and list the keywords
        reg: float | str = param("auto", unit="1", ge=0, le=1e3, choices=("auto",))

and describes its meaning in the class docstring's numpydoc ``Attributes`` section (the
first sentence is the short meaning printed by ``schlieren params``; the whole entry goes
into docs/parameters.md). A field without either is an error of the schema
(:func:`schema`), which the test suite checks for every params class, so a new field
cannot be added without them.

The same schema drives:

* validation (:func:`validate`): strict types (an integer field takes no ``2.7``, no
  ``"3"`` and no ``True``; a bool field takes only ``true``/``false``; a number field
  takes no text), finite numbers only, ranges and choices, unknown names refused with a
  suggestion; each problem is reported with its dotted name (``tomography.max_iter``).
  The checks are a pydantic model generated from the dataclass fields;
* ``schlieren params`` (a commented YAML file for ``--params``: :func:`params_yaml`);
* docs/parameters.md (:func:`params_markdown`; a test keeps the file equal to it).

Pure: no file I/O (the caller reads the YAML file and passes the mapping).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import textwrap
import types
import typing
from dataclasses import dataclass
from typing import Any, Annotated, Literal, Union

__all__ = ["Param", "param", "FieldSchema", "ParamsError", "schema", "validate", "expected",
           "params_yaml", "params_markdown"]

_KEY = "schlieren.param"


@dataclass(frozen=True)
class Param:
    """Unit and valid values of one parameter (stored in the dataclass field's metadata).

    Attributes
    ----------
    unit : str
        ``"px"`` (full-resolution image pixels), ``"flow cells"``, ``"voxels"``,
        ``"frames"``, ``"grey levels"``, ``"1"`` (dimensionless) or an SI unit;
        ``""`` for choices and switches.
    ge, gt, le, lt : float or None
        Bounds of a number (inclusive / exclusive).
    odd, even : bool
        An integer that must be odd (or even).
    choices : tuple of str
        Allowed keywords of a text field (or of the text branch of ``int | str``).
    note : str
        Appended to the meaning (e.g. where the value comes from at run time).
    """

    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    odd: bool = False
    even: bool = False
    choices: tuple[str, ...] = ()
    note: str = ""


def param(default: Any, *, unit: str = "", ge: float | None = None, gt: float | None = None,
          le: float | None = None, lt: float | None = None, odd: bool = False, even: bool = False,
          choices: tuple[str, ...] = (), note: str = "") -> Any:
    """A dataclass field with its default and its :class:`Param` metadata."""
    meta = Param(unit=unit, ge=ge, gt=gt, le=le, lt=lt, odd=odd, even=even, choices=tuple(choices), note=note)
    return dataclasses.field(default=default, metadata={_KEY: meta})


@dataclass(frozen=True)
class FieldSchema:
    """One parameter as documented and validated.

    Attributes
    ----------
    group : str
        The :class:`RunConfig` field holding it (``"flow"``), or ``""`` for run-level fields.
    name : str
    types : tuple of str
        Accepted Python types: ``"int"``, ``"float"``, ``"bool"``, ``"str"``.
    default : Any
    meaning : str
        Short meaning (first sentence of the docstring entry, plus the note).
    description : str
        The whole docstring entry (plus the note).
    spec : Param
    """

    group: str
    name: str
    types: tuple[str, ...]
    default: Any
    meaning: str
    description: str
    spec: Param

    @property
    def path(self) -> str:
        return f"{self.group}.{self.name}" if self.group else self.name

    @property
    def unit(self) -> str:
        return self.spec.unit

    @property
    def valid(self) -> str:
        """The valid values in words (``odd integer in [3, 255]``)."""
        return expected(self.types, self.spec)


class ParamsError(ValueError):
    """A run parameter of the wrong type or out of range; ``field`` is its dotted name."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(f"{field}: {message}" if field else message)
        self.message = message
        self.field = field


# --------------------------------------------------------------------------------------
# the schema of a params dataclass
# --------------------------------------------------------------------------------------
_TYPE_NAMES = {int: "int", float: "float", bool: "bool", str: "str"}


def _types_of(annotation, where: str) -> tuple[str, ...]:
    if annotation in _TYPE_NAMES:
        return (_TYPE_NAMES[annotation],)
    origin = typing.get_origin(annotation)
    if origin in (Union, types.UnionType):
        out: list[str] = []
        for a in typing.get_args(annotation):
            out.extend(_types_of(a, where))
        return tuple(out)
    if origin is Literal:
        return ("str",)
    raise TypeError(f"{where}: unsupported parameter type {annotation!r} (use int, float, bool, str "
                    "or a union of them)")


def _doc_entries(cls) -> dict[str, str]:
    """numpydoc ``Attributes`` entries of a class docstring: name -> text (one paragraph)."""
    doc = textwrap.dedent("\n".join((cls.__doc__ or "").splitlines()[1:]))
    m = re.search(r"^Attributes\n-+\n(.*?)(?:^\S[^\n]*\n-+\n|\Z)", doc, flags=re.M | re.S)
    if not m:
        return {}
    out: dict[str, str] = {}
    names: list[str] = []
    for line in m.group(1).splitlines():
        head = re.match(r"^([A-Za-z_][\w, ]*?)\s*:\s*.*$", line) if line and not line[0].isspace() else None
        if head:
            names = [n.strip() for n in head.group(1).split(",")]
            for n in names:
                out[n] = ""
        elif line.strip() and names:
            for n in names:
                out[n] = (out[n] + " " + line.strip()).strip()
    return out


def _plain(text: str) -> str:
    """reST markup to Markdown-style code: ``x`` and :func:`x` become `x`."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _first_sentence(text: str) -> str:
    """The first sentence (a period or semicolon outside parentheses, before a capital
    letter or the end); a very short one takes the next sentence along."""
    depth, cut = 0, None
    for k, ch in enumerate(text):
        depth += (ch in "([") - (ch in ")]")
        rest = text[k + 1:]
        if depth == 0 and ch in ".;" and (not rest.strip() or re.match(r"\s+[A-Z`(]", rest)):
            if k >= 25:
                cut = k
                break
            if cut is None:
                cut = k
                continue
            cut = k
            break
    if cut is None:
        return text
    return text[:cut].rstrip() + "."


def _is_group(f: dataclasses.Field) -> bool:
    return f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory)


def _leaf_fields(cls, fields, group: str) -> list[FieldSchema]:
    if not fields:
        return []
    hints = typing.get_type_hints(cls)
    docs = _doc_entries(cls)
    out = []
    for f in fields:
        where = f"{cls.__name__}.{f.name}"
        spec = f.metadata.get(_KEY)
        if spec is None:
            raise TypeError(f"{where} has no schema: declare it with param(default, unit=..., range...) "
                            "(schlieren.pipeline.params)")
        text = _plain(docs.get(f.name, ""))
        if not text:
            raise TypeError(f"{where} has no meaning: describe it in the Attributes section of "
                            f"{cls.__name__}'s docstring")
        kinds = _types_of(hints[f.name], where)
        if "str" in kinds and not spec.choices and kinds == ("str",):
            raise TypeError(f"{where}: a text parameter needs its choices")
        if spec.odd and spec.even:
            raise TypeError(f"{where}: odd and even at once")
        description = text + (f" {spec.note}" if spec.note else "")
        meaning = _first_sentence(text) + (f" {spec.note}" if spec.note else "")
        schema_ = FieldSchema(group, f.name, kinds, f.default, meaning, description, spec)
        _check_default(schema_, where)
        out.append(schema_)
    return out


def _check_default(fs: FieldSchema, where: str) -> None:
    try:
        _adapter(fs).validate_python(fs.default)
    except Exception:
        raise TypeError(f"{where}: the default {fs.default!r} is not {fs.valid}") from None


def schema(config_cls) -> list[FieldSchema]:
    """Every parameter of ``config_cls`` (a RunConfig-like dataclass), groups in field order.

    Fields whose default factory is a dataclass are groups (one level deep); the others
    are run-level parameters (group ``""``).

    Raises
    ------
    TypeError
        A field without :func:`param` metadata or without a docstring entry, an
        unsupported type, or a default outside its own range.
    """
    top = [f for f in dataclasses.fields(config_cls) if not _is_group(f)]
    out = _leaf_fields(config_cls, top, "")
    for f in dataclasses.fields(config_cls):
        if _is_group(f):
            out.extend(_leaf_fields(f.default_factory, dataclasses.fields(f.default_factory), f.name))
    return out


# --------------------------------------------------------------------------------------
# validation (pydantic)
# --------------------------------------------------------------------------------------
def _adapter(fs: FieldSchema):
    from pydantic import TypeAdapter

    return TypeAdapter(_pydantic_type(fs))


def _parity(odd: bool):
    def check(v: int) -> int:
        if (v % 2 == 1) != odd:
            raise ValueError("parity")
        return v
    return check


def _pydantic_type(fs: FieldSchema):
    from pydantic import AfterValidator, Field

    s = fs.spec
    bounds = {k: getattr(s, k) for k in ("ge", "gt", "le", "lt") if getattr(s, k) is not None}
    branches = []
    if "bool" in fs.types:
        branches.append(Annotated[bool, Field(strict=True)])
    if "int" in fs.types:
        t = Annotated[int, Field(strict=True, **bounds)]
        if s.odd or s.even:
            t = Annotated[t, AfterValidator(_parity(s.odd))]
        branches.append(t)
    if "float" in fs.types:
        branches.append(Annotated[float, Field(strict=True, allow_inf_nan=False, **bounds)])
    if "str" in fs.types:
        branches.append(Literal[tuple(s.choices)] if s.choices else Annotated[str, Field(strict=True)])
    return branches[0] if len(branches) == 1 else Union[tuple(branches)]


def _fmt(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def expected(kinds: tuple[str, ...], s: Param) -> str:
    """The valid values of a parameter in words, e.g. ``odd integer in [3, 255]``."""
    parts = []
    if "bool" in kinds:
        parts.append("true or false")
    num = [k for k in kinds if k in ("int", "float")]
    if num:
        word = "integer" if num == ["int"] else "number"
        if s.odd:
            word = "odd " + word
        if s.even:
            word = "even " + word
        lo = f"[{_fmt(s.ge)}" if s.ge is not None else (f"({_fmt(s.gt)}" if s.gt is not None else None)
        hi = f"{_fmt(s.le)}]" if s.le is not None else (f"{_fmt(s.lt)})" if s.lt is not None else None)
        if lo and hi:
            word += f" in {lo}, {hi}"
        elif lo:
            word += f" >= {_fmt(s.ge)}" if s.ge is not None else f" > {_fmt(s.gt)}"
        elif hi:
            word += f" <= {_fmt(s.le)}" if s.le is not None else f" < {_fmt(s.lt)}"
        parts.append(("a finite " if word.startswith("number") else "an " if word[0] in "aeiou" else "a ") + word)
    if "str" in kinds:
        if s.choices:
            parts.append("one of " + ", ".join(repr(c) for c in s.choices))
        else:
            parts.append("text")
    return " or ".join(parts)


def _suggest(word: str, options) -> str:
    close = difflib.get_close_matches(str(word), list(options), n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


def _got(v: Any) -> str:
    r = repr(v)
    if isinstance(v, float) and not math.isfinite(v):
        r = str(v)
    return r if len(r) <= 40 else r[:37] + "..."


def validate(config_cls, data: dict | None) -> Any:
    """Build ``config_cls`` (a RunConfig) from a nested mapping, checking every value.

    Parameters
    ----------
    config_cls : type
        The RunConfig dataclass (run-level fields plus one dataclass per group).
    data : mapping or None
        ``{group: {name: value}}`` plus run-level ``{name: value}``; missing names take
        their defaults. Lists are not accepted for scalar parameters.

    Returns
    -------
    config_cls instance

    Raises
    ------
    ParamsError
        The first problem, naming the field (``flow.window``) and the valid values;
        ``(and N more problems)`` when there are several.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ParamsError(f"the parameters must be a mapping of stage -> parameters, got "
                          f"{type(data).__name__}")
    fields = schema(config_cls)
    groups = {f.name: f for f in dataclasses.fields(config_cls) if _is_group(f)}
    by_group: dict[str, dict[str, FieldSchema]] = {}
    for fs in fields:
        by_group.setdefault(fs.group, {})[fs.name] = fs
    top_names = set(by_group.get("", {}))
    problems: list[ParamsError] = []

    def check(fs: FieldSchema, value: Any):
        if hasattr(value, "dtype") and getattr(value, "shape", None) == ():  # numpy scalars
            value = value.item()
        try:
            return _adapter(fs).validate_python(value)
        except Exception:
            problems.append(ParamsError(f"must be {fs.valid} (got {_got(value)})", fs.path))
            return fs.default

    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key in groups:
            if value is None:
                continue
            if not isinstance(value, dict):
                problems.append(ParamsError(f"must be a mapping of parameters, got {_got(value)}", str(key)))
                continue
            known = by_group.get(key, {})
            values = {}
            for name, v in value.items():
                if name not in known:
                    problems.append(ParamsError(f"unknown parameter{_suggest(name, known)}", f"{key}.{name}"))
                    continue
                values[name] = check(known[name], v)
            kwargs[key] = values
        elif key in top_names:
            kwargs[key] = check(by_group[""][key], value)
        else:
            problems.append(ParamsError(f"unknown parameter{_suggest(key, list(groups) + sorted(top_names))}",
                                        str(key)))
    if problems:
        first = problems[0]
        more = len(problems) - 1
        if more:
            raise ParamsError(first.message + f" (and {more} more problem{'s' if more > 1 else ''})", first.field)
        raise first
    built = {}
    for key, values in kwargs.items():
        if key in groups:
            try:
                built[key] = groups[key].default_factory(**values)
            except (TypeError, ValueError) as exc:
                raise ParamsError(str(exc), key) from None
        else:
            built[key] = values
    try:
        return config_cls(**built)
    except (TypeError, ValueError) as exc:
        raise ParamsError(str(exc)) from None


# --------------------------------------------------------------------------------------
# rendering: the YAML of `schlieren params` and docs/parameters.md
# --------------------------------------------------------------------------------------
def _yaml_scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if re.fullmatch(r"[A-Za-z_][\w-]*", v) and v.lower() not in {"true", "false", "yes", "no",
                                                                                "on", "off", "null"} else repr(v)
    if isinstance(v, float):
        r = repr(v)
        return r if ("." in r or "inf" in r or "nan" in r) else r.replace("e", ".0e", 1) if "e" in r else r + ".0"
    return repr(v)


def params_yaml(config_cls, values=None) -> str:
    """A commented YAML file of every parameter (``schlieren params``; valid ``--params``).

    Each parameter has a comment line with its meaning and one with its unit, valid
    values and default; ``values`` (a ``config_cls`` instance) overrides the printed values.
    """
    lines = ["# schlieren run parameters: edit what you need, delete the rest, then",
             "#   schlieren run SESSION --out STORE --params FILE",
             "# Unknown names, wrong types and values out of range are refused before any work.",
             "# Units: px = full-resolution image pixels; flow cells = cells of the flow grid",
             "# (flow.factor px each); voxels = reconstruction voxels; 1 = dimensionless.", ""]
    group = None
    for fs in schema(config_cls):
        if fs.group != group:
            group = fs.group
            if group:
                lines += ["", f"{group}:"]
        indent = "  " if fs.group else ""
        for ln in textwrap.wrap(fs.meaning, 92 - len(indent)):
            lines.append(f"{indent}# {ln}")
        unit = f"unit: {fs.unit}; " if fs.unit else ""
        lines.append(f"{indent}# {unit}valid: {fs.valid}; default: {_yaml_scalar(fs.default)}")
        v = fs.default
        if values is not None:
            v = getattr(getattr(values, fs.group), fs.name) if fs.group else getattr(values, fs.name)
        lines.append(f"{indent}{fs.name}: {_yaml_scalar(v)}")
    return "\n".join(lines) + "\n"


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def params_markdown(config_cls) -> str:
    """docs/parameters.md: one table per group with meaning, unit, default and valid values."""
    out = ["# Run parameters", "",
           "<!-- Generated from the parameter schema (schlieren.pipeline.params) by",
           "     `schlieren params --format markdown`; tests/pipeline/test_params_schema.py",
           "     fails when this file and the schema differ. Do not edit by hand. -->", "",
           "Every parameter of a run, with its meaning, unit, default and valid values. Print them "
           "as a commented YAML file with `schlieren params`, keep the ones you change, and pass "
           "the file with `schlieren run SESSION --out STORE --params FILE` (or "
           "`schlieren.run(..., params={...})` in Python). Values are checked before any work "
           "starts: unknown names, wrong types (text for a number, `2.7` or `true` for an "
           "integer, `\"no\"` for a switch), NaN/infinity and values out of range are refused "
           "with the parameter's name.", "",
           "Units: `px` = pixels of the full-resolution camera image; `flow cells` = cells of the "
           "flow grid (`flow.factor` px each); `voxels` = reconstruction voxels "
           "(`volume.voxel_size` of the session); `frames` = camera frames; `1` = dimensionless.", ""]
    group = None
    for fs in schema(config_cls):
        if fs.group != group:
            group = fs.group
            out += ["", f"## `{group}`" if group else "## Run-level", "",
                    "| parameter | meaning | unit | default | valid values |",
                    "| --- | --- | --- | --- | --- |"]
        out.append(f"| `{fs.path}` | {_md_cell(fs.description)} | {fs.unit or '-'} | "
                   f"`{_yaml_scalar(fs.default)}` | {_md_cell(fs.valid)} |")
    return "\n".join(out).replace("\n\n\n", "\n\n") + "\n"
