"""Characteristic curves of friction models, and their plots (matplotlib, Agg backend).

Curves (computed with ``model.force_along`` from the relaxed state; any registered model):

* **virgin curve**: quasi-static first loading ``0 → x_max`` at ``v_qs`` (default 1 µm/s);
* **nested hysteresis loops**: after first loading to A, symmetric cycles of amplitudes A, 0.6·A, 0.3·A
  (concentric, centred at 0) and one minor loop on the last descending branch, all at ``v_qs``;
* **Stribeck curve**: steady sliding force at constant velocities ±v (last value of a run long enough
  to leave pre-sliding and let frictional lag settle).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.errors import ConfigError
from stagectl.friction.base import FrictionModel
from stagectl.outputs import prefix_for

FloatArray = npt.NDArray[np.float64]

UM = 1e-6


@dataclass
class Curves:
    """The three characteristic curves of one model (SI units)."""

    label: str
    virgin_x_m: FloatArray
    virgin_f_n: FloatArray
    loop_x_m: FloatArray
    loop_f_n: FloatArray
    stribeck_v_m_s: FloatArray
    stribeck_f_n: FloatArray
    extra: dict[str, Any] = field(default_factory=dict)


def _finite_peak(col: np.ndarray) -> float:
    """Largest finite |value| of a column, 0 if it has none (an all-NaN column such as ``ilc_rms_m`` before a
    repetition completed made ``np.nanmax`` print a RuntimeWarning under the command's output)."""
    finite = np.abs(col[np.isfinite(col)])
    return float(finite.max()) if finite.size else 0.0


def _ramp(points: Sequence[float], step_m: float) -> FloatArray:
    """Piecewise-linear path through ``points`` sampled every ~``step_m``."""
    out = [np.array([points[0]])]
    for a, b in zip(points[:-1], points[1:]):
        n = max(2, int(np.ceil(abs(b - a) / step_m)))
        out.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(out)


def virgin_curve(model: FrictionModel, x_max_m: float = 30 * UM, n: int = 600,
                 v_qs_m_s: float = 1e-6) -> tuple[FloatArray, FloatArray]:
    """Quasi-static first-loading curve ``F(x)`` for ``0 <= x <= x_max_m``."""
    x = np.linspace(0.0, x_max_m, n + 1)
    t = x / v_qs_m_s
    return x, model.force_along(x, t)


def hysteresis_loops(model: FrictionModel, amplitude_m: float = 20 * UM, v_qs_m_s: float = 1e-6,
                     step_m: float = 0.02 * UM) -> tuple[FloatArray, FloatArray]:
    """Nested loops: 0 → A → −A → A, then ±0.6A and ±0.3A cycles, then a minor loop."""
    a = amplitude_m
    pts = [0.0, a, -a, a, -0.6 * a, 0.6 * a, -0.3 * a, 0.3 * a, -0.1 * a, 0.1 * a, -0.3 * a]
    x = _ramp(pts, step_m)
    t = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)) / v_qs_m_s)])
    # zero-length steps would make t non-increasing; _ramp never produces them
    return x, model.force_along(x, t)


def stribeck_curve(model: FrictionModel, v_max_m_s: float = 0.05, v_min_m_s: float = 1e-6, n_v: int = 41,
                   samples: int = 2000) -> tuple[FloatArray, FloatArray]:
    """Steady sliding force at ±v for ``n_v`` log-spaced speeds (returned sorted by v)."""
    speeds = np.logspace(np.log10(v_min_m_s), np.log10(v_max_m_s), n_v)
    vs, fs = [], []
    for sign in (-1.0, 1.0):
        for v in speeds:
            vs.append(sign * v)
            fs.append(steady_force(model, sign * v, samples))
    order = np.argsort(vs)
    return np.asarray(vs)[order], np.asarray(fs)[order]


def compute_curves(model: FrictionModel, label: str, x_max_m: float = 30 * UM,
                   loop_amplitude_m: float | None = None) -> Curves:
    """All three curves for one model."""
    vx, vf = virgin_curve(model, x_max_m)
    lx, lf = hysteresis_loops(model, loop_amplitude_m or 2.0 * x_max_m / 3.0)
    sv, sf = stribeck_curve(model)
    return Curves(label, vx, vf, lx, lf, sv, sf)


def steady_force(model: FrictionModel, v_m_s: float, samples: int = 2000) -> float:
    """Steady sliding force [N] at constant velocity ``v_m_s`` (as in :func:`stribeck_curve`)."""
    travel = max(1e-3, abs(v_m_s) * 0.2)
    x = np.linspace(0.0, np.copysign(travel, v_m_s), samples)
    return float(model.force_along(x, np.linspace(0.0, travel / abs(v_m_s), samples))[-1])


