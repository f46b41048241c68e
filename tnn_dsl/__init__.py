"""tnn_dsl: a declarative language for lumped thermal networks, compiled to JAX and PyTorch.

The package follows the flow of a model (docs/architecture.md): ``.thn`` text → :mod:`~tnn_dsl.lang`
(parser, units, validation) → :mod:`~tnn_dsl.ir` (the network, the single truth) →
:mod:`~tnn_dsl.compiler` (physics, learned functions, integrators, backends) → :mod:`~tnn_dsl.fit` (trainer,
model files, simulation) → :mod:`~tnn_dsl.analysis` / :mod:`~tnn_dsl.doctor` → :mod:`~tnn_dsl.cli`.

The names below are the public API; they are imported on first use so that ``import tnn_dsl`` stays
light (no JAX or torch until a model is compiled), and listed under ``TYPE_CHECKING`` so that editors
and type checkers see them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .core.errors import DataError, Diagnostic, ModelFileError, TnnError
from .core.version import __version__
from .ir.network import Network

if TYPE_CHECKING:
    from .analysis import excitation, sensitivity
    from .compiler import Model, ParamSpec, TorchCompileWarning, compile
    from .control import MPC, closed_loop
    from .data import Experiment, read_data, split_by_time
    from .doctor import Diagnosis, diagnose
    from .estimation import EKFResult, ekf, tune_process_noise
    from .fit import TrainConfig, TrainedModel, evaluate, load_model, train
    from .lang import load, loads, print_thn
    from .studies import StudyConfig, generate_case_study, run_study

_LAZY: dict[str, str] = {
    # name -> the stage subpackage that exports it
    "load": ".lang",
    "loads": ".lang",
    "print_thn": ".lang",
    "compile": ".compiler",
    "Model": ".compiler",
    "ParamSpec": ".compiler",
    "TorchCompileWarning": ".compiler",
    "read_data": ".data",
    "Experiment": ".data",
    "split_by_time": ".data",
    "train": ".fit",
    "evaluate": ".fit",
    "TrainConfig": ".fit",
    "load_model": ".fit",
    "TrainedModel": ".fit",
    "sensitivity": ".analysis",
    "excitation": ".analysis",
    "diagnose": ".doctor",
    "Diagnosis": ".doctor",
    "ekf": ".estimation",
    "EKFResult": ".estimation",
    "tune_process_noise": ".estimation",
    "MPC": ".control",
    "closed_loop": ".control",
    "generate_case_study": ".studies",
    "run_study": ".studies",
    "StudyConfig": ".studies",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tnn_dsl' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "Network", "TnnError", "DataError", "ModelFileError", "Diagnostic", "__version__",
    "load", "loads", "print_thn", "compile", "Model", "ParamSpec", "TorchCompileWarning", "read_data", "Experiment",
    "split_by_time", "train", "evaluate", "TrainConfig", "load_model", "TrainedModel", "sensitivity",
    "excitation", "diagnose", "Diagnosis", "ekf", "EKFResult", "tune_process_noise", "MPC", "closed_loop",
    "generate_case_study", "run_study", "StudyConfig",
]
assert set(__all__) == {"Network", "TnnError", "DataError", "ModelFileError", "Diagnostic", "__version__", *_LAZY}
