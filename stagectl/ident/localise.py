"""Where a force residual lives: motion regimes, position bands and time windows (discovery reports), and
the residual view the effects' evidence texts read."""

from __future__ import annotations

import math

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from stagectl.ident.signals import Signals

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class Disagreement:
    """Residual statistics over one slice of the validation samples (``report.json`` ``disagreement``)."""

    kind: str  # "regime", "position" or "time"
    regime: str
    samples: int
    share_of_samples: float
    rms_n: float
    mean_n: float
    share_of_squared_residual: float


def regimes(sig: Signals, rows: BoolArray) -> dict[str, BoolArray]:
    """Masks (within ``rows``) of the regimes used to localise the residual."""
    v = sig.v
    a = sig.acc_f
    sp = np.abs(v)
    vmax = float(np.percentile(sp[rows], 99)) if rows.any() else 1.0
    amax = float(np.percentile(np.abs(a[rows]), 95)) if rows.any() else 1.0
    span = float(np.ptp(sig.xf))
    d_pre = float(np.clip(0.002 * span, 5e-6, 1e-4))
    near = sig.x_rev_dist < d_pre
    low = (sp < 0.1 * vmax) & ~near
    const = (np.abs(a) < 0.1 * amax) & (sp >= 0.1 * vmax) & ~near
    accel = (np.abs(a) >= 0.3 * amax) & ~near
    out = {
        f"near_reversal (< {d_pre * 1e6:.3g} µm after a reversal)": near,
        f"low_speed (|v| < {0.1 * vmax:.3g} m/s)": low,
        "constant_speed": const,
        f"accelerating (|a| > {0.3 * amax:.3g} m/s²)": accel,
        "positive_direction": v > 0,
        "negative_direction": v < 0,
    }
    return {k: m & rows for k, m in out.items()}


def _slice(kind: str, regime: str, rr: FloatArray, nrows: int, tot: float) -> Disagreement:
    k = int(rr.size)
    return Disagreement(kind, regime, k, k / nrows, float(np.sqrt(np.mean(rr * rr))), float(np.mean(rr)),
                        float(np.sum(rr * rr)) / tot)


def localise(sig: Signals, rows: BoolArray, resid_all: FloatArray, n_windows: int = 12) -> list[Disagreement]:
    """Where the residual lives: per regime, per position band and per time window (on ``rows``)."""
    out: list[Disagreement] = []
    r = resid_all
    tot = float(np.sum(r[rows] ** 2)) or 1.0
    nrows = int(rows.sum()) or 1
    for name, m in regimes(sig, rows).items():
        if m.any():
            out.append(_slice("regime", name, r[m], nrows, tot))
    x = sig.xf
    lo, hi = float(x[rows].min()), float(x[rows].max())
    edges = np.linspace(lo, hi, 9)
    for i in range(8):
        m = rows & (x >= edges[i]) & (x <= edges[i + 1])
        if m.any():
            out.append(_slice("position", f"x in [{edges[i]:.6g}, {edges[i + 1]:.6g}] m", r[m], nrows, tot))
    t = sig.t
    for w in np.array_split(np.flatnonzero(rows), n_windows):
        if w.size:
            out.append(_slice("time", f"t in [{t[w[0]]:.3f}, {t[w[-1]]:.3f}] s", r[w], nrows, tot))
    return out


@dataclass(frozen=True)
class ResidualView:
    """The validation residual of the model *before* an effect was added, as the effect's evidence text
    reads it: ``sig`` and ``rows`` are the validation signals and rows, ``r`` the residual [N] (all samples)."""

    sig: Signals
    rows: BoolArray
    r: FloatArray

    @property
    def mean_positive_n(self) -> float:
        """Mean residual [N] while moving towards +x."""
        pos = self.rows & (self.sig.v > 0)
        return float(np.mean(self.r[pos])) if pos.any() else 0.0

    @property
    def mean_negative_n(self) -> float:
        """Mean residual [N] while moving towards −x."""
        neg = self.rows & (self.sig.v < 0)
        return float(np.mean(self.r[neg])) if neg.any() else 0.0

    @property
    def both_directions(self) -> bool:
        """At least 10 % of the evaluated samples move each way (direction evidence is meaningful)."""
        n = int(self.rows.sum())
        pos = int((self.rows & (self.sig.v > 0)).sum())
        return n > 0 and 0.1 * n <= pos <= 0.9 * n

    @cached_property
    def regimes(self) -> dict[str, BoolArray]:
        return regimes(self.sig, self.rows)

    def regime_text(self, prefix: str) -> str:
        """:meth:`regime_rms` for a report: ``"0.001792 N"``, or ``"no samples"`` where the regime is empty
        (a recording with no constant-speed stretch printed "nan N at constant speed")."""
        r = self.regime_rms(prefix)
        return f"{r:.4g} N" if math.isfinite(r) else "no samples"

    def regime_rms(self, prefix: str) -> float:
        """RMS residual [N] in the first regime whose name starts with ``prefix`` (NaN if empty)."""
        for k, m in self.regimes.items():
            if k.startswith(prefix) and m.any():
                return float(np.sqrt(np.mean(self.r[m] ** 2)))
        return float("nan")
