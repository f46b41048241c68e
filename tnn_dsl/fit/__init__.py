"""Fitting a network to data and keeping the result.

Owns: the trainer (``train``), free runs and error metrics (``simulate``), model directories (``model_files``:
JSON + safetensors, atomic writes). May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``.
"""

from __future__ import annotations

from .model_files import MODEL_DIR, TrainedModel, is_model_dir, load_model, save_model
from .simulation import error_metrics, initial_state, simulate, simulate_experiment
from .trainer import TrainConfig, evaluate, load_config, train

__all__ = [
    "MODEL_DIR", "TrainedModel", "is_model_dir", "load_model", "save_model", "error_metrics", "initial_state",
    "simulate", "simulate_experiment", "TrainConfig", "evaluate", "load_config", "train"
]
