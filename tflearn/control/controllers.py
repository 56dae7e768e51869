"""Controllers: torque programs (t, ν, v) → τ that track a target motion (Yin, Cline & Pai
2003) or play a learned torque-field program, all callable as :func:`tflearn.simulation.simulate.simulate`'s
``program``.

A :class:`Target` is the motion to track: its quintic spline (:class:`tflearn.motions.spline.MotionSpline`)
gives ν_d(t) and v_d(t), and its feed-forward torque τ_ff(t) is by default the spline's
inverse dynamics — the torques the learner fits (:func:`tflearn.motions.spline.torques`, body
gravity and damping included, so that τ_ff alone replays the motion on the nominal body).
Any other exact torque (e.g. a gesture's generating program along its path) can be
given instead. Outside [t₀, t₁] the target holds its end values.

The controllers (:data:`CONTROLLERS`, built by :func:`build`):

* ``ff``      τ = τ_ff(t): open-loop playback of the dynamics.
* ``ff+pd``   τ = τ_ff(t) + K (ν_d(t) ⊖ ν) + B (v_d(t) − v): Yin's feed-forward plus
  low-gain, biologically plausible stiffness K and viscosity B per joint
  (:data:`HUMAN_ARM_GAINS`); ⊖ is :func:`tflearn.physics.configspace.difference` (for a ball
  joint the rotation vector of R(ν)ᵀ R(ν_d), in the current child frame, the frame its
  torque acts in). With ``bilinear`` c > 0, the stiffness grows with the feed-forward
  torque, K_k(t) = K₀,k + c |τ_ff,k(t)| per coordinate (the bilinear muscle model the
  paper cites; c in rad⁻¹), B unchanged.
* ``pd-high`` τ = s K₀ (ν_d ⊖ ν) + √s B (v_d − v): high-gain tracking without feed-forward
  (s = ``high_gain``; B scaled by √s keeps each joint's damping ratio) — the robotic reference.
* ``fields``  the motion's learned torque-field program (a one-motion
  :class:`tflearn.model.program.FieldProgram`), which has no target term at all.

The body's own viscous damping c v (``Body.damping``) is physics, subtracted by the
simulator; it is not part of any controller. Every controller broadcasts over leading
batch dimensions of ν and v (the target depends on t only).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional

import torch

from ..errors import InputError
from ..model.program import FieldProgram
from ..motions.motion import Motion
from ..motions.spline import MotionSpline
from ..physics.body import Body
from ..physics.configspace import difference

#: Per-joint stiffness K₀ (N·m/rad) and viscosity B (N·m·s/rad) of the human arm, by the
#: arm's link names (:func:`tflearn.physics.body.arm`); a ball joint's value applies to each of its
#: three coordinates. Shoulder and elbow: the diagonal of the joint stiffness and
#: viscosity matrices of Shadmehr & Mussa-Ivaldi (1994, J. Neurosci. 14:3208), K =
#: [[15, 6], [6, 16]] N·m/rad, B = [[2.3, 0.09], [0.09, 2.4]] N·m·s/rad, also used by Wang,
#: Dordevic & Shadmehr (2001), the model Yin et al. build on; the cross-joint terms are
#: left out (per-joint gains). Wrist: 1 N·m/rad, the order of measured passive wrist
#: stiffness, with B = 0.05 K, the viscosity-to-stiffness ratio of Selen, Franklin &
#: Wolpert (2009). See docs/perturbation.md.
HUMAN_ARM_GAINS = {"upper_arm": (15.0, 2.3), "forearm": (16.0, 2.4), "hand": (1.0, 0.05)}


class ControllerError(InputError):
    """A controller that cannot be built (unknown name, missing gains or program)."""


@dataclass(frozen=True)
class ControllerOptions:
    """gains: link name → (K₀ N·m/rad, B N·m·s/rad), default :data:`HUMAN_ARM_GAINS`;
    scale: multiplies every K₀ (and B by √scale) of ``ff+pd``; bilinear: c (rad⁻¹) of
    K = K₀ + c|τ_ff| for ``ff+pd``; high_gain: s of ``pd-high`` (s K₀, √s B)."""

    gains: Optional[Mapping[str, tuple]] = None
    scale: float = 1.0
    bilinear: float = 0.0
    high_gain: float = 20.0


def joint_gains(body: Body, gains: Optional[Mapping[str, tuple]] = None) -> tuple:
    """Per-coordinate stiffness and viscosity (nv each) from per-link (K, B); raises
    :class:`ControllerError` naming a moving link without gains."""
    gains = HUMAN_ARM_GAINS if gains is None else gains
    K, B = torch.zeros(body.nv, dtype=torch.float64), torch.zeros(body.nv, dtype=torch.float64)
    for i, link in enumerate(body.links):
        if not link.dof:
            continue
        if link.name not in gains:
            raise ControllerError(f"no stiffness and viscosity for link {link.name!r} "
                                  f"(gains given for {', '.join(gains) or 'none'})")
        K[body.slice(i)], B[body.slice(i)] = gains[link.name]
    return K, B


class Target:
    """The motion a controller tracks: ν_d(t), v_d(t) from its spline and τ_ff(t).

    τ_ff(t) is the spline's inverse dynamics (on a moving ``base``, a one-member
    :class:`tflearn.motions.torso.Bases`, with its inertial terms and gravity seen from
    it), or with ``program`` (on ν (...×nv), e.g. a :class:`OneMotion`) τ_ff(t) =
    program(t, ν_d(t), v_d(t)) — a motion's exact torques when that program generated
    it. Calling the target at a time t (scalar) returns (ν_d, v_d, τ_ff), nv each; times
    outside the motion are clamped to its ends."""

    def __init__(self, body: Body, motion: Motion, program=None, base=None):
        self.body, self.motion, self.program, self.base = body, motion, program, base
        self.spline = MotionSpline(body, motion)
        self._last = (None, None)

    def __call__(self, t):
        tt = torch.as_tensor(t, dtype=torch.float64).detach().reshape(1)
        tt = tt.clamp(self.spline.t0, self.spline.t1)
        key = float(tt)
        if self._last[0] == key:                 # FSAL: the solver asks twice per step
            return self._last[1]
        if self.program is None:
            moving = None if self.base is None else self.base.terms(self.body.gravity, tt)
            tau, q, v, _ = self.spline.torques(tt, moving)
            out = q[0], v[0], tau[0]
        else:
            q, v, _, _ = self.spline(tt)
            out = q[0], v[0], self.program(tt[0], q[0], v[0])
        self._last = (key, out)
        return out


class FeedForward(torch.nn.Module):
    """τ = τ_ff(t)."""

    def __init__(self, target: Target):
        super().__init__()
        self.target = target

    def forward(self, t, q, v):
        return self.target(t)[2].expand(v.shape)


class Impedance(torch.nn.Module):
    """τ = [τ_ff(t)] + (K₀ + c|τ_ff(t)|)(ν_d(t) ⊖ ν) + B (v_d(t) − v); K₀, B (nv)."""

    def __init__(self, target: Target, stiffness: torch.Tensor, viscosity: torch.Tensor,
                 bilinear: float = 0.0, feedforward: bool = True):
        super().__init__()
        self.target, self.bilinear, self.feedforward = target, bilinear, feedforward
        self.register_buffer("K0", torch.as_tensor(stiffness, dtype=torch.float64))
        self.register_buffer("B", torch.as_tensor(viscosity, dtype=torch.float64))

    def forward(self, t, q, v):
        qd, vd, tau_ff = self.target(t)
        K = self.K0 + self.bilinear * tau_ff.abs() if self.bilinear else self.K0
        tau = K * difference(self.target.body, q, qd.expand(q.shape)) + self.B * (vd - v)
        return tau + tau_ff if self.feedforward else tau


def _ff(target, program, options):
    return FeedForward(target)


def _ff_pd(target, program, options):
    K, B = joint_gains(target.body, options.gains)
    return Impedance(target, options.scale * K, math.sqrt(options.scale) * B, options.bilinear)


def _pd_high(target, program, options):
    K, B = joint_gains(target.body, options.gains)
    s = options.high_gain
    return Impedance(target, s * K, math.sqrt(s) * B, feedforward=False)


class OneMotion(torch.nn.Module):
    """A one-motion :class:`~tflearn.model.program.FieldProgram` on ν, v (...×nv) without its
    motion dimension: τ = program(t, ν[..., None, :], v[..., None, :])[..., 0, :] (v for the
    fields' damping)."""

    def __init__(self, program: FieldProgram):
        super().__init__()
        self.program = program

    def forward(self, t, q, v):
        return self.program(t, q.unsqueeze(-2), v.unsqueeze(-2))[..., 0, :]


def _fields(target, program, options):
    if program is None:
        raise ControllerError("controller 'fields' needs the motion's learned program (a basis)")
    return OneMotion(program)


#: name → builder(target, fields program or None, ControllerOptions) → program(t, ν, v).
CONTROLLERS = {"fields": _fields, "ff+pd": _ff_pd, "ff": _ff, "pd-high": _pd_high}


def build(name: str, target: Target, program: Optional[FieldProgram] = None,
          options: ControllerOptions = ControllerOptions()):
    """The controller ``name`` (:data:`CONTROLLERS`) for ``target``; ``program`` is the
    motion's learned field program (needed by ``fields`` only)."""
    if name not in CONTROLLERS:
        raise ControllerError(f"unknown controller {name!r} (expected one of {', '.join(CONTROLLERS)})")
    return CONTROLLERS[name](target, program, options)
