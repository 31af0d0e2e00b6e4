"""The scene's small expression language, parsed by the project (never ``eval``).

    hand_free(action.params.hand) and distance(obj, "panda_hand") < 0.08
    value == false
    owner(ball, "pose") != "physics"

Literals (numbers, 'strings' or "strings", true/false/null, [lists]), names, dotted access,
indexing, calls, arithmetic (+ - * /), comparisons (== != < <= > >= in) and ``and``/``or``/``not``.
:func:`parse` returns an :class:`Expr` whose ``names`` and ``calls`` a validator can check before
anything runs; :meth:`Expr.evaluate` takes a name resolver and a function table.
"""
from __future__ import annotations

import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from protocol.errors import ExprError

_TOKEN = re.compile(r"""
    (?P<ws>\s+)
  | (?P<num>\d+\.\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|\d+(?:[eE][+-]?\d+)?)
  | (?P<str>"(?:[^"\\]|\\.)*"|'(?:[^'\\]|\\.)*')
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<op>==|!=|<=|>=|[<>+\-*/(),.\[\]])
""", re.VERBOSE)

KEYWORDS = {"and", "or", "not", "in", "true", "false", "null"}


@dataclass(frozen=True)
class Tok:
    kind: str
    text: str
    pos: int


def tokenize(src: str) -> list[Tok]:
    """The tokens of ``src``, ending with an ``end`` token; :class:`ExprError` at a character that starts none."""
    out: list[Tok] = []
    i = 0
    while i < len(src):
        m = _TOKEN.match(src, i)
        if not m:
            raise ExprError(f"unexpected character {src[i]!r}", i)
        kind = m.lastgroup or ""
        if kind != "ws":
            text = m.group()
            if kind == "name" and text in KEYWORDS:
                kind = "kw"
            out.append(Tok(kind, text, i))
        i = m.end()
    out.append(Tok("end", "", len(src)))
    return out


# AST nodes are tuples: ("lit", v) ("name", n) ("attr", obj, n) ("index", obj, idx) ("call", fname, args)
# ("list", items) ("un", op, x) ("bin", op, a, b) ("chain", comparisons, operands); names and calls also carry their
# column
Node = tuple[Any, ...]

_BIN_PREC = {"or": 1, "and": 2, "==": 4, "!=": 4, "<": 4, "<=": 4, ">": 4, ">=": 4, "in": 4,
             "+": 5, "-": 5, "*": 6, "/": 6}
_COMPARISON = 4  # the comparisons' precedence: several in a row chain


class _Parser:
    def __init__(self, src: str) -> None:
        self.src = src
        self.toks = tokenize(src)
        self.i = 0

    def peek(self) -> Tok:
        return self.toks[self.i]

    def take(self) -> Tok:
        t = self.toks[self.i]
        self.i += 1
        return t

    def expect(self, text: str) -> Tok:
        t = self.take()
        if t.text != text:
            raise ExprError(f"expected {text!r}, found {t.text or 'end of expression'!r}", t.pos)
        return t

    def parse(self) -> Node:
        if self.peek().kind == "end":
            raise ExprError("empty expression", 0)
        node = self.expr(0)
        t = self.peek()
        if t.kind != "end":
            raise ExprError(f"unexpected {t.text!r}", t.pos)
        return node

    def expr(self, min_prec: int) -> Node:
        t = self.peek()
        left: Node
        if t.kind == "kw" and t.text == "not":
            self.take()
            left = ("un", "not", self.expr(3))
        else:
            left = self.unary()
        compared: Node | None = None  # the right side of the comparison just read, if the last operator was one
        while True:
            t = self.peek()
            op = t.text if t.kind in ("op", "kw") else None
            prec = _BIN_PREC.get(op) if op is not None else None
            if prec is None or prec < min_prec:
                return left
            self.take()
            right = self.expr(prec + 1)
            if prec == _COMPARISON and compared is not None:  # 0 < x < 1 is 0 < x and x < 1, as Python reads it
                ops, operands = (left[1], left[2]) if left[0] == "chain" else ([left[1]], [left[2], left[3]])
                left = ("chain", [*ops, op], [*operands, right])  # (x read once; lists, as a call's arguments)
            else:
                left = ("bin", op, left, right)
            compared = right if prec == _COMPARISON else None

    def unary(self) -> Node:
        t = self.peek()
        if t.kind == "op" and t.text == "-":
            self.take()
            return ("un", "-", self.unary())
        return self.postfix(self.primary())

    def primary(self) -> Node:
        t = self.take()
        if t.kind == "num":
            return ("lit", float(t.text) if any(c in t.text for c in ".eE") else int(t.text))
        if t.kind == "str":
            body = t.text[1:-1]
            return ("lit", re.sub(r"\\(.)", r"\1", body))
        if t.kind == "kw":
            if t.text in ("true", "false"):
                return ("lit", t.text == "true")
            if t.text == "null":
                return ("lit", None)
            raise ExprError(f"unexpected keyword {t.text!r}", t.pos)
        if t.kind == "name":
            if self.peek().text == "(":
                self.take()
                args = self.args(")")
                return ("call", t.text, args, t.pos)
            return ("name", t.text, t.pos)
        if t.text == "(":
            node = self.expr(0)
            self.expect(")")
            return node
        if t.text == "[":
            return ("list", self.args("]"))
        raise ExprError(f"unexpected {t.text or 'end of expression'!r}", t.pos)

    def args(self, close: str) -> list[Node]:
        items: list[Node] = []
        if self.peek().text == close:
            self.take()
            return items
        while True:
            items.append(self.expr(0))
            t = self.take()
            if t.text == close:
                return items
            if t.text != ",":
                raise ExprError(f"expected ',' or {close!r}, found {t.text or 'end of expression'!r}", t.pos)

    def postfix(self, node: Node) -> Node:
        while True:
            t = self.peek()
            if t.text == ".":
                self.take()
                n = self.take()
                if n.kind not in ("name", "kw"):
                    raise ExprError("expected a field name after '.'", n.pos)
                node = ("attr", node, n.text)
            elif t.text == "[":
                self.take()
                idx = self.expr(0)
                self.expect("]")
                node = ("index", node, idx)
            else:
                return node


