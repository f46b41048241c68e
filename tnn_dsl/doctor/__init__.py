"""The model doctor: what the simulation gets wrong on measured data, its cause, the extended network.

Owns: one run as named stages (``session``; entry point ``diagnose`` in ``diagnosis``), what a candidate is
(``base``), the exactly-null candidates (``candidates``) and the structural ones (``structural``, their
score columns in ``forcing``) as IR edits, the fitting engine (``engine``: simulation, residuals, forward-mode
Jacobians, Levenberg–Marquardt), the score test and shortlist (``scoring``), proper fits (``fitting``), the
held-out decision (``selection``), the extension as IR edits printed to ``.thn`` (``extension``), linear or
MLP (``mlp_check``), causes named in words (``words``), results (``results``), the HTML page (``report``) and
Ctrl-C as a spent budget (``stopping``).
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
