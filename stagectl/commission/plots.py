"""Plots of the commissioning report (matplotlib, Agg): the FRF with the fitted model and the measured loop,
the friction force vs speed with the fitted curve, and the before/after tracking errors."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stagectl.commission import analysis as an

if TYPE_CHECKING:
    from stagectl.commission.sequence import Results


def write_plots(res: Results, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[str] = []
    T = res.config.loop.period_s
    if res.frf is not None and res.plant is not None:
        f = res.frf.f_hz
        pf = res.plant
        band = f >= pf.f_lo_hz  # the model is fitted (and drawn) only where it was fitted
        fb = f[band]
        g = an.plant_response(fb, pf.mass_kg, pf.damping_n_s_m, pf.stiffness_n_m, pf.delay_s, T)
        ph_m = np.degrees(np.unwrap(np.angle(res.frf.p)))
        ph_g = np.degrees(np.unwrap(np.angle(g)))
        if fb.size:  # draw the fit's phase on the measured branch (whole turns)
            ph_g += 360.0 * np.round((ph_m[band][0] - ph_g[0]) / 360.0)
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        ax[0].loglog(f, np.abs(res.frf.p), ".", label="measured P = X/U")
        ax[0].loglog(fb, np.abs(g), "-", label=f"fit: m {pf.mass_kg:.4g} kg, delay {pf.delay_s * 1e3:.3g} ms")
        ax[0].axvline(pf.f_lo_hz, color="0.6", lw=0.8, ls="--", label="mass fit band from here")
        ax[0].set_ylabel("|P| [m/N]")
        ax[0].legend(fontsize=8)
        ax[1].semilogx(f, ph_m, ".")
        ax[1].semilogx(fb, ph_g, "-")
        ax[1].set_ylabel("phase [deg]")
        ax[1].set_xlabel("frequency [Hz]")
        fig.suptitle("plant FRF (closed-loop, force multisine)")
        fig.tight_layout()
        p = out / "frf.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        files.append(str(p))
    if res.cv is not None:
        cv = res.cv
        v = np.array([s.v_m_s for s in cv.segments])
        fseg = np.array([s.f_n for s in cv.segments])
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.plot(v * 1e3, fseg, "o", label="segment means")
        vv = np.linspace(v.min(), v.max(), 400)
        fit = cv.coulomb_n * np.sign(vv) + cv.viscous_n_s_m * vv + cv.offset_n
        if cv.stribeck is not None:
            s = cv.stribeck
            fit = fit + np.sign(vv) * (s["fs_n"] - s["fc_n"]) * np.exp(-np.abs(vv / s["vs_m_s"]) ** s["delta"])
        ax.plot(vv * 1e3, fit, "-", label=f"Fc {cv.coulomb_n:.4g} N, Fv {cv.viscous_n_s_m:.4g} N s/m")
        ax.set_xlabel("velocity [mm/s]")
        ax.set_ylabel("friction force [N]")
        ax.legend(fontsize=8)
        fig.tight_layout()
        p = out / "friction.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        files.append(str(p))
    names = [n for n in res.verification if all(f"verify_{w}_{n}" in res.recordings for w in ("before", "after"))]
    if names:
        fig, axs = plt.subplots(len(names), 1, figsize=(9, 2.6 * len(names)))
        for ax, n in zip(np.atleast_1d(axs), names):
            for w in ("before", "after"):
                r = res.recordings[f"verify_{w}_{n}"]
                t = r.col("t")
                ax.plot(t - t[0], r.col("e") * 1e9, lw=0.7, label=w)
            ax.set_ylabel(f"{n}: e [nm]")
            ax.legend(fontsize=8)
        np.atleast_1d(axs)[-1].set_xlabel("time [s]")
        fig.tight_layout()
        p = out / "verification.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        files.append(str(p))
    return files
