"""Reading ``.thn`` sources: bytes to text with a clear error for other encodings, the nesting guard, and the
statements of a file."""

from __future__ import annotations

from lark.exceptions import VisitError

from ..core import Diagnostic, TnnError
from ..ir import (
    Span,
)
from .statements import _parse_text, _St, _ToStatements


def _decode(data: bytes, filename: str) -> str:
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        prefix = data[: err.start]
        line = prefix.count(b"\n") + 1
        line_start = prefix.rfind(b"\n") + 1
        col = len(prefix[line_start:].decode("utf-8", errors="replace")) + 1
        raise TnnError(Diagnostic(
            f"the file is not UTF-8 text: byte 0x{data[err.start]:02x} cannot be decoded",
            Span(file=filename, line=line, col=col, end_line=line, end_col=col + 1),
            hint="save the file as UTF-8 (plain ASCII is fine)")) from None
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\x00" in text:
        i = text.index("\x00")
        line = text.count("\n", 0, i) + 1
        col = i - (text.rfind("\n", 0, i) + 1) + 1
        raise TnnError(Diagnostic("the file contains a NUL byte: it is not a text file",
                                  Span(file=filename, line=line, col=col, end_line=line, end_col=col + 1)))
    return text.replace("\r\n", "\n").replace("\r", "\n")


MAX_NESTING = 64


def _check_nesting(text: str, filename: str) -> None:
    """Brackets nested deeper than ``MAX_NESTING`` are an error (the trees are walked recursively)."""
    depth = 0
    line, col = 1, 0
    in_str = in_comment = False
    for ch in text:
        col += 1
        if ch == "\n":
            line, col = line + 1, 0
            in_str = in_comment = False
            continue
        if in_comment:
            continue
        if in_str:
            in_str = ch != '"'
            continue
        if ch == '"':
            in_str = True
        elif ch == "#":
            in_comment = True
        elif ch in "([":
            depth += 1
            if depth > MAX_NESTING:
                raise TnnError(Diagnostic(f"brackets nested more than {MAX_NESTING} deep",
                                          Span(file=filename, line=line, col=col, end_line=line, end_col=col + 1),
                                          hint="split the expression with `param` definitions"))
        elif ch in ")]":
            depth = max(0, depth - 1)


def _statements(text: str, filename: str, sources: dict[str, str]) -> list[_St]:
    sources[filename] = text
    _check_nesting(text, filename)
    tree, diags = _parse_text(text, filename)
    if diags:
        raise TnnError(diags, sources=sources)
    tdiags: list[Diagnostic] = []
    try:
        stmts = _ToStatements(filename, tdiags).transform(tree)
    except VisitError as err:  # pragma: no cover - a bug in a callback
        raise err.orig_exc from None
    if tdiags:
        raise TnnError(tdiags, sources=sources)
    return stmts
