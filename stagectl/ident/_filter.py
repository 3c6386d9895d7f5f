"""Zero-phase Butterworth low-pass (the identification filter ``L``) without ``scipy.signal``.

``scipy.signal`` costs about a third of ``stagectl discover``'s start-up (it imports ``scipy.stats``), and the
discovery filters a few thousand columns, so the two functions it needs are here, compiled:

* :func:`butter_lowpass_sos` -- the digital Butterworth low-pass of ``scipy.signal.butter(N, wn,
  output="sos")``: analog poles ``p_k = ω_a·exp(iπ(2k + N + 1)/(2N))`` with the pre-warped cut-off
  ``ω_a = 4·tan(π·wn/2)`` (sample rate 2), bilinear transform ``z = (4 + p)/(4 − p)``, all zeros at
  ``z = −1``, unit gain at DC; one section per conjugate pole pair, poles nearest the unit circle last.
* :func:`sosfiltfilt` -- ``scipy.signal.sosfiltfilt`` with its defaults: odd extension by
  ``3·(2·n_sections + 1)`` samples at each end, forward and backward passes of the cascade (transposed
  direct form II) started at the steady state of the first sample of each pass.

``tests/ident/test_filter.py`` checks both against ``scipy.signal`` (the oracle) to rounding.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from stagectl.jit import kernel

FloatArray = npt.NDArray[np.float64]


def butter_lowpass_sos(order: int, wn: float) -> FloatArray:
    """Second-order sections ``[b0, b1, b2, 1, a1, a2]`` of a Butterworth low-pass of ``order`` with the
    cut-off ``wn`` as a fraction of the Nyquist frequency (0 < wn < 1)."""
    if not (0.0 < wn < 1.0) or order < 1:
        raise ValueError(f"butter_lowpass_sos: need order >= 1 and 0 < wn < 1, got {order}, {wn}")
    wa = 4.0 * math.tan(math.pi * wn / 2.0)
    ks = np.arange(-order + 1, order, 2)
    p = -np.exp(1j * np.pi * ks / (2 * order)) * wa
    pz = (4.0 + p) / (4.0 - p)
    gain = float(np.real(wa**order / np.prod(4.0 - p)))
    pairs = sorted((q for q in pz if q.imag > 1e-14), key=lambda q: abs(q))  # farthest from |z| = 1 first
    reals = [q.real for q in pz if abs(q.imag) <= 1e-14]
    rows: list[list[float]] = [[1.0, 1.0, 0.0, 1.0, -r, 0.0] for r in reals]
    rows += [[1.0, 2.0, 1.0, 1.0, -2.0 * q.real, abs(q) ** 2] for q in pairs]
    sos = np.array(rows, dtype=np.float64)
    sos[0, :3] *= gain
    return sos


def _zi(sos: FloatArray) -> FloatArray:
    """Steady-state section states for a unit step (``scipy.signal.sosfilt_zi``)."""
    zi = np.empty((sos.shape[0], 2))
    scale = 1.0
    for s in range(sos.shape[0]):
        b0, b1, b2, _, a1, a2 = sos[s]
        m = np.array([[1.0 + a1, -1.0], [a2, 1.0]])
        zi[s] = scale * np.linalg.solve(m, np.array([b1 - a1 * b0, b2 - a2 * b0]))
        scale *= (b0 + b1 + b2) / (1.0 + a1 + a2)
    return zi


@kernel(inline="always")
def _cascade(sos: FloatArray, zi: FloatArray, ext: FloatArray, st: FloatArray, start: int, stop: int,
             step: int) -> None:  # pragma: no cover
    """One pass of the section cascade (transposed direct form II) over ``ext[start:stop:step]`` in place, its
    states ``st`` started at the steady state of the pass's first sample."""
    ns = sos.shape[0]
    for s in range(ns):
        st[s, 0] = zi[s, 0] * ext[start]
        st[s, 1] = zi[s, 1] * ext[start]
    for i in range(start, stop, step):
        v = ext[i]
        for s in range(ns):
            y = sos[s, 0] * v + st[s, 0]
            st[s, 0] = sos[s, 1] * v - sos[s, 4] * y + st[s, 1]
            st[s, 1] = sos[s, 2] * v - sos[s, 5] * y
            v = y
        ext[i] = v


@kernel
def _filtfilt_cols(sos: FloatArray, zi: FloatArray, x: FloatArray, edge: int) -> FloatArray:  # pragma: no cover
    """Forward-backward cascade over each column of ``x`` (n, k) with odd extension ``edge``."""
    n, k = x.shape
    ns = sos.shape[0]
    m = n + 2 * edge
    out = np.empty((n, k))
    ext = np.empty(m)
    st = np.empty((ns, 2))
    for c in range(k):
        x0 = x[0, c]
        x1 = x[n - 1, c]
        for i in range(edge):
            ext[i] = 2.0 * x0 - x[edge - i, c]
            ext[edge + n + i] = 2.0 * x1 - x[n - 2 - i, c]
        for i in range(n):
            ext[edge + i] = x[i, c]
        _cascade(sos, zi, ext, st, 0, m, 1)  # forward
        _cascade(sos, zi, ext, st, m - 1, -1, -1)  # backward
        for i in range(n):
            out[i, c] = ext[edge + i]
    return out


def sosfiltfilt(sos: FloatArray, x: npt.ArrayLike, axis: int = -1) -> FloatArray:
    """Zero-phase filtering of ``x`` along ``axis`` (0 or -1 for 1-D; 0 for the columns of a 2-D array), as
    ``scipy.signal.sosfiltfilt(sos, x, axis)`` with its default padding."""
    a = np.asarray(x, dtype=np.float64)
    ntaps = 2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    edge = 3 * ntaps
    if a.ndim == 1:
        cols = a.reshape(-1, 1)
    elif a.ndim == 2 and axis == 0:
        cols = a
    else:
        raise ValueError("sosfiltfilt: 1-D data, or 2-D data filtered along axis 0")
    if cols.shape[0] <= edge:
        raise ValueError(f"sosfiltfilt: the data must be longer than the padding ({edge} samples)")
    out = _filtfilt_cols(np.ascontiguousarray(sos), _zi(sos), np.ascontiguousarray(cols), edge)
    return np.asarray(out.reshape(a.shape), dtype=np.float64)


__all__ = ["butter_lowpass_sos", "sosfiltfilt"]
