"""The command line's shared pieces (tnn_dsl/cli/_common.py)."""

from __future__ import annotations

import pytest

from tnn_dsl.cli import build_parser
from tnn_dsl.cli._common import INTEGRATORS


def test_the_parser_lists_the_compilers_integrators():
    from tnn_dsl.compiler import INTEGRATORS as compiled

    assert tuple(INTEGRATORS) == tuple(compiled)


@pytest.mark.parametrize("command", ["simulate", "estimate", "sensitivity"])
def test_integrator_choices(command, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args([command, "--integrator", "leapfrog"])
    assert "invalid choice" in capsys.readouterr().err


def test_every_command_has_help_text():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name, p in sub.choices.items():
        assert p.description and "``" not in p.description, name
