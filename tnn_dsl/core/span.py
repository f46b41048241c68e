"""Where something was written: a file, a line and a column (for diagnostics and the IR)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["Span"]


class Span(BaseModel):
    """Where an element was written: file path, 1-based line and column of its first and last token."""

    model_config = ConfigDict(frozen=True)
    file: str
    line: int
    col: int
    end_line: int
    end_col: int
