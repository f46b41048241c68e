"""The intermediate representation: the validated network, the single truth between the stages.

Owns: the network model (``network``: pydantic elements, the flat parameter table, expressions and the
expression walker, ``Network.graph()``), its emitters (``emit``: equations, IR JSON, Graphviz DOT; a drawing
is :func:`tnn_dsl.plots.render_png`).
May import: ``tnn_dsl.core``.
"""

from __future__ import annotations

from .emit import (
    LEARNED_COLOR,
    dot,
    element_label,
    equations,
    format_dim,
    format_expr,
    format_quantity,
    ir_json,
    network_from_json,
)
from .network import *  # noqa: F403 - the IR's element classes (network.__all__)
from .network import __all__ as _network_names

__all__ = [*_network_names, "dot", "equations", "format_dim", "format_expr", "format_quantity", "ir_json",
           "network_from_json", "element_label", "LEARNED_COLOR"]
