"""Every registered ingest adapter satisfies the one adapter contract, and the ingest command lists them all."""

from __future__ import annotations

import inspect

import pytest
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.ingest.registry import ADAPTERS, Adapter, load_adapter


@pytest.mark.parametrize("command", sorted(ADAPTERS))
def test_adapter_satisfies_the_contract(command: str) -> None:
    adapter = load_adapter(command)
    assert isinstance(adapter, Adapter)
    assert adapter.KIND in ("olat", "flat") and adapter.NAME
    assert list(inspect.signature(adapter.detect).parameters) == ["src"]
    assert list(inspect.signature(adapter.plan).parameters) == ["src", "options"]


def test_a_module_without_plan_breaks_the_contract() -> None:
    class Incomplete:
        NAME, KIND = "x", "flat"

        @staticmethod
        def detect(src):
            return "v1"

    assert not isinstance(Incomplete(), Adapter)


def test_ingest_command_has_one_subcommand_per_adapter() -> None:
    result = CliRunner().invoke(cli, ["ingest", "--help"])
    assert result.exit_code == 0
    for command in ADAPTERS:
        assert f"  {command} " in result.output
