"""Inverse-dynamics signals for identification (zero-order-hold consistent, noise-filtered).

Plant ``m·a = u(t) − F_fric − F_other`` with ``u`` held over ``[t[k], t[k+1])`` (docs/recordings.md). For a
rigid body driven by a piecewise-constant force the second difference of the sampled position is exact::

    x[k+1] − 2·x[k] + x[k−1] = dt² · (a_{k−1} + a_k) / 2

where ``a_j`` is the (constant) acceleration over ``[t[j], t[j+1])``. So the second difference at ``k`` is
paired with the **average** commanded force ``ū[k] = (u[k−1] + u[k]) / 2``, never with ``u[k]`` alone
(that pairing invents half a sample of delay, docs/discovery.md §3). A delay τ = (n + f)·dt of the applied
force shifts ``u`` by linear interpolation between samples, which is exact for a zero-order hold.

Noise: the raw second difference of a quantised position is very noisy, so every term of the linear
relation ``ū = m·a + F`` is passed through the *same* zero-phase low-pass filter ``L`` (Butterworth,
``filtfilt``). Because ``L`` is linear and identical on both sides, the relation still holds for the
filtered signals (Gautier-style parallel filtering) and no phase lag is introduced.

Stick phases (docs/discovery.md §5): while the stage is at rest the friction force is anywhere in ±Fs, so the
inverse-dynamics residual says nothing there. Samples whose raw central displacement ``x[k+1] − x[k−1]`` is within the noise band (6·√2 noise std or 2.5
counts), or with ``|v| <= v_stick``, are *stuck*; the raw residual
is set to zero there **before** filtering (so it does not leak into neighbouring samples) and the samples
within ``guard`` samples of a stuck one are not evaluated.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from stagectl.errors import DataError
from stagectl.ident._filter import butter_lowpass_sos, filtfilt_rows, sosfiltfilt
from stagectl.ident.recording import Recording

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


#: default low-pass cut-off cap [Hz]: friction and plant effects of a position-controlled stage (loop
#: bandwidths of tens of Hz) live well below it, whatever the sample rate
DEFAULT_MAX_CUTOFF_HZ = 100.0

#: bytes of cached arrays a :class:`Signals` keeps (:class:`ArrayCache`); a long recording's shape searches
#: otherwise cache every column they ever tried (660 MB on the 25 000-sample EMPS file, 850 MB resident; 325 MB with this budget, the same CPU time)
CACHE_BUDGET_BYTES = 48 * 2**20


class ArrayCache(dict[str, object]):
    """The ``Signals.cache`` dict: values that are numpy arrays are dropped least recently used beyond
    ``budget`` bytes (other values, e.g. dicts of scalars, are kept). Callers recompute what is gone."""

    def __init__(self, budget: int = CACHE_BUDGET_BYTES) -> None:
        super().__init__()
        self.budget = budget
        self.nbytes = 0
        self._lru: OrderedDict[str, int] = OrderedDict()  # array keys, least recently used first, with nbytes

    def get(self, key: str, default: object = None) -> object:
        try:
            self._lru.move_to_end(key)  # an array: now the most recently used
        except KeyError:
            return dict.get(self, key, default)
        return dict.__getitem__(self, key)

    def __setitem__(self, key: str, value: object) -> None:
        if key in self._lru:
            self.nbytes -= self._lru.pop(key)
        dict.__setitem__(self, key, value)
        if isinstance(value, np.ndarray):
            self._lru[key] = value.nbytes
            self.nbytes += value.nbytes
            while self.nbytes > self.budget and len(self._lru) > 1:
                old, size = self._lru.popitem(last=False)
                dict.__delitem__(self, old)
                self.nbytes -= size


#: samples on each side of a stick phase also treated as stuck (they contain the transition)
ERODE = 2


def lowpass_sos(cutoff_hz: float, fs_hz: float, order: int = 4) -> FloatArray:
    """Butterworth low-pass in second-order sections (cut-off clipped below Nyquist)."""
    wn = min(cutoff_hz / (0.5 * fs_hz), 0.95)
    return butter_lowpass_sos(order, wn)


@dataclass
class Signals:
    """Pre-processed recording (all arrays length ``n``, SI units).

    Attributes
    ----------
    t, x, u : raw time [s], position [m], commanded force [N]
    dt_s : sample period [s] (median)
    xf : zero-phase filtered position [m]
    v : velocity of ``xf`` by central difference [m/s]
    acc_f : filtered acceleration ``L[a_raw]`` [m/s²] (ZOH-consistent second difference)
    acc_raw : raw second difference / dt² [m/s²] (0 at the two ends)
    moving : |v| > v_stick (and not at the ends)
    evaluate : moving and at least ``guard`` samples away from any stuck sample or end
    v_stick : stick threshold [m/s]
    sos : the filter ``L``
    noise_diff_m : position noise from the 4th difference of x [m] (not biased by fast motion)
    accel_noise_gain : std of L[second difference]/dt² for unit white position noise [1/s²]; the force-residual
        floor of the sensor noise is m·σ_x·accel_noise_gain
    x_rev_dist : |x − x at the last velocity reversal| [m] (displacement since the last reversal)
    direction : sgn(x[k+1] − x[k−1]) on moving samples, 0 when stuck (the models' sgn(v))
    """

    t: FloatArray
    x: FloatArray
    u: FloatArray
    dt_s: float
    cutoff_hz: float
    sos: FloatArray
    xf: FloatArray
    v: FloatArray
    acc_raw: FloatArray
    acc_f: FloatArray
    moving: BoolArray
    evaluate: BoolArray
    v_stick: float
    guard: int
    quantum_m: float
    noise_m: float
    accel_noise_gain: float
    x_rev_dist: FloatArray
    direction: FloatArray
    source: str = ""
    noise_diff_m: float = 0.0
    cache: dict[str, object] = field(default_factory=ArrayCache)
    notes: list[str] = field(default_factory=list)  # what the preparation did to the data (resampling, ...)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    def filt(self, raw: FloatArray) -> FloatArray:
        """``L[moving · raw]``: zero stuck samples, then zero-phase low-pass."""
        return np.asarray(filtfilt_rows(self.sos, np.reshape(raw, (1, -1)), self.moving)[0], dtype=np.float64)

    def filt_rows(self, raws: list[FloatArray]) -> list[FloatArray]:
        """:meth:`filt` of each of ``raws`` in one call (two at a time in the compiled loop, ~2x faster than
        one by one); each result is a contiguous row of one (k, n) array."""
        if not raws:
            return []
        # one signal (most calls of a shape search): a (1, n) view, not a stacked copy
        x = np.reshape(raws[0], (1, -1)) if len(raws) == 1 else np.stack(raws)
        out = filtfilt_rows(self.sos, x, self.moving)
        return list(out)

    def noise_floor_n(self, mass_kg: float) -> float:
        """Force-residual RMS [N] that white position noise (and quantisation) alone produce.

        The position noise is the smaller of ``noise_m`` (spread of ``x − L[x]``) and ``noise_diff_m`` (robust
        std of the 4th difference / √70): under fast motion ``x − L[x]`` also holds the motion above the
        cut-off and overstates the noise many-fold (a 20 kg stage on 50 ms moves: 72 nm for 1 nm of noise).
        """
        sn = min(self.noise_m, self.noise_diff_m) if self.noise_diff_m > 0 else self.noise_m
        sx = math.sqrt(sn**2 + self.quantum_m**2 / 12.0)
        return float(mass_kg) * sx * self.accel_noise_gain

    def filt_many(self, raw: FloatArray) -> FloatArray:
        """:meth:`filt` applied to every column of ``raw`` (shape ``(n, k)``) in one call."""
        return np.ascontiguousarray(filtfilt_rows(self.sos, np.asarray(raw).T, self.moving).T)

    def ubar(self, delay_s: float = 0.0) -> FloatArray:
        """Applied force seen by the second difference at ``t[k]`` for an actuation delay ``delay_s`` [N].

        ``x[k+1] − 2x[k] + x[k−1] = ∫ Λ(t − t[k])·a(t) dt`` with the hat kernel Λ (height dt, support
        ±dt), so the force to pair with it is ``(1/dt²)∫Λ·u(t − τ)dt``. For a held command delayed by
        τ = (n + f)·dt this is the quadratic B-spline
        ``f²/2·u[k−n−2] + (1/2 + f − f²)·u[k−n−1] + (1−f)²/2·u[k−n]`` (τ = 0: ``(u[k−1] + u[k])/2``).
        """
        key = f"ubar:{delay_s:.6e}"
        hit = self.cache.get(key)
        if hit is not None:
            return hit  # type: ignore[return-value]
        ub = hat_average(self.u, delay_s / self.dt_s)
        self.cache[key] = ub
        return ub


def hat_average(u: FloatArray, shift_samples: float) -> FloatArray:
    """Hat-kernel average of a held command delayed by ``shift_samples`` (see :meth:`Signals.ubar`)."""
    s = max(float(shift_samples), 0.0)
    n = int(math.floor(s))
    f = s - n
    m = u.shape[0]
    pad = np.concatenate([np.full(n + 2, u[0]), u])
    u_n = pad[2 : 2 + m]  # u[k-n]
    u_n1 = pad[1 : 1 + m]  # u[k-n-1]
    u_n2 = pad[0:m]  # u[k-n-2]
    return np.asarray(0.5 * f * f * u_n2 + (0.5 + f - f * f) * u_n1 + 0.5 * (1 - f) ** 2 * u_n, dtype=np.float64)


def shift_zoh(u: FloatArray, shift_samples: float) -> FloatArray:
    """Held force delayed by ``shift_samples`` (fractional): mean over each sample interval.

    With τ = (n + f)·dt, over ``[t[k], t[k+1])`` the delayed force is ``u[k−n−1]`` for ``f·dt`` and
    ``u[k−n]`` for ``(1−f)·dt``; its interval mean is ``f·u[k−n−1] + (1−f)·u[k−n]`` (``u[j<0] = u[0]``).
    """
    if shift_samples <= 0.0:
        return np.asarray(u, dtype=np.float64)
    n = int(math.floor(shift_samples))
    f = shift_samples - n
    pad = np.concatenate([np.full(n + 1, u[0]), u])
    m = u.shape[0]
    a = pad[1 : 1 + m]  # u[k-n]
    b = pad[0:m]  # u[k-n-1]
    return np.asarray((1.0 - f) * a + f * b, dtype=np.float64)


def _robust_std(a: FloatArray) -> float:
    if a.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(a - np.median(a))))


def _quantum(x: FloatArray) -> float:
    d = np.abs(np.diff(x))
    d = d[d > 0]
    if d.size == 0:
        return 0.0
    q = float(np.min(d))
    # measurement noise makes the smallest step meaningless if it is below 1e-6 of the median step
    return q if q > 1e-6 * float(np.median(d)) else float(np.percentile(d, 1))


#: ranges a recording must stay in: far beyond any stage, even one whose positions in nm were written as metres
#: (the plausibility verdict of identify names such unit mix-ups); values outside are a corrupt export and would
#: overflow the inverse dynamics (a 1e300 m position squared is inf)
MAX_ABS_X_M = 1e9
MAX_ABS_U_N = 1e12
MAX_ABS_V_M_S = 1e9
MIN_DT_S = 1e-7
MAX_DT_S = 10.0


def check_ranges(rec: Recording) -> None:
    """One clear :class:`DataError` for a recording outside physical ranges (named row, column and unit)."""
    for name, arr, lim, unit in (("x", rec.x, MAX_ABS_X_M, "m"), ("u", rec.u, MAX_ABS_U_N, "N"),
                                 ("x_ref", rec.x_ref, MAX_ABS_X_M, "m"), ("v", rec.v, MAX_ABS_V_M_S, "m/s")):
        if arr is None:  # an optional column the recording does not have
            continue
        bad = np.flatnonzero(~(np.abs(arr) <= lim))
        if bad.size:
            k = int(bad[0])
            raise DataError(f"{rec.source}: row {k + 2}, column '{name}': {arr[k]:.6g} {unit} is outside the "
                            f"physical range ±{lim:g} {unit} (wrong unit or a corrupt export?)")
    dts = np.diff(rec.t)
    for k in (int(np.argmin(dts)), int(np.argmax(dts))):
        d = float(dts[k]) if dts.size else 0.0
        if dts.size and not (MIN_DT_S <= d <= MAX_DT_S):
            raise DataError(f"{rec.source}: row {k + 3}, column 't': time step {d:.6g} s is outside "
                            f"[{MIN_DT_S:g}, {MAX_DT_S:g}] s (wrong time unit?)")


#: a sample is "clearly smoother" in one time base when the robust scatter of its fourth difference is below this
#: fraction of the other's (used to tell jittered time stamps from irregular sampling, :func:`stamps_jitter`)
SMOOTHER = 0.5


def _roughness(x: FloatArray) -> float:
    """Robust scatter [m] of the fourth difference of ``x``: noise plus interpolation or time-base errors."""
    return _robust_std(np.diff(x, 4)) if x.size > 8 else 0.0


def _interp_x(tg: FloatArray, t: FloatArray, x: FloatArray) -> FloatArray:
    """Position at ``tg`` by monotone piecewise-cubic (PCHIP) interpolation: its error over a hole of length h
    is O(h³) (linear interpolation: a·h²/8, which the second difference turns into an acceleration error of the
    order of the acceleration itself), and it never overshoots across a long hole."""
    from scipy.interpolate import PchipInterpolator

    return np.asarray(PchipInterpolator(t, x, extrapolate=True)(tg), dtype=np.float64)


def stamps_jitter(rec: Recording) -> float | None:
    """The uniform sample period [s] when the samples were taken at a uniform period and only their time stamps
    jitter (host-side stamping of a polled drive), else None: no sample is missing (every stamp lies within half
    a period of the least-squares line ``t0 + k·T``) and the positions are clearly smoother
    (:data:`SMOOTHER`) in sample order than interpolated onto that grid by their stamps. With truly irregular
    sampling it is the other way round."""
    n = rec.t.size
    if n < 16:
        return None
    k = np.arange(n, dtype=np.float64)
    period, t0 = (float(c) for c in np.polyfit(k, rec.t, 1))  # least-squares line t ≈ t0 + k·T
    tg = t0 + period * k
    if not period > 0 or float(np.max(np.abs(rec.t - tg))) >= 0.5 * period:
        return None
    by_stamp = _interp_x(np.clip(tg, rec.t[0], rec.t[-1]), rec.t, rec.x)
    return period if _roughness(rec.x) < SMOOTHER * _roughness(by_stamp) else None


def resample_uniform(rec: Recording, dt_s: float, bridge: int = 1
                     ) -> tuple[Recording, npt.NDArray[np.bool_], int]:
    """``rec`` on a uniform grid of period ``dt_s`` [s] from its first sample: position (and reference)
    interpolated (:func:`_interp_x`), other columns linearly, the command ``u`` held (zero-order hold: the last
    command sent before each grid time). Returns the recording, the mask of grid samples that are not usable
    (inside a hole longer than ``bridge`` periods between measured samples, and farther than dt/10 from any
    measured one) and the number of grid samples interpolated across shorter holes (jitter, a few dropped
    samples: shorter than the low-pass's time resolution, which cannot tell them from measured samples)."""
    t = rec.t
    m = int(math.floor((t[-1] - t[0]) / dt_s + 1e-9)) + 1
    tg = t[0] + dt_s * np.arange(m)
    # the command held at a grid time is that of the last sample taken at or before it, where a sample within
    # dt/10 of the grid time counts as taken at it (the same tolerance that calls a grid sample measured): the
    # grid times drift against time stamps rounded in the file (a median period of 0.0016431190000005813 s
    # for 1/608.6 Hz stamps written to 1 ns), and a strict "at or before" then takes the previous sample's
    # command at nearly every grid time: a one-period lag of u behind x that biases the mass and leaves a
    # residual where the command changes fastest, right after reversals
    idx = np.clip(np.searchsorted(t, tg + 0.1 * dt_s, side="right") - 1, 0, t.size - 1)
    nxt = np.minimum(idx + 1, t.size - 1)
    nearest = np.minimum(np.abs(t[idx] - tg), np.abs(t[nxt] - tg))
    off_grid = nearest > 0.1 * dt_s
    hole = (t[nxt] - t[idx]) > (bridge + 0.5) * dt_s
    synthetic = off_grid & hole

    def interp(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else _interp_x(tg, t, a)

    out = Recording(tg, _interp_x(tg, t, rec.x), rec.u[idx].copy(), interp(rec.x_ref),
                    None if rec.v is None else np.interp(tg, t, rec.v),
                    f"{rec.source} (resampled)", {k: np.interp(tg, t, v) for k, v in rec.extra.items()})
    return out, synthetic, int((off_grid & ~hole).sum())


#: beyond these a recording is in SI units only if the machine is no precision stage: more likely positions in mm
#: or µm, or time in ms, written as SI (a note, not a refusal: the analysis runs, the user is told)
PLAUSIBLE_SPAN_M = 10.0
PLAUSIBLE_SPEED_M_S = 10.0
PLAUSIBLE_PERIOD_S = 0.05


def unit_notes(sig: Signals) -> list[str]:
    """One note per implausible scale (travel, speed, sample period) naming the likely unit mix-up."""
    out = []
    span = float(np.ptp(sig.x))
    if span > PLAUSIBLE_SPAN_M:
        out.append(f"units: the positions span {span:.4g} m (more than {PLAUSIBLE_SPAN_M:g} m, implausible for a "
                   "stage): if x is in mm or µm, convert to metres (or the fitted mass and friction are off by the "
                   "same factor)")
    vmax = float(np.max(np.abs(sig.v))) if sig.v.size else 0.0
    if vmax > PLAUSIBLE_SPEED_M_S:
        out.append(f"units: the speed reaches {vmax:.4g} m/s (more than {PLAUSIBLE_SPEED_M_S:g} m/s): if x is in mm "
                   "or µm, or t in ms, convert to metres and seconds")
    if sig.dt_s > PLAUSIBLE_PERIOD_S:
        out.append(f"units: the sample period is {sig.dt_s:.4g} s ({1 / sig.dt_s:.3g} Hz, slower than any control "
                   "loop): if t is in ms, convert to seconds")
    return out


#: relative size of the low-pass's zero-phase impulse response below which a sample is out of its reach
FILTER_REACH = 1e-4


def filter_reach(sos: FloatArray) -> int:
    """Samples on either side over which the zero-phase low-pass ``sos`` spreads one sample by more than
    :data:`FILTER_REACH` of its peak (about 5 periods of the cut-off for the 4th-order Butterworth)."""
    n = 4097
    imp = np.zeros(n)
    imp[n // 2] = 1.0
    h = np.abs(sosfiltfilt(sos, imp))
    big = np.flatnonzero(h > FILTER_REACH * h.max())
    return int(max(big.max() - n // 2, n // 2 - big.min()))


def prepare(
    rec: Recording,
    cutoff_hz: float | None = None,
    v_stick_m_s: float | None = None,
    min_rows: int = 200,
    require_motion: bool = True,
) -> Signals:
    """Build :class:`Signals` from a recording.

    Parameters
    ----------
    cutoff_hz : float, optional
        Cut-off of ``L`` [Hz]; default ``min(fs/10, DEFAULT_MAX_CUTOFF_HZ)`` (100 Hz from 1 kHz up). The
        cut-off sets the time resolution of the residual (stick guard ``0.5/fc``) and the noise floor
        (``∝ fc^2.5``); it is a property of the stage dynamics, not of the sample rate: at 5 kHz, fs/10
        would raise the noise floor 56-fold and bury effects that are plain at 1 kHz.
    v_stick_m_s : float, optional
        Stick threshold [m/s]; default from the measured position noise and quantum.
    require_motion : bool
        Raise if fewer than 50 samples are in motion (quasi-static identification data pass False).

    Raises
    ------
    DataError
        Too few rows, values outside physical ranges (:func:`check_ranges`), a cut-off outside (0, Nyquist), too
        little motion. A sample period that varies by more than 5 % is resampled (:func:`resample_uniform`), with
        a note in ``Signals.notes``.
    """
    n = len(rec)
    if n < min_rows:
        raise DataError(f"{rec.source}: {n} rows; identification needs at least {min_rows} samples")
    check_ranges(rec)
    notes: list[str] = []
    synthetic = np.zeros(n, dtype=bool)
    dts = np.diff(rec.t)
    dt = float(np.median(dts))
    jitter = float(np.max(np.abs(dts - dt)) / dt)
    if jitter > 0.05:
        # irregular time stamps (a USB-polled drive, skipped cycles). Either the stamps jitter around a uniform
        # sampling (positions smoother in sample order: keep the samples, uniform period) or the sampling is
        # irregular: resample onto a uniform grid at the median period, interpolating across holes shorter than
        # the low-pass's time resolution; samples in longer holes are kept out of the residual
        k = int(np.argmax(np.abs(dts - dt))) + 1
        fc0 = min(0.1 / dt, DEFAULT_MAX_CUTOFF_HZ)
        if cutoff_hz is not None and math.isfinite(cutoff_hz) and 0.0 < cutoff_hz < 0.5 / dt:
            fc0 = float(cutoff_hz)
        bridge = max(2, int(math.ceil(0.5 / (dt * fc0))))
        period = stamps_jitter(rec)
        if period is not None:
            rec = Recording(rec.t[0] + period * np.arange(n), rec.x, rec.u, rec.x_ref, rec.v,
                            f"{rec.source} (uniform time base)", rec.extra)
            notes.append(f"time-stamp jitter: the sample period varies by up to {100 * jitter:.0f} % of the median "
                         f"{dt:.6g} s (first at row {k + 2}), but no sample is missing and the positions are "
                         "smoother in sample order than by their stamps: the samples were taken uniformly and only "
                         f"the stamps jitter; the uniform period {period:.6g} s (fitted to all stamps) is used")
            dt = period
        else:
            rec, synthetic, bridged = resample_uniform(rec, dt, bridge)
            notes.append(f"irregular sampling: the sample period varies by up to {100 * jitter:.0f} % of the median "
                         f"{dt:.6g} s (first at row {k + 2}); resampled onto a uniform {dt:.6g} s grid (x interpolated "
                         f"piecewise-cubic, u held as commanded), {int(synthetic.sum()) + bridged} of {rec.t.size} "
                         f"grid samples were not measured: {bridged} interpolated across holes of at most {bridge} "
                         f"periods (shorter than the low-pass's time resolution), {int(synthetic.sum())} in longer "
                         "holes are excluded from the fit")
        n = len(rec)
    if cutoff_hz is not None and not (0.0 < float(cutoff_hz) < 0.5 / dt):
        raise DataError(f"--cutoff-hz: {cutoff_hz:g} Hz is outside (0, {0.5 / dt:.6g}) Hz (the Nyquist frequency of "
                        f"the {dt:.6g} s sample period of {rec.source})")
    fs = 1.0 / dt  # (a NaN or infinite cut-off fails the check above too)
    fc = float(cutoff_hz) if cutoff_hz else min(0.1 * fs, DEFAULT_MAX_CUTOFF_HZ)
    sos = lowpass_sos(fc, fs)
    x = rec.x
    x0 = float(x[0])
    xf = np.asarray(sosfiltfilt(sos, x - x0), dtype=np.float64) + x0
    v = np.gradient(xf, dt)
    acc_raw = np.zeros(n)
    acc_raw[1:-1] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / (dt * dt)
    # noise and quantum of the position
    q = _quantum(x)
    noise = _robust_std(x - xf)
    # velocity noise gain of the pipeline for unit white position noise
    rng = np.random.default_rng(12345)
    w = rng.standard_normal(4096)
    gain_v = float(np.std(np.gradient(sosfiltfilt(sos, w), dt)[64:-64]))
    w2 = np.zeros_like(w)
    w2[1:-1] = w[2:] - 2.0 * w[1:-1] + w[:-2]
    gain_a = float(np.std(sosfiltfilt(sos, w2)[64:-64])) / (dt * dt)
    sigma_x = max(noise, q / math.sqrt(12.0))
    v_th = float(v_stick_m_s) if v_stick_m_s is not None else max(6.0 * sigma_x * gain_v, 1e-12)
    guard = max(2, int(math.ceil(0.5 * fs / fc)))
    # stuck: the raw central displacement x[k+1] − x[k−1] is within the noise band (the zero-phase filtered
    # velocity anticipates a break-away by about the filter length, so it cannot decide stick). The
    # direction of motion used by the models is the sign of that raw displacement.
    dxc = np.zeros(n)
    dxc[1:-1] = x[2:] - x[:-2]
    thr = max(6.0 * math.sqrt(2.0) * noise, 2.5 * q)
    by_disp = np.abs(dxc) > thr
    by_speed = np.abs(v) > v_th
    moving = by_disp & by_speed
    if synthetic.any():
        # in a long hole, not measured: like a stick sample, and so is every sample whose filtered value the
        # hole reaches (:func:`filter_reach`): the held command and interpolated position across a hole are
        # made up, and a jump of the held command at the hole's end rings through the zero-phase low-pass
        reach = filter_reach(sos)
        near_syn = np.convolve(synthetic.astype(np.float64), np.ones(2 * reach + 3), mode="same") > 0
        moving &= ~near_syn
    moving[0] = moving[-1] = False
    # a reversal without a stick phase happens inside an interval: the friction changes sign mid-interval,
    # which no per-sample model column represents; those samples are treated like stick samples
    sd = np.sign(dxc)
    turn = moving[:-1] & moving[1:] & (sd[:-1] != sd[1:])
    moving[:-1] &= ~turn
    moving[1:] &= ~turn
    # the samples next to a stick phase contain the stick/slip transition somewhere inside the interval
    # (acceleration not constant over it): treat ERODE samples on each side as stuck too
    for _ in range(ERODE):
        moving[1:] &= moving[:-1].copy()
        moving[:-1] &= moving[1:].copy()
    stuck = ~moving
    near = np.convolve(stuck.astype(np.float64), np.ones(2 * guard + 1), mode="same") > 0
    evaluate = moving & ~near
    evaluate[: 4 * guard] = False
    evaluate[-4 * guard :] = False
    sig = Signals(
        t=rec.t,
        x=x,
        u=rec.u,
        dt_s=dt,
        cutoff_hz=fc,
        sos=sos,
        xf=xf,
        v=v,
        acc_raw=acc_raw,
        acc_f=np.zeros(n),
        moving=moving,
        evaluate=evaluate,
        v_stick=v_th,
        guard=guard,
        quantum_m=q,
        noise_m=noise,
        accel_noise_gain=gain_a,
        x_rev_dist=_reversal_distance(xf, v, v_th),
        direction=np.where(moving, np.sign(dxc), 0.0),
        source=rec.source,
        noise_diff_m=_roughness(x) / math.sqrt(70.0),
    )
    sig.acc_f = sig.filt(acc_raw)
    sig.notes = notes + unit_notes(sig)
    if require_motion and int(evaluate.sum()) < 50:
        holes = "" if not synthetic.any() else (
            f" and outside the holes of the recording ({int(synthetic.sum())} grid samples not measured, and "
            f"{reach} samples on either side that the low-pass carries them into)")
        raise DataError(
            f"{rec.source}: only {int(evaluate.sum())} samples usable in motion (identification needs 50): a sample "
            f"counts as moving when its central displacement |x[k+1] − x[k−1]| exceeds {thr:.3g} m (the noise band: "
            f"6·√2 × position noise {noise:.3g} m, at least 2.5 counts of {q:.3g} m; {int(by_disp.sum())} samples "
            f"pass) and its filtered speed exceeds {v_th:.3g} m/s ({int(by_speed.sum())} pass), {guard} samples "
            f"away from any stop{holes}; record longer or faster moves, or a finer position sensor"
        )
    return sig


def _reversal_distance(xf: FloatArray, v: FloatArray, v_th: float) -> FloatArray:
    """|x − x_r| with x_r the position at the last change of the direction of motion (inf before the first
    reversal). The direction is sgn(v) outside ±v_th; where it changes at sample k (to a direction other than
    the last one seen), x_r = x[k−1], the extreme position since the last change."""
    n = xf.shape[0]
    out = np.full(n, np.inf)
    d = np.where(v > v_th, 1.0, np.where(v < -v_th, -1.0, 0.0))
    nz = np.flatnonzero(d != 0.0)
    if nz.size == 0:
        return out
    dn = d[nz]
    change = np.empty(nz.size, dtype=bool)
    change[0] = True
    change[1:] = dn[1:] != dn[:-1]
    ev = nz[change]  # the samples where the direction of motion changes (the first one: motion starts)
    if ev.size < 2:
        return out
    xr = xf[np.maximum(ev - 1, 0)]
    k0 = int(ev[1])
    last = np.searchsorted(ev, np.arange(k0, n), side="right") - 1
    out[k0:] = np.abs(xf[k0:] - xr[last])
    return out
