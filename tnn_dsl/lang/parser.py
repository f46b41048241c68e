"""The ``.thn`` front end: text -> lark tree -> statements -> IR ``Network`` (then ``_validate``).

Public: :func:`load` and :func:`loads`. The grammar is ``grammars/thn.lark`` (its header comment is the
reference of the syntax). Stages:

1. ``_read_source``: bytes -> text (a non-UTF-8 file is an error at the first bad byte).
2. ``_parse_text``: LALR parse; a syntax error is described by the catalogue of malformed examples
   (``_CATALOGUE``, matched with lark's ``UnexpectedInput.match_examples``), the failing statement is
   blanked out and parsing goes on, so several syntax errors are reported together.
3. ``_ToStatements`` (a lark ``Transformer``): tree -> list of :class:`_St` records holding IR
   expressions (every one with its :class:`~tnn_dsl.ir.network.Span`).
4. ``_Builder``: statements -> IR elements, expanding ``include`` and ``subnet``/``use``, giving every
   numeric slot its parameter with the automatic name of docs/architecture.md.
5. ``_validate.validate``: the one validation pass (names, dimensions, signs, connectivity ...).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from lark import Lark, Token, Transformer, v_args
from lark.exceptions import UnexpectedCharacters, UnexpectedEOF, UnexpectedInput, UnexpectedToken, VisitError

from ..core import Diagnostic, TnnError
from ..ir import (
    CALL_FUNCTIONS,
    Binary,
    Boundary,
    Call,
    Fluid,
    Input,
    LearnFunction,
    LearnInput,
    LearnTarget,
    Link,
    Network,
    Num,
    Param,
    Peltier,
    Radiation,
    Ref,
    Sensor,
    Source,
    Span,
    Table,
    Temp,
    ThermalNode,
    Unary,
)
from .units import TEMPERATURE_UNITS, UnitError, dim_eq, format_dim, parse_quantity, unit_scale

MAX_ERRORS = 20
MAX_INCLUDE_DEPTH = 32
MAX_SUBNET_DEPTH = 16

# ---------------------------------------------------------------------------------------------
# Grammar loading
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Syntax errors: catalogue of malformed examples
# ---------------------------------------------------------------------------------------------

# (message, hint) -> examples that fail in the same parser state. ``{found}`` is replaced by a
# description of the offending token. Order matters only for ties.
_CATALOGUE: list[tuple[tuple[str, str | None], list[str]]] = [
    (("expected a name after `network`, found {found}",
      'write `network NAME "label"`, e.g. `network tclab "two heaters"`'),
     ["network\n", "network 3\n", 'network "x"\n']),
    (("a network label must be a quoted string, found {found}", 'write `network NAME "label"`'),
     ["network a b\n", "network a 3\n"]),
    (("expected `units temperature = degC|K|degF`",
      "the only unit setting is the temperature unit of the file and its data columns"),
     ["units\n", "units pressure\n", "units temperature degC\n", "units temperature =\n"]),
    (("expected a quoted file name after `include`", 'write `include "parts.thn"`'),
     ["include parts.thn\n", "include\n"]),
    (("expected `:` and a unit after the input name, found {found}",
      "write `input NAME : [UNIT]` (e.g. `[%]`, `[A]`, `[1]`) or `input NAME : temperature`"),
     ["input Q1\n", "input Q1 [%]\n", "input Q1 = 3\n"]),
    (("expected a unit in brackets or `temperature` after `input NAME :`, found {found}",
      "write `input Q1 : [%]`, `input I : [A]`, `input u : [1]` or `input Ta : temperature`"),
     ["input Q1 : %\n", "input Q1 : W\n", "input Q1 :\n"]),
    (("expected a name after `input`, found {found}", "write `input NAME : [UNIT]`"),
     ["input\n", "input 3 : [1]\n"]),
    (("expected `column \"NAME\"` or a quoted label, found {found}",
      'the data column is a quoted string: `column "Q1_pct"`'),
     ["input Q1 : [%] column Q1_pct\n", "input Q1 : [%] x\n"]),
    (("expected a quoted column name after `column`, found {found}", 'write `column "T1_degC"`'),
     ["input Q1 : [%] column\n", "sensor T1 = h1 column T1\n"]),
    (("expected `=` after the parameter name, found {found}", "write `param NAME = VALUE`"),
     ["param a\n", "param a 3\n", "param a : 3\n"]),
    (("expected a name after `param`, found {found}", "write `param NAME = VALUE`"),
     ["param\n", "param = 3\n", "param 3 = 3\n"]),
    (("expected a value after `=`, found {found}", "a value is an expression such as `0.05 W/K` or `a1 * Q1`"),
     ["param a =\n", "boundary amb =\n", "G a -- b =\n", "source h1 =\n",
      "param a = *\n", "param a = )\n", "node a C =\n"]),
    (("expected an operator or the end of the statement, found {found}",
      "put an operator between values (`2 * x`); units follow a number directly, without spaces (`J/K`)"),
     ["param a = 3 W/K 4\n", "param a = b c\n", "param a = b 3\n", "param a = (b) 3\n",
      "param a = 3 W/K \"x\" 4\n"]),
    (("incomplete expression: expected a value after the operator, found {found}",
      "an operator needs a value on both sides"),
     ["param a = 3 +\n", "param a = 3 *\n", "param a = b -\n", "param a = b /\n", "param a = b ^\n"]),
    (("expected `C = VALUE` for the node's heat capacity, found {found}",
      'write `node NAME "label" C = 40 J/K`; a node without capacity is a `boundary`'),
     ["node a\n", 'node a "x"\n', "node a = 3\n", "node a C 3\n", "node a 3\n"]),
    (("expected a node name or number after `node`, found {found}", "write `node NAME C = 40 J/K`"),
     ["node\n", "node C = 3\n", 'node "x" C = 3\n']),
    (("expected `=` and a temperature after the boundary name, found {found}",
      "write `boundary amb = Ta` or `boundary amb = 22 degC`"),
     ["boundary amb\n", "boundary amb 3\n", "boundary amb : 3\n"]),
    (("expected a name after `boundary`, found {found}", "write `boundary NAME = TEMPERATURE`"),
     ["boundary\n", "boundary = 3\n"]),
    (("expected `--` between the two ends of a link, found {found}",
      "write `R a -- b = 0.1 K/W` or `G a -- b = 10 W/K`"),
     ["R a b = 3\n", "R a - b = 3\n", "R a = 3\n", "G a\n", "R a -> b = 3\n", "R a, b = 3\n"]),
    (("expected a node after `--`, found {found}", "write `R a -- b = 0.1 K/W`"),
     ["R a -- = 3\n", "R a --\n", "G a -- -- b = 3\n"]),
    (("expected a node name after `R`/`G`, found {found}", "write `R a -- b = 0.1 K/W`"),
     ["R\n", "G = 3\n", "R -- b = 3\n"]),
    (("expected `=` and a value after the link's ends, found {found}", "write `R a -- b = 0.1 K/W`"),
     ["R a -- b\n", "R a -- b 3\n", "R a -- b c = 3\n", "G a -- b : 3\n"]),
    (("expected `free`, `as NAME`, a label or the end of the link, found {found}",
      "a link reads `R a -- b = VALUE [free [in [LO, HI]]] [as NAME]`"),
     ["R a -- b = 3 K/W free 4\n", "R a -- b = 3 K/W free free in\n", "R a -- b = 3 K/W free x\n"]),
    (("expected a name after `as`, found {found}", "write `as NAME`"),
     ["R a -- b = 3 K/W as\n", "R a -- b = 3 K/W as 3\n", 'source a = 3 W as "x"\n',
      "radiation a -- b area = 1 m^2 as\n"]),
    (("expected `in [LOW, HIGH]` or the end of the clause after `free`, found {found}",
      "write `free` or `free in [0.01 K/W, 1 K/W]`"),
     ["param a = 3 K free [1, 2]\n", "param a = 3 K free in 1, 2\n", "param a = 3 K free (1, 2)\n",
      "param a = 3 K free 1\n"]),
    (("bounds are two numbers: expected `[LOW, HIGH]`, found {found}",
      "write `free in [0.01 K/W, 1 K/W]`; each bound is a number with an optional unit"),
     ["param a = 3 K free in [1]\n", "param a = 3 K free in [1, 2, 3]\n", "param a = 3 K free in [a, b]\n",
      "param a = 3 K free in []\n", "param a = 3 K free in [1 2]\n", "param a = 3 K free in [1,\n",
      "param a = 3 K free in [1, x]\n", "param a = 3 K free in [1, 2\n"]),
    (("expected `=` and an expression after the source's node, found {found}",
      "write `source NODE = EXPRESSION`, e.g. `source h1 = a1 * Q1`"),
     ["source h1\n", "source h1 3\n", "source\n"]),
    (("expected `=` and a node after the sensor name, found {found}",
      'write `sensor T1 = h1 column "T1_degC"`'),
     ["sensor T1\n", "sensor T1 h1\n", "sensor\n", "sensor T1 =\n", "sensor T1 = = h1\n"]),
    (("unknown sensor clause {found}", 'a sensor reads `sensor NAME = NODE [lag TAU [free]] [offset DT [free]] [column "COL"]`'),
     ["sensor T1 = h1 x\n", "sensor T1 = h1 lag\n", "sensor T1 = h1 3\n", "sensor T1 = h1 = 3\n"]),
    (("unknown radiation clause {found}",
      "radiation reads `radiation a -- b area = A emissivity = E [view_factor = F] [as NAME]`"),
     ["radiation a -- b x = 3\n", "radiation a -- b area 3\n", "radiation a -- b 3\n", "radiation a b\n",
      "radiation\n"]),
    (("unknown peltier clause {found}",
      "a Peltier element reads `peltier NAME hot = A cold = B current = I seebeck = S resistance = R_el [R_internal = R]`"),
     ["peltier pe x = 3\n", "peltier pe hot 3\n", "peltier pe hot = a x\n", "peltier\n", "peltier pe 3\n",
      "peltier pe hot = = a\n"]),
    (("expected `through NODE` after the fluid's name, found {found}",
      "a fluid reads `fluid NAME through NODE inlet = T mdot = M cp = C UA = U`"),
     ["fluid f1\n", "fluid f1 inlet = 3\n", "fluid\n", "fluid f1 hx1\n"]),
    (("unknown fluid clause {found}",
      "a fluid reads `fluid NAME through NODE inlet = T mdot = M cp = C UA = U`"),
     ["fluid f1 through hx1 x = 3\n", "fluid f1 through hx1 mdot 3\n", "fluid f1 through hx1 3\n"]),
    (("expected what to learn after `learn`, found {found}",
      "write `learn R_hp1, R_hp2 as linear(hx1, hp, u1)`; targets are parameters, `Q[node]` or flows like `pe.Q_hot`"),
     ["learn\n", "learn as const\n", "learn 3 as const\n", "learn R_a, as const\n"]),
    (("expected `as KIND` after the learned targets, found {found}",
      "write `learn TARGET, ... as const|linear(...)|poly(...)|mlp(...)|table(...)`"),
     ["learn R_a\n", "learn R_a linear(x)\n", "learn R_a R_b as const\n", "learn R_a = const\n",
      "learn Q[a]\n"]),
    (("expected a learned-function kind after `as`, found {found}", "kinds are const, linear, poly, mlp and table"),
     ["learn R_a as\n", "learn R_a as 3\n", "learn R_a as (x)\n"]),
    (("expected the arguments of the learned function, found {found}",
      "arguments are nodes (`hx1`, `T3`, `T(hx1)`), inputs or parameters; options follow a `;`: `mlp(a, b; hidden = [8, 8])`"),
     ["learn R_a as mlp(3)\n", "learn R_a as mlp(a b)\n", "learn R_a as mlp(a,)\n", "learn R_a as mlp(a + b)\n",
      "learn R_a as mlp(a\n", "learn R_a as mlp(T(3 + 1))\n", "learn R_a as mlp(a; hidden = [8, 8]\n"]),
    (("expected a learned-function option, found {found}",
      "options are `hidden = [8, 8]`, `activation = tanh`, `degree = 2`, `knots = [...]`, `frozen`, `replace`, `init_from = \"dir\"`"),
     ["learn R_a as mlp(a; 3)\n", "learn R_a as mlp(a; hidden [8])\n", "learn R_a as mlp(a; hidden = )\n",
      "learn R_a as mlp(a; hidden = [8 8])\n", "learn R_a as mlp(a; hidden = 8 8)\n",
      "learn R_a as const 3\n", "learn R_a as mlp(a) (b)\n", "learn R_a as mlp(a; frozen frozen)\n"]),
    (("expected `)` to close the parentheses, found {found}",
      "every `(` needs its `)`; statements may continue over lines inside brackets"),
     ["param a = (3 K\n", "param a = exp(3\n", "param a = max(3, 4\n", "param a = ((3)\n"]),
    (("expected a table point `X: Y` after `;`, found {found}",
      "write `table(X; 0 degC: 2.0 W/K, 50 degC: 2.4 W/K)`: numbers with units, `:` between x and y"),
     ["param a = table(x; 1)\n", "param a = table(x; 1 2)\n", "param a = table(x; )\n", "param a = table(x; a: b)\n",
      "param a = table(x; 1:)\n", "param a = table(x; 1: 2,)\n", "param a = table(x; 1: 2 3: 4)\n"]),
    (("expected a subnet name after `subnet`, found {found}", "write `subnet NAME(P1, P2) ... end`"),
     ["subnet\n", "subnet 3\n", "subnet (a)\n"]),
    (("expected the end of the `subnet` line, found {found}",
      "write `subnet NAME(P1, P2) \"label\"` on its own line, the statements below it and `end` to close it"),
     ["subnet a(b c)\nend\n", "subnet a(3)\nend\n", "subnet a b\nend\n", "subnet a node\nend\n"]),
    (("`subnet` is not closed: expected `end`", "close the subnet's statements with a line `end`"),
     ["subnet a\n", "subnet a\nnode b C = 1 J/K\n"]),
    (("expected `as NAME` after `use SUBNET(...)`, found {found}", "write `use heater(C0 = 4 J/K) as h1`"),
     ["use a\n", "use a(b = 1)\n", "use a(b = 1) h1\n", "use a h1\n"]),
    (("expected `PARAM = VALUE` arguments in `use`, found {found}", "write `use heater(C0 = 4 J/K, G0 = 0.1 W/K) as h1`"),
     ["use a(3) as b\n", "use a(b) as c\n", "use a(b 3) as c\n", "use a(b = 1, ) as c\n", "use a(b = 1 c = 2) as d\n"]),
    (("`end` without a `subnet`", "`end` closes a `subnet` block"), ["end\n", "network a\nend\n"]),
    (("a statement starts with a keyword, found {found}",
      "statements begin with network, units, include, input, param, node, boundary, R, G, source, sensor, "
      "radiation, peltier, fluid, learn, subnet or use"),
     ["network a\nx\n", "network a\nx = 3\n", "network a\n3\n", "network a\nr a -- b = 3\n",
      "network a\n\"label\"\n", "network a\n(a)\n", "network a\n= 3\n", "x\n", "x = 3\n", "3\n", "r a -- b = 3\n", '"label"\n', "= 3\n", "(a)\n", "Node a C = 3\n",
      "-- a\n", "[1]\n", ", a\n", "T1 = h1\n"]),
]

_STATEMENT_KEYWORDS = {"network", "units", "include", "input", "param", "node", "boundary", "R", "G", "source",
                       "sensor", "radiation", "peltier", "fluid", "learn", "subnet", "use", "end"}

_TOKEN_NAMES = {
    "_NL": "the end of the line", "$END": "the end of the file", "NAME": "a name", "NUMBER": "a number",
    "UNIT": "a unit", "STRING": "a quoted string", "BRACKET_UNIT": "a unit in brackets",
    "LPAR": "`(`", "RPAR": "`)`", "LSQB": "`[`", "RSQB": "`]`", "COMMA": "`,`", "COLON": "`:`",
    "SEMICOLON": "`;`", "EQUAL": "`=`", "PLUS": "`+`", "MINUS": "`-`", "STAR": "`*`", "SLASH": "`/`",
    "CIRCUMFLEX": "`^`", "LINK_KIND": "`R` or `G`",
}


def _describe_token(tok: Token | None) -> str:
    if tok is None or tok.type == "$END":
        return "end of file"
    if tok.type == "_NL":
        return "end of line"
    val = str(tok)
    if len(val) > 30:
        val = val[:27] + "..."
    if tok.type == "NAME" or (tok.type == "UNIT" and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", val)):
        return f"`{val}`"
    if tok.type in ("NUMBER", "UNIT", "STRING", "BRACKET_UNIT"):
        return f"{_TOKEN_NAMES[tok.type].split(' ', 1)[1] if tok.type != 'UNIT' else 'unit'} `{val}`"
    return f"`{val}`"


def _describe_expected(names) -> str:
    out = []
    for n in sorted(names):
        if n in _TOKEN_NAMES:
            out.append(_TOKEN_NAMES[n])
        else:
            try:
                pat = _lark().get_terminal(n).pattern
                out.append(f"`{pat.value}`" if pat.type == "str" else n.lower())
            except KeyError:
                out.append(n.lower())
    out = sorted(set(out))
    if len(out) > 8:
        out = out[:8] + ["..."]
    return ", ".join(out)


# Statement-start errors fail in different LALR states after zero, one or more statements: the
# catalogue's statement-start examples are also tried after one and after two statements.
for _label, _examples in _CATALOGUE:
    if _label[0].startswith(("a statement starts", "`end` without")):
        _examples += [p + e for e in list(_examples) for p in ("network a\n", "network a\nnetwork b\n")]
del _label, _examples


@lru_cache(maxsize=1)
def _catalogue_dict() -> dict[tuple[str, str | None], list[str]]:
    return {label: examples for label, examples in _CATALOGUE}


def _normalise_state(err: UnexpectedInput) -> UnexpectedInput:
    """Errors raised by the contextual lexer carry the whole ``ParserState``; the catalogue compares
    LALR state numbers."""
    st = getattr(err, "state", None)
    if st is not None and not isinstance(st, int) and hasattr(st, "position"):
        err.state = st.position
    return err


def _raw_parse(text: str):
    try:
        return _lark().parse(text)
    except UnexpectedInput as err:
        raise _normalise_state(err) from None


def _state_expected(err: UnexpectedInput) -> set[str]:
    """Terminals the parser accepts in the error's state (from the LALR table)."""
    st = getattr(err, "state", None)
    try:
        table = _lark().parser.parser.parser.parse_table
        return {t for t in table.states[st].keys() if t != "$END" or True}
    except (AttributeError, KeyError, TypeError):
        return set(getattr(err, "expected", set()) or set())


