"""What a fleet is: its units, their data files and their per-unit overrides.

A fleet is given as a path (``tnnc fleet train NET FLEET``), one of

* a **directory with one sub-directory per unit**: the unit is named after the sub-directory; its data files
  (``.csv``, ``.tsv``, ``.txt``, ``.parquet``) whose names start with ``val`` are held out, the others are trained on
  (no held-out file: the last 30 % of each training file is held out, as in ``tnnc diagnose``);
* a **directory of data files**, one unit per file (named after the file's stem; its last 30 % held out);
* a **YAML manifest** (``fleet.yaml``, or a directory holding one), listing the units::

      units:
        - name: board-017
          train: [board-017/prbs.csv]          # relative to the manifest's directory
          val: [board-017/setpoint.csv]        # optional
          columns: {T1: "T1 (degC)"}           # a sensor or input of the network -> this unit's column
          params: {Ta: 22.5 degC, a1: 0.0095 W/%}   # known values: fixed at these for this unit

Every file a fleet names lies inside the fleet's directory (symbolic links resolved): a manifest cannot make the
tool read elsewhere. Unit names are letters, digits, ``-``, ``_`` and ``.`` (they name the output directories).
Problems are reported as ``file:line:col: error: ...`` with the manifest's line and a hint.
"""

from __future__ import annotations

import difflib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core import Diagnostic, TnnError
from ..core.span import Span

__all__ = ["Unit", "Fleet", "read_fleet", "DATA_SUFFIXES", "MANIFEST_NAMES"]

DATA_SUFFIXES = (".csv", ".tsv", ".txt", ".parquet")
"""The data files a fleet directory's units are made of."""

MANIFEST_NAMES = ("fleet.yaml", "fleet.yml")
"""A directory holding one of these is read as a manifest."""

UNIT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
"""A unit's name: it names the unit's output directory."""

_UNIT_KEYS = ("name", "train", "val", "columns", "params")


