"""The grammar (``grammars/thn.lark``, shipped in the wheel) and its LALR parser, with the post-lexer that makes
newlines end statements except inside brackets."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from lark import Lark, Token


def _grammar_text() -> str:
    """The grammar shipped in the wheel (``tnn_dsl/grammars/thn.lark``), else the checkout's."""
    try:
        from importlib.resources import files

        res = files("tnn_dsl").joinpath("grammars", "thn.lark")
        if res.is_file():
            return res.read_text(encoding="utf-8")
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError, OSError):
        pass
    package = Path(__file__).resolve().parents[1]  # tnn_dsl/
    for cand in (package / "grammars" / "thn.lark", package.parent / "grammars" / "thn.lark"):
        if cand.is_file():
            return cand.read_text(encoding="utf-8")
    raise RuntimeError("the .thn grammar (grammars/thn.lark) is missing from the installation")


class _Newlines:
    """Post-lexer: newlines end statements except inside ( ) and [ ]; blank lines collapse; a final
    newline is added when the text lacks one."""

    always_accept = ("_NL",)

    def process(self, stream):
        depth = 0
        prev_nl = True
        last = None
        for tok in stream:
            if tok.type == "_NL":
                if depth > 0 or prev_nl:
                    continue
                prev_nl = True
                yield tok
                continue
            if tok.type in ("LPAR", "LSQB"):
                depth += 1
            elif tok.type in ("RPAR", "RSQB"):
                depth = max(0, depth - 1)
            prev_nl = False
            last = tok
            yield tok
        if not prev_nl and last is not None:
            yield Token.new_borrow_pos("_NL", "\n", last)


@lru_cache(maxsize=1)
def _lark() -> Lark:
    return Lark(
        _grammar_text(),
        parser="lalr",
        lexer="contextual",
        propagate_positions=True,
        maybe_placeholders=False,
        postlex=_Newlines(),
    )