def summary(c: Curves, model: FrictionModel | None = None) -> dict[str, Any]:
    """Key figures of a model's curves (for ``--json``); exact steady forces when ``model`` is given."""
    def at(xq: float) -> float:
        return float(np.interp(xq, c.virgin_x_m, c.virgin_f_n))

    k0 = float((c.virgin_f_n[1] - c.virgin_f_n[0]) / (c.virgin_x_m[1] - c.virgin_x_m[0]))
    return {
        "label": c.label,
        "virgin_n": {f"{x:g}um": at(x * UM) for x in (1, 2, 5, 10, 20, 30) if x * UM <= c.virgin_x_m[-1]},
        "virgin_end_n": float(c.virgin_f_n[-1]),
        "initial_stiffness_n_m": k0,
        "stribeck_n": {f"{v:g}m_s": (steady_force(model, v) if model is not None
                                     else float(np.interp(v, c.stribeck_v_m_s, c.stribeck_f_n)))
                       for v in (-1e-3, 1e-4, 1e-3, 1e-2)},
    }


# ------------------------------------------------------------------------------------------------ plots
def _fig(title: str):  # type: ignore[no-untyped-def]
    import matplotlib  # heavy optional library: imported only when a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.8), dpi=110)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    return plt, fig, ax


def _save(plt: Any, fig: Any, path: Path, rect: tuple[float, float, float, float] | None = None) -> Path:
    fig.tight_layout(rect=rect)
    try:
        fig.savefig(path)
    except OSError as exc:
        raise ConfigError(f"--out: cannot write {path} ({exc.strerror or exc})") from exc
    finally:
        plt.close(fig)
    return path


def plot_curves(curves: Sequence[Curves], out_dir: str | Path, suffix: str = "") -> list[Path]:
    """Write ``virgin{suffix}.png``, ``hysteresis{suffix}.png`` and ``stribeck{suffix}.png``; overlay if several."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out: cannot create output directory {out} ({exc.strerror or exc})") from exc
    written = []
    # overlaid curves can coincide (e.g. two models with the same sliding parameters): later curves are
    # dashed with other markers so that every one stays visible
    styles = [("-", "."), ("--", "x"), (":", "+"), ("-.", "1")]

    plt, fig, ax = _fig("Virgin curve (quasi-static first loading)")
    for j, c in enumerate(curves):
        ax.plot(c.virgin_x_m / UM, c.virgin_f_n, ls=styles[j % 4][0], label=c.label)
    ax.set_xlabel("displacement x [µm]")
    ax.set_ylabel("friction force F [N]")
    ax.legend()
    written.append(_save(plt, fig, out / f"virgin{suffix}.png"))

    plt, fig, ax = _fig("Nested hysteresis loops (quasi-static)")
    for j, c in enumerate(curves):
        ax.plot(c.loop_x_m / UM, c.loop_f_n, ls=styles[j % 4][0], label=c.label, lw=1.0)
    ax.set_xlabel("displacement x [µm]")
    ax.set_ylabel("friction force F [N]")
    ax.legend()
    written.append(_save(plt, fig, out / f"hysteresis{suffix}.png"))

    plt, fig, ax = _fig("Stribeck curve (steady sliding)")
    for j, c in enumerate(curves):
        ls, mk = styles[j % 4]
        pos = c.stribeck_v_m_s > 0
        (line,) = ax.plot(c.stribeck_v_m_s[pos] * 1e3, c.stribeck_f_n[pos], ls=ls, marker=mk, label=c.label)
        ax.plot(c.stribeck_v_m_s[~pos] * 1e3, c.stribeck_f_n[~pos], ls=ls, marker=mk, color=line.get_color())
    ax.set_xscale("symlog", linthresh=1e-3)
    ax.set_xlabel("velocity v [mm/s] (symlog)")
    ax.set_ylabel("steady friction force F [N]")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.legend()
    written.append(_save(plt, fig, out / f"stribeck{suffix}.png"))
    return written


def presliding_extent(d_m: FloatArray, f_n: FloatArray, fraction: float = 0.95) -> float:
    """Displacement [m] at which a virgin curve ``f_n(d_m)`` (``d_m`` ascending from 0) first reaches
    ``fraction`` of its largest force: the end of the pre-sliding regime. ``d_m[-1]`` if never reached."""
    d = np.asarray(d_m, dtype=np.float64)
    f = np.abs(np.asarray(f_n, dtype=np.float64))
    if d.size == 0:
        return 0.0
    top = float(np.max(f))
    if not np.isfinite(top) or top <= 0.0:
        return float(d[-1])
    k = int(np.argmax(f >= fraction * top))
    return float(d[k])


def plot_virgin_fit(d_m: FloatArray, f_n: FloatArray, model_d_m: FloatArray, model_f_n: FloatArray,
                    path: str | Path, label: str = "model") -> Path:
    """Measured virgin points and a model's virgin curve, in two panels: the whole range, and the pre-sliding
    region (0 … 3× the displacement where the model reaches 95 % of its force), each in the unit that suits it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    zoom = min(float(np.max(model_d_m)), 3.0 * presliding_extent(model_d_m, model_f_n))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, top, title in ((axes[0], float(np.max(model_d_m)), "whole range"),
                           (axes[1], zoom, "pre-sliding region")):
        k, unit = prefix_for(top, "m")
        md = model_d_m <= top * (1 + 1e-12)
        mp = d_m <= top * (1 + 1e-12)
        ax.plot(d_m[mp] * k, f_n[mp], ".", ms=2, color="C0", label="measured virgin points")
        ax.plot(model_d_m[md] * k, model_f_n[md], lw=1.2, color="C3", label=f"{label} virgin curve")
        ax.set_xlabel(f"displacement [{unit}]")
        ax.set_ylabel("force [N]")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right", framealpha=0.8)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def compare_virgin(a: Curves, b: Curves) -> dict[str, float]:
    """RMS and max |F_a − F_b| over the common virgin-curve range [N]."""
    x = a.virgin_x_m[a.virgin_x_m <= b.virgin_x_m[-1]]
    d = np.interp(x, a.virgin_x_m, a.virgin_f_n) - np.interp(x, b.virgin_x_m, b.virgin_f_n)
    return {"virgin_rms_diff_n": float(np.sqrt(np.mean(d**2))), "virgin_max_abs_diff_n": float(np.max(np.abs(d))),
            "range_m": float(x[-1])}


