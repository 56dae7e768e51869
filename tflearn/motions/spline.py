"""Splines through a motion's samples and their inverse-dynamics torques (thesis appendix A).

The samples of a :class:`~tflearn.motions.motion.Motion` are joined by a quintic
interpolating spline (C⁴, exact derivatives) and inverse dynamics is applied to it. The
thesis splines unit quaternions with a C¹ Hermite scheme (so its ω̇ jumps at the knots);
here ball joints have two exact alternatives (``method``):

* ``"quat"`` (default): the samples' quaternions, sign-aligned along the sequence, are
  splined component-wise and ω = 2 vec(p̄ṗ)/|p|², ω̇ = 2 vec(p̄p̈)/|p|² − 2ω (p·ṗ)/|p|²
  (exact for the non-unit spline p). Regular everywhere on SO(3).
* ``"rotvec"``: the rotation vectors are unwrapped along the sequence
  (:func:`unwrap_rotvec`: the principal vector may jump to an equivalent (|v| + 2πk) v̂
  when |v| crosses π), splined, and mapped with the right Jacobian of SO(3):

      ω = J_r(v) v̇,      ω̇ = J_r(v) v̈ + (d/dt J_r(v)) v̇,
      J_r(v) = I − a(θ) [v]× + b(θ) [v]×²,  a = (1 − cos θ)/θ², b = (θ − sin θ)/θ³,

  which satisfies [ω]× = Rᵀ Ṙ for R = exp([v]×) and is smooth at v = 0 (a and b are
  even in θ, by Taylor series in θ² near 0). The chart is singular at |v| = 2π, which
  an unwrapped sequence reaches when the joint comes back near its rest rotation after
  crossing π; the derivatives there are poorly conditioned (measured: 100× the torque
  error of ``"quat"`` on such a motion), hence the quaternion default.

Hinges: the angle is splined directly.

τ = RNEA(ν, ω, ω̇) + c·ω then gives the torque the program must have applied (the body's
gravity is included; c is the body's viscous damping, which the simulator subtracts).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
import roma
import torch
from scipy.interpolate import make_interp_spline

from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import (
    align_quaternions,
    body_acceleration,
    body_velocity,
    unwrap_rotvec,
    wrap_rotvec,
)
from .motion import DTYPE, Motion

__all__ = ["SPLINE_METHODS", "RESOLVED", "quat_body_motion", "MotionSpline", "kinematics", "torques",
           "torque_resolution", "resample"]

SPLINE_METHODS = ("quat", "rotvec")


def quat_body_motion(p: torch.Tensor, pd: torch.Tensor, pdd: torch.Tensor):
    """Body angular velocity and acceleration of a non-unit quaternion path p(t) (XYZW,
    ...×4), R(t) = R(p/|p|):

        ω = 2 vec(p̄ ṗ)/|p|²,    ω̇ = 2 vec(p̄ p̈)/|p|² − ω · 2(p·ṗ)/|p|²

    (vec(conj(ṗ) ṗ) = 0). For a unit path this is thesis eq. A.1, ω = 2 q̄ q̇, in the body
    frame (q̇ = ½ q ⊗ (ω, 0), as in :mod:`tflearn.simulation.simulate`). Returns (ω, ω̇), ...×3 each.
    """
    n2 = (p * p).sum(-1, keepdim=True)
    pc = roma.quat_conjugation(p)
    w = 2 * roma.quat_product(pc, pd)[..., :3] / n2
    n2dot = 2 * (p * pd).sum(-1, keepdim=True)
    wd = 2 * roma.quat_product(pc, pdd)[..., :3] / n2 - w * (n2dot / n2)
    return w, wd


class MotionSpline:
    """A C⁴ quintic interpolating spline (k = 5, not-a-knot ends; cubic for T < 6) through
    a motion's samples, with exact derivatives mapped to body velocities.

    Ball joints, two parametrisations (``method``):

    * ``"quat"`` (default): the samples' unit quaternions, sign-aligned along the sequence
      (:func:`align_quaternions`), are splined component-wise; the spline p(t) is not
      exactly unit, which :func:`quat_body_motion` accounts for exactly. No singularity
      anywhere on SO(3).
    * ``"rotvec"``: the rotation vectors, unwrapped (:func:`unwrap_rotvec`), are splined
      and mapped with the right Jacobian (:func:`body_velocity`,
      :func:`body_acceleration`). Exact too, but the chart is singular at |v| = 2π: a
      motion whose unwrapped vector nears 2π (one that turns back to the rest rotation
      "the long way round") gets large, badly conditioned derivatives there.

    Hinges: the angle is splined directly. Only positions are interpolated; a motion's
    ``qd`` is not used (see :func:`torques`).

    Calling it at times t (T', within [t[0], t[-1]]) returns (ν, velocity, acceleration,
    rotations): ν principal coordinates (T'×nv, |v| ≤ π), velocity and acceleration
    (T'×nv) in the body convention, and the ball joints' rotation matrices as the list
    :func:`tflearn.physics.dynamics.rnea_rot` takes (T'×3×3 per ball joint, None otherwise).
    """

    def __init__(self, body: Body, motion: Motion, method: str = "quat"):
        if motion.nv != body.nv:
            raise ValueError(f"motion {motion.name!r} has nv = {motion.nv}, "
                             f"the {body.name} body has nv = {body.nv}")
        if method not in SPLINE_METHODS:
            raise ValueError(f"unknown spline method {method!r} "
                             f"(expected one of {SPLINE_METHODS})")
        self.body, self.name, self.method = body, motion.name, method
        self.t0, self.t1 = float(motion.t[0]), float(motion.t[-1])
        cols, self.columns, k = [], [], 0
        for i, link in enumerate(body.links):
            x = motion.q[:, body.slice(i)]
            if link.joint == "ball":
                x = (align_quaternions(roma.rotvec_to_unitquat(x)) if method == "quat"
                     else unwrap_rotvec(x))
            cols.append(x)
            self.columns.append(slice(k, k + x.shape[-1]))
            k += x.shape[-1]
        degree = 5 if motion.T >= 6 else 3
        self.spline = make_interp_spline(motion.t.numpy(), torch.cat(cols, -1).numpy(),
                                         k=degree, axis=0)
        self.d1, self.d2 = self.spline.derivative(1), self.spline.derivative(2)

    def _times(self, t) -> np.ndarray:
        t = np.atleast_1d(np.asarray(torch.as_tensor(t, dtype=DTYPE).cpu(), dtype=np.float64))
        tol = 1e-9 * max(1.0, abs(self.t0), abs(self.t1))
        if t.ndim != 1 or (t < self.t0 - tol).any() or (t > self.t1 + tol).any():
            raise ValueError(f"motion {self.name!r}: times must be a 1-D array within "
                             f"[{self.t0}, {self.t1}]")
        return np.clip(t, self.t0, self.t1)

    def __call__(self, t):
        t = self._times(t)
        x, xd, xdd = (torch.from_numpy(np.ascontiguousarray(f(t))) for f in
                      (self.spline, self.d1, self.d2))
        q, v, a, rots = [], [], [], []
        for i, link in enumerate(self.body.links):
            c = self.columns[i]
            p, pd, pdd = x[:, c], xd[:, c], xdd[:, c]
            if link.joint != "ball":
                q.append(p), v.append(pd), a.append(pdd), rots.append(None)
            elif self.method == "quat":
                unit = roma.quat_normalize(p)
                w, wd = quat_body_motion(p, pd, pdd)
                q.append(roma.unitquat_to_rotvec(unit, shortest_arc=True))
                v.append(w), a.append(wd), rots.append(roma.unitquat_to_rotmat(unit))
            else:
                q.append(wrap_rotvec(p)), v.append(body_velocity(p, pd))
                a.append(body_acceleration(p, pd, pdd))
                rots.append(dynamics.rotvec_to_rotmat(p))
        return torch.cat(q, -1), torch.cat(v, -1), torch.cat(a, -1), rots

    def torques(self, t, base=None):
        """Inverse-dynamics torques at times t (T'): τ = RNEA(ν, ω, ω̇) + c ω (the body's
        gravity and damping c), with ν, ω, ω̇ from this spline; ``base``: a moving base
        seen at those times, (g_b, (ω_b, ω̇_b, a_b)), T'×3 each
        (:meth:`tflearn.motions.torso.Bases.terms`). Returns (τ, ν, ω, ω̇), T'×nv each."""
        q, v, a, rots = self(t)
        moving = {} if base is None else dict(zip(("gravity", "base"), base))
        tau = dynamics.rnea_rot(self.body, rots, q, v, a, **moving)
        if self.body.damping:
            tau = tau + self.body.damping * v
        return tau, q, v, a


def kinematics(body: Optional[Body], motion: Motion, t=None, method: str = "quat"):
    """Spline coordinates ν (principal), velocities and accelerations (each T'×nv, body
    convention) of a motion at times t (T', default the motion's own t); see
    :class:`MotionSpline`. ``body`` None means ``motion.body``."""
    body = motion.body if body is None else body
    return MotionSpline(body, motion, method)(motion.t if t is None else t)[:3]


def torques(body: Optional[Body], motion: Motion, t=None, method: str = "quat", base=None):
    """Inverse-dynamics torques of a sampled motion (thesis appendix A).

    τ = RNEA(ν, ω, ω̇) + c ω with ν, ω, ω̇ from :class:`MotionSpline` at times t (T',
    default motion.t), the body's gravity and damping c (``body`` None: motion.body).
    The motion's own ``qd`` is not used: the quintic position spline already recovers ω
    and ω̇ to high order (torque errors ~1e-5 relative at 100 Hz on simulated arm
    motions), while a cubic Hermite spline through the positions and the exact velocities
    measured 1.5e-3 to 7.6e-3 on the same motions (its second derivative is only
    first-order accurate).
    ``base``: the terms of a moving base at those times (:meth:`MotionSpline.torques`).
    Returns (τ, ω, ω̇), float64 tensors T'×nv (ω, ω̇ the body-convention velocities and
    accelerations: angular for ball joints, angle rates for hinges).
    """
    body = motion.body if body is None else body
    tau, _, v, a = MotionSpline(body, motion, method).torques(motion.t if t is None else t, base)
    return tau, v, a


RESOLVED = 1e-2   # torque_resolution at or below this: the samples resolve the motion


def torque_resolution(body: Optional[Body], motion: Motion, trim: int = 5,
                      method: str = "quat") -> float:
    """Estimated relative RMS error of a motion's spline torques (:func:`torques`), from
    its samples alone (Richardson): the spline through every other sample is compared
    with the spline through all of them at the interior sample times t_i,

        ε ≈ ‖τ_h − τ_2h‖ / (15 ‖τ_h‖),

    since a quintic spline's second derivative errs by O(h⁴) (16× at 2h). Measured on
    40 random programs of :data:`tflearn.data.gestures.SUPPORTED` at 100 Hz: 0.4–5.2× their
    true error (generating program against spline torques). Above :data:`RESOLVED` the
    motion is too fast for its sampling rate and torque matching cannot be trusted;
    resample faster or smooth it. ``trim`` samples at each end are left out. Needs
    at least 4·trim + 12 samples; returns NaN for shorter motions."""
    body = motion.body if body is None else body
    if motion.T < 4 * trim + 12:
        return float("nan")
    tau, _, _ = torques(body, motion, motion.t[trim:-trim], method)
    half = Motion(motion.name, motion.t[::2], motion.q[::2], None, body)
    inside = motion.t[trim:-trim] <= half.t[-1]
    tau2, _, _ = torques(body, half, motion.t[trim:-trim][inside], method)
    diff = (tau[inside] - tau2).norm()
    return float(diff / (15 * tau[inside].norm().clamp_min(1e-12)))


def resample(motion: Motion, rate: float, body: Optional[Body] = None,
             method: str = "quat") -> Motion:
    """The motion sampled at ``rate`` Hz from t[0] (last sample ≤ t[-1]) on its spline,
    with the spline's velocities as qd."""
    if not rate > 0:
        raise ValueError(f"resample: rate must be positive, got {rate}")
    body = motion.body if body is None else body
    n = int(math.floor(motion.duration * rate + 1e-9)) + 1
    t = motion.t[0] + torch.arange(n, dtype=DTYPE) / rate
    q, v, _ = kinematics(body, motion, t, method)
    return Motion(motion.name, t, q, v, body)
