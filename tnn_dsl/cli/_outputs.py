"""What every writing command shares: the ``--force`` flag and the output checks made before any work
(:func:`tnn_dsl.core.files.check_output`: never an input, never a file of another kind, writable)."""

from __future__ import annotations

import os
from typing import Iterable

from ..core import OutputKind, check_output, write_text_atomic

FORCE_HELP = ("write even where an existing file or directory of another kind is in the way (a directory's "
              "other files are kept; a file is never deleted to make room for a directory)")


def add_force_flag(p) -> None:
    """``--force`` on a sub-parser."""
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def check_outputs(args, outputs: Iterable[tuple[str | None, OutputKind, str]],
                  inputs: Iterable[str | os.PathLike | None]) -> None:
    """Check each ``(path, kind, option)`` whose path is given against ``inputs``; the first problem is a
    :class:`TnnError` (exit 1) before the command has done anything."""
    ins = [i for i in inputs if i is not None]
    force = bool(getattr(args, "force", False))
    for path, kind, option in outputs:
        if path:
            check_output(path, kind, inputs=ins, force=force, option=option)


def write_json(path: str, text: str) -> None:
    """``-`` prints to standard output; a path is written atomically."""
    if path == "-":
        print(text)
    else:
        write_text_atomic(path, text if text.endswith("\n") else text + "\n")