# ------------------------------------------------------------------------------------------------ recordings
#: panels of a recording plot: title, SI unit, the columns it takes (in drawing order), by name
RECORDING_PANELS: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("position", "m", ("x_ref", "x")),
    ("tracking error x_ref − x", "m", ("e",)),
    ("force", "N", ("u", "u_pid", "u_dob", "u_ff", "u_inertia", "u_p", "u_i", "u_d")),
    ("velocity", "m/s", ("v_ref", "v")),
    ("acceleration", "m/s²", ("a_ref",)),
)
#: the PID's own parts are drawn thin and dashed: they sum to u_pid
_DETAIL = ("u_p", "u_i", "u_d")


def plot_recording(columns: Sequence[str], data: FloatArray, path: str | Path, title: str = "") -> Path:
    """One PNG of any recording (telemetry, simulate, commissioning, a user's CSV with t, x, u …).

    One panel per quantity present (position, error, force and its terms, velocity, acceleration; any other
    column gets its own panel), each y axis in the SI prefix that suits its range (nm, µm, mm; mN, N), one
    colour per trace from a qualitative palette, legends outside the axes so they cover no data.
    """
    import matplotlib  # heavy optional library: imported only when a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = list(columns)
    if "t" not in cols:
        raise ConfigError("plot: the recording has no 't' column (time in s)")
    t = data[:, cols.index("t")]
    known = {c for _, _, group in RECORDING_PANELS for c in group} | {"t"}
    panels = [(ttl, unit, [c for c in group if c in cols]) for ttl, unit, group in RECORDING_PANELS]
    panels = [p for p in panels if p[2]] + [(c, "", [c]) for c in cols if c not in known]
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, 2.2 + 2.0 * len(panels)), sharex=True, squeeze=False)
    colours = [f"C{i}" for i in range(10)]  # matplotlib's default cycle: the qualitative tab10 palette
    for ax, (ttl, unit, group) in zip(axes[:, 0], panels, strict=True):
        peak = max(_finite_peak(data[:, cols.index(c)]) for c in group)
        k, label = prefix_for(peak, unit) if unit else (1.0, "")
        for i, c in enumerate(group):
            detail = c in _DETAIL
            ax.plot(t, data[:, cols.index(c)] * k, lw=0.6 if detail else 0.9, ls="--" if detail else "-",
                    color=colours[i % len(colours)], label=c)
        ax.set_ylabel(f"{ttl}\n[{label}]" if label else ttl, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)
    axes[-1, 0].set_xlabel("time t [s]")
    if title:
        fig.suptitle(title)
    # room for the title above the top panel (tight_layout alone lays the panels over it)
    return _save(plt, fig, Path(path), rect=(0.0, 0.0, 1.0, 1.0 - (0.45 if title else 0.0) / fig.get_figheight()))
