"""The ``.thn`` front end: text -> lark tree -> statements -> IR ``Network`` (then ``_validate``).

Public: :func:`load` and :func:`loads`. The grammar is ``grammars/thn.lark`` (its header comment is the
reference of the syntax). Stages:

1. :mod:`.sources`: bytes -> text (a non-UTF-8 file is an error at the first bad byte).
2. :mod:`.statements` ``_parse_text`` (with :mod:`.grammar`): LALR parse; a syntax error is described by
   the catalogue of malformed examples (:mod:`.syntax_errors`, matched with lark's
   ``UnexpectedInput.match_examples``), the failing statement is blanked out and parsing goes on, so several
   syntax errors are reported together.
3. :mod:`.statements` ``_ToStatements`` (a lark ``Transformer`` with its own one-pass walk): tree -> list of
   ``_St`` records holding IR expressions (every one with its :class:`~tnn_dsl.core.Span`).

The whole parse runs with Python's cyclic garbage collector paused (:mod:`tnn_dsl.core.collector`): a
10 000-node file is a million live objects, and the collector's passes over them were half the parse time.
4. :mod:`.builder` ``_Builder``: statements -> IR elements, expanding ``include`` and ``subnet``/``use``,
   giving every numeric slot its parameter with the automatic name of docs/architecture.md.
5. :mod:`.validation`: the one validation pass (names, dimensions, signs, connectivity ...).
"""

from __future__ import annotations

import os
from collections.abc import Iterable

from ..core import Diagnostic, TnnError
from ..core.collector import collector_paused
from ..ir import (
    Network,
    Span,
)
from .builder import _Builder, _Scope
from .sources import MAX_FILE_BYTES, SourceReadError, _decode, _statements, include_roots, read_source_bytes

# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


def parse(text: str, filename: str = "<string>", *, validate: bool = True,
          include_path: Iterable[str | os.PathLike] | None = None) -> Network:
    """Parse ``text`` (and its includes) into a Network; with ``validate`` run the validation pass.
    Includes are confined to ``filename``'s directory tree (the working directory when ``filename`` is not a
    file) and the directories of ``include_path``. Raises :class:`TnnError` with every problem found."""
    if len(text) > MAX_FILE_BYTES:
        raise TnnError(Diagnostic(f"the network text is {len(text):,} characters, more than the {MAX_FILE_BYTES:,} "
                                  "a network file may have",
                                  Span(file=filename, line=1, col=1, end_line=1, end_col=1),
                                  hint="split the network into files joined by `include`"))
    try:
        with collector_paused():  # a large network is a million live objects: see core.collector
            return _parse(text, filename, validate, include_roots(filename, include_path))
    except RecursionError:
        raise TnnError(Diagnostic("the file is nested too deeply to be read (an expression or subnets too long)",
                                  Span(file=filename, line=1, col=1, end_line=1, end_col=1),
                                  hint="split long expressions with `param` definitions")) from None


def _parse(text: str, filename: str, validate: bool, roots: tuple[str, ...]) -> Network:
    sources: dict[str, str] = {}
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\x00" in text:
        _decode(text.encode("utf-8", errors="surrogatepass"), filename)
    stmts = _statements(text, filename, sources)
    b = _Builder(sources, roots)
    real = os.path.realpath(filename) if os.path.exists(filename) else filename
    b.run_file(stmts, filename, _Scope(), main=True, include_chain=(real,))
    net = b.network()
    diags = list(b.diags)
    if validate:
        from .validation import validate as _validate

        try:
            net = _validate(net, prior=diags)
        except TnnError as err:
            raise TnnError(err.diagnostics, sources=sources) from None
    if diags:
        raise TnnError(diags, sources=sources)
    return net


def loads(text: str, filename: str = "<string>", *,
          include_path: Iterable[str | os.PathLike] | None = None) -> Network:
    """Parse and validate ``.thn`` source text. ``filename`` is used in messages and to resolve
    ``include`` paths (relative to its directory, confined to that directory's tree and ``include_path``).
    Returns the validated :class:`Network`."""
    return parse(text, filename, include_path=include_path)


def load(path: str | os.PathLike, *, include_path: Iterable[str | os.PathLike] | None = None) -> Network:
    """Read, parse and validate a ``.thn`` file (with its includes); returns the :class:`Network`.

    The file must be a regular file of at most 4 MiB. Its includes must lie in its directory tree or in a
    directory of ``include_path`` (also ``tnnc --include-path`` and ``TNN_INCLUDE_PATH``); each included file
    is read once. Raises :class:`TnnError` (``file:line:col: error: ...``) for anything the user can fix."""
    path = os.fspath(path)
    try:
        data = read_source_bytes(path)
    except SourceReadError as e:
        raise TnnError(Diagnostic(f"cannot read `{path}`: {e.reason}", hint=e.hint)) from None
    text = _decode(data, path)
    return parse(text, path, include_path=include_path)


__all__ = ["load", "loads", "parse"]
