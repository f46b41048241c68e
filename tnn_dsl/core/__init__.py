"""The ground floor: what every stage shares and nothing in it knows about thermal networks.

Owns: diagnostics and errors (``errors``: ``file:line:col: error: ...`` with caret and hint), source positions
(``span``), safe output files (``files``: checks before any work, atomic writes), JSON conversion of numpy
results (``jsonable``), a Ctrl-C seen through C code (``interrupt``) and the installed version. May import:
nothing of tnn_dsl.
"""

from __future__ import annotations

from .errors import DataError, Diagnostic, ModelFileError, TnnError
from .files import (
    CSV,
    IMAGE,
    JSON,
    PLOT_DIR,
    TEXT,
    THN,
    OutputKind,
    atomic_path,
    check_output,
    exchange_paths,
    file_sha256,
    fsync_dir,
    fsync_file,
    save_figure,
    temp_sibling,
    write_text_atomic,
)
from .jsonable import to_jsonable
from .span import Span
from .version import __version__

__all__ = [
    "DataError", "Diagnostic", "ModelFileError", "TnnError", "CSV", "IMAGE", "JSON", "PLOT_DIR", "TEXT", "THN",
    "OutputKind", "atomic_path", "check_output", "exchange_paths", "fsync_dir", "fsync_file", "save_figure",
    "temp_sibling", "write_text_atomic", "file_sha256", "to_jsonable", "Span", "__version__"
]
