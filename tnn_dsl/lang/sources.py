"""Reading ``.thn`` sources: regular files only and at most ``MAX_FILE_BYTES``, includes confined to the
include roots, bytes to text with a clear error for other encodings, the nesting guard, and the statements of
a file.

The include roots are the main file's directory and the directories of ``include_path`` (the ``include_path``
argument of :func:`tnn_dsl.load`, ``tnnc --include-path DIR``, or the ``TNN_INCLUDE_PATH`` environment
variable, ``os.pathsep``-separated). An include whose real path (symbolic links resolved) lies outside every
root is refused before it is opened, so its content never appears in a message."""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import stat
from collections.abc import Iterable, Iterator

from lark.exceptions import VisitError

from ..core import Diagnostic, TnnError
from ..ir import (
    Span,
)
from .simple_lines import split_simple_lines
from .statements import _parse_text, _St, _ToStatements

MAX_FILE_BYTES = 4 * 1024 * 1024
"""The largest ``.thn`` file read (a 10 000-node network is about 1 MB)."""
MAX_TOTAL_BYTES = 16 * 1024 * 1024
"""The most bytes read for one network, its includes together."""
MAX_FILES = 512
"""The most files one network may read (each included file counts once)."""

_INCLUDE_PATH: contextvars.ContextVar[tuple[str, ...] | None] = contextvars.ContextVar("tnn_include_path",
                                                                                       default=None)


@contextlib.contextmanager
def include_path_scope(dirs: Iterable[str | os.PathLike] | None) -> Iterator[None]:
    """Within the block, :func:`include_roots` also allows ``dirs`` (what ``tnnc --include-path`` sets)."""
    token = _INCLUDE_PATH.set(tuple(os.fspath(d) for d in dirs or ()))
    try:
        yield
    finally:
        _INCLUDE_PATH.reset(token)


def include_roots(main_file: str, include_path: Iterable[str | os.PathLike] | None = None) -> tuple[str, ...]:
    """The directories includes may come from (real paths): the main file's directory (the working directory
    for text without a file), then ``include_path``, the scope's directories and ``TNN_INCLUDE_PATH``."""
    main_dir = os.path.dirname(os.path.realpath(main_file)) if os.path.exists(main_file) else os.getcwd()
    extra = [os.fspath(d) for d in include_path or ()]
    extra += list(_INCLUDE_PATH.get() or ())
    extra += [d for d in os.environ.get("TNN_INCLUDE_PATH", "").split(os.pathsep) if d]
    roots = [main_dir] + [os.path.realpath(d) for d in extra]
    return tuple(dict.fromkeys(roots))


def inside_roots(real_path: str, roots: Iterable[str]) -> bool:
    """Whether ``real_path`` lies in one of the ``roots`` directory trees (both real, absolute paths)."""
    for root in roots:
        try:
            if os.path.commonpath([root, real_path]) == root:
                return True
        except ValueError:  # different drives (Windows)
            continue
    return False


class SourceReadError(Exception):
    """A source file that cannot be read: ``reason`` says why, ``hint`` what to do."""

    def __init__(self, reason: str, hint: str | None = None):
        super().__init__(reason)
        self.reason = reason
        self.hint = hint


def read_source_bytes(path: str, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them. A FIFO, device or directory and a
    larger file raise :class:`SourceReadError` without blocking or reading past ``limit + 1`` bytes."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise SourceReadError("no such file") from None
    except IsADirectoryError:
        raise SourceReadError("it is a directory", "name a .thn file") from None
    except OSError as e:
        raise SourceReadError(e.strerror or str(e)) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise SourceReadError("it is a directory", "name a .thn file")
        if not stat.S_ISREG(st.st_mode):
            kind = ("a named pipe (FIFO)" if stat.S_ISFIFO(st.st_mode) else
                    "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                    "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise SourceReadError(f"it is {kind}, not a regular file", "network files are regular .thn files")
        if st.st_size > limit:
            raise SourceReadError(f"it is {st.st_size:,} bytes, more than the {limit:,} a network file may have",
                                  "split the network into files joined by `include`")
        chunks: list[bytes] = []
        size = 0
        while size <= limit:
            try:
                chunk = os.read(fd, min(1 << 20, limit + 1 - size))
            except BlockingIOError:  # pragma: no cover - a regular file does not block
                continue
            except OSError as e:
                if e.errno == errno.EINTR:  # pragma: no cover
                    continue
                raise SourceReadError(e.strerror or str(e)) from None
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > limit:  # the file grew while it was read
            raise SourceReadError(f"it is more than the {limit:,} bytes a network file may have",
                                  "split the network into files joined by `include`")
        return b"".join(chunks)
    finally:
        os.close(fd)


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
MAX_STRING_CHARS = 1000
"""The longest quoted string (a label, a column name, a path)."""


def _check_nesting(text: str, filename: str) -> None:
    """Brackets nested deeper than ``MAX_NESTING`` and quoted strings longer than ``MAX_STRING_CHARS`` are
    errors (the trees are walked recursively; a megabyte label costs the lexer a gigabyte)."""
    depth = 0
    line, col = 1, 0
    in_str = in_comment = False
    str_start = (0, 0)
    str_len = 0
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
            str_len += 1
            if str_len > MAX_STRING_CHARS:
                sl, sc = str_start
                raise TnnError(Diagnostic(f"a quoted string longer than {MAX_STRING_CHARS} characters",
                                          Span(file=filename, line=sl, col=sc, end_line=sl, end_col=sc + 1),
                                          hint="labels, column names and paths are short; put long notes in "
                                               "`#` comments"))
            continue
        if ch == '"':
            in_str = True
            str_start, str_len = (line, col), 0
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


def _statements(text: str, filename: str, sources: dict[str, str], *, simple_lines: bool = True) -> list[_St]:
    """The statements of one file, in line order. With ``simple_lines`` (the default) the plain node and link
    lines of generated meshes are read without the parser (:mod:`.simple_lines`; same statements and errors)."""
    sources[filename] = text
    _check_nesting(text, filename)
    fast_diags: list[Diagnostic] = []
    fast, rest = split_simple_lines(text, filename, fast_diags) if simple_lines else ([], text)
    tree, diags = _parse_text(rest, filename)
    if diags:
        raise TnnError(diags, sources=sources)
    tdiags: list[Diagnostic] = []
    try:
        stmts = _ToStatements(filename, tdiags).transform(tree)
    except VisitError as err:  # pragma: no cover - a bug in a callback
        raise err.orig_exc from None
    if fast:
        stmts = _merge_by_line(stmts, fast)
        tdiags = sorted(tdiags + fast_diags, key=lambda d: d.span.line if d.span else 0)
    if tdiags:
        raise TnnError(tdiags, sources=sources)
    return stmts


def _merge_by_line(stmts: list[_St], fast: list[tuple[int, _St]]) -> list[_St]:
    """The parser's statements and the simple lines' (both in line order) as one list in line order."""
    out: list[_St] = []
    j = 0
    for st in stmts:
        while j < len(fast) and fast[j][0] < st.span.line:
            out.append(fast[j][1])
            j += 1
        out.append(st)
    out.extend(st for _, st in fast[j:])
    return out
