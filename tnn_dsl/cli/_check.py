"""``tnnc check FILE...``: parse and validate each file, print a short summary of each network.

Exit status 0 when every file is valid, 1 when any has problems (all of them are printed, file by
file). The summary lists nodes, boundaries, links, components, inputs, sensors, free parameters (and how
many of them are per experiment) and learned functions with their number of trainable weights.
"""

from __future__ import annotations

import sys

from ..core import TnnError
from ..ir import Network
from ._common import add_command


def _names(items, limit=12) -> str:
    items = list(items)
    if not items:
        return "-"
    shown = ", ".join(items[:limit])
    return shown + (f", ... ({len(items)})" if len(items) > limit else "")


def summary(net: Network, path: str) -> str:
    """A few lines describing ``net`` (what `tnnc check` prints)."""
    comps = [f"peltier {p.name}" for p in net.peltiers] + [f"fluid {f.name}" for f in net.fluids]
    comps += [f"radiation {r.name}" for r in net.radiations]
    lines = [
        f"{path}: ok: network {net.name}" + (f' "{net.label}"' if net.label else ""),
        f"  nodes       {len(net.nodes):3d}  {_names(n.name for n in net.nodes)}",
        f"  boundaries  {len(net.boundaries):3d}  {_names(b.name for b in net.boundaries)}",
        f"  links       {len(net.links):3d}  {_names(l.name for l in net.links)}",
        f"  components  {len(comps):3d}  {_names(comps)}",
        f"  sources     {len(net.sources):3d}  {_names(s.name for s in net.sources)}",
        f"  inputs      {len(net.inputs):3d}  {_names(i.name for i in net.inputs)}",
        f"  sensors     {len(net.sensors):3d}  {_names(s.name + (' (lag)' if s.lag else '') for s in net.sensors)}",
        f"  free params {len(net.free_params):3d}  "
        + _names(p.name + (" (per experiment)" if p.per_experiment else "") for p in net.free_params),
    ]
    per = [p.name for p in net.free_params if p.per_experiment]
    if per:
        lines.append(f"    of which {len(per)} per experiment (one value per data file)")
    total = 0
    for fn in net.learned:
        n = fn.weight_count()
        total += n
        arch = fn.kind
        if fn.kind == "mlp":
            arch += f"[{', '.join(map(str, fn.hidden))}] {fn.activation}"
        elif fn.kind == "poly":
            arch += f" degree {fn.degree}"
        flags = " frozen" if fn.frozen else ""
        tgts = ", ".join(f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in fn.targets)
        args = ", ".join(i.name for i in fn.inputs)
        lines.append(f"  learn {fn.name}: {tgts} <- {arch}({args}){flags}: {n} weight" + ("" if n == 1 else "s"))
    if net.learned:
        lines.append(f"  learned functions {len(net.learned)}, {total} weights")
    return "\n".join(lines)


def register(subparsers) -> None:
    p = add_command(subparsers, "check", "validate .thn files and summarise them",
                    description="Parse and validate each FILE; print a summary or the problems.")
    p.add_argument("files", nargs="+", metavar="FILE", help=".thn network files")
    p.add_argument("-q", "--quiet", action="store_true", help="print problems only")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..lang import load, magnitude_warnings

    status = 0
    for path in args.files:
        try:
            net = load(path)
        except TnnError as err:
            print(err.format(), file=sys.stderr)
            status = 1
            continue
        for w in magnitude_warnings(net):  # printed with -q too
            print(w.format(), file=sys.stderr)
        if not args.quiet:
            print(summary(net, path))
    return status
