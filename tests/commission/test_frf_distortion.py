"""The margins on the measured FRF of a stage excited under its breakaway (lock-step, simulated time).

Generated plant 29 (0.60 kg, six GMS elements of 2.08e6 N/m together, no structural mode) is commissioned up to
the FRF (the run is stopped at the start of friction_cv). Its multisine stays under half the breakaway, so the
stage stands on its pre-sliding spring: the lines near √(Σk/m)/2π = 296 Hz show that spring against the mass
as a clean, linear resonance (ζ = (Σσ1 + c)/(2√(Σk·m)) = 0.11), and a loop that keeps too little gain margin
there rings at rest. The low-frequency lines, where the elements slip and re-stick, are the friction's
intermodulation products: the 11 Hz line came out with phase +45°, which no passive stage has, and alone ruled
out every PID from 22 to 35 Hz (3.3 dB for the 30 Hz one). About 3 s of CPU.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from plant_gen import hidden_plant, stage_yaml

from stagectl.cli import main
from stagectl.commission import analysis as an
from stagectl.commission import sequence as seq
from stagectl.commission.controllers import log_bins
from stagectl.control import design


def test_distorted_lines_do_not_decide_the_margins_and_the_presliding_resonance_does(tmp_path: Path) -> None:
    plant = hidden_plant(29)
    out = tmp_path / "out"
    rc = main(["commission", "--config", str(stage_yaml(tmp_path / "p29.yaml", plant)), "--out", str(out),
               "--no-plots", "--no-verify", "--quiet", "--max-stroke", "0.002", "--inject-fault", "friction_cv@0.0"])
    assert rc == 1  # the injected stop after the FRF
    data = np.genfromtxt(out / "recordings" / "frf.csv", delimiter=",", names=True)
    k0 = int(np.flatnonzero(data["u_exc"] != 0.0)[0])
    T, n = 1e-3, 1000
    bins = log_bins(n, 2, int(0.45 * n), seq.FRF_LINES)
    frf = an.estimate_frf(np.asarray(data["x"][k0:]), np.asarray(data["u"][k0:]), n, bins, T)
    frf.delay_s = 1.5 * T  # the one-cycle I/O delay and the zero-order hold's half period
    m = plant["mass_kg"]

    # a 30 Hz PID keeps its margins on the mass model and, with the distorted lines read as what they are, on
    # the measured FRF (3.3 dB at 11 Hz when the 11 Hz line counted)
    pid = design.design_pid(m, 30.0, T, 1)
    mod = design.analyse_design(m, T, pid, 1)[-1]
    assert mod.phase_margin_deg >= seq.MIN_PHASE_MARGIN_DEG and mod.gain_margin_db >= seq.MIN_GAIN_MARGIN_DB
    mm = an.measured_margins(frf, an.controller_response(frf.f_hz, T, pid, "none", 100.0, m, 1))
    assert mm.gain_margin_db >= seq.MIN_GAIN_MARGIN_DB and mm.phase_margin_deg >= seq.MIN_PHASE_MARGIN_DEG, mm

    # the impossible line: distortion dominates it, and its phase (delay taken out) leads
    i11 = int(np.argmin(np.abs(frf.f_hz - 11.0)))
    assert frf.distortion is not None and frf.distortion[i11] > an.FRF_DISTORTION_MAX, frf.distortion[i11]
    assert (frf.p[i11] * np.exp(1j * 2 * np.pi * 11.0 * frf.delay_s)).imag > 0.0, frf.p[i11]
    keep = frf.margin_lines()
    assert not keep[i11] and keep.sum() >= frf.f_hz.shape[0] - 5, frf.f_hz[~keep]
    rep = json.loads((out / "report.json").read_text())  # the sequence's own FRF says the same
    assert rep["frf"]["margin_lines_left_out_hz"] == frf.f_hz[~keep].tolist(), rep["frf"]

    # the pre-sliding resonance is clean and still limits: a 22 Hz PID + Q-filter 100 Hz, healthy on the mass
    # model, has under 8 dB at the spring's resonance (delay: the crossing a little below it)
    fr = plant["friction"]
    f0 = math.sqrt(sum(fr["k_n_m"]) / m) / (2 * math.pi)
    near = np.abs(frf.f_hz / f0 - 1.0) < 0.1
    assert near.any() and (frf.distortion[near] < 0.2).all(), frf.distortion[near]
    pid22 = design.design_pid(m, 22.0, T, 1)
    mod22 = design.analyse_design(m, T, pid22, 1, 100.0, 1, dob_mass_kg=m)[-1]
    assert mod22.phase_margin_deg >= seq.MIN_PHASE_MARGIN_DEG and mod22.gain_margin_db >= seq.MIN_GAIN_MARGIN_DB
    L22 = frf.p * an.controller_response(frf.f_hz, T, pid22, "qfilter", 100.0, m, 1)
    assert an.measured_margins(frf, L22 / frf.p).gain_margin_db < seq.MIN_GAIN_MARGIN_DB
    hi = keep & (frf.f_hz > 0.5 * f0)  # the crossing at the resonance on its own
    at_f0 = an.margins_from_response(frf.f_hz[hi], L22[hi])
    assert at_f0.gain_margin_db < seq.MIN_GAIN_MARGIN_DB, at_f0
    assert at_f0.phase_crossover_hz == pytest.approx(0.95 * f0, rel=0.08), (at_f0, f0)


def test_a_linear_loop_shows_no_distortion() -> None:
    """Plain reference (tests/commission/test_analysis.py's closed loop: a mass on a spring, exact ZOH, PD,
    0.5 nm noise): the non-excited bins hold only noise, so every line is kept."""
    from test_analysis import _closed_loop_record

    T, n_per = 1e-3, 500
    x, u, bins = _closed_loop_record(m=3.0, k=2e5, c=30.0, delay=1, T=T, n_per=n_per, periods=5)
    frf = an.estimate_frf(x, u, n_per, bins, T)
    assert frf.distortion is not None and float(frf.distortion.max()) < 0.2, frf.distortion.max()
    assert frf.margin_lines().all() and frf.linear_lines().all()


def test_no_line_is_left_out_before_the_delay_is_known() -> None:
    """A delayed damped mass, its four lowest lines distorted, the fourth with a +45° lead once the delay is out:
    with the delay measured only that line is left out; before it is (an FRF whose plant fit failed, reported as
    measured), none is, since with no delay taken out every line of a delayed mass leads (all four were left out)."""
    T, m, tau = 1e-3, 0.6, 1.5e-3
    f = np.geomspace(5.0, 300.0, 12)
    w = 2 * np.pi * f
    p = np.exp(-1j * w * tau) / (-m * w**2 + 1j * w * 20.0)
    p[3] = abs(p[3]) * np.exp(-1j * w[3] * tau + 1j * np.radians(45.0))  # leading by 45° once the delay is out
    dist = np.where(np.arange(12) < 4, 2.0, 0.1)
    frf = an.Frf(f, p.astype(np.complex128), np.abs(p) * 0.01, 3, dist)
    assert frf.margin_lines().all()
    frf.delay_s = tau
    assert frf.margin_lines().tolist() == [i != 3 for i in range(12)]
