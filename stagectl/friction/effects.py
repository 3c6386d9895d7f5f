"""Additional physical effects beyond the friction model (pure math).

The plant hides them in test data; the discovery workflow names and fits them; the controller's
feed-forward evaluates them. All are off unless configured. Each is a frozen dataclass in SI units.

With the friction model force ``F`` (opposing motion, N) at position ``x`` (m) and velocity ``v`` (m/s)::

    position_ripple:  F ← F · (1 + a · sin(2π x / λ + φ))          a = amplitude [–], λ = wavelength_m, φ = phase_rad
    asymmetry:        F ← F · (1 + r · sgn(F))                     r = ratio [–], |r| < 1
                      (friction levels differ by direction: Fc+ = (1+r)Fc, Fc− = (1−r)Fc, and likewise Fv)
    viscous_asymmetry: F ← F + d_v · |v|                           d_v = difference_n_s_m [N·s/m]
                      (only the viscous part differs: Fv+ = Fv + d_v, Fv− = Fv − d_v; Coulomb unchanged)
    F_other(x) = A · sin(2π x / λ_c + φ_c)                          cogging (conservative, direction-independent) [N]
               + F_0                                                offset (gravity on an incline, cable pull) [N]
               + k_s · (x − x0)                                     spring (cable carrier, flexure) [N]
    delay:      the applied force is the commanded force delayed by τ = delay_s [s] (actuator path, see sim)

The plant is ``m·a = u(t − τ) − F − F_other``. ``F_other`` has the same sign convention as friction:
positive ``F_other`` pushes towards negative x.

Three paths compute the same math and are checked to agree (``tests/friction/test_effects.py``): the scalar
methods :meth:`Effects.modify_friction` / :meth:`Effects.other_force`, the numpy-vectorised ``*_array``
methods, and the compiled kernels :func:`modify_friction_kernel` / :func:`other_force_kernel` that the plant
inlines into its integrator, reading the parameters packed by :meth:`Effects.packed` (:func:`pack_layout`).
Adding an effect means: a frozen dataclass here, a field on :class:`Effects`, its term in all three paths
and, if the plant should simulate it, its packed entries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from stagectl.jit import kernel
from stagectl.schema import param


@dataclass(frozen=True)
class Asymmetry:
    """Direction-dependent friction level: ``F ← F·(1 + r·sgn(F))``."""

    ratio: float = param(unit="", desc="relative level difference r: F+ = (1+r)F, F- = (1-r)F", gt=-1.0, lt=1.0)


@dataclass(frozen=True)
class ViscousAsymmetry:
    """Direction-dependent viscous friction: ``F ← F + d_v·|v|``, so that ``Fv+ = Fv + d_v`` and
    ``Fv− = Fv − d_v`` while the Coulomb level is the same in both directions (a real axis whose lubricant
    film or seal drags more one way; EMPS: Fv+ ≈ 167, Fv− ≈ 240 N·s/m)."""

    difference_n_s_m: float = param(unit="N·s/m", desc="half difference d_v = (Fv+ − Fv−)/2 of the viscous "
                                    "coefficients between the two directions")


@dataclass(frozen=True)
class PositionRipple:
    """Friction magnitude varying with position: ``F ← F·(1 + a·sin(2πx/λ + φ))``."""

    amplitude: float = param(unit="", desc="relative ripple amplitude a", ge=0.0, lt=1.0)
    wavelength_m: float = param(unit="m", desc="ripple period in position λ", gt=0.0)
    phase_rad: float = param(0.0, unit="rad", desc="ripple phase φ")


@dataclass(frozen=True)
class Cogging:
    """Conservative periodic force ``A·sin(2πx/λ + φ)``, independent of the direction of motion."""

    amplitude_n: float = param(unit="N", desc="cogging amplitude A", ge=0.0)
    wavelength_m: float = param(unit="m", desc="cogging period in position λ", gt=0.0)
    phase_rad: float = param(0.0, unit="rad", desc="cogging phase φ")


@dataclass(frozen=True)
class Offset:
    """Constant force ``F_0`` (gravity on an inclined axis, cable pull)."""

    force_n: float = param(unit="N", desc="constant force F_0 (positive pushes towards -x)")


@dataclass(frozen=True)
class Spring:
    """Position-proportional force ``k_s·(x − x0)`` (cable carrier, flexure)."""

    stiffness_n_m: float = param(unit="N/m", desc="spring stiffness k_s")
    x0_m: float = param(0.0, unit="m", desc="spring rest position x0")


@dataclass(frozen=True)
class Delay:
    """Actuation delay: the applied force is the commanded force delayed by ``delay_s``."""

    delay_s: float = param(unit="s", desc="pure delay τ between command and applied force", ge=0.0, le=0.1)


@dataclass(frozen=True)
class Effects:
    """The set of additional effects (YAML block ``effects:``). Every entry is optional (``null`` = off)."""

    asymmetry: Asymmetry | None = param(None, desc="direction-dependent friction level")
    viscous_asymmetry: ViscousAsymmetry | None = param(None, desc="direction-dependent viscous coefficient")
    position_ripple: PositionRipple | None = param(None, desc="friction magnitude periodic in position")
    cogging: Cogging | None = param(None, desc="conservative periodic force")
    offset: Offset | None = param(None, desc="constant force")
    spring: Spring | None = param(None, desc="position-proportional force")
    delay: Delay | None = param(None, desc="actuation delay")

    # ------------------------------------------------------------------ queries
    def active(self) -> list[str]:
        """Names of the effects that are switched on."""
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]

    def packed(self) -> npt.NDArray[np.float64]:
        """Parameters packed for compiled kernels (see :func:`pack_layout`)."""
        r = self.asymmetry.ratio if self.asymmetry else 0.0
        pr = self.position_ripple
        cg = self.cogging
        sp = self.spring
        return np.array(
            [
                r,
                pr.amplitude if pr else 0.0,
                pr.wavelength_m if pr else 1.0,
                pr.phase_rad if pr else 0.0,
                cg.amplitude_n if cg else 0.0,
                cg.wavelength_m if cg else 1.0,
                cg.phase_rad if cg else 0.0,
                self.offset.force_n if self.offset else 0.0,
                sp.stiffness_n_m if sp else 0.0,
                sp.x0_m if sp else 0.0,
                self.delay.delay_s if self.delay else 0.0,
                self.viscous_asymmetry.difference_n_s_m if self.viscous_asymmetry else 0.0,
            ],
            dtype=np.float64,
        )

    # ------------------------------------------------------------------ scalar path
    def modify_friction(self, f_n: float, x_m: float) -> float:
        """Apply ripple and asymmetry to a friction force ``f_n`` [N] at position ``x_m`` [m]."""
        pr = self.position_ripple
        if pr is not None:
            f_n *= 1.0 + pr.amplitude * math.sin(2.0 * math.pi * x_m / pr.wavelength_m + pr.phase_rad)
        if self.asymmetry is not None and f_n != 0.0:
            f_n *= 1.0 + self.asymmetry.ratio * (1.0 if f_n > 0.0 else -1.0)
        return f_n

    def velocity_force(self, v_m_s: float) -> float:
        """Friction term that depends on the velocity alone [N]: ``d_v·|v|`` (viscous asymmetry), added to the
        friction force after :meth:`modify_friction`."""
        va = self.viscous_asymmetry
        return va.difference_n_s_m * abs(v_m_s) if va is not None else 0.0

    def other_force(self, x_m: float) -> float:
        """``F_other(x)`` [N]: cogging + offset + spring."""
        out = 0.0
        cg = self.cogging
        if cg is not None:
            out += cg.amplitude_n * math.sin(2.0 * math.pi * x_m / cg.wavelength_m + cg.phase_rad)
        if self.offset is not None:
            out += self.offset.force_n
        if self.spring is not None:
            out += self.spring.stiffness_n_m * (x_m - self.spring.x0_m)
        return out

    # ------------------------------------------------------------------ vectorised path
    def modify_friction_array(self, f_n: npt.ArrayLike, x_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        f = np.array(f_n, dtype=np.float64, copy=True)
        x = np.asarray(x_m, dtype=np.float64)
        pr = self.position_ripple
        if pr is not None:
            f *= 1.0 + pr.amplitude * np.sin(2.0 * np.pi * x / pr.wavelength_m + pr.phase_rad)
        if self.asymmetry is not None:
            f *= 1.0 + self.asymmetry.ratio * np.sign(f)
        return f

    def velocity_force_array(self, v_m_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        v = np.asarray(v_m_s, dtype=np.float64)
        va = self.viscous_asymmetry
        return va.difference_n_s_m * np.abs(v) if va is not None else np.zeros_like(v)

    def other_force_array(self, x_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        x = np.asarray(x_m, dtype=np.float64)
        out = np.zeros_like(x)
        cg = self.cogging
        if cg is not None:
            out += cg.amplitude_n * np.sin(2.0 * np.pi * x / cg.wavelength_m + cg.phase_rad)
        if self.offset is not None:
            out += self.offset.force_n
        if self.spring is not None:
            out += self.spring.stiffness_n_m * (x - self.spring.x0_m)
        return out

    def spec(self) -> dict[str, Any]:
        """Plain mapping for YAML (only active effects)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            val = getattr(self, f.name)
            if val is not None:
                out[f.name] = {g.name: getattr(val, g.name) for g in fields(val)}
        return out


