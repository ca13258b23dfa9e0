"""YAML parsing for config and robot files, bounded against alias bombs.

YAML anchors let a few hundred bytes name a document of billions of nodes (`&a [x, x, ...]`,
`&b [*a, *a, ...]`, ...). PyYAML builds it with shared references, cheaply, but everything after
it (merging, validation, pydantic's error message quoting the value) walks the expanded tree:
a 700-byte file became a 312 MB error message. So the node graph is composed first and its
expanded size counted (each node once per path that reaches it) before any Python object is
constructed; over the budget, or an alias that contains itself, is refused.
"""

from __future__ import annotations

from typing import Any

import yaml

__all__ = ["MAX_BYTES", "MAX_NODES", "YAMLBudgetError", "load_yaml"]

#: Largest expanded document (nodes, aliases counted as often as they are used); the default
#: config and a robot definition are ~1,000 nodes.
MAX_NODES = 100_000
#: Largest YAML text accepted (characters); the biggest shipped file is ~7 KB.
MAX_BYTES = 1_000_000


class YAMLBudgetError(ValueError):
    """A YAML text over the size or expanded-node budget, or with a self-referencing alias."""


def _expanded_size(root: yaml.Node, limit: int) -> int:
    """Nodes in the document with every alias expanded; stops counting past `limit`."""
    sizes: dict[int, int] = {}
    open_: set[int] = set()
    # iterative post-order walk: deep nesting must not hit Python's recursion limit here
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        nid = id(node)
        if nid in sizes:
            continue
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        else:
            sizes[nid] = 1
            continue
        if children_done:
            open_.discard(nid)
            total = 1 + sum(sizes[id(c)] for c in children)
            sizes[nid] = min(total, limit + 1)
            continue
        if nid in open_:
            raise YAMLBudgetError("an alias refers to a node that contains it")
        open_.add(nid)
        stack.append((node, True))
        for child in children:
            if id(child) in open_:
                raise YAMLBudgetError("an alias refers to a node that contains it")
            if id(child) not in sizes:
                stack.append((child, False))
    return sizes[id(root)]


def load_yaml(text: str, *, max_nodes: int = MAX_NODES, max_bytes: int = MAX_BYTES) -> Any:
    """`yaml.safe_load(text)`, refusing (YAMLBudgetError) a text over `max_bytes`, a document
    whose alias-expanded size is over `max_nodes`, or a recursive alias. YAML syntax errors
    are PyYAML's own `yaml.YAMLError`."""
    if len(text) > max_bytes:
        raise YAMLBudgetError(f"{len(text):,} characters, more than the {max_bytes:,} accepted")
    loader = yaml.SafeLoader(text)
    try:
        try:
            node = loader.get_single_node()
        except RecursionError:
            raise YAMLBudgetError("nested too deeply") from None
        if node is None:
            return None
        size = _expanded_size(node, max_nodes)
        if size > max_nodes:
            raise YAMLBudgetError(f"aliases expand it to over {max_nodes:,} nodes")
        return loader.construct_document(node)
    finally:
        loader.dispose()
