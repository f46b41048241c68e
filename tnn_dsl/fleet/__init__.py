"""Fleets: one network template, many units (boards, heat exchangers, buildings), each fitted and diagnosed as a
Ray task; across the fleet, which units deviate from their siblings and why (see ``README.md`` here).

Flow: :func:`read_fleet` (a directory or a YAML manifest) -> :func:`run_fleet` (per unit
:func:`~tnn_dsl.fleet.units.run_unit`, written under ``OUT/units/<unit>/``) -> :func:`fleet_report` (distributions,
robust z-score outliers with a reading, units grouped by finding; ``report.json``, ``report.html``)."""

from .engine import FLEET_DIR, FleetRun, load_results, run_fleet
from .generate import FAULT_KINDS, generate_fleet, template_path
from .manifest import Fleet, Unit, read_fleet
from .report import fleet_report, report_html, report_text, robust_z
from .units import FleetOptions, run_unit, unit_network

__all__ = ["FLEET_DIR", "FleetRun", "load_results", "run_fleet", "FAULT_KINDS", "generate_fleet", "template_path",
           "Fleet", "Unit", "read_fleet", "fleet_report", "report_html", "report_text", "robust_z", "FleetOptions",
           "run_unit", "unit_network"]
