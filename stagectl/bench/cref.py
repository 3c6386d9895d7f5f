"""A minimal C implementation of the GMS (N elements) + rigid-body recurrence, the compiled reference of
``stagectl bench models``.

The same equations as ``stagectl.friction.gms`` inside ``stagectl.sim.plant`` with one sub-step per step
(semi-implicit Euler, exact exponential slip update, micro-damping, viscous term; no effects, no delay)::

    v ← v + h·(u[k] − F)/m ;  dx = h·v ;  x ← x + dx ;  F ← GMS step(dx, v, h) ;  x_out[k] = x

written the way a C programmer would: flat arrays, the exponential computed once per step, no function
pointers. ``gms_batch`` runs many parameter sets over one input, interleaving the sets per time step
(structure of arrays). Compiled at benchmark time with the system C compiler (``$CC``, else ``cc``) at
``-O2``; :func:`load` returns ``None`` with the reason when no compiler is available.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

C_SOURCE = r"""
#include <math.h>

static inline double excess(double v, double vs, double delta) {
    double r = fabs(v / vs);
    double e = (delta == 2.0) ? r * r : (delta == 1.0 ? r : pow(r, delta));
    return e > 745.0 ? 0.0 : exp(-e);
}

/* one trajectory; par = [n, fc, fs, vs, delta, C, viscous, k[n], alpha[n], sigma1[n]] */
void gms_single(long n_steps, const double *u, double h, double m, const double *par, double *xo) {
    int n = (int)par[0];
    double fc = par[1], fs = par[2], vs = par[3], delta = par[4], c = par[5], s2 = par[6];
    const double *k = par + 7, *a = par + 7 + n, *s1 = par + 7 + 2 * n;
    double f[64], mode[64], ck[64];
    for (int i = 0; i < n; i++) { f[i] = 0.0; mode[i] = 0.0; ck[i] = c / k[i]; }
    double x = 0.0, v = 0.0, ff = 0.0, inv_m = 1.0 / m;
    for (long t = 0; t < n_steps; t++) {
        v += h * (u[t] - ff) * inv_m;
        double dx = h * v;
        x += dx;
        xo[t] = x;
        if (v == 0.0) { double s = 0.0; for (int i = 0; i < n; i++) s += f[i]; ff = s; continue; }
        double s = v > 0.0 ? 1.0 : -1.0;
        double g = fc + (fs - fc) * excess(v, vs, delta);
        double inv_g = 1.0 / g;
        double decay = exp(-c * h * inv_g);
        double tot = 0.0;
        for (int i = 0; i < n; i++) {
            double fi = f[i], mi = mode[i], lim = a[i] * g;
            if (mi != 0.0 && mi != s) mi = 0.0;
            if (mi == 0.0) {
                if (s * fi >= lim) { mi = s; fi = s * lim + (fi - s * lim) * decay; }
                else { fi += k[i] * dx; if (s * fi >= lim) { fi = s * lim; mi = s; } }
            } else {
                fi = s * lim + (fi - s * lim) * decay;
            }
            f[i] = fi; mode[i] = mi;
            double rate = mi == 0.0 ? v : ck[i] * (s * a[i] - fi * inv_g);
            tot += fi + s1[i] * rate;
        }
        ff = tot + s2 * v;
    }
}

/* n_sets parameter sets (rows of P, each laid out as in gms_single, all with the same n), one input,
   sets interleaved per time step; xo is (n_sets, n_steps) row-major */
