"""``stagectl bench startup`` runs the real ``stagectl run`` in a child and reads its time stamps: the hooks it
places on ``load_app_config``, ``build_stage`` and ``LoopHost.start`` must find those names, and the stamps must
come in the order the command takes (structure only; no time is asserted); byte code is written once, by the
priming start."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from stagectl.bench import startup


def test_one_start_is_measured_to_the_first_cycle_in_order(tmp_path: Path) -> None:
    """The priming start writes the byte code of what the command imports (stagectl's own modules included) into
    the private prefix; a measured start reads it and writes none."""
    r = startup._one(sys.executable, str(startup.REPO_CONFIG), tmp_path / "numba", tmp_path / "pyc", prime=True)
    parts = ("interpreter_s", "imports_s", "config_s", "build_s", "start_and_first_cycle_s")
    assert all(r[p] >= 0.0 for p in parts), r
    assert sum(r[p] for p in parts) == pytest.approx(r["first_cycle_s"], abs=1e-6)
    assert r["process_cpu_s"] > 0.0
    assert any((tmp_path / "numba").rglob("*.nbi"))  # the child used the private cache it was given
    written = {p.name.split(".")[0] for p in (tmp_path / "pyc").rglob("*.pyc")}
    assert {"controller", "plant", "gms", "cli"} <= written, sorted(written)[:20]
    startup._one(sys.executable, str(startup.REPO_CONFIG), tmp_path / "numba", tmp_path / "pyc2")
    assert not any((tmp_path / "pyc2").rglob("*.pyc"))
