"""`tnn_dsl.core.memory.huge_pages_environment` and the `tnnc` console script (`tnn_dsl.cli.entry`) that starts the
model doctor's commands again in it (`diagnose`, `demo`): glibc's tunable for transparent huge pages on the blocks
`malloc` maps, asked for only where it changes something, never twice, never for other commands, and not with
`TNN_HUGE_PAGES=0`."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tnn_dsl.core import memory
from tnn_dsl.core.memory import GLIBC_HUGETLB, HUGE_PAGES_ENV, huge_pages_environment


@pytest.mark.parametrize("tunables, expected", [
    (None, "glibc.malloc.hugetlb=1"),
    ("", "glibc.malloc.hugetlb=1"),
    ("glibc.malloc.arena_max=2", "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"),
])
def test_the_tunable_is_added_to_what_the_environment_sets(tunables, expected):
    env = {"PATH": "/usr/bin"} if tunables is None else {"PATH": "/usr/bin", "GLIBC_TUNABLES": tunables}
    got = huge_pages_environment(env, thp_mode="madvise", glibc_version=(2, 36))
    assert got == {"PATH": "/usr/bin", "GLIBC_TUNABLES": expected}
    assert env.get("GLIBC_TUNABLES") == tunables  # the caller's mapping is left as it was


@pytest.mark.parametrize("env, thp_mode, version", [
    ({}, "always", (2, 36)),  # the kernel gives huge pages without being asked
    ({}, "never", (2, 36)),  # nor at all
    ({}, None, (2, 36)),  # a kernel that does not say
    ({}, "madvise", (2, 34)),  # a glibc without the tunable
    ({}, "madvise", None),  # not glibc
    ({HUGE_PAGES_ENV: "0"}, "madvise", (2, 36)),  # turned off
    ({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, "madvise", (2, 36)),  # the user's own choice
    ({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}, "madvise", (2, 36)),  # already started again: never twice
])
def test_no_environment_where_the_tunable_changes_nothing_or_is_not_wanted(monkeypatch, env, thp_mode, version):
    monkeypatch.setattr(memory, "_thp_mode", lambda: thp_mode)  # the machine, as the parameters say
    monkeypatch.setattr(memory, "_glibc_version", lambda: version)
    assert huge_pages_environment(env) is None
    if thp_mode == "madvise" and version == (2, 36):  # only the environment stands in the way
        assert huge_pages_environment({}) is not None


@pytest.mark.parametrize("text, mode", [("always [madvise] never\n", "madvise"), ("[always] madvise never", "always"),
                                        ("always madvise [never]", "never"), ("garbled", None)])
def test_the_kernels_mode_is_the_one_in_brackets(tmp_path, monkeypatch, text, mode):
    f = tmp_path / "enabled"
    f.write_text(text)
    monkeypatch.setattr(memory, "THP_MODE_FILE", str(f))
    assert memory._thp_mode() == mode
    monkeypatch.setattr(memory, "THP_MODE_FILE", str(tmp_path / "missing"))
    assert memory._thp_mode() is None


CHILD = ("import os, sys; print(os.environ.get('GLIBC_TUNABLES', '-'), flush=True); "
         "from tnn_dsl.cli import entry; entry()")


def _tnnc(*args: str, **extra: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", HUGE_PAGES_ENV)}
    out = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True, timeout=120,
                         env={**env, **extra}, check=True)
    return out.stdout.splitlines()


def test_the_doctors_commands_start_again_in_that_environment_and_others_do_not():
    """The child prints its ``GLIBC_TUNABLES`` before ``entry()``: a program started again prints it a second time,
    with the tunable; it then runs the command (its help here) as usual."""
    wanted = huge_pages_environment({}) is not None  # this machine: glibc ≥ 2.35 and the kernel's mode madvise
    lines = _tnnc("diagnose", "--help")
    assert lines[0] == "-"
    if wanted:
        assert lines[1] == f"{GLIBC_HUGETLB}=1" and lines[2].startswith("usage: tnnc diagnose"), lines[:3]
    else:
        assert lines[1].startswith("usage: tnnc diagnose"), lines[:2]
    demo = _tnnc("--debug", "demo", "--help")  # the command after the global option
    assert demo[1] == f"{GLIBC_HUGETLB}=1" if wanted else demo[1].startswith("usage: tnnc demo"), demo[:2]
    for other in ("check", "fleet"):  # not the doctor in this process (fleet's run in Ray's workers)
        lines = _tnnc(other, "--help")
        assert lines[0] == "-" and lines[1].startswith(f"usage: tnnc {other}"), lines[:2]
    off = _tnnc("diagnose", "--help", **{HUGE_PAGES_ENV: "0"})
    assert off[0] == "-" and off[1].startswith("usage: tnnc diagnose"), off[:2]
