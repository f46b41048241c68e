"""A picture of a network: Graphviz's ``dot`` when it is installed (the DOT text of :func:`tnn_dsl.ir.dot`),
else a matplotlib drawing of the networkx graph (learned parts in red, sensors under their nodes)."""

from __future__ import annotations

import math
import shutil
import subprocess
from typing import Any

from ..core import TnnError, atomic_path, save_figure
from ..ir import LEARNED_COLOR, Network, dot, element_label
from .figure import new_figure

__all__ = ["network", "render_png"]


def render_png(net: Network, path: str, *, dpi: int = 150) -> str:
    """Write a PNG picture of ``net`` to ``path`` (atomically): Graphviz's ``dot`` binary when it is on PATH
    (the same picture as :func:`tnn_dsl.ir.dot`), otherwise :func:`network`. Returns ``"graphviz"`` or
    ``"matplotlib"``, whichever drew it."""
    exe = shutil.which("dot")
    if exe is not None:
        with atomic_path(path) as tmp:
            proc = subprocess.run([exe, "-Tpng", f"-Gdpi={dpi}", "-o", str(tmp)], input=dot(net).encode("utf-8"),
                                  capture_output=True, timeout=120, check=False)
            if proc.returncode != 0:
                raise TnnError(f"graphviz `dot` failed on this network: "
                               f"{proc.stderr.decode('utf-8', 'replace').strip()}")
        return "graphviz"
    save_figure(network(net), path, dpi=dpi)
    return "matplotlib"


def network(net: Network, ax: Any | None = None) -> Any:
    """The network drawn with matplotlib and networkx: nodes (circles), boundaries (squares), fluid inlets,
    links labelled with their values, components; learned parts in red."""
    import networkx as nx

    g = net.graph()
    n = max(g.number_of_nodes(), 1)
    fig, axs = new_figure(1, 1, figsize=(min(4 + 1.6 * math.sqrt(n) * 2, 24), min(3 + 1.4 * math.sqrt(n) * 2, 18)),
                          axes=None if ax is None else [ax])
    ax = axs[0, 0]
    targets = net.learned_targets()
    pos = nx.kamada_kawai_layout(nx.Graph(g)) if n > 2 else nx.spring_layout(nx.Graph(g), seed=0)
    kinds = nx.get_node_attributes(g, "kind")
    colors = {"node": "#dbe9f6", "boundary": "#e6e6e6", "fluid_inlet": "#d9f2e6"}
    shapes = {"node": "o", "boundary": "s", "fluid_inlet": ">"}
    for kind, shape in shapes.items():
        vs = [v for v in g.nodes if kinds.get(v) == kind]
        if vs:
            edge = [LEARNED_COLOR if kind == "node" and
                    next(x for x in net.nodes if x.name == v).capacitance in targets else "#333333" for v in vs]
            nx.draw_networkx_nodes(g, pos, nodelist=vs, node_color=colors[kind], node_shape=shape,
                                   node_size=1400, edgecolors=edge, linewidths=1.5, ax=ax)
    read_by: dict[str, list[str]] = {}
    for sen in net.sensors:
        read_by.setdefault(sen.node, []).append(sen.name)
    labels = {v: (f"{v}\n[{', '.join(read_by[v])}]" if v in read_by else
                  f"{v[:-len('.inlet')]}\ninlet" if kinds.get(v) == "fluid_inlet" else v) for v in g.nodes}
    nx.draw_networkx_labels(g, pos, labels=labels, font_size=8, ax=ax)
    edge_colors = {"link": "#333333", "radiation": "#e07b00", "peltier": "#1f77b4", "fluid": "#2e7d4f"}
    edge_labels: dict[tuple[str, str], list[str]] = {}
    for u, v, _key, data in g.edges(keys=True, data=True):
        el = data["element"]
        kind = data["kind"]
        if kind == "link":
            learned = el.value in targets
            text = element_label(net, el.value)[0]
        elif kind == "peltier":
            learned = any(f"{el.name}.{fl}" in targets for fl in ("Q_hot", "Q_cold"))
            text = f"Peltier {el.name}"
        elif kind == "fluid":
            learned = f"{el.name}.Q" in targets
            text = f"fluid {el.name}"
        else:
            learned = any(x in targets for x in (el.area, el.emissivity, el.view_factor))
            text = f"radiation {el.name}"
        k = len(edge_labels.get((u, v), []))  # parallel edges (a link and radiation ...) bend apart
        rad = 0.0 if k == 0 else (0.2 * ((k + 1) // 2)) * (1 if k % 2 else -1)
        nx.draw_networkx_edges(g, pos, edgelist=[(u, v)], ax=ax, width=2.5 if learned else 1.2,
                               edge_color=LEARNED_COLOR if learned else edge_colors[kind],
                               style="dashed" if kind == "radiation" else "solid",
                               arrows=True, arrowstyle="-", connectionstyle=f"arc3,rad={rad}",
                               node_size=1400)
        edge_labels.setdefault((u, v), []).append(text)
    nx.draw_networkx_edge_labels(g, pos, edge_labels={k: "\n".join(v) for k, v in edge_labels.items()},
                                 font_size=7, ax=ax)
    ax.set_title(net.name + (f" — {net.label}" if net.label else ""))
    ax.text(0.01, 0.01, "learned parts in red; [sensors] under the node they read "
            "(drawn with matplotlib; install graphviz for the full picture)",
            transform=ax.transAxes, fontsize=7, color="#666666")
    ax.axis("off")
    fig.tight_layout()
    return fig
