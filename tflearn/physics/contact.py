"""Ground contact: penalty spring–dampers with regularised Coulomb friction on named points.

Each contact point k (a point fixed in a link) at world position p = (x, y, z) with
velocity ṗ = J v (:func:`tflearn.physics.dynamics.points_kinematics_rot`, linear rows) meets the
plane z = h. With depth d = h − z:

    f_n = max(0, k d − c ż)            where d > 0, else 0       (normal, +z)
    f_t = −μ f_n ṗ_t / √(|ṗ_t|² + v_s²)                          (tangential, ṗ_t = (ẋ, ẏ))

— a linear spring–damper that only pushes, and Coulomb friction |f_t| ≤ μ f_n whose
sign function is smoothed over the slip speed v_s (viscous, μ f_n/v_s, below it). The
forces act on the joints as τ = Σ_k J_kᵀ (f_k, 0). Parameters (:class:`Ground`) are per
point, so a body resting on P points sinks by m g/(P k) (the test checks it).

A body sliding on the plane at speed u under this law decelerates by μ g u/√(u² + v_s²),
so from speed u₀ it stops after (u₀ √(u₀² + v_s²) + v_s² asinh(u₀/v_s))/(2 μ g) — the
Coulomb distance u₀²/(2 μ g) as v_s → 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from . import dynamics
from .body import Body


@dataclass(frozen=True)
class Ground:
    """The plane z = ``height`` and its contact law (per contact point): ``stiffness`` k
    (N/m), ``damping`` c (N·s/m), ``friction`` μ and the regularising ``slip`` speed
    v_s (m/s)."""

    stiffness: float = 1000.0
    damping: float = 5.0
    friction: float = 0.8
    slip: float = 0.01
    height: float = 0.0

    def __post_init__(self):
        for name in ("stiffness", "damping", "friction", "slip"):
            if not 0 <= getattr(self, name) < math.inf:
                raise ValueError(f"ground.{name}: must be finite and non-negative, "
                                 f"got {getattr(self, name)}")
        if not self.slip > 0:
            raise ValueError("ground.slip: must be positive")


def contact_forces(p: torch.Tensor, pd: torch.Tensor, ground: Ground) -> torch.Tensor:
    """World forces (...×P×3) on points at p with velocities pd (...×P×3 each)."""
    depth = ground.height - p[..., 2]
    push = torch.clamp(ground.stiffness * depth - ground.damping * pd[..., 2], min=0.0)
    fn = torch.where(depth > 0, push, torch.zeros_like(push))
    vt = pd[..., :2]
    speed = torch.sqrt((vt * vt).sum(-1) + ground.slip * ground.slip)
    ft = -ground.friction * (fn / speed)[..., None] * vt
    return torch.cat([ft, fn[..., None]], dim=-1)


def contact_torques(body: Body, q: torch.Tensor, v: torch.Tensor, links: Sequence[int],
                    points: torch.Tensor, ground: Ground) -> torch.Tensor:
    """τ = Σ_k J_kᵀ (f_k, 0) (...×nv) of the ground's forces on the contact points."""
    p, J = dynamics.points_kinematics_rot(body, dynamics.joint_rotations(body, q), q, links,
                                          points)
    J = J[..., :3, :]                                                          # ...×P×3×nv
    f = contact_forces(p, (J @ v[..., None, :, None])[..., 0], ground)
    return (J.transpose(-1, -2) @ f[..., None])[..., 0].sum(-2)


def with_ground(body: Body, program, ground: Ground, links: Sequence[int], points):
    """The torque program τ(t, q, v) = program(t, q, v) + the ground's contact torques."""
    points = torch.as_tensor(points, dtype=torch.float64)

    def total(t, q, v):
        return program(t, q, v) + contact_torques(body, q, v, links, points, ground)
    return total
