"""Motion made of vibration modes (Kry et al. 2007, §4): kinematic and PD-driven.

Kinematic (the paper's eq. 4 with the postural offsets of §4.3): in the modes' chart
(:mod:`tflearn.modes.analysis`) the displacement from the rest pose is

    x(t) = Σᵢ αᵢ ûᵢ sin(2π f̃ᵢ t + γᵢ) + Σᵢ βᵢ ûᵢ

with ûᵢ the joint part of shape uᵢ scaled so that its largest coordinate is 1 (so α and
β are in rad of the joint coordinate that moves most; the M-orthonormal scale of
:mod:`tflearn.modes.analysis` depends on the body's size)

and the pose is θ(t) = θ₀ ⊕ x(t): per ball joint R(θ₀) exp([x]×) in the tangent chart
(ν₀ + x in the rotation-vector chart), per hinge θ₀ + x. Soft joint limits then act on
the coordinates: a coordinate past its limit by d is pulled back by d²/(d + Δθ_soft), so
that it ends d·Δθ_soft/(d + Δθ_soft) < Δθ_soft past the limit, smoothly (C¹) and never
clamped.

Dynamic (§4.1): a PD controller whose set point follows that motion,

    τ = K_t (θ_set(t) ⊖ θ) − c v,

with K_t the analysis stiffness in the tangent chart (:func:`tflearn.modes.analysis.tangent_stiffness`),
simulated by :func:`tflearn.simulation.simulate.simulate`, for fixed-base bodies; a floating base
on the ground is :mod:`tflearn.modes.locomotion`'s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from ..physics.configspace import difference, integrate, unwrap_rotvec
from ..simulation.simulate import SimOptions, Trajectory, simulate
from .analysis import ModalError, Modes, link_index, tangent_stiffness


@dataclass(frozen=True)
class ModeDrive:
    """One mode's part of a motion: α sin(2π f̃ t + γ) + β times shape ``mode`` (0-based,
    lowest first, rigid modes included, as in the paper's table 1), scaled to a largest
    joint coordinate of 1 (:func:`unit_shapes`). ``frequency`` None: the mode's own."""

    mode: int
    amplitude: float = 0.0
    frequency: Optional[float] = None
    phase: float = 0.0
    offset: float = 0.0


@dataclass(frozen=True)
class Limits:
    """Soft joint limits: lower, upper (nv, rad; ±inf where none) and Δθ_soft (rad)."""

    lower: np.ndarray
    upper: np.ndarray
    soft: float = 0.1

    @classmethod
    def from_config(cls, body, spec: Optional[dict], soft: float = 0.1) -> Limits:
        """``{link name: [lo, hi]}`` (the same for each of that joint's coordinates)."""
        lo, hi = np.full(body.nv, -np.inf), np.full(body.nv, np.inf)
        for name, bounds in (spec or {}).items():
            i = link_index(body, name, "limits")
            if len(bounds) != 2 or not bounds[0] < bounds[1]:
                raise ModalError(f"limits[{name!r}]: expected [lower, upper] with lower < upper, "
                                 f"got {bounds!r}")
            lo[body.slice(i)], hi[body.slice(i)] = bounds
        if not soft > 0:
            raise ModalError(f"soft limit: must be positive, got {soft}")
        return cls(lo, hi, float(soft))


def drive_frequencies(modes: Modes, drives: Sequence[ModeDrive]) -> list:
    """f̃ of each drive (its own, or the mode's frequency); ModalError for a bad index."""
    n = modes.frequencies.size
    for d in drives:
        if not 0 <= d.mode < n:
            raise ModalError(f"drive: mode {d.mode} does not exist (the body has {n} modes, "
                             f"0 … {n - 1})")
    return [float(modes.frequencies[d.mode]) if d.frequency is None else float(d.frequency)
            for d in drives]


