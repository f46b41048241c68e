"""``tnnc``: the command-line front end. Every command is a thin layer over the public Python API.

Each command lives in its own module ``tnn_dsl/cli/_<command>.py`` exposing

    def register(subparsers) -> None   # adds its argparse sub-parser and sets ``func=run``
    def run(args) -> int               # exit status

Problems the user can fix raise :class:`tnn_dsl.TnnError` (printed, exit 1). Anything else is an
internal error: a one-line message and exit 2 (``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

# command name -> module (in tnn_dsl.cli); listed here in the order `tnnc --help` shows them.
COMMANDS = {
    "check": "_check",
    "compile": "_compile",
    "simulate": "_simulate",
    "train": "_train",
    "evaluate": "_evaluate",
    "inspect": "_inspect",
    "sensitivity": "_sensitivity",
    "excitation": "_excitation",
    "diagnose": "_diagnose",
    "generate": "_generate",
    "estimate": "_estimate",
    "compare": "_compare",
    "fleet": "_fleet",
    "demo": "_demo",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tnnc",
        description="Lumped thermal networks: check, compile, simulate, train, diagnose.",
    )
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks for internal errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in COMMANDS.items():
        if importlib.util.find_spec(f"{__name__}.{module}") is None:
            continue
        importlib.import_module(f"{__name__}.{module}").register(sub)
    return parser


HUGE_PAGE_COMMANDS = frozenset({"diagnose", "demo"})
"""The commands that run the model doctor in this process, whose rounds map and free large blocks by the thousand
(``core.memory.large_blocks_mapped``): :func:`entry` starts them again with glibc's mapped blocks on transparent huge
pages (``core.memory.huge_pages_environment``: the case study's diagnosis 67.6–70.2 s against 75.4–78.4 s; ``demo``'s
trainings, which reuse their buffers, neither faster nor larger: M2 on JAX 23.9–24.3 against 24.4 s, 545 against
547 MB, BENCHMARKS.md). Not
``fleet``: its diagnoses run in Ray's workers, beside Ray's own daemons, which would start with the tunable too
(not measured)."""


def entry() -> None:
    """The ``tnnc`` console script: :func:`main` on the command line. For a command of :data:`HUGE_PAGE_COMMANDS` on a
    machine where glibc's huge-page tunable would change something, the program is first started again (``execve``,
    the same process, arguments and standard streams) in the environment of
    :func:`~tnn_dsl.core.memory.huge_pages_environment`: glibc reads its tunables only when a program starts. Nothing
    has been read or written by then; ``TNN_HUGE_PAGES=0`` turns it off, and a failed ``execve`` runs the command as
    it is. (:func:`main` itself never does this: Python code and the tests call it in their own process.)"""
    argv = sys.argv[1:]
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in HUGE_PAGE_COMMANDS and sys.executable and getattr(sys, "orig_argv", None):
        from ..core.memory import huge_pages_environment

        env = huge_pages_environment()
        if env is not None:
            import os

            sys.stdout.flush()
            sys.stderr.flush()
            try:
                os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
            except OSError:
                pass  # run as it is
    sys.exit(main())


def main(argv: list[str] | None = None) -> int:
    from ..core import TnnError
    from ..core.interrupt import is_interrupt

    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "func", None) is None:
            parser.print_help()
            return 1
        from ..lang import include_path_scope

        with include_path_scope(getattr(args, "include_path", None)):
            return int(args.func(args) or 0)
    except TnnError as err:
        print(err.format(), file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as err:  # noqa: BLE001 - the one place that turns a bug into exit 2
        if is_interrupt(err):  # Ctrl-C that came out of C code as a SystemError (core/interrupt.py)
            print("interrupted", file=sys.stderr)
            return 130
        if debug:
            raise
        print(f"tnnc: internal error: {type(err).__name__}: {err}", file=sys.stderr)
        print("This is a bug in tnnc, not in your files. Re-run with --debug for the traceback.", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
