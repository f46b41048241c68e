"""The model doctor: what the simulation gets wrong on measured data, its cause, the extended network.

May import: every stage below it (``core`` … ``analysis``); not ``control``, ``studies`` or ``cli``.
"""

from __future__ import annotations

from .base import STRUCTURAL_KINDS, Candidate
from .candidates import build_extended
from .diagnosis import Diagnosis, Finding, diagnose
from .engine import normalisation_stats
from .report import REPORT_DIR, write_report
from .structural import apply_structural, structural_candidates

__all__ = [
    "STRUCTURAL_KINDS", "Candidate", "apply_structural", "build_extended", "structural_candidates", "Diagnosis",
    "Finding", "diagnose", "normalisation_stats", "REPORT_DIR", "write_report"
]
