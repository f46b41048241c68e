"""``tnnc compile FILE --emit equations|ir-json|graph|thn [-o OUT]``: the network written out.

* ``equations`` (default): the ODE system per node, component flows, learned functions, parameters.
* ``ir-json``: the validated IR as JSON (``Network.from_json`` reads it back; the round trip is exact).
* ``graph``: Graphviz DOT text; with ``-o NAME.png`` a picture (Graphviz ``dot`` if installed, else
  matplotlib), with ``-o NAME.svg``/``.pdf`` a picture through Graphviz.
* ``thn``: the network printed back as one flat ``.thn`` file from its IR (includes and subnets expanded, values
  in the units written, comments not kept); reading it back gives the same IR. An IR JSON file becomes ``.thn``.

``FILE`` is a ``.thn`` file or an IR JSON file (``*.json``) as ``--emit ir-json`` writes it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

from ..core import IMAGE, JSON, TEXT, THN, Diagnostic, OutputKind, TnnError, atomic_path, write_text_atomic
from ._common import add_command, add_force_flag, check_outputs

EMITS = ("equations", "ir-json", "graph", "thn")


def register(subparsers) -> None:
    p = add_command(
        subparsers, "compile", "write a network out: its equations, its IR as JSON, a picture, or flat .thn",
        description="Write a network out: the ODE system per node (equations), the validated IR as JSON "
                    "(ir-json; round-trips exactly), a picture (graph: DOT text, or PNG/SVG/PDF by the "
                    "-o suffix), or the network printed back as one flat .thn file (thn). FILE may also be an IR "
                    ".json file.",
    )
    p.add_argument("file", metavar="FILE", help="a .thn network, or an IR .json file")
    p.add_argument("--emit", choices=EMITS, default="equations",
                   help="what to write (default: equations)")
    p.add_argument("-o", "--output", metavar="OUT",
                   help="write here instead of stdout; for --emit graph the suffix picks the format "
                        "(.dot, .png, .svg, .pdf)")
    p.add_argument("--ascii", action="store_true",
                   help="equations in plain ASCII (* - ^) instead of · − and superscripts")
    add_force_flag(p)
    p.set_defaults(func=run)


def load_network(path: str):
    """A ``.thn`` file through the parser, or an IR JSON file."""
    if path.endswith(".json"):
        from ..ir import network_from_json

        try:
            with open(path, "rb") as f:
                text = f.read().decode("utf-8")
        except FileNotFoundError:
            raise TnnError(Diagnostic(f"{path}: no such file")) from None
        except UnicodeDecodeError:
            raise TnnError(Diagnostic(f"{path}: not UTF-8 text", hint="IR files are JSON written by "
                                      "`tnnc compile FILE.thn --emit ir-json -o OUT.json`")) from None
        except OSError as err:
            raise TnnError(Diagnostic(f"{path}: cannot read: {err.strerror}")) from None
        from ..lang import validate

        try:  # an edited IR file is held to the checks of a .thn
            return validate(network_from_json(text, path))
        except TnnError as err:
            head = Diagnostic(f"{path}: the IR is not a valid network (the positions below are in the .thn file "
                              "it was written from; the values are the IR's)")
            raise TnnError([head, *err.diagnostics]) from None
    import tnn_dsl

    return tnn_dsl.load(path)


def _write_text(path: str | None, text: str) -> None:
    if path is None or path == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    write_text_atomic(path, text)


def _output_kind(emit: str, out: str) -> OutputKind:
    """What ``-o`` receives: equations are text, the IR is JSON, a picture is DOT text or an image."""
    if emit == "ir-json":
        return JSON
    if emit == "thn":
        return THN
    if emit == "graph":
        return IMAGE if os.path.splitext(out)[1].lower() in IMAGE.suffixes else OutputKind(
            "Graphviz file", suffixes=(".dot", ".gv"), example="net.dot")
    return TEXT


def run(args) -> int:
    from .. import plots
    from ..ir import emit as _emit

    out = args.output
    if out and out != "-":
        check_outputs(args, [(out, _output_kind(args.emit, out), "-o")], inputs=[args.file])
    net = load_network(args.file)
    if out and out != "-":  # and the files the network includes
        check_outputs(args, [(out, _output_kind(args.emit, out), "-o")], inputs=[args.file, *net.source_files])
    if args.emit == "equations":
        _write_text(out, _emit.equations(net, ascii_only=args.ascii))
    elif args.emit == "ir-json":
        _write_text(out, _emit.ir_json(net))
    elif args.emit == "thn":
        from ..lang import print_thn

        _write_text(out, print_thn(net))
    else:
        suffix = os.path.splitext(out)[1].lower() if out and out != "-" else ".dot"
        if suffix in (".dot", ".gv"):
            _write_text(out, _emit.dot(net))
        elif suffix == ".png":
            try:
                how = plots.render_png(net, out)
            except OSError as err:
                raise TnnError(Diagnostic(f"{out}: cannot write: {err.strerror}",
                                          hint="check that the directory exists and is writable")) from None
            if how != "graphviz":
                print("note: Graphviz `dot` is not installed; drew the network with matplotlib instead "
                      "(install graphviz, e.g. `apt install graphviz` or `brew install graphviz`, "
                      "for the full labelled picture)", file=sys.stderr)
        elif suffix in (".svg", ".pdf"):
            exe = shutil.which("dot")
            if exe is None:
                raise TnnError(Diagnostic(
                    f"{out}: writing {suffix} needs Graphviz's `dot` program, which is not installed",
                    hint="install graphviz (`apt install graphviz`, `brew install graphviz`, "
                         "`conda install graphviz`), or write `-o NAME.png` (drawn with matplotlib) "
                         "or `-o NAME.dot`"))
            with atomic_path(out) as tmp:
                proc = subprocess.run([exe, f"-T{suffix[1:]}", "-o", str(tmp)], input=_emit.dot(net).encode("utf-8"),
                                      capture_output=True, timeout=120, check=False)
                if proc.returncode != 0:
                    raise TnnError(Diagnostic(f"{out}: graphviz failed: "
                                              f"{proc.stderr.decode('utf-8', 'replace').strip()}"))
        else:
            raise TnnError(Diagnostic(f"{out}: unknown picture format {suffix or '(no suffix)'!r}",
                                      hint="use -o NAME.dot (Graphviz text), NAME.png, NAME.svg or NAME.pdf"))
    return 0