def _walk(node: Node, names: dict[str, None], calls: dict[str, None],
          literals: list[tuple[str, int, str]] | None = None) -> None:
    """Collect the names read and the functions called under ``node``, in the order they are written (and into
    ``literals``, each call's arguments written as a string: (function, position, text))."""
    k = node[0]
    if k == "name":
        names[node[1]] = None
    elif k == "call":
        calls[node[1]] = None
        for i, a in enumerate(node[2]):
            if literals is not None and a[0] == "lit" and isinstance(a[1], str):
                literals.append((node[1], i, a[1]))
            _walk(a, names, calls, literals)
    elif k == "attr":
        _walk(node[1], names, calls, literals)
    elif k == "index":
        _walk(node[1], names, calls, literals)
        _walk(node[2], names, calls, literals)
    elif k == "list":
        for a in node[1]:
            _walk(a, names, calls, literals)
    elif k == "un":
        _walk(node[2], names, calls, literals)
    elif k == "bin":
        _walk(node[2], names, calls, literals)
        _walk(node[3], names, calls, literals)
    elif k == "chain":
        for a in node[2]:
            _walk(a, names, calls, literals)


MAX_LENGTH = 2000  # characters: a scene expression is one line of logic, not a program


class Expr:
    """A parsed expression: its ``source``, syntax ``tree``, the ``names`` it reads and the functions it
    ``calls`` (each once, in the order they are first written), and ``literals``: the arguments of its calls
    written as strings, (function, position, text), for a checker to look up (``owner('bal', 'pose')``). Two
    expressions are equal when their sources are."""

    __slots__ = ("source", "tree", "names", "calls", "literals")

    def __init__(self, source: str) -> None:
        if len(source) > MAX_LENGTH:
            raise ExprError(f"expression too long ({len(source)} characters; at most {MAX_LENGTH})")
        self.source = source
        names: dict[str, None] = {}
        calls: dict[str, None] = {}
        literals: list[tuple[str, int, str]] = []
        try:
            self.tree = _Parser(source).parse()
            _walk(self.tree, names, calls, literals)
        except RecursionError:
            raise ExprError("expression nested too deeply") from None
        self.names: tuple[str, ...] = tuple(names)
        self.calls: tuple[str, ...] = tuple(calls)
        self.literals: tuple[tuple[str, int, str], ...] = tuple(literals)

    def __repr__(self) -> str:
        return f"Expr({self.source!r})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Expr):
            return NotImplemented
        return self.source == other.source

    def __hash__(self) -> int:
        return hash(self.source)

    def evaluate(self, resolve: Callable[[str], Any], functions: Mapping[str, Callable[..., Any]]) -> Any:
        """The value of the expression: ``resolve`` gives each name's value, ``functions`` each callable."""
        return _eval(self.tree, resolve, functions)


