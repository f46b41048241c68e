"""The compiled model: a network as a differentiable simulator on JAX or torch.

Owns: the heat-flow laws written once against an array namespace (``physics``), learned functions
(``learned``), expression evaluation (``expressions``), integrators (``integrators``), the array namespaces
and the one autodiff adapter (``backends``), the model itself (``model``) and its contract (``protocol``).
May import: ``tnn_dsl.core``, ``tnn_dsl.ir`` (never ``tnn_dsl.lang``: the compiler knows nothing of syntax).
"""

from __future__ import annotations

from .backends import get_xp
from .backends.adapter import Backend, backend_of
from .expressions import evaluate as evaluate_expr
from .integrators import INTEGRATORS, check_step
from .learned import apply as apply_learned
from .learned import target_value
from .model import Model, ParamSpec, TorchCompileWarning, compile
from .protocol import CompiledModel

__all__ = [
    "get_xp", "Backend", "backend_of", "evaluate_expr", "INTEGRATORS", "check_step", "apply_learned", "target_value",
    "Model", "ParamSpec", "TorchCompileWarning", "compile", "CompiledModel"
]