def unit_shapes(modes: Modes) -> np.ndarray:
    """(shapes (nx × n), scale (n)): every shape divided by its largest joint coordinate
    (absolute value), so that its joint part peaks at 1 rad; scale is that divisor."""
    scale = np.abs(modes.joint_shapes).max(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    return modes.shapes / scale, scale


def displacement(modes: Modes, drives: Sequence[ModeDrive], t: torch.Tensor) -> torch.Tensor:
    """x(t) (...×nv) at times t (...) in the modes' chart (see the module)."""
    U = unit_shapes(modes)[0]
    U = torch.as_tensor(U[-modes.body.nv:], dtype=torch.float64)
    x = torch.zeros(t.shape + (U.shape[0],), dtype=torch.float64)
    for d, f in zip(drives, drive_frequencies(modes, drives)):
        w = d.amplitude * torch.sin(2 * math.pi * f * t + d.phase) + d.offset
        x = x + w[..., None] * U[:, d.mode]
    return x


def retract(modes: Modes, x: torch.Tensor) -> torch.Tensor:
    """θ₀ ⊕ x (...×nv) in the modes' chart: per ball joint log(R(ν₀) exp([x]×)) (tangent)
    or ν₀ + x (rotvec), per hinge θ₀ + x."""
    q0 = torch.as_tensor(modes.q0, dtype=torch.float64)
    if modes.options.chart == "rotvec":
        return q0 + x
    return integrate(modes.body, q0.expand(x.shape), x)


def soft_limit(q: torch.Tensor, limits: Optional[Limits]) -> torch.Tensor:
    """Coordinates past a limit by d moved back by d²/(d + Δθ_soft) (...×nv)."""
    if limits is None:
        return q
    lo = torch.as_tensor(limits.lower, dtype=q.dtype)
    hi = torch.as_tensor(limits.upper, dtype=q.dtype)
    s = limits.soft
    over = torch.clamp(q - hi, min=0.0)
    under = torch.clamp(lo - q, min=0.0)
    return q - over * over / (over + s) + under * under / (under + s)


def set_point(modes: Modes, drives: Sequence[ModeDrive], t: torch.Tensor,
              limits: Optional[Limits] = None) -> torch.Tensor:
    """The kinematic pose θ(t) (...×nv): soft-limited θ₀ ⊕ x(t)."""
    return soft_limit(retract(modes, displacement(modes, drives, t)), limits)


def kinematic(modes: Modes, drives: Sequence[ModeDrive], t, limits: Optional[Limits] = None):
    """The kinematic motion sampled at t (T): θ (T×nv), ball joints unwrapped in time."""
    t = torch.as_tensor(t, dtype=torch.float64)
    q = set_point(modes, drives, t, limits)
    parts = []
    for i, link in enumerate(modes.body.links):
        s = modes.body.slice(i)
        parts.append(unwrap_rotvec(q[:, s]) if link.joint == "ball" else q[:, s])
    return torch.cat(parts, dim=-1)


@dataclass(frozen=True)
class Following:
    """How a PD-driven simulation followed its kinematic set point: the path, and the
    joint error |θ_set ⊖ θ| (rad) as an RMS over samples and coordinates and a maximum."""

    trajectory: Trajectory
    rms: float
    max: float


def pd_program(modes: Modes, drives: Sequence[ModeDrive], limits: Optional[Limits] = None,
               damping: float = 0.0):
    """τ(t, θ, v) = K_t (θ_set(t) ⊖ θ) − c v (see the module)."""
    if modes.options.floating:
        raise ModalError("dynamic: PD-driven following needs a fixed-base body "
                         "(modes.floating: false); a floating one walks in tflearn.modes.locomotion")
    Kt = torch.as_tensor(tangent_stiffness(modes), dtype=torch.float64)
    body = modes.body

    still = set_point(modes, (), torch.zeros(()), limits) if not drives else None

    def program(t, q, v):
        target = still if still is not None else set_point(
            modes, drives, t.reshape(()).to(torch.float64), limits)
        err = difference(body, q, target.expand(q.shape))
        return err @ Kt.T - damping * v
    return program


def follow(modes: Modes, drives: Sequence[ModeDrive], t, limits: Optional[Limits] = None,
           damping: float = 0.0, options: SimOptions = SimOptions(), q_start=None,
           ) -> Following:
    """Simulate the PD controller from the set point at t[0] (or ``q_start``) at rest."""
    t = torch.as_tensor(t, dtype=torch.float64)
    target = set_point(modes, drives, t, limits)
    q_init = target[0] if q_start is None else torch.as_tensor(q_start, dtype=torch.float64)
    traj = simulate(modes.body, pd_program(modes, drives, limits, damping), q_init,
                    torch.zeros(modes.body.nv, dtype=torch.float64), t, options)
    err = difference(modes.body, traj.q, target).norm(dim=-1)
    return Following(traj, float(err.pow(2).mean().sqrt()), float(err.max()))


def modal_coordinate(modes: Modes, q: torch.Tensor, mode: int) -> np.ndarray:
    """c(t) = uᵀ M x(t) (T) with x = θ₀ ⊖ θ(t) in the modes' chart (tangent; rotvec: ν − ν₀):
    the amount of mode ``mode`` in a path (fixed base)."""
    q0 = torch.as_tensor(modes.q0, dtype=torch.float64)
    if modes.options.chart == "rotvec":
        x = q - q0
    else:
        x = difference(modes.body, q0.expand(q.shape), q)
    u = modes.shapes[:, mode]
    return x.numpy() @ (modes.M @ u)


def measured_frequency(t, c) -> float:
    """Frequency (Hz) of an oscillating signal c(t) from its upward zero crossings
    (linearly interpolated): (number of periods) / (last − first crossing)."""
    t, c = np.asarray(t), np.asarray(c)
    k = np.nonzero((c[:-1] < 0) & (c[1:] >= 0))[0]
    if k.size < 2:
        return float("nan")
    tc = t[k] - c[k] * (t[k + 1] - t[k]) / (c[k + 1] - c[k])
    return float((tc.size - 1) / (tc[-1] - tc[0]))
