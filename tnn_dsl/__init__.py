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
    from .analysis.sensitivity import excitation, sensitivity
    from .compiler.model import Model, ParamSpec, TorchCompileWarning, compile
    from .control.mpc import MPC, closed_loop
    from .data.io import Experiment, read_data, split_by_time
    from .doctor.diagnose import Diagnosis, diagnose
    from .estimation.ekf import EKFResult, ekf, tune_process_noise
    from .fit.model_files import TrainedModel, load_model
    from .fit.train import TrainConfig, evaluate, train
    from .lang.parser import load, loads
    from .studies.casestudy import generate_case_study
    from .studies.thesis import StudyConfig, run_study

_LAZY: dict[str, str] = {
    # name -> module that defines it
    "load": ".lang.parser",
    "loads": ".lang.parser",
    "compile": ".compiler.model",
    "Model": ".compiler.model",
    "ParamSpec": ".compiler.model",
    "TorchCompileWarning": ".compiler.model",
    "read_data": ".data.io",
    "Experiment": ".data.io",
    "split_by_time": ".data.io",
    "train": ".fit.train",
    "evaluate": ".fit.train",
    "TrainConfig": ".fit.train",
    "load_model": ".fit.model_files",
    "TrainedModel": ".fit.model_files",
    "sensitivity": ".analysis.sensitivity",
    "excitation": ".analysis.sensitivity",
    "diagnose": ".doctor.diagnose",
    "Diagnosis": ".doctor.diagnose",
    "ekf": ".estimation.ekf",
    "EKFResult": ".estimation.ekf",
    "tune_process_noise": ".estimation.ekf",
    "MPC": ".control.mpc",
    "closed_loop": ".control.mpc",
    "generate_case_study": ".studies.casestudy",
    "run_study": ".studies.thesis",
    "StudyConfig": ".studies.thesis",
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
    "load", "loads", "compile", "Model", "ParamSpec", "TorchCompileWarning", "read_data", "Experiment",
    "split_by_time", "train", "evaluate", "TrainConfig", "load_model", "TrainedModel", "sensitivity",
    "excitation", "diagnose", "Diagnosis", "ekf", "EKFResult", "tune_process_noise", "MPC", "closed_loop",
    "generate_case_study", "run_study", "StudyConfig",
]
assert set(__all__) == {"Network", "TnnError", "DataError", "ModelFileError", "Diagnostic", "__version__", *_LAZY}