_CHAR_HINTS = {
    "'": "strings are written in double quotes: \"label\"",
    "{": "braces are not used in .thn; a `subnet` block ends with `end`",
    "}": "braces are not used in .thn; a `subnet` block ends with `end`",
    ";": "`;` separates the arguments from the options or points, inside parentheses only",
    "\"": "a string must end on the same line with `\"`",
    "→": "write links as `a -- b`",
    "−": "use the ASCII minus sign `-`",
    "×": "use `*` for multiplication",
    "·": "use `*` for multiplication",
}


def _syntax_diagnostic(err: UnexpectedInput, filename: str, lines: list[str]) -> Diagnostic:
    _normalise_state(err)
    line = getattr(err, "line", None) or 0
    ln_text = lines[line - 1] if isinstance(line, int) and 1 <= line <= len(lines) else ""
    first_word = (ln_text.split() or [""])[0]
    word_index = len(ln_text[: max(0, (getattr(err, "column", 1) or 1) - 1)].split())
    col = getattr(err, "column", None) or 0
    tok = getattr(err, "token", None)
    if isinstance(err, UnexpectedToken) and (tok is None or tok.type == "$END" or not line or line < 0):
        line = max(1, len(lines))
        col = len(lines[-1]) + 1 if lines else 1
    if line < 1:
        line, col = 1, 1
    if col < 1:
        col = 1
    width = 1
    if isinstance(err, UnexpectedToken) and tok is not None and tok.type not in ("_NL", "$END"):
        width = max(1, len(str(tok)))
    span = Span(file=filename, line=line, col=col, end_line=line, end_col=col + width)
    if isinstance(err, UnexpectedCharacters):
        ch = err.char
        text_line = lines[line - 1] if 1 <= line <= len(lines) else ""
        if ch == '"':
            return Diagnostic("unterminated string", span, hint=_CHAR_HINTS['"'])
        if ch.isdigit() or ch.isalpha() or ch == "_":
            # a legal character in an illegal place (the contextual lexer found no token here)
            label = _match_catalogue(err, first_word, word_index)
            m = re.match(r"[A-Za-z0-9_.%/*^()]+", text_line[col - 1:]) if text_line else None
            found = f"`{m.group(0)}`" if m else f"`{ch}`"
            if label is not None:
                return Diagnostic(label[0].replace("{found}", found), span, hint=label[1])
            return Diagnostic(f"unexpected {found}", span, hint=None)
        shown = ch if ch.isprintable() else repr(ch)
        label = _match_catalogue(err, first_word, word_index) if ch in "()[],:;=+-*/^" else None
        if label is not None:
            return Diagnostic(label[0].replace("{found}", f"`{shown}`"), span, hint=label[1])
        return Diagnostic(f"unexpected character `{shown}`", span,
                          hint=_CHAR_HINTS.get(ch, "comments start with `#`; names use letters, digits, `_` and `.`"))
    at_line_start = col == len(ln_text) - len(ln_text.lstrip()) + 1
    if isinstance(err, UnexpectedToken) and tok is not None and (
            tok.type == "$END" or (at_line_start and str(tok) in _STATEMENT_KEYWORDS)):
        open_ = _unclosed_bracket(lines, line if tok.type != "$END" else len(lines) + 1)
        if open_ is not None:
            oline, ocol, ch = open_
            close = ")" if ch == "(" else "]"
            return Diagnostic(f"`{ch}` is never closed", Span(file=filename, line=oline, col=ocol, end_line=oline,
                                                             end_col=ocol + 1),
                              hint=f"add the matching `{close}`; a statement continues over lines while a bracket is open")
    label = _match_catalogue(err, first_word, word_index)
    found = _describe_token(tok)
    if label is not None:
        return Diagnostic(label[0].replace("{found}", found), span, hint=label[1])
    exp = _state_expected(err)
    if len(exp) > 1:
        exp.discard("_NL") if tok is not None and tok.type != "_NL" and len(exp - {"_NL"}) else None
    expected = _describe_expected(exp)
    return Diagnostic(f"unexpected {found}", span, hint=f"expected {expected}" if expected else None)


