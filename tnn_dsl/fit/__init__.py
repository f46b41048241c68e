"""Fitting a network to data and keeping the result.

Owns: the training options (``config``), the flat parameter vector and its transforms (``transforms``), windows of
multiple shooting (``windows``), the rollouts fitted (``rollouts``: single or multiple shooting), the trainer
(``trainer``: loss, Adam, divergence guard, L-BFGS polish), the pre-fit of ``replace``-mode flows to the nominal law
(``prefit``: Levenberg–Marquardt) and its entry points (``training``: ``train``,
``evaluate``), initial states by one rule (``initial``), free runs and error metrics (``simulation``), model
directories (``model_files``: JSON + safetensors, atomic writes).
May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``.
"""

from __future__ import annotations

from .config import TrainConfig, load_config
from .initial import INIT_RULES, InitialState, initial_state
from .model_files import MODEL_DIR, TrainedModel, is_model_dir, load_model, save_model
from .simulation import FreeRun, error_metrics, free_run, simulate
from .training import evaluate, train

__all__ = [
    "MODEL_DIR", "TrainedModel", "is_model_dir", "load_model", "save_model", "error_metrics", "INIT_RULES",
    "InitialState", "initial_state", "FreeRun", "free_run", "simulate", "TrainConfig", "evaluate", "load_config",
    "train"
]
