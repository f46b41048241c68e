"""Syntax errors that a person can act on: a catalogue of malformed examples (Lark's ``match_examples`` idea,
kept here in its own module) mapped to messages and hints, descriptions of the token found and what was
expected, and the bracket scanner behind "`(` is never closed"."""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import yaml
from lark import Token
from lark.exceptions import UnexpectedCharacters, UnexpectedInput, UnexpectedToken

from ..core import Diagnostic
from ..ir import (
    Span,
)
from .grammar import _lark

_CATALOGUE_FILE = Path(__file__).with_name("syntax_errors.yaml")


def _load_catalogue() -> list[tuple[tuple[str, str | None], list[str]]]:
    """``[((message, hint), [examples])]`` from ``syntax_errors.yaml`` (shipped with the package)."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    entries = yaml.load(_CATALOGUE_FILE.read_text(encoding="utf-8"), Loader=loader)
    return [((e["message"], e.get("hint")), list(e["examples"])) for e in entries]


# (message, hint) -> examples that fail in the same parser state. ``{found}`` is replaced by a
# description of the offending token. Order matters only for ties.
_CATALOGUE = _load_catalogue()


# Statement-start errors fail in different LALR states after zero, one or more statements: the
# catalogue's statement-start examples are also tried after one and after two statements.
for _label, _examples in _CATALOGUE:
    if _label[0].startswith(("a statement starts", "`end` without")):
        _examples += [p + e for e in list(_examples) for p in ("network a\n", "network a\nnetwork b\n")]
del _label, _examples


_STATEMENT_KEYWORDS = {"network", "units", "include", "input", "param", "node", "boundary", "R", "G", "source",
                       "sensor", "radiation", "peltier", "fluid", "learn", "subnet", "use", "end"}


_TOKEN_NAMES = {
    "_NL": "the end of the line", "$END": "the end of the file", "NAME": "a name", "NUMBER": "a number",
    "UNIT": "a unit", "STRING": "a quoted string", "BRACKET_UNIT": "a unit in brackets",
    "LPAR": "`(`", "RPAR": "`)`", "LSQB": "`[`", "RSQB": "`]`", "COMMA": "`,`", "COLON": "`:`",
    "SEMICOLON": "`;`", "EQUAL": "`=`", "PLUS": "`+`", "MINUS": "`-`", "STAR": "`*`", "SLASH": "`/`",
    "CIRCUMFLEX": "`^`", "LINK_KIND": "`R` or `G`",
}


def _describe_token(tok: Token | None) -> str:
    if tok is None or tok.type == "$END":
        return "end of file"
    if tok.type == "_NL":
        return "end of line"
    val = str(tok)
    if len(val) > 30:
        val = val[:27] + "..."
    if tok.type == "NAME" or (tok.type == "UNIT" and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", val)):
        return f"`{val}`"
    if tok.type in ("NUMBER", "UNIT", "STRING", "BRACKET_UNIT"):
        return f"{_TOKEN_NAMES[tok.type].split(' ', 1)[1] if tok.type != 'UNIT' else 'unit'} `{val}`"
    return f"`{val}`"


def _describe_expected(names) -> str:
    out = []
    for n in sorted(names):
        if n in _TOKEN_NAMES:
            out.append(_TOKEN_NAMES[n])
        else:
            try:
                pat = _lark().get_terminal(n).pattern
                out.append(f"`{pat.value}`" if pat.type == "str" else n.lower())
            except KeyError:
                out.append(n.lower())
    out = sorted(set(out))
    if len(out) > 8:
        out = out[:8] + ["..."]
    return ", ".join(out)


@lru_cache(maxsize=1)
def _catalogue_dict() -> dict[tuple[str, str | None], list[str]]:
    return {label: examples for label, examples in _CATALOGUE}


def _normalise_state(err: UnexpectedInput) -> UnexpectedInput:
    """Errors raised by the contextual lexer carry the whole ``ParserState``; the catalogue compares
    LALR state numbers."""
    st = getattr(err, "state", None)
    if st is not None and not isinstance(st, int) and hasattr(st, "position"):
        err.state = st.position
    return err


def _raw_parse(text: str):
    try:
        return _lark().parse(text)
    except UnexpectedInput as err:
        raise _normalise_state(err) from None


def _state_expected(err: UnexpectedInput) -> set[str]:
    """Terminals the parser accepts in the error's state (from the LALR table)."""
    st = getattr(err, "state", None)
    try:
        table = _lark().parser.parser.parser.parse_table
        return {t for t in table.states[st].keys() if t != "$END" or True}
    except (AttributeError, KeyError, TypeError):
        return set(getattr(err, "expected", set()) or set())


