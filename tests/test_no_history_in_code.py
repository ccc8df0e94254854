"""Docstrings and comments say what and why; measurement history lives in docs/tuning.md.

A dB figure, a date or a commit hash in a docstring or comment of pipeline/, storage/ or
workers/ is a measurement that will go stale in the code (the numbers move with every
change of defaults, machine or benchmark). It belongs in ``benchmarks/results/<name>.md``
or ``docs/tuning.md``, which the code links instead. Plain ``ast`` and ``tokenize``: no
import of the scanned modules.
"""

from __future__ import annotations

import ast
import functools
import io
import re
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("pipeline", "storage", "workers")

#: What counts as history: a decibel figure ("3.6 dB", "+0.4dB"), a calendar date
#: ("2026-11-25") and a commit hash (7-12 hex digits, letters and digits mixed: "e89a4bb").
HISTORY = {
    "dB figure": re.compile(r"\d\s*dB\b"),
    "date": re.compile(r"\b(?:19|20)\d\d-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12]\d|3[01])\b"),
    "commit hash": re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,12}\b"),
}

#: Matches that are not history: ``(file, text matched)``, each with its reason. (E.g. a
#: unit definition such as "PSNR in dB = 20 log10(1 / RMS)" carries no figure and needs no
#: entry.) Keep this short.
ALLOWED: frozenset[tuple[str, str]] = frozenset()

#: Classes exempted while their history is moved out: ``(file, class)``. Empty since the
#: parameter pass of issue 34 cut every params class's help to one or two sentences; keep it
#: empty (:func:`test_pending_exemptions_are_still_needed` says when an entry is stale).
PENDING: frozenset[tuple[str, str]] = frozenset()


def _texts(path: Path):
    """``(line, owner, text)`` of every docstring (any string statement, so attribute
    docstrings too) and every comment of one file; ``owner`` is the enclosing class or
    function of a docstring (``""`` at module level and for comments)."""
    src = path.read_text()
    tree = ast.parse(src, filename=str(path))

    def visit(node, owner):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Expr) and isinstance(child.value, ast.Constant) \
                    and isinstance(child.value.value, str):
                yield child.lineno, owner, child.value.value
            name = child.name if isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) else owner
            yield from visit(child, name)

    yield from visit(tree, "")
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], "", tok.string


@functools.lru_cache(maxsize=1)
def _findings() -> tuple:
    found = []
    for root in ROOTS:
        for path in sorted((REPO / root).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            for line, owner, text in _texts(path):
                for kind, rx in HISTORY.items():
                    for m in rx.finditer(text):
                        found.append((rel, line, owner, kind, m.group(0)))
    return tuple(found)


def test_the_scanner_sees_docstrings_and_comments(tmp_path):
    p = tmp_path / "m.py"
    p.write_text('"""Module: 1.2 dB."""\n\n\nclass A:\n    """on 2026-11-25."""\n\n    x = 1\n'
                 '    """attribute: e89a4bb."""\n\n\ndef f():  # 0.5 dB\n    return "3 dB is data, not a docstring"\n')
    hits = [(line, owner, kind) for line, owner, text in _texts(p) for kind, rx in HISTORY.items()
            if rx.search(text)]
    assert hits == [(1, "", "dB figure"), (5, "A", "date"), (8, "A", "commit hash"), (11, "", "dB figure")]


def test_docstrings_and_comments_carry_no_measurement_history():
    bad = [f"{rel}:{line} ({owner or 'module'}): {kind} {text!r}"
           for rel, line, owner, kind, text in _findings()
           if (rel, text) not in ALLOWED and (rel, owner) not in PENDING]
    assert not bad, ("measurement history in code; move it to docs/tuning.md or "
                     "benchmarks/results/<name>.md and link that instead:\n" + "\n".join(bad))


def test_pending_exemptions_are_still_needed():
    owners = {(rel, owner) for rel, _, owner, _, _ in _findings()}
    stale = sorted(PENDING - owners)
    assert not stale, f"no history left in {stale}: remove them from PENDING in {Path(__file__).name}"


def test_allowed_entries_still_match():
    seen = {(rel, text) for rel, _, _, _, text in _findings()}
    assert not ALLOWED - seen, f"stale ALLOWED entries: {sorted(ALLOWED - seen)}"


def test_the_code_points_at_sections_docs_tuning_has():
    """``docs/tuning.md, "Section"`` in a docstring or comment names a heading of that page."""
    headings = {m.group(1).strip() for m in re.finditer(r"^#+ (.+)$", (REPO / "docs" / "tuning.md").read_text(), re.M)}
    cited = set()
    for root in ROOTS:
        for path in sorted((REPO / root).rglob("*.py")):
            text = path.read_text()
            for m in re.finditer(r"docs/tuning\.md", text):
                quoted = re.match(r'docs/tuning\.md,?[\s#:]*"([^"]+)"', text[m.start():])
                assert quoted, f"{path.name}: docs/tuning.md without a section name: {text[m.start():m.start() + 60]!r}"
                name = re.sub(r"\s*\n\s*(?:#:?\s*)?", " ", quoted.group(1))  # a name broken over lines
                cited.add((path.relative_to(REPO).as_posix(), name))
    assert cited, "no reference found: the pattern is wrong"
    missing = sorted((rel, name) for rel, name in cited if name not in headings)
    assert not missing, f"sections not in docs/tuning.md: {missing}"
