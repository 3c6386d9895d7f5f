"""``stagectl bench startup`` runs the real ``stagectl run`` in a child and reads its time stamps: the hooks it
places on ``load_app_config``, ``build_stage`` and ``LoopHost.start`` must find those names, and the stamps must
come in the order the command takes (structure only; no time is asserted)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from stagectl.bench import startup


def test_one_start_is_measured_to_the_first_cycle_in_order(tmp_path: Path) -> None:
    r = startup._one(sys.executable, str(startup.REPO_CONFIG), tmp_path / "numba")
    parts = ("interpreter_s", "imports_s", "config_s", "build_s", "start_and_first_cycle_s")
    assert all(r[p] >= 0.0 for p in parts), r
    assert sum(r[p] for p in parts) == pytest.approx(r["first_cycle_s"], abs=1e-6)
    assert r["process_cpu_s"] > 0.0
    assert any((tmp_path / "numba").rglob("*.nbi"))  # the child used the private cache it was given