@dataclass(frozen=True)
class Unit:
    """One unit of a fleet: ``name``, its training and held-out data files (absolute paths), and its overrides:
    ``columns`` (an input or sensor name of the network -> the column in this unit's files) and ``params``
    (a parameter name -> its known value as written, e.g. ``"22.5 degC"``: fixed at it for this unit)."""

    name: str
    train: tuple[str, ...]
    val: tuple[str, ...] = ()
    columns: tuple[tuple[str, str], ...] = ()
    params: tuple[tuple[str, str], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "train": list(self.train), "val": list(self.val),
                "columns": dict(self.columns), "params": dict(self.params)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Unit":
        return cls(str(d["name"]), tuple(d.get("train") or ()), tuple(d.get("val") or ()),
                   tuple(sorted((d.get("columns") or {}).items())), tuple(sorted((d.get("params") or {}).items())))


@dataclass(frozen=True)
class Fleet:
    """The units of a fleet, in a stable order (by name), and where they were read from (``source``)."""

    source: str
    units: tuple[Unit, ...] = field(default_factory=tuple)

    def names(self) -> list[str]:
        return [u.name for u in self.units]


def _error(msg: str, hint: str | None = None, span: Span | None = None) -> TnnError:
    return TnnError(Diagnostic(msg, span=span, hint=hint))


def _is_data(p: Path) -> bool:
    return p.is_file() and p.suffix.lower() in DATA_SUFFIXES and not p.name.startswith(".")


def _check_name(name: str, where: str, span: Span | None = None) -> str:
    if not UNIT_NAME.match(name):
        raise _error(f"{where}: unit name {name!r} is not usable as a directory name",
                     "use letters, digits, '-', '_' and '.', starting with a letter or digit (at most 100 characters)",
                     span)
    return name


def read_fleet(path: str | os.PathLike) -> Fleet:
    """The :class:`Fleet` at ``path`` (module docstring): a manifest, a directory of unit directories, or a
    directory of data files. Raises :class:`~tnn_dsl.core.TnnError` with what was wrong and how to fix it."""
    p = Path(path)
    if not p.exists():
        raise _error(f"fleet {str(path)!r} does not exist",
                     "pass a directory with one sub-directory (or data file) per unit, or a fleet.yaml manifest")
    if p.is_file():
        if p.suffix.lower() not in (".yaml", ".yml"):
            raise _error(f"fleet {str(path)!r} is a file but not a YAML manifest (.yaml)",
                         "pass a directory with one sub-directory per unit, or a fleet.yaml manifest")
        return _read_manifest(p)
    for name in MANIFEST_NAMES:
        if (p / name).is_file():
            return _read_manifest(p / name)
    subdirs = sorted(c for c in p.iterdir() if c.is_dir() and not c.name.startswith("."))
    files = sorted(c for c in p.iterdir() if _is_data(c))
    if subdirs and files:
        raise _error(f"fleet directory {str(path)!r} holds both unit directories ({subdirs[0].name}, ...) and data "
                     f"files ({files[0].name}, ...)",
                     "put every unit's files in its own sub-directory, or list the units in a fleet.yaml manifest")
    units = []
    root = p.resolve()
    if subdirs:
        for d in subdirs:
            data = sorted(c for c in d.iterdir() if _is_data(c) and _inside(c, root))
            if not data:
                raise _error(f"unit directory {str(d)!r} holds no data file ({', '.join(DATA_SUFFIXES)})",
                             "put the unit's measurements in it, or remove the directory from the fleet")
            val = [c for c in data if c.name.lower().startswith("val")]
            train = [c for c in data if c not in val]
            if not train:
                raise _error(f"unit directory {str(d)!r} holds only held-out files (names starting with 'val')",
                             "add a training file (any data file whose name does not start with 'val')")
            units.append(Unit(_check_name(d.name, str(d)), tuple(str(c.resolve()) for c in train),
                              tuple(str(c.resolve()) for c in val)))
    else:
        for f in files:
            if not _inside(f, root):
                continue
            units.append(Unit(_check_name(f.stem, str(f)), (str(f.resolve()),)))
    if not units:
        raise _error(f"fleet directory {str(path)!r} holds no unit",
                     "put one sub-directory (or one data file) per unit in it, or a fleet.yaml manifest")
    return Fleet(str(p), tuple(units))


def _inside(child: Path, root: Path) -> bool:
    try:
        child.resolve().relative_to(root)
    except (ValueError, OSError):
        return False
    return True


def _span(file: str, node: Any) -> Span:
    s, e = node.start_mark, node.end_mark
    end_col = e.column + 1 if e.line == s.line else s.column + 2
    return Span(file=file, line=s.line + 1, col=s.column + 1, end_line=s.line + 1, end_col=max(end_col, s.column + 2))


def _read_manifest(path: Path) -> Fleet:
    import yaml

    file = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise _error(f"cannot read the fleet manifest {file}: {getattr(e, 'strerror', None) or e}",
                     "pass a readable UTF-8 YAML file")
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        span = Span(file=file, line=mark.line + 1, col=mark.column + 1, end_line=mark.line + 1,
                    end_col=mark.column + 2) if mark is not None else None
        raise _error(f"the fleet manifest is not valid YAML: {getattr(e, 'problem', e)}", "see the example in "
                     "`tnnc fleet --help`: `units:` then one `- name: ...` entry per unit", span)
    if not isinstance(root, yaml.MappingNode):
        raise _error(f"{file}: the fleet manifest must be a mapping with a `units:` list",
                     "write `units:` then one `- name: ...` entry per unit")
    top = {k.value: (k, v) for k, v in root.value}
    for key, (knode, _) in top.items():
        if key != "units":
            raise _error(f"unknown key {key!r} in the fleet manifest", "the manifest has one key, `units:`",
                         _span(file, knode))
    if "units" not in top or not isinstance(top["units"][1], yaml.SequenceNode) or not top["units"][1].value:
        node = top["units"][1] if "units" in top else root
        raise _error("the fleet manifest lists no unit", "write `units:` then one `- name: ...` entry per unit",
                     _span(file, node))
    base = path.parent.resolve()
    units: list[Unit] = []
    seen: dict[str, Span] = {}
    for item in top["units"][1].value:
        if not isinstance(item, yaml.MappingNode):
            raise _error("a unit must be a mapping (`- name: ...`, `train: [...]`)",
                         "write each unit as `- name: NAME` with `train: [FILE, ...]` under it", _span(file, item))
        fields = {k.value: (k, v) for k, v in item.value}
        for key, (knode, _) in fields.items():
            if key not in _UNIT_KEYS:
                close = difflib.get_close_matches(key, _UNIT_KEYS, n=1)
                raise _error(f"unknown key {key!r} in a unit", f"did you mean `{close[0]}`?" if close else
                             f"a unit's keys are {', '.join(_UNIT_KEYS)}", _span(file, knode))
        if "name" not in fields or not isinstance(fields["name"][1], yaml.ScalarNode):
            raise _error("a unit has no `name:`", "give each unit a `name:` (it names its output directory)",
                         _span(file, item))
        name_node = fields["name"][1]
        name = _check_name(str(name_node.value), "fleet manifest", _span(file, name_node))
        if name in seen:
            raise TnnError(Diagnostic(f"unit {name!r} is listed twice", span=_span(file, name_node),
                                      hint="give each unit its own name",
                                      related=(("first listed here", seen[name]),)))
        seen[name] = _span(file, name_node)
        if "train" not in fields:
            raise _error(f"unit {name!r} has no `train:` files", "list its training data: `train: [FILE, ...]`",
                         _span(file, item))
        train = _files(file, base, fields["train"][1], name, "train")
        val = _files(file, base, fields["val"][1], name, "val") if "val" in fields else ()
        columns = _mapping(file, fields["columns"][1], name, "columns") if "columns" in fields else ()
        params = _mapping(file, fields["params"][1], name, "params") if "params" in fields else ()
        units.append(Unit(name, train, val, columns, params))
    return Fleet(file, tuple(sorted(units, key=lambda u: u.name)))


def _files(file: str, base: Path, node: Any, unit: str, key: str) -> tuple[str, ...]:
    import yaml

    items = node.value if isinstance(node, yaml.SequenceNode) else [node]
    if not items or not all(isinstance(i, yaml.ScalarNode) and i.value for i in items):
        raise _error(f"unit {unit!r}: `{key}:` must be a file or a list of files",
                     f"write `{key}: [FILE, ...]` with paths relative to the manifest", _span(file, node))
    out = []
    for i in items:
        p = (base / str(i.value))
        if not _inside(p, base):
            raise _error(f"unit {unit!r}: {i.value!r} lies outside the manifest's directory {base}",
                         "a fleet reads only files under its manifest's directory: move or link the data there "
                         "(a link must point inside it too)", _span(file, i))
        if not p.is_file():
            raise _error(f"unit {unit!r}: data file {i.value!r} does not exist",
                         "paths are relative to the manifest's directory", _span(file, i))
        out.append(str(p.resolve()))
    return tuple(out)


def _mapping(file: str, node: Any, unit: str, key: str) -> tuple[tuple[str, str], ...]:
    import yaml

    if not isinstance(node, yaml.MappingNode) or not all(
            isinstance(k, yaml.ScalarNode) and isinstance(v, yaml.ScalarNode) for k, v in node.value):
        what = "NAME: COLUMN" if key == "columns" else "NAME: VALUE UNIT"
        raise _error(f"unit {unit!r}: `{key}:` must map names to values ({what})",
                     f"e.g. `{key}: {{T1: \"T1 (degC)\"}}`" if key == "columns" else
                     f"e.g. `{key}: {{Ta: 22.5 degC}}`", _span(file, node))
    return tuple(sorted((str(k.value), str(v.value)) for k, v in node.value))


def manifest_span(fleet: Fleet, unit: str, key: str | None = None) -> Span | None:
    """Where ``unit`` (its ``key`` entry if given) is written in the fleet's manifest, for messages about an
    override; ``None`` for a directory fleet."""
    if not fleet.source.lower().endswith((".yaml", ".yml")):
        return None
    import yaml

    try:
        root = yaml.compose(Path(fleet.source).read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except (OSError, yaml.YAMLError):
        return None
    for k, v in root.value:
        if k.value != "units":
            continue
        for item in v.value:
            fields = {kk.value: (kk, vv) for kk, vv in item.value}
            if "name" in fields and fields["name"][1].value == unit:
                if key is not None and key in fields:
                    return _span(fleet.source, fields[key][0])
                return _span(fleet.source, fields["name"][1])
    return None
