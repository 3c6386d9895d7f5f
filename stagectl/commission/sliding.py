"""Which constant sliding speeds the chosen loop cannot hold: friction that falls with speed faster than
viscous damping rises.

Sliding at a speed v > 0, the fitted curve F(v) = F_c + (F_s − F_c)·exp(−(v/v_s)^δ) + F_v·v
(:func:`stagectl.commission.analysis.stribeck_curve_at`) acts on small speed deviations as a damper of
coefficient

    c(v) = dF/dv = F_v − (F_s − F_c)·(δ/v_s)·(v/v_s)^(δ−1)·exp(−(v/v_s)^δ)        [N·s/m]

which is negative on a steep Stribeck drop: an open-loop unstable plant 1/(m·s² + c·s) (pole at −c/m > 0).
The loop holds that speed only if the linear loop :mod:`stagectl.control.design` uses for the gains
(:func:`~stagectl.control.design.plant_tf` with damping c and the I/O delay, the PID, the Q-filter observer with
its command delay) is closed-loop stable there; below the loop's negative-damping limit c_min it is not and
constant-speed motion limit-cycles near the frequency of the unstable closed-loop pair. A feed-forward evaluated
on the reference cannot cancel this (it does not see the speed deviation). The check is the linearisation about
each speed; the exact model of the stage (same friction, same gains) does the same.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from stagectl.control.pid import PidConfig

#: speed grid of the check: log-spaced from v_s·GRID_LO to v_s·GRID_HI, GRID_POINTS points
GRID_LO, GRID_HI, GRID_POINTS = 1e-3, 1e2, 121


def net_slope(curve: dict[str, float], v: np.ndarray) -> np.ndarray:
    """dF/dv [N·s/m] of the fitted sliding curve at speeds ``v`` > 0 [m/s] (module docstring)."""
    vs, d = float(curve["vs_m_s"]), float(curve["delta"])
    u = np.asarray(v, np.float64) / vs
    drop = (float(curve["fs_n"]) - float(curve["fc_n"])) * (d / vs) * u ** (d - 1.0) * np.exp(-u ** d)
    return np.asarray(float(curve["viscous_n_s_m"]) - drop, np.float64)


def _closed_loop_poles(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int, dob_kind: str,
                       dob_bandwidth_hz: float, damping_n_s_m: float) -> np.ndarray:
    import control

    from stagectl.control import design

    P = design.plant_tf(mass_kg, period_s, delay_samples, damping_n_s_m)
    C = design.pid_tf(pid, period_s)
    if dob_kind == "qfilter" and dob_bandwidth_hz > 0.0:
        Hu, Hy = design.qfilter_tfs(mass_kg, dob_bandwidth_hz, period_s, delay_samples)
        L = design.dob_loop(P, C, Hu, Hy, period_s)
    else:
        L = control.ss(P) * control.ss(C)
    return np.asarray(control.poles(control.feedback(L, 1)), dtype=complex)


def _stable(poles: np.ndarray) -> bool:
    return bool(np.all(np.abs(poles) < 1.0))


def damping_limit(mass_kg: float, period_s: float, pid: PidConfig, delay_samples: int, dob_kind: str,
                  dob_bandwidth_hz: float, c_floor_n_s_m: float, tol_n_s_m: float = 1.0) -> float | None:
    """The most negative plant damping [N·s/m] down to ``c_floor_n_s_m`` (< 0) the loop stays stable with
    (bisection to ``tol_n_s_m``); None when it is stable at the floor too; 0.0 when it is not stable even on
    the damping-free plant (it tolerates no negative damping at all; a bisection that assumed stability at 0
    would report a limit near 0 as if it were measured)."""
    def ok(c: float) -> bool:
        return _stable(_closed_loop_poles(mass_kg, period_s, pid, delay_samples, dob_kind, dob_bandwidth_hz, c))

    if ok(c_floor_n_s_m):
        return None
    if not ok(0.0):
        return 0.0
    hi, lo = 0.0, c_floor_n_s_m  # ok(hi), not ok(lo)
    while hi - lo > tol_n_s_m:
        mid = 0.5 * (hi + lo)
        if ok(mid):
            hi = mid
        else:
            lo = mid
    return hi


def unstable_sliding(curve: dict[str, float] | None, mass_kg: float, period_s: float, pid: PidConfig,
                     delay_samples: int, dob_kind: str, dob_bandwidth_hz: float) -> dict[str, Any] | None:
    """Speeds at which the chosen loop cannot hold constant sliding on ``curve`` (the fitted Stribeck curve;
    None: nothing to check, returns None).

    Over a log-spaced grid (``GRID_LO``..``GRID_HI`` × v_s) the net slope c(v) (:func:`net_slope`); at each
    negative one, the linear loop with damping c(v) (:func:`_closed_loop_poles`). Returns the bands of
    unstable speeds ``bands_m_s`` ([[v_lo, v_hi], ...]; each edge bisected between its outer unstable grid
    point and the stable neighbour), the worst
    (most negative) slope and its speed, the loop's negative-damping limit (:func:`damping_limit`), and the
    frequency [Hz] of the unstable closed-loop pair at the worst slope and at the band's onset (the onset's is
    near the limit cycle's). ``confidence``: high (a linearisation of the fitted curve with the chosen gains;
    the curve's own uncertainty moves the band's edges), medium where a band reaches below the curve's slowest
    sliding pass ``v_min_m_s`` (extrapolated), low on a flat curve (``stribeck_identified`` False); then
    ``confidence_why`` says so."""
    if not curve or not all(k in curve for k in ("fs_n", "fc_n", "vs_m_s", "delta", "viscous_n_s_m")):
        return None
    if not (float(curve["vs_m_s"]) > 0.0 and float(curve["delta"]) > 0.0):
        return None
    v = float(curve["vs_m_s"]) * np.logspace(math.log10(GRID_LO), math.log10(GRID_HI), GRID_POINTS)
    c = net_slope(curve, v)
    i_w = int(np.argmin(c))
    out: dict[str, Any] = {"grid_m_s": [float(v[0]), float(v[-1]), GRID_POINTS],
                           "worst_net_slope_n_s_m": float(c[i_w]), "worst_speed_m_s": float(v[i_w]),
                           "bands_m_s": [], "damping_limit_n_s_m": None, "limit_cycle_hz": None,
                           "confidence": "high"}
    neg = np.nonzero(c < 0.0)[0]
    if neg.size == 0:
        out["why"] = "the net slope (viscous + Stribeck drop) is nowhere negative: sliding is damped at every speed"
        return out
    args = (mass_kg, period_s, pid, delay_samples, dob_kind, dob_bandwidth_hz)
    bad = np.zeros(v.size, bool)
    for i in neg.tolist():
        bad[i] = not _stable(_closed_loop_poles(*args, float(c[i])))
    out["damping_limit_n_s_m"] = damping_limit(*args, min(float(c[i_w]), -1.0) * 1.5)
    bands: list[list[float]] = []
    for i in np.nonzero(bad)[0].tolist():
        if bands and bad[i - 1]:
            bands[-1][1] = float(v[i])
        else:
            bands.append([float(v[i]), float(v[i])])

    def unstable_at(x: float) -> bool:
        return not _stable(_closed_loop_poles(*args, float(net_slope(curve, np.array([x]))[0])))

    def edge(a: float, b: float) -> float:  # unstable at a, stable at b: the crossing, to 0.1 % (log bisection)
        for _ in range(8):
            mid = math.sqrt(a * b)
            a, b = (mid, b) if unstable_at(mid) else (a, mid)
        return math.sqrt(a * b)

    step = float(v[1] / v[0])
    for band in bands:  # the band's edges between its outer grid points and their stable neighbours
        if band[0] > v[0]:
            band[0] = edge(band[0], band[0] / step)
        if band[1] < v[-1]:
            band[1] = edge(band[1], band[1] * step)
    out["bands_m_s"] = bands
    # the curve is measured only over the sliding passes: a flat curve (no drop identified: only its viscous
    # slope) or a band below the slowest pass (the drop there is the curve's extrapolation, where passes that
    # stick-slip are left out) is not the high-confidence linearisation of a measured curve
    v_min = float(curve.get("v_min_m_s", 0.0) or 0.0)
    if curve.get("stribeck_identified") is False:
        out["confidence"] = "low"
        out["confidence_why"] = "no Stribeck drop was identified: the band comes from the fitted viscous slope alone"
    elif v_min > 0.0 and any(a < v_min for a, _ in bands):
        out["confidence"] = "medium"
        out["confidence_why"] = (f"below the slowest sliding pass ({1e3 * v_min:.2g} mm/s) the curve is "
                                 "extrapolated")
    if not bands:
        out["why"] = "the net slope is negative but the loop stays stable at every grid speed"
        return out

    def unstable_hz(cv: float) -> float:
        p = _closed_loop_poles(*args, cv)
        p = p[np.abs(p) >= 1.0]
        return float(np.max(np.abs(np.angle(p)))) / (2 * math.pi * period_s) if p.size else math.nan

    out["worst_unstable_hz"] = unstable_hz(float(c[i_w]))
    lim = out["damping_limit_n_s_m"]
    out["limit_cycle_hz"] = unstable_hz((lim if lim is not None else float(c[i_w])) - 1.0)
    return out


def band_words(band: list[float], grid: list[float] | None, sep: str = " and ") -> str:
    """A band [v_lo, v_hi] [m/s] in words (mm/s): an end that is the grid's end (``grid_m_s``: the band runs on
    beyond the speeds checked, e.g. a δ <= 1 drop steepest at v → 0, or a negative viscous slope) is no edge and
    is not given as one. A closed band reads "a{sep}b mm/s"."""
    a, b = band
    lo = grid is not None and a <= float(grid[0]) * (1 + 1e-9)
    hi = grid is not None and b >= float(grid[1]) * (1 - 1e-9)
    if lo and hi:
        return f"over the whole range checked ({1e3 * a:.2g} to {1e3 * b:.2g} mm/s, and likely beyond)"
    if lo:
        return f"up to {1e3 * b:.2g} mm/s (and below the slowest checked, {1e3 * a:.2g} mm/s)"
    if hi:
        return f"from {1e3 * a:.2g} mm/s (and above the fastest checked, {1e3 * b:.2g} mm/s)"
    return f"{1e3 * a:.2g}{sep}{1e3 * b:.2g} mm/s"


def sliding_line(s: dict[str, Any] | None) -> str | None:
    """report.md's sentence for :func:`unstable_sliding`'s result (None: nothing to say)."""
    if not s or not s.get("bands_m_s"):
        return None
    grid = s.get("grid_m_s")
    words = [band_words(bd, grid) for bd in s["bands_m_s"]]
    closed = all(w[:1].isdigit() for w in words)
    bands = " and ".join(words)
    hz = s.get("limit_cycle_hz")
    lim = s.get("damping_limit_n_s_m")
    return ((f"Constant speeds between {bands}" if closed else f"Constant speeds {bands}") + " will limit-cycle"
            + (f" near {hz:.2g} Hz" if hz is not None and math.isfinite(hz) else "")
            + " with these gains (confidence " + str(s.get("confidence"))
            + (f": {s['confidence_why']}" if s.get("confidence_why") else "") + "; the edges move with the fitted "
            "curve's v_s and δ, and near them the cycle grows slowly): the fitted friction falls with "
            f"speed faster than viscous damping rises (net slope down to {s['worst_net_slope_n_s_m']:.3g} N s/m at "
            f"{1e3 * s['worst_speed_m_s']:.2g} mm/s), beyond the "
            + (f"{lim:.3g} N s/m" if lim is not None else "given")
            + " of negative damping the loop stays stable with; the exact model does the same, and the "
            "feed-forward cannot cancel it. A stated limit, not a gains change (report.json "
            "gains.unstable_sliding).")