@lru_cache(maxsize=1)
def _catalogue_states() -> list[tuple[int, str, tuple[str, str | None]]]:
    """(LALR state, first word of the example, label) for every example of the catalogue."""
    out = []
    for label, examples in _CATALOGUE:
        for ex in examples:
            try:
                _raw_parse(ex)
            except UnexpectedInput as ut:
                if isinstance(ut.state, int):
                    ln = ex.split("\n")[(ut.line or 1) - 1] if isinstance(getattr(ut, "line", None), int) and ut.line > 0 else ex
                    col = ut.column if isinstance(getattr(ut, "column", None), int) and ut.column > 0 else len(ln) + 1
                    ttype = getattr(getattr(ut, "token", None), "type", "")
                    out.append((ut.state, (ln.split() or [""])[0], len(ln[: col - 1].split()), ttype, label))
    return out


def _match_catalogue(err: UnexpectedInput, first_word: str = "", word_index: int = -1):
    """The catalogue label of examples failing in the same parser state; among several, one whose
    example starts with the same statement keyword as the failing line, and fails at the same word."""
    st = getattr(err, "state", None)
    if not isinstance(st, int):
        return None
    ttype = getattr(getattr(err, "token", None), "type", "")
    cands = [(w, i, t, label) for s_, w, i, t, label in _catalogue_states() if s_ == st]
    if not cands:
        return None
    best = max(cands, key=lambda c: (c[0] == first_word, c[0] == first_word and c[1] == word_index, c[2] == ttype))
    return best[3]


def _brackets(line: str):
    """``(col, char)`` of each bracket in one line, 1-based, skipping strings and a trailing comment."""
    in_str = False
    j = 0
    while j < len(line):
        c = line[j]
        if in_str:
            if c == "\\":
                j += 1
            elif c == '"':
                in_str = False
        elif c == '"':
            in_str = True
        elif c == "#":
            return
        elif c in "([)]":
            yield j + 1, c
        j += 1


def _unclosed_bracket(lines: list[str], upto_line: int) -> tuple[int, int, str] | None:
    """Position (line, col, char) of the innermost bracket still open before line ``upto_line``."""
    stack: list[tuple[int, int, str]] = []
    for i, ln in enumerate(lines[: max(0, upto_line - 1)], start=1):
        for col, c in _brackets(ln):
            if c in "([":
                stack.append((i, col, c))
            elif stack:
                stack.pop()
    return stack[-1] if stack else None


def _bracket_depths(lines: list[str]) -> list[int]:
    """Bracket depth at the start of each line (strings and comments skipped)."""
    depths = []
    depth = 0
    for ln in lines:
        depths.append(depth)
        for _, c in _brackets(ln):
            depth = depth + 1 if c in "([" else max(0, depth - 1)
    depths.append(depth)
    return depths


def _parse_text(text: str, filename: str):
    """Parse; on syntax errors return ``(None, diagnostics)`` with up to ``MAX_ERRORS`` of them."""
    lines = text.split("\n")
    diags: list[Diagnostic] = []
    current = lines[:]
    seen: set[tuple[int, int]] = set()
    while True:
        try:
            tree = _lark().parse("\n".join(current))
            return (tree, []) if not diags else (None, diags)
        except UnexpectedInput as err:
            d = _syntax_diagnostic(err, filename, lines)
            key = (d.span.line, d.span.col) if d.span else (0, 0)
            if key in seen:
                return None, diags
            seen.add(key)
            diags.append(d)
            if len(diags) >= MAX_ERRORS or isinstance(err, UnexpectedEOF):
                return None, diags
            # blank out the failing statement (all the lines of a bracketed continuation) and go on
            depths = _bracket_depths(current)
            ln = min(max(1, d.span.line), len(current)) - 1
            start = ln
            while start > 0 and depths[start] > 0:
                start -= 1
            end = ln
            while end + 1 < len(current) and depths[end + 1] > 0:
                end += 1
            if depths[end + 1] > 0 or end + 1 >= len(current) and depths[-1] > 0:
                return None, diags
            blanked = False
            for i in range(start, end + 1):
                if current[i].strip():
                    blanked = True
                current[i] = ""
            if not blanked:
                return None, diags
            # an unclosed `subnet` swallows everything after it: stop here
            if "subnet" in d.message and "not closed" in d.message:
                return None, diags


# ---------------------------------------------------------------------------------------------
# Tree -> statements
# ---------------------------------------------------------------------------------------------


@dataclass
class _Q:
    """A quantity literal before conversion: the number as written and its unit text."""

    number: float
    unit: str | None
    span: Span
    text: str


@dataclass
class _Free:
    lo: _Q | None
    hi: _Q | None
    span: Span


@dataclass
class _Clause:
    tag: str
    value: Any
    span: Span
    free: _Free | None = None


@dataclass
class _St:
    kind: str
    span: Span
    data: dict[str, Any] = field(default_factory=dict)
    clauses: list[_Clause] = field(default_factory=list)
    file: str = ""


