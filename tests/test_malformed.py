"""The corpus of malformed files: each gives exactly the expected first line (tests/malformed/expected.txt),
exit status 1 and never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from tnn_dsl.cli import main

HERE = Path(__file__).parent / "malformed"


def _expected() -> dict[str, str]:
    out = {}
    for line in (HERE / "expected.txt").read_text(encoding="utf-8").splitlines():
        if line.strip():
            out[line.split(":", 1)[0]] = line
    return out


EXPECTED = _expected()


def test_corpus_is_large_and_complete():
    files = sorted(p.name for p in HERE.glob("*.thn"))
    assert len(files) >= 45
    assert sorted(EXPECTED) == files, "every malformed file has exactly one expected line"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_malformed_first_line(name, monkeypatch, capsys):
    monkeypatch.chdir(HERE)
    status = main(["check", name])
    err = capsys.readouterr().err
    assert status == 1, err
    first = err.splitlines()[0]
    assert first == EXPECTED[name]
    assert "Traceback" not in err
    # the source line and a caret follow a positioned message
    lines = err.splitlines()
    if len(lines) > 2 and " | " in lines[1]:
        assert "^" in lines[2]