_CHAR_HINTS = {
    "'": "strings are written in double quotes: \"label\"",
    "{": "braces are not used in .thn; a `subnet` block ends with `end`",
    "}": "braces are not used in .thn; a `subnet` block ends with `end`",
    ";": "`;` separates the arguments from the options or points, inside parentheses only",
    "\"": "a string must end on the same line with `\"`",
    "→": "write links as `a -- b`",
    "−": "use the ASCII minus sign `-`",
    "×": "use `*` for multiplication",
    "·": "use `*` for multiplication",
}


def _syntax_diagnostic(err: UnexpectedInput, filename: str, lines: list[str]) -> Diagnostic:
    _normalise_state(err)
    line = getattr(err, "line", None) or 0
    ln_text = lines[line - 1] if isinstance(line, int) and 1 <= line <= len(lines) else ""
    first_word = (ln_text.split() or [""])[0]
    word_index = len(ln_text[: max(0, (getattr(err, "column", 1) or 1) - 1)].split())
    col = getattr(err, "column", None) or 0
    tok = getattr(err, "token", None)
    if isinstance(err, UnexpectedToken) and (tok is None or tok.type == "$END" or not line or line < 0):
        line = max(1, len(lines))
        col = len(lines[-1]) + 1 if lines else 1
    if line < 1:
        line, col = 1, 1
    if col < 1:
        col = 1
    width = 1
    if isinstance(err, UnexpectedToken) and tok is not None and tok.type not in ("_NL", "$END"):
        width = max(1, len(str(tok)))
    span = Span(file=filename, line=line, col=col, end_line=line, end_col=col + width)
    if isinstance(err, UnexpectedCharacters):
        ch = err.char
        text_line = lines[line - 1] if 1 <= line <= len(lines) else ""
        if ch == '"':
            return Diagnostic("unterminated string", span, hint=_CHAR_HINTS['"'])
        if ch.isdigit() or ch.isalpha() or ch == "_":
            # a legal character in an illegal place (the contextual lexer found no token here)
            label = _match_catalogue(err, first_word, word_index)
            m = re.match(r"[A-Za-z0-9_.%/*^()]+", text_line[col - 1:]) if text_line else None
            found = f"`{m.group(0)}`" if m else f"`{ch}`"
            if label is not None:
                return Diagnostic(label[0].replace("{found}", found), span, hint=label[1])
            return Diagnostic(f"unexpected {found}", span, hint=None)
        shown = ch if ch.isprintable() else repr(ch)
        label = _match_catalogue(err, first_word, word_index) if ch in "()[],:;=+-*/^" else None
        if label is not None:
            return Diagnostic(label[0].replace("{found}", f"`{shown}`"), span, hint=label[1])
        return Diagnostic(f"unexpected character `{shown}`", span,
                          hint=_CHAR_HINTS.get(ch, "comments start with `#`; names use letters, digits, `_` and `.`"))
    at_line_start = col == len(ln_text) - len(ln_text.lstrip()) + 1
    if isinstance(err, UnexpectedToken) and tok is not None and (
            tok.type == "$END" or (at_line_start and str(tok) in _STATEMENT_KEYWORDS)):
        open_ = _unclosed_bracket(lines, line if tok.type != "$END" else len(lines) + 1)
        if open_ is not None:
            oline, ocol, ch = open_
            close = ")" if ch == "(" else "]"
            return Diagnostic(f"`{ch}` is never closed", Span(file=filename, line=oline, col=ocol, end_line=oline,
                                                             end_col=ocol + 1),
                              hint=f"add the matching `{close}`; a statement continues over lines while a bracket "
                                   "is open")
    label = _match_catalogue(err, first_word, word_index)
    found = _describe_token(tok)
    if label is not None:
        return Diagnostic(label[0].replace("{found}", found), span, hint=label[1])
    exp = _state_expected(err)
    if len(exp) > 1:
        exp.discard("_NL") if tok is not None and tok.type != "_NL" and len(exp - {"_NL"}) else None
    expected = _describe_expected(exp)
    return Diagnostic(f"unexpected {found}", span, hint=f"expected {expected}" if expected else None)