class _ToStatements(Transformer):
    """lark tree -> list of :class:`_St`; expressions become IR ``Expr`` with spans."""

    def __init__(self, filename: str, diags: list[Diagnostic]):
        super().__init__(visit_tokens=False)
        self.filename = filename
        self.diags = diags

    # -- helpers --------------------------------------------------------------------------

    def _span(self, meta) -> Span:
        if getattr(meta, "empty", True):
            return Span(file=self.filename, line=1, col=1, end_line=1, end_col=1)
        return Span(file=self.filename, line=meta.line, col=meta.column, end_line=meta.end_line,
                    end_col=meta.end_column)

    def _tspan(self, tok: Token) -> Span:
        return Span(file=self.filename, line=tok.line, col=tok.column, end_line=tok.end_line or tok.line,
                    end_col=tok.end_column or tok.column + len(str(tok)))

    def _num(self, q: _Q, negate: bool = False) -> Num:
        number = -q.number if negate else q.number
        try:
            value, dim = parse_quantity(number, q.unit)
        except UnitError as err:
            self.diags.append(Diagnostic(err.message, q.span, hint=err.hint))
            value, dim = number, {}
        if not math.isfinite(value):
            self.diags.append(Diagnostic(f"number `{q.text}` is too large", q.span,
                                         hint="numbers must be finite double-precision values"))
            value = 0.0
        return Num(value=value, dim=dim, unit=q.unit, span=q.span)

    def _e(self, x):
        return self._num(x) if isinstance(x, _Q) else x

    # -- expressions ----------------------------------------------------------------------

    @v_args(meta=True)
    def quantity(self, meta, ch):
        text = str(ch[0])
        try:
            number = float(text)
        except ValueError:  # pragma: no cover - the lexer only passes numbers
            number = 0.0
        unit = str(ch[1]) if len(ch) > 1 else None
        return _Q(number, unit, self._span(meta), text if unit is None else f"{text} {unit}")

    @v_args(meta=True)
    def signed_quantity(self, meta, ch):
        return ch[0]

    @v_args(meta=True)
    def neg_quantity(self, meta, ch):
        q = ch[0]
        return _Q(-q.number, q.unit, self._span(meta), "-" + q.text)

    @v_args(meta=True)
    def ref(self, meta, ch):
        return Ref(name=str(ch[0]), span=self._span(meta))

    def _bin(self, op, meta, ch):
        return Binary(op=op, left=self._e(ch[0]), right=self._e(ch[1]), span=self._span(meta))

    @v_args(meta=True)
    def add(self, meta, ch):
        return self._bin("+", meta, ch)

    @v_args(meta=True)
    def sub(self, meta, ch):
        return self._bin("-", meta, ch)

    @v_args(meta=True)
    def mul(self, meta, ch):
        return self._bin("*", meta, ch)

    @v_args(meta=True)
    def div(self, meta, ch):
        return self._bin("/", meta, ch)

    @v_args(meta=True)
    def pow(self, meta, ch):
        return self._bin("^", meta, ch)

    def paren(self, ch):
        return self._e(ch[0])

    @v_args(meta=True)
    def neg(self, meta, ch):
        x = ch[0]
        if isinstance(x, _Q):  # `-5 degC` is minus five degrees Celsius, not minus (5 degC in K)
            return self._num(x, negate=True).model_copy(update={"span": self._span(meta)})
        return Unary(op="neg", arg=x, span=self._span(meta))

    @v_args(meta=True)
    def call(self, meta, ch):
        name = str(ch[0])
        span = self._span(meta)
        args = [self._e(a) for a in ch[1:]]
        if name == "T":
            if len(args) == 1 and isinstance(args[0], Ref):
                return Temp(node=args[0].name, span=span)
            if len(args) == 1 and isinstance(args[0], Num) and args[0].unit is None and float(args[0].value).is_integer():
                return Temp(node=str(int(args[0].value)), span=span)
            self.diags.append(Diagnostic("`T(...)` takes one node name", span,
                                         hint="write `T(hx1)` or `T3` for the temperature of node 3"))
            return Num(value=0.0, span=span)
        if name not in CALL_FUNCTIONS:
            hint = "functions are " + ", ".join(CALL_FUNCTIONS) + ", T(node) and table(x; x0: y0, ...)"
            if name == "table":
                hint = "write `table(X; X0: Y0, X1: Y1, ...)` with a `;` after the variable"
            self.diags.append(Diagnostic(f"unknown function `{name}`", Span(
                file=self.filename, line=ch[0].line, col=ch[0].column, end_line=ch[0].line,
                end_col=ch[0].column + len(name)), hint=hint))
            return Num(value=0.0, span=span)
        arity = {"exp": 1, "log": 1, "sqrt": 1, "abs": 1}
        if name in arity and len(args) != 1:
            self.diags.append(Diagnostic(f"`{name}` takes one argument, got {len(args)}", span))
            return Num(value=0.0, span=span)
        if name not in arity and len(args) < 2 and not (name in ("min", "max", "mean") and len(args) == 1):
            self.diags.append(Diagnostic(f"`{name}` takes at least two arguments, got {len(args)}", span))
            return Num(value=0.0, span=span)
        return Call(fn=name, args=args, span=span)

    @v_args(meta=True)
    def table_point(self, meta, ch):
        return (ch[0], ch[1], self._span(meta))

    @v_args(meta=True)
    def table(self, meta, ch):
        name = str(ch[0])
        span = self._span(meta)
        if name != "table":
            self.diags.append(Diagnostic(f"`;` inside the arguments of `{name}`: only `table(x; x0: y0, ...)` has points",
                                         span, hint="separate function arguments with `,`"))
            return Num(value=0.0, span=span)
        x = self._e(ch[1])
        pts = ch[2:]
        xs, ys = [], []
        xdim = ydim = None
        ok = True
        for qx, qy, pspan in pts:
            nx, ny = self._num(qx), self._num(qy)
            if xdim is None:
                xdim, ydim = nx.dim, ny.dim
            elif not dim_eq(xdim, nx.dim) or not dim_eq(ydim, ny.dim):
                bad = qx if not dim_eq(xdim, nx.dim) else qy
                self.diags.append(Diagnostic(
                    f"table point `{bad.text}` is in `{format_dim(nx.dim if bad is qx else ny.dim)}` but the first point "
                    f"is in `{format_dim(xdim if bad is qx else ydim)}`", bad.span,
                    hint="all x values share one unit dimension, and all y values another"))
                ok = False
            xs.append(nx.value)
            ys.append(ny.value)
        if ok:
            for i in range(1, len(xs)):
                if not xs[i] > xs[i - 1]:
                    self.diags.append(Diagnostic("table x values must be strictly increasing", pts[i][0].span,
                                                 hint=f"point {i + 1} is not above point {i}"))
                    break
        if len(pts) < 2:
            self.diags.append(Diagnostic("a table needs at least two points", span))
        return Table(x=x, xs=xs, ys=ys, x_dim=xdim or {}, y_dim=ydim or {}, span=span)

    # -- clauses --------------------------------------------------------------------------

    @v_args(meta=True)
    def free_clause(self, meta, ch):
        lo = ch[0] if len(ch) > 0 else None
        hi = ch[1] if len(ch) > 1 else None
        return _Free(lo, hi, self._span(meta))

    @v_args(meta=True)
    def as_clause(self, meta, ch):
        return _Clause("as", str(ch[0]), self._tspan(ch[0]))

    @v_args(meta=True)
    def column(self, meta, ch):
        return _Clause("column", _unquote(ch[0]), self._span(meta))

    @v_args(meta=True)
    def label(self, meta, ch):
        return _Clause("label", _unquote(ch[0]), self._span(meta))

    @v_args(meta=True)
    def node_id(self, meta, ch):
        tok = ch[0]
        text = str(tok)
        if tok.type == "NUMBER":
            try:
                v = float(text)
                ok = v.is_integer() and v >= 0 and "e" not in text.lower() and "." not in text
            except ValueError:  # pragma: no cover
                ok = False
            if not ok:
                self.diags.append(Diagnostic(f"`{text}` is not a node: numbered nodes are whole numbers like `3`",
                                             self._tspan(tok)))
            text = str(int(text)) if ok else text
        return (text, self._tspan(tok))

    def _valued(tag):  # noqa: N805 - a small factory of clause callbacks
        @v_args(meta=True)
        def cb(self, meta, ch):
            free = ch[1] if len(ch) > 1 and isinstance(ch[1], _Free) else None
            return _Clause(tag, self._e(ch[0]), self._span(meta), free)

        return cb

    sensor_lag = _valued("lag")
    sensor_offset = _valued("offset")
    rad_area = _valued("area")
    rad_emissivity = _valued("emissivity")
    rad_view_factor = _valued("view_factor")
    pe_current = _valued("current")
    pe_seebeck = _valued("seebeck")
    pe_resistance = _valued("resistance")
    pe_r_internal = _valued("R_internal")
    fl_inlet = _valued("inlet")
    fl_mdot = _valued("mdot")
    fl_cp = _valued("cp")
    fl_ua = _valued("UA")
    del _valued

    @v_args(meta=True)
    def pe_hot(self, meta, ch):
        return _Clause("hot", ch[0], self._span(meta))

    @v_args(meta=True)
    def pe_cold(self, meta, ch):
        return _Clause("cold", ch[0], self._span(meta))

    # -- learn ----------------------------------------------------------------------------

    @v_args(meta=True)
    def target_name(self, meta, ch):
        return ("name", str(ch[0]), self._span(meta))

    @v_args(meta=True)
    def target_load(self, meta, ch):
        head = str(ch[0])
        span = self._span(meta)
        if head != "Q":
            self.diags.append(Diagnostic(f"`{head}[...]` is not a learn target", span,
                                         hint="`Q[node]` is a node's extra heat load"))
        return ("load", ch[1][0], span)

    @v_args(meta=True)
    def li_name(self, meta, ch):
        return ("input", str(ch[0]), self._span(meta))

    @v_args(meta=True)
    def li_call(self, meta, ch):
        span = self._span(meta)
        if str(ch[0]) != "T":
            self.diags.append(Diagnostic(f"`{ch[0]}(...)` cannot be a learned-function argument", span,
                                         hint="arguments are nodes (`hx1`, `T3`, `T(hx1)`), inputs or parameters"))
        return ("node", ch[1][0], span)

    @v_args(meta=True)
    def learn_opt(self, meta, ch):
        return ("opt", str(ch[0]), ch[1] if len(ch) > 1 else None, self._span(meta))

    @v_args(meta=True)
    def opt_name(self, meta, ch):
        return ("name", str(ch[0]))

    @v_args(meta=True)
    def opt_string(self, meta, ch):
        return ("string", _unquote(ch[0]))

    @v_args(meta=True)
    def opt_list(self, meta, ch):
        return ("list", list(ch))

    @v_args(meta=True)
    def learn_args(self, meta, ch):
        return ("args", list(ch))

    # -- statements -----------------------------------------------------------------------

    def _st(self, kind, meta, data=None, clauses=None):
        return _St(kind, self._span(meta), dict(data or {}), list(clauses or []), self.filename)

    @v_args(meta=True)
    def network(self, meta, ch):
        lab = ch[1].value if len(ch) > 1 else None
        return self._st("network", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0]), "label": lab})

    @v_args(meta=True)
    def units(self, meta, ch):
        return self._st("units", meta, {"unit": str(ch[0]), "unit_span": self._tspan(ch[0])})

    @v_args(meta=True)
    def include(self, meta, ch):
        return self._st("include", meta, {"path": _unquote(ch[0])})

    @v_args(meta=True)
    def input_unit(self, meta, ch):
        return ("unit", str(ch[0])[1:-1].strip(), self._tspan(ch[0]))

    @v_args(meta=True)
    def input_temperature(self, meta, ch):
        return ("temperature", None, self._span(meta))

    @v_args(meta=True)
    def input(self, meta, ch):
        return self._st("input", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0]), "type": ch[1]},
                        [c for c in ch[2:]])

    @v_args(meta=True)
    def param(self, meta, ch):
        rest = ch[2:]
        free = next((c for c in rest if isinstance(c, _Free)), None)
        return self._st("param", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0]), "expr": self._e(ch[1]),
                                        "free": free}, [c for c in rest if isinstance(c, _Clause)])

    @v_args(meta=True)
    def node(self, meta, ch):
        nid = ch[0]
        clauses = [c for c in ch[1:] if isinstance(c, _Clause)]
        expr = next(self._e(c) for c in ch[1:] if not isinstance(c, (_Clause, _Free)))
        free = next((c for c in ch[1:] if isinstance(c, _Free)), None)
        return self._st("node", meta, {"name": nid[0], "name_span": nid[1], "expr": expr, "free": free}, clauses)

    @v_args(meta=True)
    def boundary(self, meta, ch):
        nid = ch[0]
        clauses = [c for c in ch[1:] if isinstance(c, _Clause)]
        expr = next(self._e(c) for c in ch[1:] if not isinstance(c, _Clause))
        return self._st("boundary", meta, {"name": nid[0], "name_span": nid[1], "expr": expr}, clauses)

    @v_args(meta=True)
    def link(self, meta, ch):
        kind = str(ch[0])
        a, b = ch[1], ch[2]
        rest = ch[3:]
        clauses = [c for c in rest if isinstance(c, _Clause)]
        frees = [c for c in rest if isinstance(c, _Free)]
        expr = next(self._e(c) for c in rest if not isinstance(c, (_Clause, _Free)))
        if len(frees) > 1:
            self.diags.append(Diagnostic("`free` is given twice", frees[1].span))
        return self._st("link", meta, {"form": kind, "a": a, "b": b, "expr": expr,
                                       "free": frees[0] if frees else None}, clauses)

    @v_args(meta=True)
    def source(self, meta, ch):
        return self._st("source", meta, {"node": ch[0], "expr": self._e(ch[1])}, ch[2:])

    @v_args(meta=True)
    def sensor(self, meta, ch):
        clauses = list(ch[1:])
        node = next(c for c in clauses if isinstance(c, tuple))
        clauses = [c for c in clauses if not isinstance(c, tuple)]
        return self._st("sensor", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0]), "node": node}, clauses)

    @v_args(meta=True)
    def radiation(self, meta, ch):
        return self._st("radiation", meta, {"a": ch[0], "b": ch[1]}, ch[2:])

    @v_args(meta=True)
    def peltier(self, meta, ch):
        return self._st("peltier", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0])}, ch[1:])

    @v_args(meta=True)
    def fluid(self, meta, ch):
        clauses = [c for c in ch[1:] if isinstance(c, _Clause)]
        node = next(c for c in ch[1:] if isinstance(c, tuple))
        return self._st("fluid", meta, {"name": str(ch[0]), "name_span": self._tspan(ch[0]), "node": node}, clauses)

    @v_args(meta=True)
    def learn(self, meta, ch):
        targets = [c for c in ch if isinstance(c, tuple) and c[0] in ("name", "load")]
        kind_tok = next(c for c in ch if isinstance(c, Token))
        args = next((c[1] for c in ch if isinstance(c, tuple) and c[0] == "args"), None)
        trailing = [c for c in ch if isinstance(c, tuple) and c[0] == "opt"]
        inputs = [a for a in (args or []) if a[0] != "opt"]
        opts = [a for a in (args or []) if a[0] == "opt"] + trailing
        return self._st("learn", meta, {"targets": targets, "kind": str(kind_tok), "kind_span": self._tspan(kind_tok),
                                        "inputs": inputs, "opts": opts, "has_args": args is not None})

    @v_args(meta=True)
    def subnet_params(self, meta, ch):
        return ("params", [(str(t), self._tspan(t)) for t in ch])

    @v_args(meta=True)
    def subnet(self, meta, ch):
        name = str(ch[0])
        params = next((c[1] for c in ch[1:] if isinstance(c, tuple) and c[0] == "params"), [])
        lab = next((c.value for c in ch[1:] if isinstance(c, _Clause)), None)
        body = [c for c in ch[1:] if isinstance(c, _St)]
        return self._st("subnet", meta, {"name": name, "name_span": self._tspan(ch[0]), "params": params,
                                         "label": lab, "body": body})

    @v_args(meta=True)
    def use_arg(self, meta, ch):
        return ("arg", str(ch[0]), self._e(ch[1]), self._span(meta))

    @v_args(meta=True)
    def use_args(self, meta, ch):
        return ("args", list(ch))

    @v_args(meta=True)
    def use(self, meta, ch):
        args = next((c[1] for c in ch if isinstance(c, tuple) and c[0] == "args"), [])
        names = [c for c in ch if isinstance(c, Token)]
        return self._st("use", meta, {"subnet": str(names[0]), "subnet_span": self._tspan(names[0]),
                                      "inst": str(names[1]), "inst_span": self._tspan(names[1]), "args": args})

    def start(self, ch):
        return [c for c in ch if isinstance(c, _St)]


