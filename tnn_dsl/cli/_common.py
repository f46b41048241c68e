"""What the commands share: a sub-parser built from the command module's docstring, the common options
(backend, integrator, time columns, ``--force``), the output checks made before any work
(:func:`tnn_dsl.core.check_output`: never an input, never a file of another kind, writable) and JSON output."""

from __future__ import annotations

import argparse
import os
from typing import Iterable

from ..core import OutputKind, check_output, write_text_atomic

INTEGRATORS = ("euler", "rk4", "expeuler")
"""The integrators every backend offers (``tnn_dsl.compiler.INTEGRATORS``; written here so that the parser is
built without importing the compiler; a test checks that the two agree)."""

FORCE_HELP = ("write even where an existing file or directory of another kind is in the way (a directory's "
              "other files are kept; a file is never deleted to make room for a directory)")


def add_command(subparsers, name: str, help: str, doc: str | None = None,
                description: str | None = None) -> argparse.ArgumentParser:
    """A sub-parser whose ``--help`` text is ``description``, else the command module's docstring ``doc``
    without its first paragraph (the usage line) and without reST double back-quotes."""
    if description is None and doc:
        parts = doc.split("\n\n", 1)
        description = parts[1].replace("``", "") if len(parts) > 1 else None
    p = subparsers.add_parser(name, help=help, description=description,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--include-path", action="append", metavar="DIR", default=[],
                   help="a directory network files may include from besides the main file's directory tree "
                        "(repeatable; also TNN_INCLUDE_PATH)")
    return p


def add_network_and_data(p, data: str = "data", val_help: str = "validation data files") -> None:
    """``NET DATA... [--val VAL...]``: the network and its training and held-out data files."""
    p.add_argument("net", metavar="NET", help="the network (.thn)")
    p.add_argument(data, nargs="+", metavar=data.upper(), help="training data files (CSV or Parquet)")
    p.add_argument("--val", nargs="+", default=None, metavar="VAL", help=val_help)


def add_backend(p, default: str | None = "jax", what: str = "compute backend", shown: str | None = None) -> None:
    """``--backend jax|torch``; ``shown`` is what the help calls the default (``default`` None: the model's)."""
    shown = shown or default or "the model's"
    p.add_argument("--backend", choices=("jax", "torch"), default=default, help=f"{what} (default {shown})")


def add_integration(p, default: str | None = "rk4", default_help: str | None = None) -> None:
    """``--integrator`` and ``--substeps``."""
    p.add_argument("--integrator", choices=INTEGRATORS, default=default,
                   help=f"integrator (default {default_help or default})")
    p.add_argument("--substeps", type=int, default=None, metavar="K",
                   help="integrator sub-steps per data step (default: chosen from the fastest time constant)")


INIT_CHOICES = ("estimate", "filter", "steady", "measured")


_INIT_HELP = {
    "estimate": "estimate (default: fitted to a burn-in at the file's start, not scored; a training file continues "
                "from its fitted state)",
    "filter": "filter (EKF over the burn-in)",
    "steady": "steady (steady state of the first inputs)",
    "measured": "measured (that, with sensed nodes at the first readings)",
}


def add_init(p, choices: tuple[str, ...] = INIT_CHOICES, estimate_help: str | None = None) -> None:
    """``--init`` (one of ``choices``, default estimate) and ``--burn-in SECONDS``: how a free run starts (see
    :mod:`tnn_dsl.fit.initial`); ``estimate_help`` replaces the default rule's description."""
    words = [estimate_help if c == "estimate" and estimate_help else _INIT_HELP[c] for c in choices]
    p.add_argument("--init", choices=choices, default="estimate",
                   help="initial state: " + ", ".join(words[:-1]) + " or " + words[-1])
    p.add_argument("--burn-in", type=float, default=None, metavar="SECONDS", dest="burn_in",
                   help="burn-in for --init " + "/".join(c for c in choices if c in ("estimate", "filter"))
                        + " (default: a tenth of the file, at least 10 samples)")


def add_time_columns(p) -> None:
    """``--time-col``, ``--dt`` and ``--time-unit``: how a data file's time is read."""
    p.add_argument("--time-col", default=None, metavar="NAME", help="the time column (default: detected)")
    p.add_argument("--dt", type=float, default=None, metavar="S", help="model step in s (default: the file's step)")
    p.add_argument("--time-unit", default=None, choices=("s", "ms", "min", "h", "d"),
                   help="unit of a numeric time column (default: from its name, else s)")


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