def pack_layout() -> tuple[str, ...]:
    """Names of the entries of :meth:`Effects.packed`, in order (for compiled kernels)."""
    return (
        "asym_ratio",
        "ripple_amplitude",
        "ripple_wavelength_m",
        "ripple_phase_rad",
        "cogging_amplitude_n",
        "cogging_wavelength_m",
        "cogging_phase_rad",
        "offset_n",
        "spring_n_m",
        "spring_x0_m",
        "delay_s",
        "viscous_asym_n_s_m",
    )


NO_EFFECTS = Effects()


# ---------------------------------------------------------------------------------------------- compiled path
# The plant's integrator (``stagectl.sim.plant``) inlines these two kernels. Its cache key includes this
# file's source hash (``stagectl.jit.kernel``), so an edit here recompiles the plant: no stale machine code.
@kernel(inline="always")
def modify_friction_kernel(ep: npt.NDArray[np.float64], f: float, x: float) -> float:  # pragma: no cover
    """Compiled :meth:`Effects.modify_friction` on packed parameters ``ep`` (:meth:`Effects.packed`):
    ripple ``F·(1 + a·sin(2πx/λ + φ))``, then asymmetry ``F·(1 + r·sgn(F))``. Real-time safe."""
    a = ep[1]
    if a != 0.0:
        f *= 1.0 + a * math.sin(2.0 * math.pi * x / ep[2] + ep[3])
    r = ep[0]
    if r != 0.0 and f != 0.0:
        f *= 1.0 + r * (1.0 if f > 0.0 else -1.0)
    return f


@kernel(inline="always")
def other_force_kernel(ep: npt.NDArray[np.float64], x: float) -> float:  # pragma: no cover - compiled
    """Compiled :meth:`Effects.other_force` on packed parameters ``ep``: offset ``F_0`` + cogging
    ``A·sin(2πx/λ_c + φ_c)`` + spring ``k_s·(x − x0)`` [N]. Real-time safe."""
    out = float(ep[7])
    if ep[4] != 0.0:
        out += ep[4] * math.sin(2.0 * math.pi * x / ep[5] + ep[6])
    if ep[8] != 0.0:
        out += ep[8] * (x - ep[9])
    return out


@kernel(inline="always")
def velocity_force_kernel(ep: npt.NDArray[np.float64], v: float) -> float:  # pragma: no cover - compiled
    """Compiled :meth:`Effects.velocity_force` on packed parameters ``ep``: ``d_v·|v|`` [N]. Real-time safe."""
    return float(ep[11]) * abs(v)