def parse(source: Any) -> Expr:
    """``source`` parsed (a YAML number or boolean is read as its literal); :class:`ExprError` otherwise."""
    if isinstance(source, bool) or isinstance(source, (int, float)):
        try:
            source = str(source).lower() if isinstance(source, bool) else repr(source)
        except ValueError as e:  # an integer too long to print
            raise ExprError(f"bad number: {e}") from None
    if not isinstance(source, str):
        raise ExprError(f"an expression must be a string, got {type(source).__name__}")
    return Expr(source)


def _get(obj: Any, name: str) -> Any:
    if isinstance(obj, dict):
        if name not in obj:
            raise ExprError(f"no field {name!r} (has {', '.join(map(str, obj)) or 'none'})")
        return obj[name]
    raise ExprError(f"cannot read field {name!r} of {type(obj).__name__}")


_Functions = Mapping[str, Callable[..., Any]]

MAX_REPEAT = 100_000
"""The longest string or list ``*`` may make (items): a trigger's expression runs on every tick."""


def _times(a: Any, b: Any) -> Any:
    """``a * b``, refusing a string or list repeated past :data:`MAX_REPEAT` items."""
    for seq, n in ((a, b), (b, a)):
        if isinstance(seq, (str, list)) and isinstance(n, int) and len(seq) * n > MAX_REPEAT:
            raise ExprError(f"*: a {type(seq).__name__} of {len(seq) * n} items (at most {MAX_REPEAT})")
    return operator.mul(a, b)


_BINARY: dict[str, Callable[[Any, Any], Any]] = {
    "==": operator.eq, "!=": operator.ne, "<": operator.lt, "<=": operator.le, ">": operator.gt,
    ">=": operator.ge, "in": lambda a, b: a in b, "+": operator.add, "-": operator.sub, "*": _times,
    "/": operator.truediv,
}


def _eval(node: Node, resolve: Callable[[str], Any], functions: _Functions) -> Any:
    k = node[0]
    if k == "lit":
        return node[1]
    if k == "name":
        return resolve(node[1])
    if k == "attr":
        return _get(_eval(node[1], resolve, functions), node[2])
    if k == "index":
        obj = _eval(node[1], resolve, functions)
        idx = _eval(node[2], resolve, functions)
        try:
            return obj[idx]
        except (KeyError, IndexError, TypeError) as e:
            raise ExprError(f"cannot index: {e}") from None
    if k == "list":
        return [_eval(a, resolve, functions) for a in node[1]]
    if k == "call":
        fn = functions.get(node[1])
        if fn is None:
            raise ExprError(f"unknown function {node[1]!r}", node[3])
        args = [_eval(a, resolve, functions) for a in node[2]]
        try:
            return fn(*args)
        except ExprError:
            raise
        except (TypeError, ValueError, KeyError, IndexError, AttributeError, ArithmeticError) as e:
            # (a value of a type the function does not take: a list where a name goes, from a service call)
            raise ExprError(f"{node[1]}({', '.join(map(repr, args))}): {type(e).__name__}: {e}", node[3]) from None
    if k == "un":
        v = _eval(node[2], resolve, functions)
        if node[1] == "not":
            return not v
        try:
            return -v
        except TypeError as e:
            raise ExprError(f"-: {e}") from None
    if k == "chain":
        return _chain(node, resolve, functions)
    return _binary(node, resolve, functions)


def _chain(node: Node, resolve: Callable[[str], Any], functions: _Functions) -> Any:
    """``a < b <= c``: each comparison in turn, each operand read once, stopping at the first that fails."""
    a = _eval(node[2][0], resolve, functions)
    for op, operand in zip(node[1], node[2][1:], strict=True):
        b = _eval(operand, resolve, functions)
        try:
            ok = _BINARY[op](a, b)
        except TypeError as e:
            raise ExprError(f"{op}: {e}") from None
        if not ok:
            return ok
        a = b
    return ok


def _binary(node: Node, resolve: Callable[[str], Any], functions: _Functions) -> Any:
    op = node[1]
    a = _eval(node[2], resolve, functions)
    # and/or evaluate their right side only when needed, as Python's do
    if op == "and":
        return a and _eval(node[3], resolve, functions)
    if op == "or":
        return a or _eval(node[3], resolve, functions)
    b = _eval(node[3], resolve, functions)
    fn = _BINARY.get(op)
    if fn is None:
        raise ExprError(f"unknown operator {op!r}")
    try:
        return fn(a, b)
    except (TypeError, ArithmeticError) as e:  # (a division by zero; a whole number too big for a float)
        raise ExprError(f"{op}: {e}") from None
