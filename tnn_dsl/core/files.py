"""Output files that never cost the user a file: checks made before any work, and atomic writes.

Every command that writes (``-o``, ``--json``, ``--plot``, ``--report``) calls :func:`check_output` for
each destination *before* it reads data or trains, so a refusal costs nothing. The rules:

* an output is never one of the command's inputs (the same file, or a file inside an input directory);
* an output that exists must be of the kind being written: a file with one of the kind's suffixes, or a
  directory that this tool wrote (a model directory, a report, a case-study data set) or an empty one.
  Anything else is refused unless ``force=True`` (``--force``), and even then a file is never deleted to
  make room for a directory, nor a directory for a file;
* the place must be writable (checked on the nearest existing ancestor when the path does not exist yet).

Writes go to a temporary sibling that is flushed to disk (``fsync``) and renamed over the destination in
one step (:func:`atomic_path`, :func:`write_text_atomic`): a reader sees the old file or the new one,
never a half-written one, and an interrupted write leaves no temporary file behind.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from .errors import Diagnostic, TnnError


@dataclass(frozen=True)
class OutputKind:
    """What a command writes at one destination.

    ``what``: words for messages ("CSV file"); ``is_dir``: a directory (else a file); ``suffixes``: the
    suffixes an existing file may have to be overwritten without ``--force`` (lower case, with the dot;
    empty: any); ``ours``: for a directory kind, whether an existing non-empty directory was written by
    this tool (then it may be replaced or added to)."""

    what: str
    is_dir: bool = False
    suffixes: tuple[str, ...] = ()
    ours: Callable[[Path], bool] | None = None
    example: str = "OUT"


CSV = OutputKind("CSV file", suffixes=(".csv", ".txt", ".tsv"), example="out.csv")
JSON = OutputKind("JSON file", suffixes=(".json",), example="out.json")
IMAGE = OutputKind("image", suffixes=(".png", ".svg", ".pdf", ".jpg", ".jpeg"), example="plot.png")
THN = OutputKind(".thn network file", suffixes=(".thn",), example="extended.thn")
TEXT = OutputKind("text file", suffixes=(".txt", ".md", ".eq", ".tex", ".json", ".dot", ".gv"), example="out.txt")
PLOT_DIR = OutputKind("plot directory", is_dir=True, ours=lambda p: all(
    c.suffix.lower() == ".png" for c in p.iterdir()), example="plots/")


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _inside(child: Path, parent: Path) -> bool:
    try:
        child.resolve().relative_to(parent.resolve())
    except (ValueError, OSError):
        return False
    return True


def _refuse(message: str, hint: str) -> TnnError:
    return TnnError(Diagnostic(message, hint=hint))


def check_output(
    path: str | os.PathLike,
    kind: OutputKind,
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
    force: bool = False,
    option: str = "-o",
) -> Path:
    """Refuse (:class:`TnnError`) an output that would destroy something, before any work is done.

    ``inputs``: the files and directories the command reads (``None`` entries are skipped). Returns the
    path. ``-`` (standard output) is always accepted."""
    p = Path(path)
    if str(path) == "-":
        return p
    shown = f"{option} {path}"
    for src in inputs:
        if src is None or str(src) == "-":
            continue
        s = Path(src)
        if _same(p, s) or (p.exists() and s.exists() and p.resolve() == s.resolve()):
            raise _refuse(f"{shown}: the output is also an input of this command; writing it would destroy "
                          f"{src}", f"write somewhere else, e.g. {option} {kind.example}")
        if s.is_dir() and _inside(p, s):
            raise _refuse(f"{shown}: the output lies inside the input directory {src}; writing it would change "
                          "that input", f"write somewhere else, e.g. {option} {kind.example}")
        if kind.is_dir and p.is_dir() and s.exists() and _inside(s, p) and not force:
            raise _refuse(f"{shown}: the input {src} lies inside this output directory",
                          f"write to a new directory, e.g. {option} {kind.example}")
    if p.is_symlink() and not p.exists():
        raise _refuse(f"{shown}: is a broken symbolic link", "remove it or choose another name")
    if p.exists():
        if kind.is_dir:
            if not p.is_dir():
                raise _refuse(f"{shown}: a file of that name exists, and the output is a {kind.what}",
                              f"choose a new directory name, e.g. {option} {kind.example} (the file is never "
                              "deleted, not even with --force)")
            empty = not any(p.iterdir())
            if not empty and not force and not (kind.ours is not None and kind.ours(p)):
                raise _refuse(f"{shown}: the directory exists and is not a {kind.what} written by tnnc",
                              f"choose a new directory name, e.g. {option} {kind.example}; or add --force to "
                              f"write the {kind.what} into it (its other files are kept)")
            if not os.access(p, os.W_OK | os.X_OK):
                raise _refuse(f"{shown}: cannot write there: the directory is not writable", "choose a writable place")
        else:
            if p.is_dir():
                raise _refuse(f"{shown}: is a directory, and the output is a {kind.what}",
                              f"name a file, e.g. {option} {p / kind.example}")
            if kind.suffixes and p.suffix.lower() not in kind.suffixes and not force:
                raise _refuse(f"{shown}: the file exists and is not a {kind.what} "
                              f"({'/'.join(kind.suffixes)}); it would be replaced",
                              f"choose another name, e.g. {option} {kind.example}; or add --force to replace it")
            if not os.access(p, os.W_OK) or not os.access(p.parent if str(p.parent) else Path("."), os.W_OK):
                raise _refuse(f"{shown}: cannot write there: the file is not writable", "choose a writable place")
        return p
    # not there yet: the nearest existing ancestor must be a writable directory
    anc = p.absolute().parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise _refuse(f"{shown}: cannot write there: {anc} is a file, not a directory", "choose another place")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise _refuse(f"{shown}: cannot write there: {anc} is not writable", "choose a writable place")
    return p


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------


def fsync_dir(path: str | os.PathLike) -> None:
    """Flush a directory's entries (a rename in it) to disk; a no-op where directories cannot be opened."""
    try:
        fd = os.open(os.fspath(path), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def fsync_file(path: str | os.PathLike) -> None:
    """Flush a written file's bytes to disk."""
    fd = os.open(os.fspath(path), os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def temp_sibling(path: Path, tag: str = "tmp") -> Path:
    """A fresh name next to ``path``: ``.NAME.tmp-PID-RANDOM`` plus ``path``'s suffix (so that writers
    choosing a format by suffix, like matplotlib, still do)."""
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """``with atomic_path(dest) as tmp: write(tmp)``: on success ``tmp`` is flushed and renamed over
    ``dest`` in one step; on any error (Ctrl-C included) ``tmp`` is removed and ``dest`` is untouched.
    Parent directories are created."""
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(dest)
    try:
        yield tmp
        fsync_file(tmp)
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(dest.parent)


def save_figure(fig: Any, path: str | os.PathLike, **savefig_kw: Any) -> None:
    """``fig.savefig`` through :func:`atomic_path` (the format from ``path``'s suffix)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".").lower() or None, **savefig_kw)


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex), read in 1 MiB chunks."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 text (``\\n`` line ends) through :func:`atomic_path`; :class:`TnnError` if the place is
    not writable."""
    try:
        with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
    except OSError as err:
        raise TnnError(Diagnostic(f"{path}: cannot write: {err.strerror or err}",
                                  hint="check that the directory exists and is writable")) from None


# ---------------------------------------------------------------------------------------------
# swapping two directories in one step
# ---------------------------------------------------------------------------------------------

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2  # Linux renameat2 flag; macOS renamex_np's RENAME_SWAP has the same value
_swap_fn: list = []


def _swap_function():
    """The C library's atomic swap (Linux ``renameat2(RENAME_EXCHANGE)``, macOS ``renamex_np(RENAME_SWAP)``),
    or ``None``."""
    if not _swap_fn:
        fn = None
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if hasattr(libc, "renameat2"):
                f = libc.renameat2
                f.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]

                def fn(a: bytes, b: bytes) -> int:
                    return f(_AT_FDCWD, a, _AT_FDCWD, b, _RENAME_EXCHANGE)
            elif hasattr(libc, "renamex_np"):
                g = libc.renamex_np
                g.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint]

                def fn(a: bytes, b: bytes) -> int:
                    return g(a, b, _RENAME_EXCHANGE)
        except (OSError, AttributeError):
            fn = None
        _swap_fn.append(fn)
    return _swap_fn[0]


def exchange_paths(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Swap two existing paths in one atomic step. ``False`` where the system or file system cannot (the
    caller falls back to two renames); :class:`OSError` for other failures (``b`` vanished ...)."""
    fn = _swap_function()
    if fn is None:
        return False
    import ctypes
    import errno

    if fn(os.fsencode(a), os.fsencode(b)) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
        return False
    raise OSError(err, os.strerror(err), os.fspath(b))


__all__ = ["OutputKind", "CSV", "JSON", "IMAGE", "THN", "TEXT", "PLOT_DIR", "check_output", "atomic_path",
           "write_text_atomic", "file_sha256", "save_figure", "fsync_dir", "fsync_file", "temp_sibling",
           "exchange_paths"]
