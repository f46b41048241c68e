"""The installed version of tnn_dsl (from the package metadata)."""

from __future__ import annotations

from importlib import metadata

try:
    __version__ = metadata.version("tnn_dsl")
except metadata.PackageNotFoundError:  # a checkout that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
