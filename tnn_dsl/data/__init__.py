"""Measured data: CSV/Parquet files to :class:`Experiment` objects in SI units, and CSV out.

Owns: time columns, column units, missing values, splits, the shared ``as_experiments`` and ``write_csv``.
May import: ``tnn_dsl.core``, ``tnn_dsl.ir``, ``tnn_dsl.lang`` (units).
"""

from __future__ import annotations

from .experiment import Experiment, split_by_time, warning_lines
from .reading import as_experiments, columns_read, read_data
from .tables import read_table
from .units import from_kelvin, to_kelvin, unit_factor, unit_scale_offset
from .write import write_csv

__all__ = [
    "Experiment", "as_experiments", "columns_read", "from_kelvin", "read_data", "read_table", "split_by_time",
    "to_kelvin", "unit_factor", "unit_scale_offset", "warning_lines", "write_csv"
]
