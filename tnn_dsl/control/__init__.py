"""Control with a compiled, differentiable model: gradient-based receding-horizon MPC.

May import: every stage below it (``core`` … ``analysis``); not ``doctor``, ``studies`` or ``cli``.
"""

from __future__ import annotations

from .mpc import MPC, ClosedLoopResult, closed_loop

__all__ = [
    "MPC", "ClosedLoopResult", "closed_loop"
]
