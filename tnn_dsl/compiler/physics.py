"""Heat-flow laws, one function per component kind, written once against an array namespace ``xp``.

All functions are element-wise and broadcast: pass scalars, per-element vectors ``(n_elements,)`` or
batched arrays ``(..., n_elements)``. Sign convention: a returned flow is the heat (W) flowing **into**
the first-named node (``a`` of a link, the node of a fluid, the hot/cold side of a Peltier element).
Temperatures are absolute (K).

The compiler (:mod:`tnn_dsl.compiler.model`) assembles these per-element flows into node heat balances
``C_i dT_i/dt = Σ flows into i`` with incidence matrices (one matmul per element group), not Python
loops over links. For the common case of constant conductances it pre-multiplies the whole linear part
into one conductance matrix (:func:`conductance_matrix`), thesis eq. 2.4 ``C Ṫ = G T + g_a T_a + Q``.
"""

from __future__ import annotations

import numpy as np

STEFAN_BOLTZMANN = 5.670374419e-8
"""σ in W/(m²·K⁴) (CODATA 2018, exact in the 2019 SI)."""


def link_heat_flow(g, T_a, T_b):
    """Conduction/convection into ``a``: ``g·(T_b − T_a)`` (W); ``g`` conductance (W/K) = 1/R."""
    return g * (T_b - T_a)


def radiation_coefficient(area, emissivity, view_factor):
    """``σ·ε·A·F`` (W/K⁴) of a grey-body radiation path: area m², emissivity and view factor 1."""
    return STEFAN_BOLTZMANN * emissivity * area * view_factor


def radiation_heat_flow(area, emissivity, view_factor, T_a, T_b):
    """Radiation into ``a``: ``σ·ε·A·F·(T_b⁴ − T_a⁴)`` (W), absolute temperatures (K)."""
    return radiation_coefficient(area, emissivity, view_factor) * (T_b**4 - T_a**4)


def peltier_heat_flows(seebeck, resistance, current, T_hot, T_cold):
    """Thermoelectric element (thesis eq. 2.12–2.13): ``(Q_hot, Q_cold)`` in W into the hot and the cold
    side, ``Q_hot = S·T_hot·I + ½·R_el·I²``, ``Q_cold = −S·T_cold·I + ½·R_el·I²``.

    ``seebeck`` S in V/K, ``resistance`` R_el in Ω, ``current`` I in A, temperatures in K. The internal
    conduction between the sides is an ordinary link (:func:`link_heat_flow`)."""
    joule = 0.5 * resistance * current * current
    return seebeck * T_hot * current + joule, -seebeck * T_cold * current + joule


def fluid_conductance(xp, mdot, cp, ua):
    """Effective conductance (W/K) of a fluid stream through a node (thesis eq. 2.14):
    ``ṁ·cp·(1 − a)``, ``a = exp(−UA/(ṁ·cp))``; ṁ kg/s, cp J/(kg·K), UA W/K. Uses ``expm1`` so it stays
    accurate when ``UA ≪ ṁ·cp``."""
    mcp = mdot * cp
    if isinstance(mcp, (int, float)) and mcp == 0:
        return 0.0  # no flow: ṁ·cp·(1 − e^(−UA/ṁcp)) → 0 as ṁ → 0
    return -mcp * _expm1(xp, -ua / mcp)


def fluid_heat_flow(xp, mdot, cp, ua, T_in, T_node):
    """Heat into the node from the stream: ``ṁ·cp·(1 − a)·(T_in − T_node)`` (W), eq. 2.14 with
    ``T_out = a·T_in + (1 − a)·T_node``."""
    return fluid_conductance(xp, mdot, cp, ua) * (T_in - T_node)


def sensor_lag_rate(T_node, T_sensor, tau):
    """First-order sensor: ``dT_s/dt = (T_node − T_s)/τ`` (K/s), τ in s."""
    return (T_node - T_sensor) / tau


def conductance_matrix(xp, g, D, Inc):
    """The linear part of the heat balance for a group of links with conductances ``g (n_links,)``:
    ``M = D·diag(g)·Inc`` (W/K), so that the heat into the nodes is ``X @ M`` for potentials
    ``X (..., n_vertices)``. ``D (n_vertices, n_links)`` has +1 at each link's ``b`` and −1 at its ``a``;
    ``Inc (n_links, n_nodes)`` has +1 at ``a`` and −1 at ``b`` (only for endpoints that are nodes).
    Equals summing :func:`link_heat_flow` over links."""
    return xp.matmul(D * g, Inc)


def _expm1(xp, x):
    if isinstance(x, (int, float)):
        return float(np.expm1(x))
    return xp.expm1(x)


__all__ = [
    "STEFAN_BOLTZMANN", "link_heat_flow", "radiation_coefficient", "radiation_heat_flow",
    "peltier_heat_flows", "fluid_conductance", "fluid_heat_flow", "sensor_lag_rate", "conductance_matrix",
]