@lru_cache(maxsize=1)
def _catalogue_states() -> list[tuple[int, str, tuple[str, str | None]]]:
    """(LALR state, first word of the example, label) for every example of the catalogue."""
    out = []
    for label, examples in _CATALOGUE:
        for ex in examples:
            try:
                _raw_parse(ex)
            except UnexpectedInput as ut:
                if isinstance(ut.state, int):
                    ln = (ex.split("\n")[(ut.line or 1) - 1]
                          if isinstance(getattr(ut, "line", None), int) and ut.line > 0 else ex)
                    col = ut.column if isinstance(getattr(ut, "column", None), int) and ut.column > 0 else len(ln) + 1
                    ttype = getattr(getattr(ut, "token", None), "type", "")
                    out.append((ut.state, (ln.split() or [""])[0], len(ln[: col - 1].split()), ttype, label))
    return out


def _match_catalogue(err: UnexpectedInput, first_word: str = "", word_index: int = -1):
    """The catalogue label of examples failing in the same parser state; among several, one whose
    example starts with the same statement keyword as the failing line, and fails at the same word."""
    st = getattr(err, "state", None)
    if not isinstance(st, int):
        return None
    ttype = getattr(getattr(err, "token", None), "type", "")
    cands = [(w, i, t, label) for s_, w, i, t, label in _catalogue_states() if s_ == st]
    if not cands:
        return None
    best = max(cands, key=lambda c: (c[0] == first_word, c[0] == first_word and c[1] == word_index, c[2] == ttype))
    return best[3]


def _brackets(line: str):
    """``(col, char)`` of each bracket in one line, 1-based, skipping strings and a trailing comment."""
    in_str = False
    j = 0
    while j < len(line):
        c = line[j]
        if in_str:
            if c == "\\":
                j += 1
            elif c == '"':
                in_str = False
        elif c == '"':
            in_str = True
        elif c == "#":
            return
        elif c in "([)]":
            yield j + 1, c
        j += 1


def _unclosed_bracket(lines: list[str], upto_line: int) -> tuple[int, int, str] | None:
    """Position (line, col, char) of the innermost bracket still open before line ``upto_line``."""
    stack: list[tuple[int, int, str]] = []
    for i, ln in enumerate(lines[: max(0, upto_line - 1)], start=1):
        for col, c in _brackets(ln):
            if c in "([":
                stack.append((i, col, c))
            elif stack:
                stack.pop()
    return stack[-1] if stack else None


def _bracket_depths(lines: list[str], start: int = 0) -> list[int]:
    """Bracket depth at the start of each line and after the last (strings and comments skipped), from depth
    ``start`` before the first line."""
    depths = []
    depth = start
    for ln in lines:
        depths.append(depth)
        for _, c in _brackets(ln):
            depth = depth + 1 if c in "([" else max(0, depth - 1)
    depths.append(depth)
    return depths