void gms_batch(long n_sets, long n_steps, const double *u, double h, double m, const double *P, long stride,
               double *F, double *M, double *xo) {
    int n = (int)P[0];
    double *x = F + n_sets * n, *v = x + n_sets, *ff = v + n_sets;
    for (long j = 0; j < n_sets; j++) { x[j] = 0.0; v[j] = 0.0; ff[j] = 0.0; }
    for (long q = 0; q < n_sets * n; q++) { F[q] = 0.0; M[q] = 0.0; }
    double inv_m = 1.0 / m;
    for (long t = 0; t < n_steps; t++) {
        double ut = u[t];
        for (long j = 0; j < n_sets; j++) {
            const double *par = P + j * stride;
            double fc = par[1], fs = par[2], vs = par[3], delta = par[4], c = par[5], s2 = par[6];
            const double *k = par + 7, *a = par + 7 + n, *s1 = par + 7 + 2 * n;
            double *f = F + j * n, *mode = M + j * n;
            double vj = v[j] + h * (ut - ff[j]) * inv_m;
            double dx = h * vj;
            v[j] = vj;
            x[j] += dx;
            xo[j * n_steps + t] = x[j];
            if (vj == 0.0) { double s = 0.0; for (int i = 0; i < n; i++) s += f[i]; ff[j] = s; continue; }
            double s = vj > 0.0 ? 1.0 : -1.0;
            double g = fc + (fs - fc) * excess(vj, vs, delta);
            double inv_g = 1.0 / g;
            double decay = exp(-c * h * inv_g);
            double tot = 0.0;
            for (int i = 0; i < n; i++) {
                double fi = f[i], mi = mode[i], lim = a[i] * g;
                if (mi != 0.0 && mi != s) mi = 0.0;
                if (mi == 0.0) {
                    if (s * fi >= lim) { mi = s; fi = s * lim + (fi - s * lim) * decay; }
                    else { fi += k[i] * dx; if (s * fi >= lim) { fi = s * lim; mi = s; } }
                } else {
                    fi = s * lim + (fi - s * lim) * decay;
                }
                f[i] = fi; mode[i] = mi;
                double rate = mi == 0.0 ? vj : c / k[i] * (s * a[i] - fi * inv_g);
                tot += fi + s1[i] * rate;
            }
            ff[j] = tot + s2 * vj;
        }
    }
}
"""

_LIB: Any = None
_WHY: str | None = None


def compiler() -> str | None:
    """The system C compiler (``$CC``, else ``cc``/``gcc``/``clang`` on PATH), or None."""
    for cand in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if cand and shutil.which(cand):
            return cand
    return None


def load() -> tuple[Any, str | None]:
    """(the compiled library, None), or (None, why not). Compiled once per process into a temporary dir."""
    global _LIB, _WHY
    if _LIB is not None or _WHY is not None:
        return _LIB, _WHY
    cc = compiler()
    if cc is None:
        _WHY = "no C compiler found ($CC, cc, gcc, clang): C reference skipped"
        return None, _WHY
    tmp = Path(tempfile.mkdtemp(prefix="stagectl-cref-"))
    src, lib = tmp / "gms_ref.c", tmp / "gms_ref.so"
    src.write_text(C_SOURCE)
    out = subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(lib), str(src), "-lm"], capture_output=True,
                         text=True)
    if out.returncode != 0:
        _WHY = f"{cc} -O2 failed: {out.stderr.strip()[:300]}: C reference skipped"
        return None, _WHY
    dll = ctypes.CDLL(str(lib))
    dp = ctypes.POINTER(ctypes.c_double)
    dll.gms_single.argtypes = [ctypes.c_long, dp, ctypes.c_double, ctypes.c_double, dp, dp]
    dll.gms_single.restype = None
    dll.gms_batch.argtypes = [ctypes.c_long, ctypes.c_long, dp, ctypes.c_double, ctypes.c_double, dp,
                              ctypes.c_long, dp, dp, dp]
    dll.gms_batch.restype = None
    _LIB = dll
    return _LIB, None


def pack(spec: dict[str, Any]) -> npt.NDArray[np.float64]:
    """The C layout ``[n, fc, fs, vs, delta, C, viscous, k…, alpha…, sigma1…]`` of a GMS spec (SI units)."""
    k = [float(e) for e in spec["k_n_m"]]
    n = len(k)
    s1 = spec.get("sigma1_n_s_m", 0.0)
    s1l = [float(e) for e in s1] if isinstance(s1, (list, tuple)) else [float(s1)]
    if len(s1l) == 1:
        s1l = s1l * n
    return np.array([n, spec["fc_n"], spec["fs_n"], spec.get("vs_m_s", 1e-3), spec.get("delta", 2.0),
                     spec.get("c_n_s", 1e4), spec.get("viscous_n_s_m", 0.0), *k,
                     *[float(e) for e in spec["alpha"]], *s1l], dtype=np.float64)


def _ptr(a: npt.NDArray[np.float64]) -> Any:
    return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


def single(lib: Any, u: npt.NDArray[np.float64], h: float, m: float, par: npt.NDArray[np.float64],
           out: npt.NDArray[np.float64]) -> None:
    """x after each step into ``out`` (preallocated, len(u))."""
    lib.gms_single(u.shape[0], _ptr(u), h, m, _ptr(par), _ptr(out))


def batch(lib: Any, u: npt.NDArray[np.float64], h: float, m: float, P: npt.NDArray[np.float64],
          out: npt.NDArray[np.float64]) -> None:
    """x of every set (rows of ``P``) after each step into ``out`` (preallocated, (len(P), len(u)))."""
    n_sets, stride = P.shape
    n = int(P[0, 0])
    work_f = np.zeros(n_sets * n + 3 * n_sets)
    work_m = np.zeros(n_sets * n)
    lib.gms_batch(n_sets, u.shape[0], _ptr(u), h, m, _ptr(P), stride, _ptr(work_f), _ptr(work_m), _ptr(out))
