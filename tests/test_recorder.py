"""The in-memory recorder of run/simulate/commission: a run longer than announced keeps every row, and growing
never copies the rows already recorded (it doubled the array in the loop thread: `stagectl run` without
--duration copied 600 000 rows at 600 s, 1.5 s of one cycle at load 7; audit16)."""

from __future__ import annotations

import tracemalloc

import numpy as np

from stagectl.recorder import Recorder


def test_rows_beyond_the_capacity_are_all_kept_in_order() -> None:
    rec = Recorder(("t", "x"), capacity=20)
    rec.block_rows = 7
    for k in range(100):
        rec.append((k * 1e-3, float(k)))
    assert rec.n == 100
    assert np.array_equal(rec.col("x"), np.arange(100.0))
    assert np.array_equal(rec.data[:, 0], np.arange(100) * 1e-3)
    rec.append((0.1, 100.0))  # appending after a read goes on
    assert np.array_equal(rec.col("x"), np.arange(101.0))


def test_growth_allocates_one_block_not_a_copy_of_the_recording() -> None:
    cols = ("t", "x", "u")
    rec = Recorder(cols, capacity=400_000)  # 9.6 MB recorded
    row = (1.0, 2.0, 3.0)
    for _ in range(400_000):
        rec.append(row)
    tracemalloc.start()
    try:
        rec.append(row)  # the first row beyond the announced length
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= 1.1 * rec.block_rows * len(cols) * 8, peak  # one block (1.6 MB), not 2 x 9.6 MB
    assert rec.n == 400_001 and rec.col("u")[-1] == 3.0
