"""Fitting a network to data and keeping the result.

Owns: the training options (``config``), the flat parameter vector and its transforms (``transforms``), windows
of multiple shooting (``windows``), the trainer (``trainer``: loss, Adam, divergence guard, L-BFGS polish) and
its entry points (``training``: ``train``, ``evaluate``), free runs and error metrics (``simulation``), model
directories (``model_files``: JSON + safetensors, atomic writes).
May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``.
"""

from __future__ import annotations

from .config import TrainConfig, load_config
from .model_files import MODEL_DIR, TrainedModel, is_model_dir, load_model, save_model
from .simulation import error_metrics, initial_state, simulate, simulate_experiment
from .training import evaluate, train

__all__ = [
    "MODEL_DIR", "TrainedModel", "is_model_dir", "load_model", "save_model", "error_metrics", "initial_state",
    "simulate", "simulate_experiment", "TrainConfig", "evaluate", "load_config", "train"
]
