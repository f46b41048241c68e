"""Diagnostics: every problem the user can fix is reported as

    file:line:col: error: what was wrong
       12 | R ph -- hs = 0.08 W/K
          |              ^^^^^^^^
    hint: a resistance is in K/W; use `G a -- b = ...` for a conductance

Modules collect :class:`Diagnostic` objects and raise one :class:`TnnError` holding all of them.
The CLI prints ``TnnError`` and exits 1; anything else is an internal error (exit 2, ``--debug`` for the
traceback). Data-file problems use the same format with the CSV row as line.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Iterable, Literal

from .span import Span


@dataclass(frozen=True)
class Diagnostic:
    """One problem. ``span`` may be ``None`` for problems with no position (a missing file)."""

    message: str
    span: Span | None = None
    hint: str | None = None
    severity: Literal["error", "warning", "note"] = "error"
    related: tuple[tuple[str, Span], ...] = field(default_factory=tuple)
    """Further positions with a message each, e.g. ``("first defined here", span)``."""

    def format(self, source_lines: list[str] | None = None, *, color: bool = False) -> str:
        """Render as ``file:line:col: severity: message`` + source line + caret + hint."""
        parts: list[str] = []
        if self.span is not None:
            head = f"{self.span.file}:{self.span.line}:{self.span.col}: {self.severity}: {self.message}"
        else:
            head = f"{self.severity}: {self.message}"
        parts.append(head)
        if self.span is not None:
            lines = source_lines if source_lines is not None else _read_lines(self.span.file)
            if lines is not None and 1 <= self.span.line <= len(lines):
                text = lines[self.span.line - 1].rstrip("\n").expandtabs(1)
                num = str(self.span.line)
                parts.append(f" {num} | {text}")
                start = max(self.span.col, 1)
                if self.span.end_line == self.span.line and self.span.end_col > start:
                    width = self.span.end_col - start
                else:
                    width = max(1, len(text) - start + 1) if text[start - 1 :].strip() else 1
                width = max(1, min(width, max(1, len(text) - start + 1)))
                if len(text) > MAX_SHOWN_CHARS:  # a window of a long line around the caret
                    lo = max(0, start - 1 - MAX_SHOWN_CHARS // 4)
                    hi = min(len(text), lo + MAX_SHOWN_CHARS)
                    text = ("…" if lo else "") + text[lo:hi] + ("…" if hi < len(text) else "")
                    start = start - lo + (1 if lo else 0)
                    width = max(1, min(width, hi - lo - (start - 1 - (1 if lo else 0))))
                    parts[-1] = f" {num} | {text}"
                parts.append(f" {' ' * len(num)} | {' ' * (start - 1)}{'^' * width}")
        for msg, span in self.related:
            parts.append(f"{span.file}:{span.line}:{span.col}: note: {msg}")
        if self.hint:
            parts.append(f"hint: {self.hint}")
        return "\n".join(parts)


MAX_SHOWN_CHARS = 160
"""The longest source line shown under a message; a longer one is shown as a window around the caret."""


def _read_lines(path: str) -> list[str] | None:
    try:
        if not os.path.isfile(path):
            return None
        with open(path, "rb") as f:
            return f.read().decode("utf-8", errors="replace").splitlines()
    except OSError:
        return None


class TnnError(Exception):
    """One or more problems the user can fix. ``str(err)`` is the full formatted report."""

    def __init__(self, diagnostics: Iterable[Diagnostic] | Diagnostic | str, *,
                 sources: dict[str, str] | None = None) -> None:
        if isinstance(diagnostics, str):
            diagnostics = [Diagnostic(diagnostics)]
        elif isinstance(diagnostics, Diagnostic):
            diagnostics = [diagnostics]
        seen: set[tuple] = set()
        self.diagnostics: list[Diagnostic] = []
        for d in diagnostics:  # the same problem found by two passes is reported once
            key = (d.severity, d.message, d.span, d.hint)
            if key not in seen:
                seen.add(key)
                self.diagnostics.append(d)
        self.sources: dict[str, str] = dict(sources or {})
        super().__init__(self.format())

    def format(self, *, color: bool = False) -> str:
        out = []
        for d in self.diagnostics:
            lines = None
            if d.span is not None and d.span.file in self.sources:
                lines = self.sources[d.span.file].splitlines()
            out.append(d.format(lines, color=color))
        n = sum(d.severity == "error" for d in self.diagnostics)
        if n > 1:
            out.append(f"{n} errors")
        return "\n".join(out)


class DataError(TnnError):
    """A problem with a data file (missing column, NaN in an input, non-monotonic time ...)."""


class ModelFileError(TnnError):
    """A saved model directory that cannot be read (missing or corrupted file)."""


__all__ = ["Diagnostic", "TnnError", "DataError", "ModelFileError"]
