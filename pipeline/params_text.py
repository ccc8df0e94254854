"""The texts for people made from the parameter declarations (:mod:`schlieren.pipeline.params`):
the commented YAML file ``schlieren params`` prints (a valid ``--params`` file of the
defaults) and docs/parameters.md (``schlieren params --format markdown``; a test keeps the
file equal to it). Pure: the caller writes the text.
"""

from __future__ import annotations

import re
import textwrap

from schlieren.pipeline.params import _plain, _yaml_scalar, schema

__all__ = ["params_yaml", "params_markdown", "tuning_anchor"]


def params_yaml(config_cls, values=None) -> str:
    """A commented YAML file of every parameter (``schlieren params``; valid ``--params``).

    Each parameter has comment lines with its help (and what the run derives it from),
    then one with its unit, valid values and default; ``values`` (a ``config_cls``
    instance) overrides the printed values.
    """
    lines = ["# schlieren run parameters: edit what you need, delete the rest, then",
             "#   schlieren run SESSION --out STORE --params FILE",
             "# Unknown names, wrong types and values out of range are refused before any work.",
             "# Units: px = full-resolution image pixels; flow cells = cells of the flow grid",
             "# (flow.factor px each); voxels = reconstruction voxels; 1 = dimensionless.",
             "# 'Derived by the run': the run replaces the value as said, logs it and stores both.", ""]
    group = None
    for fs in schema(config_cls):
        if fs.group != group:
            group = fs.group
            if group:
                lines += ["", f"{group}:"]
        indent = "  " if fs.group else ""
        text = fs.meaning + (f" Derived by the run: {_plain(fs.spec.derived)}" if fs.spec.derived else "")
        for ln in textwrap.wrap(text, 92 - len(indent), break_on_hyphens=False):
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


def _md_link(path: str) -> str:
    """A repository path as a link from docs/parameters.md."""
    target = path[len("docs/"):] if path.startswith("docs/") else "../" + path
    return f"[{path.split('/')[-1].split('#')[0]}]({target})"


def tuning_anchor(path: str) -> str:
    """The link from docs/parameters.md to a tuned parameter's heading on the tuning page
    (the heading is the dotted name in backticks: GitHub's anchor drops the dot)."""
    return "tuning.md#" + re.sub(r"[^\w\- ]", "", path.lower()).replace(" ", "-")


def params_markdown(config_cls) -> str:
    """docs/parameters.md: one table per group with meaning, unit, default and valid values."""
    out = ["# Run parameters", "",
           "<!-- Generated from the parameter declarations (schlieren.pipeline.params) by",
           "     `schlieren params --format markdown`; tests/pipeline/test_params_schema.py",
           "     fails when this file and the declarations differ. Do not edit by hand. -->", "",
           "Every parameter of a run, with its meaning, unit, default and valid values. Print them "
           "as a commented YAML file with `schlieren params`, keep the ones you change, and pass "
           "the file with `schlieren run SESSION --out STORE --params FILE` (or "
           "`schlieren.run(..., params={...})` in Python). Values are checked before any work "
           "starts: unknown names, wrong types (text for a number, `2.7` or `true` for an "
           "integer, `\"no\"` for a switch), NaN/infinity and values out of range are refused "
           "with the parameter's name.", "",
           "Units: `px` = pixels of the full-resolution camera image; `flow cells` = cells of the "
           "flow grid (`flow.factor` px each); `voxels` = reconstruction voxels "
           "(`volume.voxel_size` of the session); `frames` = camera frames; `1` = dimensionless.", "",
           "*Derived by the run*: the run replaces the value as said; it logs each replacement "
           "(`flow.window 17 -> 9 px from window_per_voxel 3.8 ...`) and records the requested and "
           "the effective value in the store's `derived` attribute ([store](store.md)). The measurements "
           "behind the defaults are in the linked results.", ""]
    group = None
    for fs in schema(config_cls):
        if fs.group != group:
            group = fs.group
            out += ["", f"## `{group}`" if group else "## Run-level", "",
                    "| parameter | meaning | unit | default | valid values |",
                    "| --- | --- | --- | --- | --- |"]
        text = fs.meaning
        if fs.spec.derived:
            text += f" *Derived by the run*: {_plain(fs.spec.derived)}"
        see = [_md_link(p) for p in fs.spec.see] + [f"[tuning]({tuning_anchor(fs.path)})"] * fs.spec.tuned
        if see:
            text += " See " + ", ".join(see) + "."
        out.append(f"| `{fs.path}` | {_md_cell(text)} | {fs.unit or '-'} | "
                   f"`{_yaml_scalar(fs.default)}` | {_md_cell(fs.valid)} |")
    return "\n".join(out).replace("\n\n\n", "\n\n") + "\n"
