"""Lines that need no parser: the two statement forms generated meshes are made of, read without Lark.

A 10 000-node plate is 40 000 lines of ``node NAME C = NUMBER UNIT`` and ``G NAME -- NAME = NUMBER UNIT``; the
LALR parser spends about 10 µs per token on them (most of the time it took to load the plate: parsing went from
4.6–5.6 s to 2.9–3.5 s with this module, docs/measurement-log.md, "Large networks"). Such a line, when it
is exactly one of these two forms (no label, clause, sign or expression; an optional trailing comment), at bracket
depth 0 and outside any ``subnet`` block, is tokenised here with the grammar's own terminal patterns (``NAME``,
``NUMBER``, ``UNIT``, ``WS``, ``COMMENT`` taken from the loaded grammar, not copied) and turned into its statement by
the very transformer callbacks the parse tree goes through (:class:`.statements._ToStatements`): same spans, same
unit conversion, same messages. Every other line, and any line in doubt (a node named like a keyword, a "unit" that
starts with a keyword such as ``1 free``, a token the lexer would cut differently), is left to the parser.
``tests/test_simple_lines.py`` checks, on generated lines, that the two paths give equal statements and errors.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

from lark import Token

from .grammar import _lark
from .statements import _callbacks, _St, _ToStatements
from .syntax_errors import _bracket_depths


class _Meta(NamedTuple):
    """What the transformer reads of a rule's position (lark's ``Meta`` with ``propagate_positions``)."""

    line: int
    column: int
    end_line: int
    end_column: int
    empty: bool = False


@dataclass(frozen=True)
class _Lexicon:
    node: re.Pattern
    link: re.Pattern
    name: re.Pattern
    number: re.Pattern
    unit: re.Pattern
    keywords: frozenset[str]
    subnet_open: re.Pattern
    subnet_end: re.Pattern


@lru_cache(maxsize=1)
def _lexicon() -> _Lexicon:
    terms = {t.name: t for t in _lark().terminals}
    pat = {k: terms[k].pattern.to_regexp() for k in ("NAME", "NUMBER", "UNIT", "WS", "COMMENT", "LINK_KIND")}
    keywords = frozenset(t.pattern.value for t in terms.values() if type(t.pattern).__name__ == "PatternStr")
    keywords |= frozenset(k for k in ("R", "G") if re.fullmatch(pat["LINK_KIND"], k))
    ws, ows = f"(?:{pat['WS']})", f"(?:{pat['WS']})?"
    ident = f"(?:{pat['NAME']}|{pat['NUMBER']})"
    tail = (f"{ows}={ows}(?P<num>{pat['NUMBER']})(?:{ows}(?P<unit>{pat['UNIT']}))?"
            f"{ows}(?:{pat['COMMENT']})?")
    node = re.compile(f"{ows}(?P<kw>node){ws}(?P<a>{ident}){ws}C{tail}")
    link = re.compile(f"{ows}(?P<kw>{pat['LINK_KIND']}){ws}(?P<a>{ident}){ows}--{ows}(?P<b>{ident}){tail}")
    return _Lexicon(node=node, link=link, name=re.compile(pat["NAME"]), number=re.compile(pat["NUMBER"]),
                    unit=re.compile(pat["UNIT"]), keywords=keywords,
                    subnet_open=re.compile(f"{ows}subnet(?![A-Za-z0-9_.])"),
                    subnet_end=re.compile(f"{ows}end{ows}(?:{pat['COMMENT']})?"))


def split_simple_lines(text: str, filename: str, diags: list) -> tuple[list[tuple[int, _St]], str]:
    """``([(line number, statement), ...], text for the parser)``: the simple lines as statements (their errors,
    e.g. an unknown unit, appended to ``diags``) and the text with those lines blanked (line numbers kept)."""
    lex = _lexicon()
    if "node" not in text and "--" not in text:
        return [], text
    lines = text.split("\n")
    tr = _ToStatements(filename, diags)
    table = _callbacks(_ToStatements)
    cb_node_id, cb_quantity = table["node_id"][0], table["quantity"][0]
    cb_node, cb_link = table["node"][0], table["link"][0]
    out: list[tuple[int, _St]] = []
    subnet_level = 0  # inside `subnet ... end` (nested blocks counted): the block's lines stay with the parser
    depth = 0  # bracket depth at the start of the line (strings and comments skipped, as the parser's messages)
    for i, line in enumerate(lines):
        start_depth = depth
        if "(" in line or ")" in line or "[" in line or "]" in line:
            depth = _bracket_depths([line], start=depth)[-1]
        if start_depth == 0 and lex.subnet_open.match(line):
            subnet_level += 1
            continue
        if subnet_level:
            if start_depth == 0 and lex.subnet_end.fullmatch(line):
                subnet_level -= 1
            continue
        if start_depth > 0 or depth > 0:
            continue
        m = lex.node.fullmatch(line) if "node" in line else None
        if m is None and "--" in line:
            m = lex.link.fullmatch(line)
        if m is None:
            continue
        ln = i + 1
        ids = []
        for g in ("a", "b") if m.re is lex.link else ("a",):
            tok = _token_at(line, m.start(g), m.end(g), ln, lex)
            if tok is None:
                break
            ids.append(tok)
        else:
            num = _exact(lex.number, line, m.start("num"), m.end("num"), "NUMBER", ln)
            unit = (_exact(lex.unit, line, m.start("unit"), m.end("unit"), "UNIT", ln)
                    if m.group("unit") is not None else None)
            if num is None or (m.group("unit") is not None and unit is None):
                continue
            if unit is not None and re.match(r"[A-Za-z_]*", str(unit)).group() in lex.keywords:
                continue  # `1 free`: a keyword the parser reads as a clause, not a unit
            last = unit or num
            q = cb_quantity(tr, _meta(num, last), [num, unit] if unit is not None else [num])
            nids = [cb_node_id(tr, _meta(t, t), [t]) for t in ids]
            kw_start = m.start("kw")
            kw = Token("LINK_KIND" if m.re is lex.link else "NODE", m.group("kw"), None, ln, kw_start + 1, ln,
                       kw_start + 1 + len(m.group("kw")))
            meta = _meta(kw, last)
            st = cb_link(tr, meta, [kw, *nids, q]) if m.re is lex.link else cb_node(tr, meta, [*nids, q])
            out.append((ln, st))
            lines[i] = ""
    if not out:
        return [], text
    return out, "\n".join(lines)


def _meta(first: Token, last: Token) -> _Meta:
    return _Meta(line=first.line, column=first.column, end_line=last.end_line, end_column=last.end_column)


def _exact(pattern: re.Pattern, line: str, start: int, end: int, kind: str, ln: int) -> Token | None:
    """The token ``line[start:end]`` if the lexer's own match at ``start`` ends exactly at ``end``, else None."""
    m = pattern.match(line, start)
    if m is None or m.end() != end:
        return None
    return Token(kind, line[start:end], None, ln, start + 1, ln, end + 1)


def _token_at(line: str, start: int, end: int, ln: int, lex: _Lexicon) -> Token | None:
    """A node id (``NAME`` or ``NUMBER``) as the lexer would cut it; None for a keyword or any other doubt."""
    text = line[start:end]
    if text in lex.keywords:
        return None
    return _exact(lex.name if not text[0].isdigit() and text[0] != "." else lex.number, line, start, end,
                  "NAME" if not text[0].isdigit() and text[0] != "." else "NUMBER", ln)