def _unquote(tok) -> str:
    s = str(tok)[1:-1]
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s)


# ---------------------------------------------------------------------------------------------
# Reading files
# ---------------------------------------------------------------------------------------------


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


def _check_nesting(text: str, filename: str) -> None:
    """Brackets nested deeper than ``MAX_NESTING`` are an error (the trees are walked recursively)."""
    depth = 0
    line, col = 1, 0
    in_str = in_comment = False
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
            continue
        if ch == '"':
            in_str = True
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


def _statements(text: str, filename: str, sources: dict[str, str]) -> list[_St]:
    sources[filename] = text
    _check_nesting(text, filename)
    tree, diags = _parse_text(text, filename)
    if diags:
        raise TnnError(diags, sources=sources)
    tdiags: list[Diagnostic] = []
    try:
        stmts = _ToStatements(filename, tdiags).transform(tree)
    except VisitError as err:  # pragma: no cover - a bug in a callback
        raise err.orig_exc from None
    if tdiags:
        raise TnnError(tdiags, sources=sources)
    return stmts


# ---------------------------------------------------------------------------------------------
# Statements -> IR
# ---------------------------------------------------------------------------------------------

_T_NUM = re.compile(r"^T(\d+)$")


class _Scope:
    """Name resolution while expanding subnets. The top scope maps every name to itself; an instance
    scope maps the names declared in the subnet body to ``<inst>.<name>``, the subnet parameters to
    their argument expressions, and everything else through the enclosing scope."""

    def __init__(self, prefix: str = "", local: set[str] | None = None, subst: dict | None = None,
                 parent: "_Scope | None" = None, chain: tuple[str, ...] = ()):
        self.prefix = prefix
        self.local = local or set()
        self.subst = subst or {}
        self.parent = parent
        self.chain = chain

    def decl(self, name: str | None) -> str | None:
        return None if name is None else self.prefix + name

    def name(self, name: str) -> str:
        """A referenced element/param name (dotted `pe.seebeck` resolves through its head)."""
        if self.parent is None:
            return name
        if name in self.local:
            return self.prefix + name
        head = name.split(".", 1)[0]
        if head in self.local:
            return self.prefix + name
        m = _T_NUM.match(name)
        if m and m.group(1) in self.local:
            return self.prefix + m.group(1)  # `T3` of a local node 3: that node (learn arguments)
        return self.parent.name(name)

    def node(self, name: str) -> str:
        if self.parent is None or name in self.subst:
            return name if self.parent is None else self._subst_node(name)
        if name in self.local or name.split(".", 1)[0] in self.local:
            return self.prefix + name
        return self.parent.node(name)

    def _subst_node(self, name: str) -> str:
        e = self.subst[name]
        if isinstance(e, Ref):
            return e.name
        if isinstance(e, Temp):
            return e.node
        return name

    def expr(self, e):
        """Rename the names of an expression for this scope."""
        if self.parent is None:
            return e
        if isinstance(e, Ref):
            if e.name in self.subst:
                return self.subst[e.name]
            m = _T_NUM.match(e.name)
            if m and m.group(1) in self.local and e.name not in self.local:
                return Temp(node=self.prefix + m.group(1), span=e.span)
            if e.name in self.local or e.name.split(".", 1)[0] in self.local:
                return e.model_copy(update={"name": self.prefix + e.name})
            return self.parent.expr(e)
        if isinstance(e, Temp):
            return e.model_copy(update={"node": self.node(e.node)})
        if isinstance(e, Unary):
            return e.model_copy(update={"arg": self.expr(e.arg)})
        if isinstance(e, Binary):
            return e.model_copy(update={"left": self.expr(e.left), "right": self.expr(e.right)})
        if isinstance(e, Call):
            return e.model_copy(update={"args": [self.expr(a) for a in e.args]})
        if isinstance(e, Table):
            return e.model_copy(update={"x": self.expr(e.x)})
        return e


