"""Irregular time stamps (issue 13): jittered stamps of a uniform sampling, truly irregular sampling, dropped
samples and a long hole each give a usable recording with a note, never a refusal or a traceback."""

from __future__ import annotations

import numpy as np

from stagectl.ident.discover import fit_start, make_dataset
from stagectl.ident.recording import Recording
from stagectl.ident.signals import filter_reach, prepare, resample_uniform

DT = 1e-3
M, FC, FV = 2.0, 1.0, 20.0


def _motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and the force [N] that moves a 2 kg stage with Coulomb + viscous friction along it."""
    w1, w2 = 2 * np.pi * 0.7, 2 * np.pi * 1.9
    x = 2e-3 * np.sin(w1 * t) + 0.5e-3 * np.sin(w2 * t)
    v = 2e-3 * w1 * np.cos(w1 * t) + 0.5e-3 * w2 * np.cos(w2 * t)
    a = -2e-3 * w1 ** 2 * np.sin(w1 * t) - 0.5e-3 * w2 ** 2 * np.sin(w2 * t)
    return x, M * a + FC * np.tanh(v / 1e-4) + FV * v


def _rec(t_true: np.ndarray, t_stamp: np.ndarray, rng: np.random.Generator) -> Recording:
    x, u = _motion(t_true)
    x = x + 2e-9 * rng.standard_normal(x.size)
    return Recording(t_stamp, x, u, None, None, "test.csv", {})


def _uniform_evaluated() -> int:
    t = DT * np.arange(6000)
    return int(prepare(_rec(t, t, np.random.default_rng(0))).evaluate.sum())


def test_jittered_stamps_of_a_uniform_sampling_keep_the_samples() -> None:
    """Host-side stamps ±40 % of a period around a uniform sampling: the samples are kept on the uniform time
    base (a resampling by the stamps would turn the stamp error into position error v·δt and refuse or
    invent a delay)."""
    rng = np.random.default_rng(1)
    t = DT * np.arange(6000)
    sig = prepare(_rec(t, t + rng.uniform(-0.4, 0.4, t.size) * DT, rng))
    assert any("time-stamp jitter" in n for n in sig.notes), sig.notes
    assert abs(sig.dt_s - DT) < 1e-3 * DT
    assert sig.evaluate.sum() >= 0.9 * _uniform_evaluated()


def test_truly_irregular_sampling_is_resampled_and_kept() -> None:
    """Samples really taken at irregular times (stamps right): resampled, and the grid samples between close
    measured ones are used, not excluded as unmeasured."""
    rng = np.random.default_rng(2)
    t = DT * np.arange(6000) + rng.uniform(-0.4, 0.4, 6000) * DT
    sig = prepare(_rec(t, t, rng))
    assert any("resampled onto a uniform" in n for n in sig.notes), sig.notes
    assert sig.evaluate.sum() >= 0.9 * _uniform_evaluated()


def test_randomly_dropped_samples_are_bridged_and_held_out_blocks_work() -> None:
    """30 % of the rows lost at random (a polled drive): short holes are interpolated; held-out validation
    blocks are cut from the resampled recording."""
    rng = np.random.default_rng(3)
    t = DT * np.arange(6000)
    keep = rng.random(t.size) > 0.3
    keep[[0, -1]] = True
    ds = make_dataset(_rec(t[keep], t[keep], rng))
    assert ds.est.evaluate.sum() >= 0.7 * _uniform_evaluated()
    assert "held-out" in ds.split and ds.val_rows.sum() > 500


def test_samples_the_filter_carries_a_long_hole_into_are_not_evaluated() -> None:
    """A 1 s hole: nothing within the low-pass's reach of it is evaluated (the held command and the interpolated
    position across the hole are made up)."""
    rng = np.random.default_rng(4)
    t = DT * np.arange(8000)
    keep = np.ones(t.size, bool)
    keep[3000:4000] = False
    sig = prepare(_rec(t[keep], t[keep], rng))
    reach = filter_reach(sig.sos)
    assert reach > sig.guard
    assert not sig.evaluate[3000 - reach : 4000 + reach].any()
    assert sig.evaluate[: 3000 - reach].sum() > 1000 and sig.evaluate[4000 + reach :].sum() > 1000


def test_positions_in_mm_or_time_in_ms_give_a_unit_note() -> None:
    """A recording in mm (or ms) written as SI runs, with a note naming the likely unit; SI gives none."""
    t = DT * np.arange(3000)
    rec = _rec(t, t, np.random.default_rng(5))
    assert not any(n.startswith("units:") for n in prepare(rec).notes)
    mm = Recording(rec.t, 1e3 * rec.x, rec.u, None, None, "mm.csv", {})
    mm.x = 1e3 * mm.x  # positions in µm: a 5 mm stroke spans 5000 "m"
    assert any(n.startswith("units: the positions span") and "µm" in n for n in prepare(mm).notes)
    ms = Recording(1e3 * rec.t, rec.x, rec.u, None, None, "ms.csv", {})
    assert any(n.startswith("units: the sample period") and "ms" in n for n in prepare(ms).notes)


def _closed_loop_null(seconds: float = 24.0, fs: float = 608.598487560893) -> tuple[Recording, float]:
    """A plain closed-loop recording with nothing hidden: a mass with Coulomb + viscous friction (smoothed over
    10 µm/s) under a sampled PD law with feed-forward tracking a sine, the command held over each period (ZOH, u[k] acts from t[k]),
    positions quantised to 1 nm, time stamps written to 1 ns as a CSV would (so the median period is not
    exactly the true one). Returns the recording and the true mass [kg]."""
    m, fc, fv, kp, kd = 1.7, 0.8, 43.6, 2.0e3, 20.0
    dt, sub = 1.0 / fs, 8
    h = dt / sub
    n = int(seconds * fs)
    t = dt * np.arange(n)
    w = 2 * np.pi * 0.45
    ref, vref, aref = 2e-3 * np.sin(w * t), 2e-3 * w * np.cos(w * t), -2e-3 * w * w * np.sin(w * t)
    xs, us = np.empty(n), np.empty(n)
    x = v = 0.0
    e_prev = 0.0
    for k in range(n):
        xm = 1e-9 * round(x / 1e-9)
        e = ref[k] - xm
        u = m * aref[k] + fc * np.tanh(vref[k] / 1e-5) + fv * vref[k] + kp * e + kd * (e - e_prev) / dt
        e_prev = e
        xs[k], us[k] = xm, u
        for _ in range(sub):  # semi-implicit Euler, fine steps
            a = (u - fc * np.tanh(v / 1e-5) - fv * v) / m
            v += h * a
            x += h * v
    return Recording(np.round(t, 9), xs, us, None, None, "null_hole.csv", {}), m


def test_a_hole_does_not_lag_the_command_or_bias_the_mass() -> None:
    """A null recording with a 3 s hole is resampled at its median period, which drifts against stamps rounded
    to 1 ns: each measured grid sample must keep its own command (a "last sample at or before the grid time"
    rule took the previous one at nearly every grid time, a one-period lag of u behind x; the mass came out
    3 % low and the residual right after reversals, where the loop's command changes fastest, named
    pre-sliding on a recording with nothing hidden)."""
    rec, m_true = _closed_loop_null()
    keep = np.ones(rec.t.size, bool)
    keep[8000:8000 + int(3.0 / (rec.t[1] - rec.t[0]))] = False
    holed = Recording(rec.t[keep], rec.x[keep], rec.u[keep], None, None, rec.source, {})
    dt = float(np.median(np.diff(holed.t)))
    out, synthetic, _ = resample_uniform(holed, dt, bridge=5)
    # every measured grid sample carries the command of the measured sample it stands for
    j = np.clip(np.searchsorted(holed.t, out.t), 1, holed.t.size - 1)
    nearest = np.where(np.abs(holed.t[j - 1] - out.t) < np.abs(holed.t[j] - out.t), j - 1, j)
    measured = ~synthetic
    assert np.array_equal(out.u[measured], holed.u[nearest[measured]])
    # the start model's mass is unbiased, as without the hole
    fit = fit_start(make_dataset(holed))
    assert abs(fit.hyp.theta["m"] / m_true - 1.0) < 0.01, fit.hyp.theta
