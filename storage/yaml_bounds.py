"""A YAML loader that refuses documents whose aliases expand them beyond a size.

YAML anchors and aliases (``&a`` ... ``*a``) let a few lines stand for an exponentially
large document (the "billion laughs" bomb): PyYAML builds it cheaply as shared objects,
and the first code that walks it (validation, JSON encoding) then runs for hours.
:class:`BoundedSafeLoader` counts, once the document's node graph is composed and before
any Python object is built, how many values the document would hold with every alias
expanded (shared nodes counted once per use, in time linear in the graph), and refuses it
above :data:`MAX_YAML_VALUES`. Session manifests and ``--params`` files both load with it.
"""

from __future__ import annotations

import yaml

__all__ = ["BoundedSafeLoader", "YamlTooLarge", "MAX_YAML_VALUES"]

#: Most values (scalars, lists and mappings, aliases expanded) a document may hold. A
#: manifest of 1000 cameras holds some 60,000.
MAX_YAML_VALUES = 1_000_000


class YamlTooLarge(yaml.YAMLError):
    """A document whose aliases expand it beyond :data:`MAX_YAML_VALUES` values, or refer to themselves."""

    def __init__(self, problem: str):
        self.problem = problem
        self.problem_mark = None
        super().__init__(problem)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def expanded_size(root: yaml.Node, limit: int = MAX_YAML_VALUES) -> int:
    """Values in the document under ``root`` with every alias expanded; raises
    :class:`YamlTooLarge` as soon as the count passes ``limit`` (or an alias refers to a
    node that contains it)."""
    size: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if key in size:
            continue
        kids = _children(node)
        if children_done:
            open_.discard(key)
            total = 1 + sum(size[id(k)] for k in kids)
            if total > limit:
                raise YamlTooLarge(f"the document expands to more than {limit:,} values through its aliases "
                                   "(*name): refused (a 'billion laughs' YAML bomb?)")
            size[key] = total
            continue
        open_.add(key)
        stack.append((node, True))
        for k in kids:
            if id(k) in open_:
                raise YamlTooLarge("an alias (*name) refers to a value that contains it: refused")
            if id(k) not in size:
                stack.append((k, False))
    return size[id(root)]


class BoundedSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses documents expanding beyond :data:`MAX_YAML_VALUES`
    values (:func:`expanded_size`), before constructing any of it."""

    max_values = MAX_YAML_VALUES

    def compose_document(self):
        node = super().compose_document()
        if node is not None:
            expanded_size(node, self.max_values)
        return node
