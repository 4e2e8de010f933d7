"""The mask expression language: tokenizer and recursive-descent parser (no eval).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Iterator, NamedTuple

import numpy as np

from gesturedb.errors import ParameterError, echo

# unit -> (dimension, power of ten relative to the SI unit)
_UNITS: dict[str, tuple[str, int]] = {
    "m": ("length", 0),
    "cm": ("length", -2),
    "mm": ("length", -3),
    "m/s": ("speed", 0),
    "cm/s": ("speed", -2),
    "mm/s": ("speed", -3),
}

# --------------------------------------------------------------------------------------
# Expression tokenizer and parser
# --------------------------------------------------------------------------------------

_KEYWORDS = frozenset({"and", "or", "not"})
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_NUM_RE = re.compile(r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_PCT_RE = re.compile(r"[pP](\d+(?:\.\d*)?|\.\d+)(?![A-Za-z0-9_.])")
_UNIT_AFTER_NUM_RE = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z_][A-Za-z0-9_]*)?)")
_OP_RE = re.compile(r"<=|>=|==|!=|=>|=<|<>|<|>|=")
_BAD_OPS = {
    "==": "equality is not supported on continuous features; use <, <=, > or >=",
    "=": "'=' is not an operator; use <, <=, > or >=",
    "!=": "'!=' is not supported; use 'not (...)' or <, >",
    "<>": "'<>' is not supported; use 'not (...)' or <, >",
    "=>": "did you mean '>='?",
    "=<": "did you mean '<='?",
}
_CHAR_HINTS = {"&": "use 'and'", "|": "use 'or'", "!": "use 'not'", "~": "use 'not'"}
#: explicit limits, so a hostile expression gets a one-line error instead of a RecursionError
#: (the tree is walked recursively): nesting of '(' and 'not', and terms (comparisons and mask names)
MAX_EXPRESSION_DEPTH = 64
MAX_EXPRESSION_TERMS = 256
MAX_EXPRESSION_CHARS = 10_000
_OPS = {"<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal}


#: characters of the expression shown on each side of the caret (a 10,000-character
#: expression is shown around its error, not whole)
CARET_CONTEXT = 60


def _caret_error(text: str, col: int, message: str) -> ParameterError:
    shown = text.translate({9: " ", 10: " ", 13: " "})
    at = col
    if len(shown) > 2 * CARET_CONTEXT + 8:
        a, b = max(0, col - CARET_CONTEXT), min(len(shown), col + CARET_CONTEXT)
        pre, post = ("..." if a > 0 else ""), ("..." if b < len(shown) else "")
        shown, at = pre + shown[a:b] + post, col - a + len(pre)
    return ParameterError(
        f"mask expression: column {col + 1}: {message}\n    {shown}\n    {' ' * at}^"
    )


class _Tok(NamedTuple):
    kind: str  # num pct name kw op lpar rpar sign eof
    text: str
    col: int
    unit: str | None = None
    unit_col: int | None = None


def _tokenize(text: str) -> list[_Tok]:
    toks: list[_Tok] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c.isspace():
            i += 1
            continue
        m = _PCT_RE.match(text, i)
        if m:
            toks.append(_Tok("pct", m.group(0), i))
            i = m.end()
            continue
        m = _NAME_RE.match(text, i)
        if m:
            word = m.group(0)
            kind = "kw" if word.lower() in _KEYWORDS else "name"
            toks.append(_Tok(kind, word.lower() if kind == "kw" else word, i))
            i = m.end()
            continue
        m = _NUM_RE.match(text, i)
        if m:
            j = m.end()
            unit = unit_col = None
            mu = _UNIT_AFTER_NUM_RE.match(text, j)
            if mu and mu.group(1).lower() not in _KEYWORDS:
                unit, unit_col, j = mu.group(1), mu.start(1), mu.end()
            toks.append(_Tok("num", m.group(0), i, unit, unit_col))
            i = j
            continue
        m = _OP_RE.match(text, i)
        if m:
            op = m.group(0)
            if op in _BAD_OPS:
                raise _caret_error(text, i, f"operator {op!r}: {_BAD_OPS[op]}")
            toks.append(_Tok("op", op, i))
            i = m.end()
            continue
        if c in "()":
            toks.append(_Tok("lpar" if c == "(" else "rpar", c, i))
        elif c in "+-":
            toks.append(_Tok("sign", c, i))
        else:
            hint = f" ({_CHAR_HINTS[c]})" if c in _CHAR_HINTS else ""
            raise _caret_error(text, i, f"unexpected character {c!r}{hint}")
        i += 1
    toks.append(_Tok("eof", "", n))
    return toks


@dataclass(eq=False)
class _Cmp:
    feature: str
    col: int
    op: str
    value: float  # as written, in `unit` (or the feature's unit when unit is None)
    unit: str | None
    percentile: bool
    value_text: str
    value_col: int

    def text(self) -> str:
        return f"{self.feature} {self.op} {self.value_text}"


@dataclass(eq=False)
class _Ref:
    name: str
    col: int


@dataclass(eq=False)
class _Not:
    operand: object
    col: int


@dataclass(eq=False)
class _Bin:
    op: str  # "and" | "or"
    left: object
    right: object


def _describe_tok(t: _Tok) -> str:
    if t.kind == "eof":
        return "the end of the expression"
    return echo(t.text)


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.toks = _tokenize(text)
        self.pos = 0
        self.depth = 0
        terms = [t for t in self.toks if t.kind == "name"]
        if len(terms) > MAX_EXPRESSION_TERMS:
            raise self.error(terms[MAX_EXPRESSION_TERMS], f"more than {MAX_EXPRESSION_TERMS} terms "
                             f"(comparisons and mask names; the limit is MAX_EXPRESSION_TERMS)")

    def enter(self, tok: _Tok) -> None:
        self.depth += 1
        if self.depth > MAX_EXPRESSION_DEPTH:
            raise self.error(tok, f"nested more than {MAX_EXPRESSION_DEPTH} deep ('(' and 'not'; "
                             f"the limit is MAX_EXPRESSION_DEPTH)")

    def peek(self) -> _Tok:
        return self.toks[self.pos]

    def take(self) -> _Tok:
        t = self.toks[self.pos]
        self.pos += 1
        return t

    def error(self, tok: _Tok, message: str) -> ParameterError:
        return _caret_error(self.text, tok.col, message)

    def parse(self):
        if self.peek().kind == "eof":
            raise ParameterError("mask expression is empty: expected e.g. 'left_wrist_height > p85'")
        node = self.or_expr()
        t = self.peek()
        if t.kind != "eof":
            if t.kind == "rpar":
                raise self.error(t, "unmatched ')'")
            raise self.error(
                t, f"expected 'and', 'or' or the end of the expression; got {_describe_tok(t)}"
            )
        return node

    def or_expr(self):
        node = self.and_expr()
        while self.peek().kind == "kw" and self.peek().text == "or":
            self.take()
            node = _Bin("or", node, self.and_expr())
        return node

    def and_expr(self):
        node = self.not_expr()
        while self.peek().kind == "kw" and self.peek().text == "and":
            self.take()
            node = _Bin("and", node, self.not_expr())
        return node

    def not_expr(self):
        t = self.peek()
        if t.kind == "kw" and t.text == "not":
            self.take()
            self.enter(t)
            node = _Not(self.not_expr(), t.col)
            self.depth -= 1
            return node
        return self.primary()

    def primary(self):
        t = self.take()
        if t.kind == "lpar":
            self.enter(t)
            node = self.or_expr()
            self.depth -= 1
            close = self.peek()
            if close.kind != "rpar":
                raise self.error(
                    close,
                    f"expected ')' to close the '(' at column {t.col + 1}; got {_describe_tok(close)}",
                )
            self.take()
            return node
        if t.kind == "name":
            if self.peek().kind == "op":
                return self.comparison(t)
            return _Ref(t.text, t.col)
        expected = "expected a mask name, a comparison such as 'left_wrist_height > p85', or '('"
        if t.kind == "num":
            raise self.error(t, f"{expected}; got the number {echo(t.text)} (the feature goes on the left)")
        if t.kind == "pct":
            raise self.error(
                t, f"{expected}; got the percentile {echo(t.text)} (percentiles go on the right of <, >)"
            )
        if t.kind == "op":
            raise self.error(t, f"comparison {echo(t.text)} needs a control feature on its left")
        raise self.error(t, f"{expected}; got {_describe_tok(t)}")

    def comparison(self, feature: _Tok) -> _Cmp:
        op = self.take()
        sign = 1.0
        first = self.peek()
        if first.kind == "sign":
            self.take()
            sign = -1.0 if first.text == "-" else 1.0
        t = self.take()
        if t.kind == "pct":
            if first.kind == "sign":
                raise self.error(first, "a percentile takes no sign")
            p = float(t.text[1:])
            if not 0.0 <= p <= 100.0:
                raise self.error(t, f"percentile {echo(t.text)} is outside p0..p100")
            return _Cmp(feature.text, feature.col, op.text, p, None, True, t.text.lower(), t.col)
        if t.kind == "num":
            value = sign * float(t.text)
            if not math.isfinite(value):
                raise self.error(t, f"number {echo(t.text)} is not finite")
            if t.unit is not None and t.unit not in _UNITS:
                raise _caret_error(
                    self.text,
                    t.unit_col,
                    f"unknown unit {echo(t.unit)} after {t.text}; expected one of "
                    f"{', '.join(_UNITS)} (comparisons combine with 'and' / 'or')",
                )
            value_text = ("-" if sign < 0 else "") + t.text + (f" {t.unit}" if t.unit else "")
            start = first.col if first.kind == "sign" else t.col
            return _Cmp(feature.text, feature.col, op.text, value, t.unit, False, value_text, start)
        raise self.error(
            t,
            f"expected a number (e.g. 0.3, 5 cm, 20 cm/s) or a percentile (e.g. p85) after "
            f"{echo(op.text)}; got {_describe_tok(t)}",
        )


def _canonical(node) -> str:
    if isinstance(node, _Cmp):
        return node.text()
    if isinstance(node, _Ref):
        return node.name
    if isinstance(node, _Not):
        return f"(not {_canonical(node.operand)})"
    return f"({_canonical(node.left)} {node.op} {_canonical(node.right)})"


def _walk(node) -> Iterator[object]:
    yield node
    if isinstance(node, _Not):
        yield from _walk(node.operand)
    elif isinstance(node, _Bin):
        yield from _walk(node.left)
        yield from _walk(node.right)


@dataclass(frozen=True, eq=False)
class MaskExpression:
    """A parsed mask expression (syntax checked, names not yet resolved).

    Attributes
    ----------
    text : str
        The expression as written (stripped).
    canonical : str
        Fully parenthesised form, showing how precedence grouped it:
        ``a or b and not c`` -> ``(a or (b and (not c)))``.
    features : tuple of str
        Control features compared, in order of appearance.
    names : tuple of str
        Named masks referenced, in order of appearance.
    """

    text: str
    canonical: str
    features: tuple[str, ...]
    names: tuple[str, ...]
    _tree: object = field(repr=False)


def parse_mask_expression(text: str) -> MaskExpression:
    """Tokenize and parse a mask expression.

    Raises
    ------
    ParameterError
        On a syntax error, with the column and a caret under the offending token.
    """
    if not isinstance(text, str):
        raise ParameterError(f"mask expression: expected a string; got {type(text).__name__}")
    text = text.strip()
    if len(text) > MAX_EXPRESSION_CHARS:
        raise ParameterError(f"mask expression: expected at most {MAX_EXPRESSION_CHARS} characters "
                             f"(MAX_EXPRESSION_CHARS), got {len(text)}")
    tree = _Parser(text).parse()
    nodes = list(_walk(tree))
    features = tuple(dict.fromkeys(n.feature for n in nodes if isinstance(n, _Cmp)))
    names = tuple(dict.fromkeys(n.name for n in nodes if isinstance(n, _Ref)))
    return MaskExpression(text, _canonical(tree), features, names, tree)