def _declared_names(body: list[_St]) -> set[str]:
    out: set[str] = set()
    for st in body:
        d = st.data
        if st.kind in ("param", "sensor", "peltier", "fluid"):
            out.add(d["name"])
        elif st.kind in ("node", "boundary"):
            out.add(d["name"])
        elif st.kind == "use":
            out.add(d["inst"])
        for c in st.clauses:
            if c.tag == "as":
                out.add(c.value)
    return out


_ROLE_OF_KEY = {
    "lag": "time_constant", "offset": "offset", "area": "component", "emissivity": "component",
    "view_factor": "component", "current": "component", "seebeck": "component", "resistance": "component",
    "R_internal": "resistance", "inlet": "temperature", "mdot": "component", "cp": "component", "UA": "component",
}

_LEARN_KINDS = ("const", "linear", "poly", "mlp", "table")
_ACTIVATIONS = ("sigmoid", "tanh", "relu", "softplus", "silu")
_LEARN_OPTIONS = {
    "const": ("frozen", "init_from", "replace"),
    "linear": ("frozen", "init_from", "replace"),
    "poly": ("degree", "frozen", "init_from", "replace"),
    "mlp": ("hidden", "activation", "frozen", "init_from", "replace"),
    "table": ("knots", "frozen", "init_from", "replace"),
}
DEFAULT_HIDDEN = [8, 8]
DEFAULT_DEGREE = 2


