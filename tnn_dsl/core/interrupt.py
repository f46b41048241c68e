"""Ctrl-C seen through C code.

A ``KeyboardInterrupt`` raised while C code is running a Python callback (numpy asking JAX's scalar types for their
dtype, ``_ScalarMeta.__numpy_dtype__``) can come back out of that C code as CPython's ``SystemError: <function ...>
returned a result with an exception set``, the interrupt as its cause: a ``tnnc train`` stopped with Ctrl-C then
ended as an internal error with its best model unwritten (CI, 2026-12-05, ``tests/test_cli_train.py::
test_ctrl_c_keeps_best_model``). :func:`is_interrupt` tells such an exception from a real error, so that every
place that keeps the work done so far on Ctrl-C keeps it in this case too."""

from __future__ import annotations


def is_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` is a Ctrl-C: a ``KeyboardInterrupt``, or a ``SystemError`` whose chain of causes and contexts
    holds one (C code that a ``KeyboardInterrupt`` left with an exception set)."""
    if isinstance(exc, KeyboardInterrupt):
        return True
    if not isinstance(exc, SystemError):
        return False
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ if e.__cause__ is not None else e.__context__
    return False


__all__ = ["is_interrupt"]
