"""Every public function and method has annotations on all its parameters and its return.

Public: the names in ``tnn_dsl.__all__`` and in each subpackage's ``__all__`` (``tnn_dsl/*/__init__.py``)
that are functions, and the public methods (plus ``__init__`` and ``__call__``) of the classes among them
that tnn_dsl defines. Methods a class inherits from pydantic or the standard library are skipped.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable, Iterator
from typing import Any

import tnn_dsl

_DUNDERS = {"__init__", "__call__"}


def _public_modules() -> list[Any]:
    mods = [tnn_dsl]
    for info in pkgutil.iter_modules(tnn_dsl.__path__):
        if info.ispkg:
            mods.append(importlib.import_module(f"tnn_dsl.{info.name}"))
    return mods


def _ours(obj: object) -> bool:
    return (getattr(obj, "__module__", "") or "").startswith("tnn_dsl")


def _methods(cls: type) -> Iterator[tuple[str, Callable[..., Any]]]:
    """The methods ``cls`` itself or a tnn_dsl base class defines (not pydantic's, dataclass-generated
    ``__init__`` included only when written by hand)."""
    seen: set[str] = set()
    for klass in cls.__mro__:
        if not _ours(klass):
            continue
        for name, raw in vars(klass).items():
            if name in seen or (name.startswith("_") and name not in _DUNDERS):
                continue
            seen.add(name)
            if isinstance(raw, (staticmethod, classmethod)):
                fn = raw.__func__
            elif isinstance(raw, property):
                fn = raw.fget
            else:
                fn = raw
            if not inspect.isfunction(fn) or not _ours(fn):
                continue
            # dataclass/pydantic-generated methods are compiled from strings: their file is not ours
            code_file = getattr(getattr(fn, "__code__", None), "co_filename", "")
            if "tnn_dsl" not in code_file:
                continue
            yield name, fn


def _targets() -> dict[str, Callable[..., Any]]:
    out: dict[str, Callable[..., Any]] = {}
    for mod in _public_modules():
        for name in getattr(mod, "__all__", []):
            obj = getattr(mod, name)
            if inspect.isclass(obj) and _ours(obj):
                for mname, fn in _methods(obj):
                    out.setdefault(f"{obj.__module__}.{obj.__qualname__}.{mname}", fn)
            elif inspect.isfunction(obj) and _ours(obj):
                out.setdefault(f"{obj.__module__}.{obj.__qualname__}", obj)
    return out


def _missing(fn: Callable[..., Any]) -> list[str]:
    sig = inspect.signature(fn)
    params = list(sig.parameters.values())
    if params and params[0].name in ("self", "cls"):
        params = params[1:]
    out = [p.name for p in params if p.annotation is inspect.Parameter.empty]
    if sig.return_annotation is inspect.Signature.empty:
        out.append("return")
    return out


def test_walk_finds_the_public_api() -> None:
    targets = _targets()
    assert "tnn_dsl.doctor.diagnosis.diagnose" in targets or any(k.endswith(".diagnose") for k in targets)
    assert any(k.endswith("TrainedModel.predict") for k in targets)
    assert len(targets) > 100


def test_every_public_function_is_annotated() -> None:
    problems = []
    for name, fn in sorted(_targets().items()):
        missing = _missing(fn)
        if missing:
            problems.append(f"{name}: {', '.join(missing)}")
    assert not problems, f"{len(problems)} public functions lack annotations:\n" + "\n".join(problems)
