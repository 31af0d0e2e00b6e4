"""Reading a scene's YAML with the line of every key, so every problem can name its line.

:func:`load_yaml` builds plain Python values from PyYAML's node tree, recording the line where each key
path starts (:class:`Lines`) and refusing what would make the loader itself a hazard: documents nested
deeper than :data:`MAX_DEPTH`, aliases that expand into more than :data:`MAX_VALUES` values, keys that
are not scalars, duplicate keys.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import yaml

from protocol.errors import SceneError


@dataclass
class Lines:
    """The line where each key path of a scene starts (``("models", "physics", "rate") -> 5``)."""

    lines: dict[tuple[Any, ...], int] = field(default_factory=dict)

    def get(self, path: tuple[Any, ...]) -> int | None:
        """The line of ``path``, or of its nearest ancestor that has one (1 for the whole document)."""
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return self.lines.get((), 1)


MAX_DEPTH = 32          # nesting levels a scene may use
MAX_VALUES = 200_000    # values after alias expansion (a few aliases must not explode into millions)


def _construct(loader: yaml.SafeLoader, node: yaml.Node, path: tuple[Any, ...], file: str) -> Any:
    try:
        return loader.construct_object(node, deep=True)
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError, yaml.YAMLError) as e:
        # e.g. 'name: 2020-02-30' (YAML reads it as a date) or '!!int x'
        raise SceneError(file, node.start_mark.line + 1, fmt_path(path),
                         f"cannot read the value {getattr(node, 'value', '')!r}: {type(e).__name__}: {e} "
                         "(quote it to make it a string)") from None


_UNCLOSED = {"while parsing a flow mapping": "the '{' opened here is not closed",
             "while parsing a flow sequence": "the '[' opened here is not closed",
             "while scanning a quoted scalar": "the quote opened here is not closed"}
"""Parser contexts whose start, not where the parser noticed, is the line to look at."""


def _syntax_error(e: yaml.MarkedYAMLError) -> tuple[int | None, str, str]:
    """(line, key, problem) of a YAML syntax error. The parser notices an unclosed bracket or quote only on a
    later line; the line given is then the one that opened it, and the problem says where it was noticed."""
    problem, ctx = e.problem_mark, e.context_mark
    what = e.problem or str(e)
    if e.context in _UNCLOSED and ctx is not None and (problem is None or problem.line != ctx.line):
        where = f"line {problem.line + 1}: " if problem is not None else ""
        return ctx.line + 1, "", f"YAML syntax error: {_UNCLOSED[e.context]} ({where}{what})"
    mark = problem or ctx
    if "expected <block end>" in what:  # (the parser's words for a misindented line)
        what += " (a line indented differently from the keys beside it?)"
    return (mark.line + 1 if mark else None), "", f"YAML syntax error: {what}"


def _build(loader: yaml.SafeLoader, node: yaml.Node, path: tuple[Any, ...], lines: Lines, file: str,
           budget: list[int] | None = None) -> Any:
    if budget is None:
        budget = [MAX_VALUES]
    budget[0] -= 1
    if budget[0] < 0:
        raise SceneError(file, node.start_mark.line + 1, fmt_path(path),
                         f"more than {MAX_VALUES} values (aliases expanding into each other?)")
    if len(path) > MAX_DEPTH:
        raise SceneError(file, node.start_mark.line + 1, fmt_path(path[:3]),
                         f"nested deeper than {MAX_DEPTH} levels (or an alias that contains itself)")
    lines.lines.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        pairs, n_merged = _merge_keys(node, path, file, budget)
        merged = {_key(loader, k, path, file) for k, _ in pairs[:n_merged]}
        for i, (knode, vnode) in enumerate(pairs):
            key = _key(loader, knode, path, file)
            if key in out and key not in merged:
                raise SceneError(file, knode.start_mark.line + 1, fmt_path(path + (key,)),
                                 f"duplicate key {key!r} (first defined on line {lines.lines[path + (key,)]})")
            if i < n_merged and key in out:  # (of several maps merged, the first that gives a key wins, as YAML says)
                continue
            if i >= n_merged:  # (a key given beside a merge key overrides the merged one)
                merged.discard(key)
            lines.lines[path + (key,)] = knode.start_mark.line + 1
            out[key] = _build(loader, vnode, path + (key,), lines, file, budget)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_build(loader, v, path + (i,), lines, file, budget) for i, v in enumerate(node.value)]
    return _construct(loader, node, path, file)


_MERGE = "tag:yaml.org,2002:merge"


def _key(loader: yaml.SafeLoader, knode: yaml.Node, path: tuple[Any, ...], file: str) -> Any:
    """A mapping key as the scene means it: a scalar, kept as written where YAML 1.1 reads a boolean ('on')."""
    if not isinstance(knode, yaml.ScalarNode):
        raise SceneError(file, knode.start_mark.line + 1, fmt_path(path), "mapping keys must be scalars")
    key = _construct(loader, knode, path, file)
    if isinstance(key, bool):  # YAML 1.1 reads 'on', 'yes', ... as booleans: keep keys as written
        key = knode.value
    try:
        hash(key)
    except TypeError:
        raise SceneError(file, knode.start_mark.line + 1, fmt_path(path), "mapping keys must be scalars") from None
    return key


Pairs = list[tuple[yaml.Node, yaml.Node]]


def _merge_keys(node: yaml.MappingNode, path: tuple[Any, ...], file: str, budget: list[int]) -> tuple[Pairs, int]:
    """``node``'s pairs with its YAML merge keys (``<<: *defaults``) resolved, and how many of them are merged: the
    merged pairs come first, the one that takes precedence first (a merged map's own keys before what it merges, the
    maps of ``<<: [*a, *b]`` in order), then the mapping's own, which override them. The nodes are left as they are
    (PyYAML's flattening changes them: a map reached again through an alias had lost its merge keys)."""
    if not any(k.tag == _MERGE for k, _ in node.value):
        return node.value, 0
    merged = _merged(node, path, file, budget, (id(node),))
    return merged + [(k, v) for k, v in node.value if k.tag != _MERGE], len(merged)


def _merged(node: yaml.MappingNode, path: tuple[Any, ...], file: str, budget: list[int],
            inside: tuple[int, ...]) -> Pairs:
    """The pairs ``node``'s merge keys bring in, in precedence order, counted against the ``budget`` of values."""
    out: Pairs = []
    for k, v in node.value:
        if k.tag != _MERGE:
            continue
        for src in v.value if isinstance(v, yaml.SequenceNode) else [v]:
            if not isinstance(src, yaml.MappingNode):
                raise SceneError(file, src.start_mark.line + 1, fmt_path(path),
                                 f"merge key '<<': expected a mapping or a list of mappings to merge, found {src.id}")
            if id(src) in inside:
                raise SceneError(file, src.start_mark.line + 1, fmt_path(path), "merge key '<<': a map merges itself")
            out += [(sk, sv) for sk, sv in src.value if sk.tag != _MERGE]
            out += _merged(src, path, file, budget, (*inside, id(src)))
    budget[0] -= len(out)
    if budget[0] < 0:
        raise SceneError(file, node.start_mark.line + 1, fmt_path(path),
                         f"more than {MAX_VALUES} values (aliases expanding into each other?)")
    return out


def fmt_path(path: tuple[Any, ...]) -> str:
    """A key path as written in messages: ``triggers[0].do[1].transfer``."""
    s = ""
    for p in path:
        s += f"[{p}]" if isinstance(p, int) else (f".{p}" if s else str(p))
    return s


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, reading ``1e3`` and ``1e-05`` as the numbers they are (YAML 1.2 and JSON do, and
    Python's json writes them so; YAML 1.1 wants a dot, ``1.0e3``, and read them as strings)."""


_EXPONENT = re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT, list("-+0123456789"))


def load_yaml(text: str, file: str) -> tuple[Any, Lines]:
    """The document in ``text`` as plain Python values, and the line of every key path; a
    :class:`SceneError` naming ``file`` for anything PyYAML or the limits above refuse."""
    lines = Lines()
    try:
        loader = _Loader(text)
        try:
            node = loader.get_single_node()
            if node is None:
                raise SceneError(file, 1, "", "the scene file is empty")
            data = _build(loader, node, (), lines, file)
        finally:
            loader.dispose()
    except yaml.MarkedYAMLError as e:
        raise SceneError(file, *_syntax_error(e)) from None
    except RecursionError:
        raise SceneError(file, None, "", f"nested deeper than {MAX_DEPTH} levels") from None
    except yaml.reader.ReaderError as e:  # e.g. a control character: say on which line
        line = text.count("\n", 0, e.position) + 1 if isinstance(e.position, int) else None
        raise SceneError(file, line, "", f"YAML error: {e.reason} {e.character!r} at column "
                                         f"{e.position - text.rfind(chr(10), 0, e.position)}") from None
    except yaml.YAMLError as e:
        raise SceneError(file, None, "", f"YAML error: {e}") from None
    return data, lines


