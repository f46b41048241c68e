"""The compiled-model contract: what the trainer, the sensitivity pass, the doctor, the filter, the
controller and the command line may rely on, whatever the backend (:class:`~tnn_dsl.compiler.model.Model`
implements it; ``isinstance(model, CompiledModel)`` checks the names at run time).

Shapes and units: ``T (..., n_states)`` K; ``u (..., n_inputs)`` SI with temperature inputs in K;
outputs ``(..., n_outputs)`` K; heat flows W; time constants s. Leading axes broadcast (batches of
windows). ``params`` is the parameter table: name → backend array (see :attr:`param_specs`).
"""

from __future__ import annotations

from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np

from ..ir import Network

__all__ = ["CompiledModel"]

Array = Any
"""A backend array (``jax.Array`` or ``torch.Tensor``)."""
Params = Mapping[str, Array]


@runtime_checkable
class CompiledModel(Protocol):
    """A network compiled for one backend."""

    network: Network
    backend: str
    """``"jax"`` or ``"torch"`` (``"numpy"``: the reference backend, no autodiff)."""
    dtype: str
    """``"float64"`` or ``"float32"``."""
    xp: Any
    """The array namespace the model computes with (``exp``, ``where``, ``concat``, ``matmul`` ...)."""
    state_names: tuple[str, ...]
    """Node names in declaration order, then ``"<sensor>.lag"`` for lagged sensors."""
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    param_specs: dict[str, Any]
    """Every array the model reads: name → ``ParamSpec(name, shape, kind, trainable, positive, lower,
    upper, role)``."""

    def init_params(self, seed: int = 0) -> dict[str, Array]:
        """Constants at their SI values, learned arrays initialised (an untrained model is the nominal one)."""
        ...

    def to_numpy(self, params: Params) -> dict[str, np.ndarray]:
        ...

    def from_numpy(self, arrays: Mapping[str, np.ndarray]) -> dict[str, Array]:
        ...

    def rhs(self, params: Params, T: Array, u: Array) -> Array:
        """``dT/dt (..., n_states)`` K/s."""
        ...

    def outputs(self, params: Params, T: Array, u: Array) -> Array:
        """Sensor readings ``(..., n_outputs)`` K."""
        ...

    def heat_flows(self, params: Params, T: Array, u: Array) -> dict[str, Array]:
        """Every component and link flow (W), keyed by flow name."""
        ...

    def rollout(self, params: Params, T0: Array, inputs: Array, dt: float, integrator: str = "rk4",
                substeps: int | None = None) -> tuple[Array, Array]:
        """``T0 (..., n_states)``, ``inputs (..., N, n_inputs)`` held over each interval of ``dt`` s →
        ``states (..., N, n_states)`` (``states[..., 0, :] = T0``) and ``outputs (..., N, n_outputs)``."""
        ...

    def steady_state(self, params: Params, u: Array, T_init: Array | None = None, max_iter: int = 50,
                     tol: float = 1e-10) -> Array:
        """The steady state ``(..., n_states)`` K for constant inputs ``u``; differentiable."""
        ...

    def time_constants(self, params: Params | None = None) -> dict[str, float]:
        ...

    def fastest_time_constant(self) -> tuple[float, str]:
        ...
