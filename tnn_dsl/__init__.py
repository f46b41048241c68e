"""tnn_dsl: a declarative language for lumped thermal networks, compiled to JAX and PyTorch.

Public API (everything else is private; see docs/architecture.md):

* ``load(path) -> Network`` / ``loads(text, filename) -> Network``: parse and validate a ``.thn`` file.
* ``Network``: the validated IR (pydantic; ``.graph()`` gives the networkx view).
* ``TnnError``: raised for any problem the user can fix; ``str(err)`` is the formatted report.
"""

from __future__ import annotations

from ._errors import DataError, Diagnostic, ModelFileError, TnnError
from ._ir import Network

__version__ = "0.1.0"

_LAZY = {
    # name: (module, attribute) — imported on first use so `import tnn_dsl` stays light
    "sensitivity": ("._sensitivity", "sensitivity"),
    "excitation": ("._sensitivity", "excitation"),
    "compile": ("._compile", "compile"),
    "Model": ("._compile", "Model"),
    "ParamSpec": ("._compile", "ParamSpec"),
    "TorchCompileWarning": ("._compile", "TorchCompileWarning"),
    "load": ("._parser", "load"),
    "loads": ("._parser", "loads"),
    "read_data": ("._data", "read_data"),
    "Experiment": ("._data", "Experiment"),
    "split_by_time": ("._data", "split_by_time"),
    "generate_case_study": ("._casestudy", "generate_case_study"),
    "diagnose": ("._diagnose", "diagnose"),
    "train": ("._train", "train"),
    "evaluate": ("._train", "evaluate"),
    "TrainConfig": ("._train", "TrainConfig"),
    "load_model": ("._model_io", "load_model"),
    "TrainedModel": ("._model_io", "TrainedModel"),
    "ekf": ("._estimate", "ekf"),
    "EKFResult": ("._estimate", "EKFResult"),
    "tune_process_noise": ("._estimate", "tune_process_noise"),
    "MPC": ("._mpc", "MPC"),
    "closed_loop": ("._mpc", "closed_loop"),
    "run_study": ("._study", "run_study"),
    "StudyConfig": ("._study", "StudyConfig"),
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module, __name__), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tnn_dsl' has no attribute {name!r}")


__all__ = ["Network", "TnnError", "DataError", "ModelFileError", "Diagnostic", "__version__", *_LAZY]
