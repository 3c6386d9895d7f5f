"""The CLI's parser stays light: listing the commands, or running a control-socket client, must not import
the controller/plant/driver stack (numpy kernels, numba, canopen: about 1 s on this machine)."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("numba", "canopen", "can", "scipy", "matplotlib", "stagectl.app", "stagectl.config.loader")

PROBE = """
import sys
from stagectl import cli
cli.build_parser({only!r})
print(",".join(m for m in {heavy!r} if m in sys.modules))
"""


def _loaded(only: str | None) -> list[str]:
    r = subprocess.run([sys.executable, "-c", PROBE.format(only=only, heavy=HEAVY)], capture_output=True,
                       text=True, timeout=120, check=True)
    return [m for m in r.stdout.strip().split(",") if m]


def test_full_parser_imports_no_heavy_module():
    assert _loaded(None) == []


def test_client_commands_import_no_heavy_module():
    assert cli_module("move") == "clients"
    assert _loaded("clients") == []


def cli_module(name: str) -> str:
    from stagectl import cli

    return cli.COMMAND_ALIASES.get(name, name.replace("-", "_"))
