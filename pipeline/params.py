"""Run parameters: each declared once, and everything else made from that declaration.

A params class is a frozen dataclass declared with :func:`parameters`; each of its fields
is declared once, with :func:`param`: default, unit, valid values, a one- or two-sentence
help (what it is and why; measurement history goes to the results it links with ``see``
or to its entry on the tuning page, ``tuned=True``) and, for a value the run replaces by a
derived one, what it derives it from::

    @parameters
    class FlowParams:
        \"\"\"Parameters of the deflection stage (paper sec. 4).\"\"\"

        window: int = param(17, unit="px", ge=3, le=255, odd=True,
                            help="Edge of the Lucas-Kanade integration window.",
                            derived="with `window_per_voxel` > 0, per camera from the voxel's footprint.")
        # a number or a keyword: annotate the union and list the keywords
        reg: float | str = param("auto", unit="1", ge=0, le=1e3, choices=("auto",), help="...")

From these declarations come:

* validation, one set of rules for every way in: constructing a params object in code
  (``FlowParams(window=4)`` raises :class:`ParamsError`, a ``ValueError`` naming
  ``FlowParams.window``) and :func:`validate` for a ``--params`` mapping (dotted names
  such as ``tomography.max_iter``, unknown names with a suggestion, every problem
  counted). Strict types (an integer field takes no ``2.7``, no ``"3"`` and no ``True``;
  a bool field only ``true``/``false``; a number field no text), finite numbers, ranges,
  parity and choices; pydantic checks them underneath;
* the class docstring's numpydoc ``Attributes`` section (:func:`parameters` writes it);
* ``schlieren params`` (a commented YAML file for ``--params``) and docs/parameters.md (a
  test keeps the file equal to it): :mod:`schlieren.pipeline.params_text`.

The params classes stay plain frozen dataclasses (not pydantic models) because the rest
of the code treats them as values: ``dataclasses.replace`` for the values a run derives,
``asdict`` for the store attributes, equality and hashing for the geometry cache key.
The rules between fields that are not bounds would be declared beside the fields and run
by the same validation; the stages have none (each former ``__post_init__`` check was a
bound or a choice).

Pure: no file I/O (the caller reads the YAML file and passes the mapping).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import re
import textwrap
import types
import typing
from dataclasses import dataclass
from typing import Any, Annotated, Literal, Union

__all__ = ["Param", "param", "parameters", "FieldSchema", "ParamsError", "schema", "class_schema", "validate",
           "expected"]

_KEY = "schlieren.param"
_MARK = "__schlieren_parameters__"


@dataclass(frozen=True)
class Param:
    """Unit, valid values and help of one parameter (stored in the dataclass field's metadata).

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
    help : str
        What the parameter is and why, in one or two sentences.
    derived : str
        For a value a run replaces by a derived one: from what (printed as "Derived by
        the run: ..."; the run logs the replacement and stores both values).
    see : tuple of str
        Repository paths of the results behind the default (``benchmarks/results/<name>.md``).
    tuned : bool
        The tuning page keeps this parameter's history under a heading of its dotted name
        (section "Run parameters"); docs/parameters.md links it.
    """

    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    odd: bool = False
    even: bool = False
    choices: tuple[str, ...] = ()
    help: str = ""
    derived: str = ""
    see: tuple[str, ...] = ()
    tuned: bool = False


def param(default: Any, *, help: str = "", unit: str = "", ge: float | None = None, gt: float | None = None,
          le: float | None = None, lt: float | None = None, odd: bool = False, even: bool = False,
          choices: tuple[str, ...] = (), derived: str = "", see: str | tuple[str, ...] = (),
          tuned: bool = False) -> Any:
    """A dataclass field with its default and its :class:`Param` declaration."""
    meta = Param(unit=unit, ge=ge, gt=gt, le=le, lt=lt, odd=odd, even=even, choices=tuple(choices),
                 help=help, derived=derived, see=(see,) if isinstance(see, str) else tuple(see), tuned=tuned)
    return dataclasses.field(default=default, metadata={_KEY: meta})


@dataclass(frozen=True)
class FieldSchema:
    """One parameter as documented and validated.

    Attributes
    ----------
    group : str
        The :class:`RunConfig` field holding it (``"flow"``), or ``""`` for run-level
        fields (and for the fields of a class on its own, :func:`class_schema`).
    name : str
    types : tuple of str
        Accepted Python types: ``"int"``, ``"float"``, ``"bool"``, ``"str"``.
    default : Any
    spec : Param
    owner : str
        The params class declaring it (``"FlowParams"``).
    """

    group: str
    name: str
    types: tuple[str, ...]
    default: Any
    spec: Param
    owner: str = ""

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

    @property
    def meaning(self) -> str:
        """The help: what the parameter is and why."""
        return _plain(self.spec.help)

    @property
    def description(self) -> str:
        """The help, and what the run derives the value from (if it does)."""
        derived = f" Derived by the run: {_plain(self.spec.derived)}" if self.spec.derived else ""
        return self.meaning + derived


class ParamsError(ValueError):
    """A run parameter of the wrong type or out of range; ``field`` is its dotted name."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(f"{field}: {message}" if field else message)
        self.message = message
        self.field = field


# --------------------------------------------------------------------------------------
# declaring a params class
# --------------------------------------------------------------------------------------
def parameters(cls):
    """Declare a params class: a frozen dataclass whose construction validates every field.

    Every field must be declared with :func:`param` (with its ``help``), or be a group
    (``field(default_factory=<params class>)``, :class:`~schlieren.pipeline.stages.RunConfig`).
    The class docstring gets the generated numpydoc ``Attributes`` section; write only
    what the class is above it.

    Raises
    ------
    TypeError
        A field without :func:`param` or without help, an unsupported type, a default
        outside its own valid values, or a hand-written ``Attributes`` section or
        ``__post_init__``.
    """
    if "__post_init__" in cls.__dict__:
        raise TypeError(f"{cls.__name__}: declare valid values with param(), not in __post_init__")
    if re.search(r"^\s*Attributes\n\s*-+\n", cls.__doc__ or "", flags=re.M):
        raise TypeError(f"{cls.__name__}: the Attributes section is generated from param(help=...)")
    cls.__post_init__ = _check_instance
    cls = dataclass(frozen=True)(cls)
    setattr(cls, _MARK, True)
    class_schema(cls)  # every field declared, every default valid: at import
    cls.__doc__ = _docstring(cls)
    return cls


def _check_instance(self) -> None:
    """Construction check of a :func:`parameters` class (its ``__post_init__``)."""
    problems = []
    cls = type(self)
    for fs in class_schema(cls):
        value = getattr(self, fs.name)
        if not _valid(fs, value)[0]:
            problems.append(ParamsError(f"must be {fs.valid} (got {_got(value)})", f"{cls.__name__}.{fs.name}"))
    for f in dataclasses.fields(cls):
        if _is_group(f) and not isinstance(getattr(self, f.name), f.default_factory):
            problems.append(ParamsError(f"must be a {f.default_factory.__name__} (got "
                                        f"{_got(getattr(self, f.name))})", f"{cls.__name__}.{f.name}"))
    _raise_first(problems)


# --------------------------------------------------------------------------------------
# the schema of a params class
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


def _plain(text: str) -> str:
    """reST markup to Markdown-style code: ``x`` and :func:`x` become `x`."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _is_group(f: dataclasses.Field) -> bool:
    return f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory)


@functools.cache
def class_schema(cls) -> tuple[FieldSchema, ...]:
    """The parameters (non-group fields) of one params class, in field order (group ``""``).

    Raises
    ------
    TypeError
        A field without :func:`param` metadata or without help, an unsupported type, or a
        default outside its own valid values.
    """
    leaves = [f for f in dataclasses.fields(cls) if not _is_group(f)]
    hints = typing.get_type_hints(cls) if leaves else {}
    out = []
    for f in leaves:
        where = f"{cls.__name__}.{f.name}"
        spec = f.metadata.get(_KEY)
        if spec is None:
            raise TypeError(f"{where} has no schema: declare it with param(default, unit=..., range..., help=...) "
                            "(schlieren.pipeline.params)")
        if not spec.help.strip():
            raise TypeError(f"{where} has no meaning: say what it is and why in param(help=...)")
        kinds = _types_of(hints[f.name], where)
        if kinds == ("str",) and not spec.choices:
            raise TypeError(f"{where}: a text parameter needs its choices")
        if spec.odd and spec.even:
            raise TypeError(f"{where}: odd and even at once")
        fs = FieldSchema("", f.name, kinds, f.default, spec, cls.__name__)
        if not _valid(fs, fs.default)[0]:
            raise TypeError(f"{where}: the default {fs.default!r} is not {fs.valid}")
        out.append(fs)
    return tuple(out)


def schema(config_cls) -> list[FieldSchema]:
    """Every parameter of ``config_cls`` (a RunConfig-like dataclass), groups in field order.

    Fields whose default factory is a dataclass are groups (one level deep); the others
    are run-level parameters (group ``""``).

    Raises
    ------
    TypeError
        As :func:`class_schema`, for the class or any group.
    """
    out = list(class_schema(config_cls))
    for f in dataclasses.fields(config_cls):
        if _is_group(f):
            out.extend(dataclasses.replace(fs, group=f.name) for fs in class_schema(f.default_factory))
    return out


# --------------------------------------------------------------------------------------
# validation (pydantic)
# --------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _adapter(kinds: tuple[str, ...], spec: Param):
    from pydantic import TypeAdapter

    return TypeAdapter(_pydantic_type(kinds, spec))


def _parity(odd: bool):
    def check(v: int) -> int:
        if (v % 2 == 1) != odd:
            raise ValueError("parity")
        return v
    return check


def _pydantic_type(kinds: tuple[str, ...], s: Param):
    from pydantic import AfterValidator, Field

    bounds = {k: getattr(s, k) for k in ("ge", "gt", "le", "lt") if getattr(s, k) is not None}
    branches = []
    if "bool" in kinds:
        branches.append(Annotated[bool, Field(strict=True)])
    if "int" in kinds:
        t = Annotated[int, Field(strict=True, **bounds)]
        if s.odd or s.even:
            t = Annotated[t, AfterValidator(_parity(s.odd))]
        branches.append(t)
    if "float" in kinds:
        branches.append(Annotated[float, Field(strict=True, allow_inf_nan=False, **bounds)])
    if "str" in kinds:
        branches.append(Literal[tuple(s.choices)] if s.choices else Annotated[str, Field(strict=True)])
    return branches[0] if len(branches) == 1 else Union[tuple(branches)]


def _valid(fs: FieldSchema, value: Any) -> tuple[bool, Any]:
    """``(True, the value as validated)`` or ``(False, None)``; numpy scalars count as numbers."""
    if hasattr(value, "dtype") and getattr(value, "shape", None) == ():
        value = value.item()
    try:
        return True, _adapter(fs.types, fs.spec).validate_python(value)
    except Exception:
        return False, None


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


def _raise_first(problems: list[ParamsError]) -> None:
    """Raise the first problem, saying how many more there are."""
    if not problems:
        return
    first = problems[0]
    more = len(problems) - 1
    if more:
        raise ParamsError(first.message + f" (and {more} more problem{'s' if more > 1 else ''})", first.field)
    raise first


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
    groups = {f.name: f for f in dataclasses.fields(config_cls) if _is_group(f)}
    by_group: dict[str, dict[str, FieldSchema]] = {}
    for fs in schema(config_cls):
        by_group.setdefault(fs.group, {})[fs.name] = fs
    top_names = set(by_group.get("", {}))
    problems: list[ParamsError] = []

    def check(fs: FieldSchema, value: Any):
        ok, v = _valid(fs, value)
        if not ok:
            problems.append(ParamsError(f"must be {fs.valid} (got {_got(value)})", fs.path))
            return fs.default
        return v

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
    _raise_first(problems)
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
# the class docstrings (the YAML of `schlieren params` and docs/parameters.md: params_text.py)
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


def _type_text(fs: FieldSchema) -> str:
    """The numpydoc type of a parameter: ``int``, ``{"box", "gaussian"}``, ``int or {"auto"}``."""
    words = [k for k in fs.types if k != "str"]
    if "str" in fs.types:
        words.append("{" + ", ".join(f'"{c}"' for c in fs.spec.choices) + "}")
    return " or ".join(words)


def _docstring(cls) -> str:
    """The class docstring with the generated numpydoc ``Attributes`` section."""
    head = textwrap.dedent("\n".join((cls.__doc__ or "").splitlines()[1:])).strip("\n")
    first = (cls.__doc__ or "").splitlines()[0].strip() if cls.__doc__ else cls.__name__
    lines = [first] + ([""] + head.splitlines() if head else []) + ["", "Attributes", "----------"]
    schemas = {fs.name: fs for fs in class_schema(cls)}
    for f in dataclasses.fields(cls):
        if _is_group(f):
            sub = f.default_factory
            lines += [f"{f.name} : {sub.__name__}", f"    {(sub.__doc__ or '').splitlines()[0].strip()}"]
            continue
        fs = schemas[f.name]
        text = fs.spec.help + (f" Derived by the run: {fs.spec.derived}" if fs.spec.derived else "")
        text += (f" Unit {fs.unit}, default" if fs.unit else " Default") + f" ``{_yaml_scalar(fs.default)}``."
        see = list(fs.spec.see) + ['docs/tuning.md, "Run parameters"'] * fs.spec.tuned
        if see:
            text += " See " + ", ".join(see) + "."
        lines.append(f"{f.name} : {_type_text(fs)}")
        lines += textwrap.wrap(text, 88, initial_indent="    ", subsequent_indent="    ", break_on_hyphens=False)
    return "\n".join(lines) + "\n"
