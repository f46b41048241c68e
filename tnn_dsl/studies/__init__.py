"""Studies and generated data: the thesis case study (generator and M1–M5 study) and planted effects for
testing the doctor. May import: every stage but ``cli``.
"""

from __future__ import annotations

from .casestudy import generate_case_study, network_path
from .planted import plant
from .thesis import STUDY_DIR, StudyConfig, plot_study, ratios_table, results_table, run_study

__all__ = [
    "generate_case_study", "network_path", "plant", "STUDY_DIR", "StudyConfig", "plot_study", "ratios_table",
    "results_table", "run_study"
]