class _Builder:
    def __init__(self, sources: dict[str, str]):
        self.sources = sources
        self.diags: list[Diagnostic] = []
        self.name: str | None = None
        self.label: str | None = None
        self.temperature_unit = "degC"
        self.files: list[str] = []
        self.params: list[Param] = []
        self.inputs: list[Input] = []
        self.nodes: list[ThermalNode] = []
        self.boundaries: list[Boundary] = []
        self.links: list[Link] = []
        self.radiations: list[Radiation] = []
        self.peltiers: list[Peltier] = []
        self.fluids: list[Fluid] = []
        self.sources_: list[Source] = []
        self.sensors: list[Sensor] = []
        self.learn_stmts: list[tuple[_St, _Scope]] = []
        self.subnets: dict[str, _St] = {}
        self.auto_counts: dict[str, int] = {}

    # -- helpers --------------------------------------------------------------------------

    def err(self, msg: str, span: Span | None, hint: str | None = None, related=()):
        self.diags.append(Diagnostic(msg, span, hint=hint, related=tuple(related)))

    def auto(self, base: str) -> str:
        n = self.auto_counts.get(base, 0) + 1
        self.auto_counts[base] = n
        return base if n == 1 else f"{base}_{n}"

    def temp_literal(self, e):
        """A bare number in a temperature slot is in the file's temperature unit."""
        if isinstance(e, Num) and e.unit is None and not e.dim:
            scale, offset = unit_scale(self.temperature_unit)
            return e.model_copy(update={"value": e.value * scale + offset, "dim": {"K": 1.0},
                                        "unit": self.temperature_unit})
        return e

    def bound(self, q: _Q, value_unit: str | None, temp_slot: bool) -> tuple[float, dict] | None:
        unit = q.unit
        if unit is None:
            unit = value_unit if value_unit is not None else (self.temperature_unit if temp_slot else None)
        try:
            return parse_quantity(q.number, unit)
        except UnitError as err:
            self.err(err.message, q.span, err.hint)
            return None

    def slot(self, name: str, expr, role: str, owner: str | None, span: Span, free: _Free | None = None,
             label: str | None = None, temp_slot: bool = False) -> str:
        if temp_slot:
            expr = self.temp_literal(expr)
        lower = upper = None
        if free is not None and (free.lo is not None or free.hi is not None):
            vunit = expr.unit if isinstance(expr, Num) else None
            vdim = expr.dim if isinstance(expr, Num) else None
            for which, q in (("lower", free.lo), ("upper", free.hi)):
                res = self.bound(q, vunit, temp_slot)
                if res is None:
                    continue
                val, dim = res
                if vdim is not None and (q.unit is not None) and not dim_eq(dim, vdim):
                    self.err(f"the {which} bound `{q.text}` is in `{format_dim(dim)}` but the value is in "
                             f"`{format_dim(vdim)}`", q.span, hint="bounds use the unit of the value")
                if which == "lower":
                    lower = val
                else:
                    upper = val
        p = Param(name=name, expr=expr, dim=expr.dim if isinstance(expr, Num) else {},
                  unit=expr.unit if isinstance(expr, Num) else None, role=role, free=free is not None,
                  lower=lower, upper=upper, owner=owner, label=label, span=span)
        self.params.append(p)
        return name

    @staticmethod
    def label_of(st: _St) -> str | None:
        labs = [c.value for c in st.clauses if c.tag == "label"]
        return labs[0] if labs else None

    def single(self, st: _St, tag: str) -> _Clause | None:
        cs = [c for c in st.clauses if c.tag == tag]
        if len(cs) > 1:
            self.err(f"`{tag}` is given twice in this {st.kind}", cs[1].span, related=[("first given here", cs[0].span)])
        return cs[0] if cs else None

    # -- files ----------------------------------------------------------------------------

    def run_file(self, stmts: list[_St], filename: str, scope: _Scope, main: bool, include_chain: tuple[str, ...]):
        self.files.append(filename)
        if main:
            # `network` and `units` apply to the whole file wherever they are written
            nets = [s for s in stmts if s.kind == "network"]
            if not nets:
                first = stmts[0].span if stmts else Span(file=filename, line=1, col=1, end_line=1, end_col=1)
                self.err("missing `network NAME` at the top of the file" if stmts else "the file is empty",
                         Span(file=filename, line=1, col=1, end_line=1, end_col=1) if not stmts else first,
                         hint='a network file starts with `network NAME "label"`')
            else:
                self.name = nets[0].data["name"]
                self.label = nets[0].data["label"]
                for extra in nets[1:]:
                    self.err("`network` is given twice", extra.span, related=[("first given here", nets[0].span)])
            units = [s for s in stmts if s.kind == "units"]
            for u in units[:1]:
                unit = u.data["unit"]
                canon = {"degC": "degC", "K": "K", "degF": "degF", "celsius": "degC", "kelvin": "K",
                         "fahrenheit": "degF"}.get(unit)
                if canon is None:
                    self.err(f"unknown temperature unit `{unit}`", u.data["unit_span"],
                             hint="write `units temperature = degC`, `K` or `degF`")
                else:
                    self.temperature_unit = canon
            for extra in units[1:]:
                self.err("`units` is given twice", extra.span, related=[("first given here", units[0].span)])
        for st in stmts:
            if st.kind in ("network", "units"):
                if not main:
                    self.err(f"`{st.kind}` in an included file", st.span,
                             hint="only the main file names the network and its temperature unit")
                continue
            self.statement(st, scope, include_chain)

    def include(self, st: _St, scope: _Scope, chain: tuple[str, ...]):
        rel = st.data["path"]
        shown = os.path.normpath(os.path.join(os.path.dirname(st.file), rel)) if os.path.exists(st.file) else rel
        path = os.path.abspath(shown)
        key = os.path.realpath(path)
        if key in chain:
            names = " -> ".join(os.path.basename(c) for c in (*chain, key))
            self.err(f"include cycle: {names}", st.span, hint="a file cannot include itself, even indirectly")
            return
        if len(chain) > MAX_INCLUDE_DEPTH:
            self.err("includes nested too deeply", st.span)
            return
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError as e:
            self.err(f"cannot read the included file `{rel}`: {e.strerror or e}", st.span,
                     hint="include paths are relative to the including file")
            return
        try:
            text = _decode(data, shown)
            stmts = _statements(text, shown, self.sources)
        except TnnError as e:
            self.diags.extend(e.diagnostics)
            return
        self.run_file(stmts, shown, scope, main=False, include_chain=(*chain, key))

    # -- statements -----------------------------------------------------------------------

    def statement(self, st: _St, scope: _Scope, chain: tuple[str, ...]):
        getattr(self, "st_" + st.kind)(st, scope, chain)

    def st_include(self, st, scope, chain):
        if scope.parent is not None:
            self.err("`include` inside a subnet", st.span, hint="include files at the top level")
            return
        self.include(st, scope, chain)

    def st_input(self, st, scope, chain):
        d = st.data
        if scope.parent is not None:
            self.err("`input` inside a subnet", st.span,
                     hint="inputs belong to the network; declare them at the top level and use them inside")
            return
        kind, unit, uspan = d["type"]
        col = self.single(st, "column")
        lab = self.label_of(st)
        if kind == "temperature":
            inp = Input(name=d["name"], dim={"K": 1.0}, unit=self.temperature_unit, is_temperature=True,
                        column=col.value if col else d["name"], label=lab, span=st.span)
        else:
            try:
                _, dim = parse_quantity(1.0, unit if unit not in ("", "1") else None)
            except UnitError as e:
                self.err(e.message, uspan, e.hint)
                dim = {}
            is_t = unit in TEMPERATURE_UNITS
            inp = Input(name=d["name"], dim=dim, unit=unit or "1", is_temperature=is_t,
                        column=col.value if col else d["name"], label=lab, span=st.span)
        self.inputs.append(inp)

    def st_param(self, st, scope, chain):
        d = st.data
        self.slot(scope.decl(d["name"]), scope.expr(d["expr"]), "generic", None, st.span, d["free"],
                  self.label_of(st))

    def st_node(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        p = self.slot(scope.decl(f"C_{d['name']}"), scope.expr(d["expr"]), "capacitance", f"node {name}", st.span, d["free"])
        self.nodes.append(ThermalNode(name=name, capacitance=p, label=self.label_of(st), span=st.span))

    def st_boundary(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        p = self.slot(scope.decl(f"T_{d['name']}"), scope.expr(d["expr"]), "temperature", f"boundary {name}", st.span,
                      temp_slot=True)
        self.boundaries.append(Boundary(name=name, temperature=p, label=self.label_of(st), span=st.span))

    def st_link(self, st, scope, chain):
        d = st.data
        a, b = scope.node(d["a"][0]), scope.node(d["b"][0])
        as_ = self.single(st, "as")
        form = d["form"]
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"{form}_{d['a'][0]}_{d['b'][0]}"))
        role = "resistance" if form == "R" else "conductance"
        self.slot(name, scope.expr(d["expr"]), role, f"link {name}", st.span, d["free"])
        self.links.append(Link(name=name, a=a, b=b, form=form, value=name, label=self.label_of(st), span=st.span))

    def st_source(self, st, scope, chain):
        d = st.data
        node = scope.node(d["node"][0])
        as_ = self.single(st, "as")
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"Q_src_{d['node'][0]}"))
        self.slot(name, scope.expr(d["expr"]), "heat_flow", f"source {name}", st.span, label=self.label_of(st))
        self.sources_.append(Source(name=name, node=node, value=name, span=st.span))

    def st_sensor(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        node = scope.node(d["node"][0])
        lag = self.single(st, "lag")
        off = self.single(st, "offset")
        col = self.single(st, "column")
        lag_p = off_p = None
        if lag is not None:
            lag_p = self.slot(f"{name}.lag", scope.expr(lag.value), "time_constant", f"sensor {name}", lag.span, lag.free)
        if off is not None:
            off_p = self.slot(f"{name}.offset", scope.expr(off.value), "offset", f"sensor {name}", off.span, off.free)
        self.sensors.append(Sensor(name=name, node=node, column=col.value if col else name, lag=lag_p, offset=off_p,
                                   label=self.label_of(st), span=st.span))

    def _component(self, st, scope, cname, keys, required, owner):
        out = {}
        for key in keys:
            c = self.single(st, key)
            if c is None:
                if key in required:
                    self.err(f"{owner} needs `{key} = ...`", st.span, hint=f"add `{key} = VALUE` to the statement")
                out[key] = None
                continue
            out[key] = self.slot(f"{cname}.{key}", scope.expr(c.value), _ROLE_OF_KEY[key], owner, c.span, c.free,
                                 temp_slot=key == "inlet")
        return out

    def st_radiation(self, st, scope, chain):
        d = st.data
        a, b = scope.node(d["a"][0]), scope.node(d["b"][0])
        as_ = self.single(st, "as")
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"rad_{d['a'][0]}_{d['b'][0]}"))
        owner = f"radiation {name}"
        out = self._component(st, scope, name, ("area", "emissivity", "view_factor"), ("area", "emissivity"), owner)
        if out["view_factor"] is None:
            out["view_factor"] = self.slot(f"{name}.view_factor", Num(value=1.0, span=st.span), "component", owner,
                                           st.span)
        self.radiations.append(Radiation(name=name, a=a, b=b, area=out["area"] or f"{name}.area",
                                         emissivity=out["emissivity"] or f"{name}.emissivity",
                                         view_factor=out["view_factor"], span=st.span))

    def st_peltier(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        owner = f"peltier {name}"
        hot, cold = self.single(st, "hot"), self.single(st, "cold")
        for key, c in (("hot", hot), ("cold", cold)):
            if c is None:
                self.err(f"{owner} needs `{key} = NODE`", st.span, hint=f"add `{key} = NODE` to the statement")
        out = self._component(st, scope, name, ("current", "seebeck", "resistance", "R_internal"),
                              ("current", "seebeck", "resistance"), owner)
        self.peltiers.append(Peltier(
            name=name, hot=scope.node(hot.value[0]) if hot else "?", cold=scope.node(cold.value[0]) if cold else "?",
            current=out["current"] or f"{name}.current", seebeck=out["seebeck"] or f"{name}.seebeck",
            resistance=out["resistance"] or f"{name}.resistance", r_internal=out["R_internal"], span=st.span))

    def st_fluid(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        owner = f"fluid {name}"
        out = self._component(st, scope, name, ("inlet", "mdot", "cp", "UA"), ("inlet", "mdot", "cp", "UA"), owner)
        self.fluids.append(Fluid(name=name, node=scope.node(d["node"][0]), inlet=out["inlet"] or f"{name}.inlet",
                                 mdot=out["mdot"] or f"{name}.mdot", cp=out["cp"] or f"{name}.cp",
                                 ua=out["UA"] or f"{name}.UA", span=st.span))

    def st_learn(self, st, scope, chain):
        self.learn_stmts.append((st, scope))

    def st_subnet(self, st, scope, chain):
        name = st.data["name"]
        if scope.parent is not None:
            self.err("a `subnet` cannot be defined inside another subnet", st.span,
                     hint="define subnets at the top level; `use` may appear inside a subnet")
            return
        if name in self.subnets:
            self.err(f"subnet `{name}` is defined twice", st.data["name_span"],
                     related=[("first defined here", self.subnets[name].data["name_span"])])
            return
        for sub in st.data["body"]:
            if sub.kind in ("network", "units", "include", "input"):
                self.err(f"`{sub.kind}` inside a subnet", sub.span,
                         hint="a subnet holds nodes, boundaries, links, components, sources, sensors, params, learn and use")
        seen: dict[str, Span] = {}
        for p, pspan in st.data["params"]:
            if p in seen:
                self.err(f"subnet parameter `{p}` is listed twice", pspan, related=[("first listed here", seen[p])])
            seen[p] = pspan
        self.subnets[name] = st

    def st_use(self, st, scope, chain):
        d = st.data
        sub = self.subnets.get(d["subnet"])
        if sub is None:
            known = ", ".join(sorted(self.subnets)) or "none defined"
            self.err(f"unknown subnet `{d['subnet']}`", d["subnet_span"],
                     hint=f"subnets must be defined before they are used (known: {known})")
            return
        if d["subnet"] in scope.chain:
            self.err(f"subnet `{d['subnet']}` uses itself", st.span, hint="subnets cannot be recursive")
            return
        if len(scope.chain) >= MAX_SUBNET_DEPTH:
            self.err("subnets nested too deeply", st.span)
            return
        params = {p for p, _ in sub.data["params"]}
        subst = {}
        for _tag, pname, expr, aspan in d["args"]:
            if pname not in params:
                listed = ", ".join(p for p, _ in sub.data["params"]) or "none"
                self.err(f"subnet `{d['subnet']}` has no parameter `{pname}`", aspan, hint=f"its parameters: {listed}")
                continue
            if pname in subst:
                self.err(f"argument `{pname}` is given twice", aspan)
                continue
            subst[pname] = scope.expr(expr)
        missing = [p for p, _ in sub.data["params"] if p not in subst]
        if missing:
            self.err(f"`use {d['subnet']}` is missing the argument{'s' if len(missing) > 1 else ''} "
                     f"{', '.join('`' + m + '`' for m in missing)}", st.span,
                     hint="give every subnet parameter: `use NAME(P = VALUE, ...) as INSTANCE`")
            return
        inst = scope.decl(d["inst"])
        body = [b for b in sub.data["body"] if b.kind not in ("network", "units", "include", "input")]
        local = _declared_names(body)
        inner = _Scope(prefix=inst + ".", local=local, subst=subst, parent=scope, chain=(*scope.chain, d["subnet"]))
        for b in body:
            self.statement(b, inner, chain)

    # -- learn (after everything is declared) ---------------------------------------------

    def build_learned(self) -> list[LearnFunction]:
        taken = {p.name.split(".")[0] for p in self.params} | {x.name for x in self.inputs}
        taken |= {x.name for x in (*self.nodes, *self.boundaries, *self.links, *self.radiations, *self.peltiers,
                                   *self.fluids, *self.sources_, *self.sensors)}
        node_names = {n.name for n in self.nodes} | {b.name for b in self.boundaries}
        out = []
        for st, scope in self.learn_stmts:
            fname = _function_name(st.data["targets"], taken)
            taken.add(fname)
            out.append(self.learn(st, scope, fname, node_names))
        return [f for f in out if f is not None]

    def learn(self, st: _St, scope: _Scope, fname: str, node_names: set[str]) -> LearnFunction | None:
        d = st.data
        kind = d["kind"]
        if kind not in _LEARN_KINDS:
            self.err(f"unknown learned-function kind `{kind}`", d["kind_span"],
                     hint="kinds are const, linear, poly, mlp and table")
            return None
        targets = []
        for tkind, tname, tspan in d["targets"]:
            if tkind == "load":
                targets.append(LearnTarget(kind="heat_load", name=scope.node(tname), span=tspan))
                continue
            resolved = scope.name(tname)
            if resolved.rsplit(".", 1)[-1] in ("Q_hot", "Q_cold", "Q") and "." in resolved:
                targets.append(LearnTarget(kind="flow", name=resolved, span=tspan))
            else:
                targets.append(LearnTarget(kind="param", name=resolved, span=tspan))
        inputs = []
        for ikind, iname, ispan in d["inputs"]:
            if ikind == "node":
                inputs.append(LearnInput(kind="node", name=scope.node(iname), span=ispan))
                continue
            if iname in scope.subst:
                e = scope.subst[iname]
                if isinstance(e, Ref):
                    inputs.append(LearnInput(name=e.name, span=ispan))
                elif isinstance(e, Temp):
                    inputs.append(LearnInput(kind="node", name=e.node, span=ispan))
                else:
                    self.err(f"learned-function argument `{iname}` is an expression here", ispan,
                             hint="arguments must be names of nodes, inputs or parameters")
                continue
            resolved = scope.name(iname)
            inputs.append(LearnInput(name=resolved, span=ispan))
        opts: dict[str, Any] = {}
        allowed = _LEARN_OPTIONS[kind]
        for _tag, oname, oval, ospan in d["opts"]:
            if oname not in ("hidden", "activation", "degree", "knots", "frozen", "init_from", "replace"):
                self.err(f"unknown option `{oname}` for `{kind}`", ospan, hint="options of `" + kind + "`: " + ", ".join(allowed))
                continue
            if oname not in allowed:
                self.err(f"`{oname}` is not an option of `{kind}`", ospan, hint="options of `" + kind + "`: " + ", ".join(allowed))
                continue
            if oname in opts:
                self.err(f"option `{oname}` is given twice", ospan)
                continue
            opts[oname] = (oval, ospan)
        fn: dict[str, Any] = {"name": fname, "kind": kind, "targets": targets, "inputs": inputs, "span": st.span}
        for flag in ("frozen", "replace"):
            if flag in opts:
                val, ospan = opts[flag]
                if val is not None:
                    self.err(f"`{flag}` is a flag: write it without a value", ospan)
                fn[flag] = True
        if "init_from" in opts:
            val, ospan = opts["init_from"]
            if not (isinstance(val, tuple) and val[0] == "string"):
                self.err("`init_from` takes a quoted model directory", ospan, hint='write `init_from = "models/m4"`')
            else:
                base = os.path.dirname(os.path.abspath(st.file)) if os.path.exists(st.file) else os.getcwd()
                fn["init_from"] = os.path.normpath(os.path.join(base, val[1]))
        if kind == "mlp":
            hidden = list(DEFAULT_HIDDEN)
            if "hidden" in opts:
                val, ospan = opts["hidden"]
                sizes = self._ints(val, ospan, "hidden", allow_scalar=True)
                if sizes is not None:
                    hidden = sizes
            fn["hidden"] = hidden
            if "activation" in opts:
                val, ospan = opts["activation"]
                if not (isinstance(val, tuple) and val[0] == "name" and val[1] in _ACTIVATIONS):
                    self.err("unknown activation", ospan, hint="activations: " + ", ".join(_ACTIVATIONS))
                else:
                    fn["activation"] = val[1]
        if kind == "poly":
            deg = DEFAULT_DEGREE
            if "degree" in opts:
                val, ospan = opts["degree"]
                v = self._ints(val, ospan, "degree", allow_scalar=True, scalar_only=True)
                if v is not None:
                    deg = v[0]
            fn["degree"] = deg
        if kind == "const" and inputs:
            self.err("`const` takes no arguments", st.span, hint="write `learn TARGET as const`")
        if kind in ("linear", "poly", "mlp") and not inputs:
            self.err(f"`{kind}` needs at least one argument", d["kind_span"],
                     hint=f"write `as {kind}(hx1, u1)` with the nodes, inputs or parameters it depends on")
        if kind == "table":
            if len(inputs) != 1:
                self.err("a learned `table` has exactly one argument", d["kind_span"],
                         hint="write `as table(T(hx1); knots = [0 degC, 25 degC, 50 degC])`")
            if "knots" not in opts:
                self.err("a learned `table` needs `knots = [...]`", d["kind_span"],
                         hint="write `as table(x; knots = [0 degC, 25 degC, 50 degC])`")
            else:
                val, ospan = opts["knots"]
                is_node = bool(inputs) and (inputs[0].kind == "node" or inputs[0].name in node_names)
                fn["knots"] = self._knots(val, ospan, is_node)
        return LearnFunction(**fn)

    def _ints(self, val, span, what, allow_scalar=False, scalar_only=False):
        items = None
        if isinstance(val, tuple) and val[0] == "list" and not scalar_only:
            items = val[1]
        elif isinstance(val, _Q) and allow_scalar:
            items = [val]
        if items is None:
            self.err(f"`{what}` takes {'a whole number' if scalar_only else 'a list of layer sizes'}", span,
                     hint="e.g. `degree = 2`" if scalar_only else "e.g. `hidden = [8, 8]`")
            return None
        out = []
        for q in items:
            if q.unit is not None or not float(q.number).is_integer() or q.number < (0 if scalar_only else 1) or q.number > 100000:
                self.err(f"`{what}` must be {'a whole number' if scalar_only else 'whole numbers of at least 1'}, "
                         f"got `{q.text}`", q.span)
                return None
            out.append(int(q.number))
        if not out and not scalar_only:
            self.err(f"`{what}` is empty", span, hint="e.g. `hidden = [8, 8]`")
            return None
        return out

    def _knots(self, val, span, temp):
        if not (isinstance(val, tuple) and val[0] == "list"):
            self.err("`knots` takes a list of values", span, hint="e.g. `knots = [0 degC, 25 degC, 50 degC]`")
            return []
        out = []
        for q in val[1]:
            unit = q.unit if q.unit is not None else (self.temperature_unit if temp else None)
            try:
                v, _ = parse_quantity(q.number, unit)
            except UnitError as e:
                self.err(e.message, q.span, e.hint)
                return []
            out.append(v)
        if len(out) < 2:
            self.err("`knots` needs at least two values", span)
        elif any(b <= a for a, b in zip(out, out[1:])):
            self.err("`knots` must be strictly increasing", span)
        return out

    def network(self) -> Network:
        learned = self.build_learned()
        return Network(
            name=self.name or "unnamed", label=self.label, temperature_unit=self.temperature_unit,
            source_files=list(dict.fromkeys(self.files)), params=self.params, inputs=self.inputs, nodes=self.nodes,
            boundaries=self.boundaries, links=self.links, radiations=self.radiations, peltiers=self.peltiers,
            fluids=self.fluids, sources=self.sources_, sensors=self.sensors, learned=learned,
        )


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


def _function_name(targets, taken: set[str]) -> str:
    """A learned function's name: ``fn_`` + its first target, dots and brackets folded to ``_``
    (``fn_R_hp1``, ``fn_pe_Q_hot``, ``fn_Q_hx2``); ``_2``, ``_3`` … if that is taken. Stable across
    files that learn the same target (M4's Peltier net and M5's share ``fn_pe_Q_hot``)."""
    first = targets[0][1] if targets else "learned"
    if targets and targets[0][0] == "load":
        first = f"Q_{first}"
    base = "fn_" + re.sub(r"[^A-Za-z0-9_]+", "_", str(first)).strip("_")
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    return name
