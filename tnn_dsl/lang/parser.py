"""The ``.thn`` front end: text -> lark tree -> statements -> IR ``Network`` (then ``_validate``).

Public: :func:`load` and :func:`loads`. The grammar is ``grammars/thn.lark`` (its header comment is the
reference of the syntax). Stages:

1. :mod:`.sources`: bytes -> text (a non-UTF-8 file is an error at the first bad byte).
2. :mod:`.statements` ``_parse_text`` (with :mod:`.grammar`): LALR parse; a syntax error is described by
   the catalogue of malformed examples (:mod:`.syntax_errors`, matched with lark's
   ``UnexpectedInput.match_examples``), the failing statement is blanked out and parsing goes on, so several
   syntax errors are reported together.
3. :mod:`.statements` ``_ToStatements`` (a lark ``Transformer``): tree -> list of ``_St`` records holding
   IR expressions (every one with its :class:`~tnn_dsl.core.Span`).
4. :mod:`.builder` ``_Builder``: statements -> IR elements, expanding ``include`` and ``subnet``/``use``,
   giving every numeric slot its parameter with the automatic name of docs/architecture.md.
5. :mod:`.validation`: the one validation pass (names, dimensions, signs, connectivity ...).
"""

from __future__ import annotations

import os

from ..core import Diagnostic, TnnError
from ..ir import (
    Network,
    Span,
)
from .builder import _Builder, _Scope
from .sources import _decode, _statements

# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


def parse(text: str, filename: str = "<string>", *, validate: bool = True) -> Network:
    """Parse ``text`` (and its includes) into a Network; with ``validate`` run the validation pass.
    Raises :class:`TnnError` with every problem found."""
    try:
        return _parse(text, filename, validate)
    except RecursionError:
        raise TnnError(Diagnostic("the file is nested too deeply to be read (an expression or subnets too long)",
                                  Span(file=filename, line=1, col=1, end_line=1, end_col=1),
                                  hint="split long expressions with `param` definitions")) from None


def _parse(text: str, filename: str, validate: bool) -> Network:
    sources: dict[str, str] = {}
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\x00" in text:
        _decode(text.encode("utf-8", errors="surrogatepass"), filename)
    stmts = _statements(text, filename, sources)
    b = _Builder(sources)
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


def loads(text: str, filename: str = "<string>") -> Network:
    """Parse and validate ``.thn`` source text. ``filename`` is used in messages and to resolve
    ``include`` paths (relative to its directory). Returns the validated :class:`Network`."""
    return parse(text, filename)


def load(path: str | os.PathLike) -> Network:
    """Read, parse and validate a ``.thn`` file (with its includes); returns the :class:`Network`.
    Raises :class:`TnnError` (``file:line:col: error: ...``) for anything the user can fix."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise TnnError(Diagnostic(f"cannot read `{path}`: no such file")) from None
    except IsADirectoryError:
        raise TnnError(Diagnostic(f"cannot read `{path}`: it is a directory")) from None
    except OSError as e:
        raise TnnError(Diagnostic(f"cannot read `{path}`: {e.strerror or e}")) from None
    text = _decode(data, path)
    return parse(text, path)


__all__ = ["load", "loads", "parse"]
