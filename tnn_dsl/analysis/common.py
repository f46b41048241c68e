"""What the analysis modules share: number formatting for their tables and reading a network argument."""

from __future__ import annotations

import math
import os

from ..ir import Network


def _fmt(x: float, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if math.isinf(x):
        return "inf"
    return f"{x:.{digits}g}"


def _pct(x: float) -> str:
    if x is None or math.isnan(x):
        return "-"
    if math.isinf(x) or x > 1e4:
        return "inf" if math.isinf(x) else ">1e6 %"
    return f"{100 * x:.3g} %"


def _as_network(net) -> Network:
    if isinstance(net, Network):
        return net
    if hasattr(net, "network") and hasattr(net, "rhs"):
        return net.network
    from ..lang import load

    return load(os.fspath(net))
