"""Notebook views: the small HTML fragments that ``_repr_html_`` methods return (Jupyter shows them in
place of the text ``repr``). Self-contained: inline styles only, no scripts, no external files; every
piece of text is escaped here, so callers pass plain strings and numbers."""

from __future__ import annotations

import html
import math
from typing import Any, Callable, Iterable, Sequence

__all__ = ["cell", "heading", "html_list", "html_table", "pre", "safe_repr_html", "view"]

_TABLE = "border-collapse:collapse;margin:0.3em 0 0.8em 0;font-size:90%"
_CELL = "padding:0.15em 0.6em;border-bottom:1px solid #ddd;text-align:{align};vertical-align:top"


def cell(value: Any, digits: int = 4) -> str:
    """The escaped text of one table cell: numbers with ``digits`` significant digits, ``None`` and NaN as
    an en dash, booleans as yes/no."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float) or type(value).__name__.startswith("float"):
        x = float(value)
        if math.isnan(x):
            return "–"
        return html.escape(f"{x:.{digits}g}")
    return html.escape(str(value))


def html_table(header: Sequence[str], rows: Iterable[Sequence[Any]], *, digits: int = 4,
               numeric: Sequence[bool] | None = None) -> str:
    """A ``<table>`` with one header row; cells go through :func:`cell` (escaped). ``numeric`` marks the
    right-aligned columns (default: a column whose first row holds a number)."""
    rows = [list(r) for r in rows]
    if numeric is None:
        first = rows[0] if rows else []
        numeric = [i < len(first) and isinstance(first[i], (int, float)) and not isinstance(first[i], bool)
                   for i in range(len(header))]
    align = ["right" if n else "left" for n in numeric]
    head = "".join(f'<th style="{_CELL.format(align=a)}">{html.escape(h)}</th>' for h, a in zip(header, align))
    body = "".join(
        "<tr>" + "".join(f'<td style="{_CELL.format(align=a)}">{cell(v, digits)}</td>' for v, a in zip(r, align))
        + "</tr>" for r in rows)
    return f'<table style="{_TABLE}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def heading(text: str, level: int = 4) -> str:
    """An escaped ``<hN>`` heading."""
    return f'<h{level} style="margin:0.6em 0 0.2em 0">{html.escape(text)}</h{level}>'


def html_list(items: Iterable[str]) -> str:
    """An escaped ``<ul>`` (empty string for no items)."""
    items = list(items)
    if not items:
        return ""
    return "<ul>" + "".join(f"<li>{html.escape(s)}</li>" for s in items) + "</ul>"


def pre(text: str) -> str:
    """Escaped preformatted text."""
    return f"<pre>{html.escape(text)}</pre>"


def view(title: str, *parts: str) -> str:
    """The whole fragment: a titled ``<div>`` around ``parts`` (already HTML)."""
    return f'<div class="tnn-dsl-view">{heading(title, 3)}{"".join(parts)}</div>'


def safe_repr_html(build: Callable[[], str], text: Callable[[], str], fallback: str = "") -> str:
    """``build()``, or, should it raise, ``<pre>`` of ``text()`` (the object's text summary), or of
    ``fallback`` should that raise too: a notebook view never raises."""
    try:
        return build()
    except Exception:  # noqa: BLE001 - a display must not fail; the text summary is the fallback
        pass
    try:
        return pre(text())
    except Exception:  # noqa: BLE001
        return pre(fallback)
