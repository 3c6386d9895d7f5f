"""Simulated CiA 406 linear encoder: its own node id, position value 0x6004 (UNSIGNED32, counts modulo
2³²) in TPDO1 on every SYNC, reading the same plant as the drive.

At each SYNC (after the drive has stepped the plant, :class:`~stagectl.sim.world.SimWorld` dispatches
SYNC to the drive first)::

    0x6004 = round((plant.measure() + jump) / resolution_m) mod 2³²

NMT, heartbeat, SDO, PDO engine and fault injection come from
:class:`~stagectl.sim.cia402_drive.SimCanopenDevice`; ``drive_fault`` on an encoder sets the operating
status 0x6500 error bit and sends the EMCY (no state machine).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
from stagectl.sim.cia402_drive import SimCanopenDevice
from stagectl.sim.faults import SimFault

from stagectl.resources import EDS_DIR
from stagectl.world_schema import SimEncoderConfig as SimEncoderConfig


class SimCia406Encoder(SimCanopenDevice):
    """Simulated CiA 406 encoder (see module docstring)."""

    def __init__(self, plant: Any, cfg: SimEncoderConfig, send: Callable[[can.Message], None],
                 base_dir: Path | None = None) -> None:
        eds = Path(cfg.eds_file) if cfg.eds_file else EDS_DIR / "stagectl_cia406.eds"
        if base_dir is not None and not eds.is_absolute():
            eds = base_dir / eds
        super().__init__(cfg.node_id, eds, send, "encoder")
        self.plant = plant
        self.cfg = cfg
        self.jump_m = 0.0
        self.status = 0
        self.position_counts = self._sample()

    def _sample(self) -> int:
        return round((float(self.plant.measure()) + self.jump_m) / self.cfg.resolution_m) & 0xFFFFFFFF

    def live_value(self, index: int, sub: int) -> int | None:
        if index == 0x6004:
            return self.position_counts
        if index == 0x6500:
            return self.status
        if index == 0x6005 and sub == 1:
            return max(1, round(self.cfg.resolution_m * 1e9))
        return super().live_value(index, sub)

    def on_internal_error(self) -> None:
        self.status |= 0x0001  # operating status 0x6500: error (EMCY 0x6100 already sent)

    def on_sync(self, active: set[SimFault]) -> None:
        if SimFault.DRIVE_FAULT in active:
            spec = self.faults.spec_of(SimFault.DRIVE_FAULT)
            self.status |= 0x0001
            self.send_emcy(spec.code if spec else 0x5000)
        self.jump_m = self.faults.jump_m(active)
        self.position_counts = self._sample()
