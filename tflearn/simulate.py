"""Simulation of a body under a torque program with torchdiffeq's ``odeint``.

State packing: each ball joint's orientation is a unit quaternion (XYZW, as in roma and
Pinocchio), each hinge an angle, followed by the velocities v (nv). The state is

    y = [quat_1 (4), θ_2 (1), quat_3 (4), ..., v (nv)]       (...×(n_pos + nv))

and evolves by
    q̇_ball = ½ q ⊗ (ω, 0)     (ω the child-frame angular velocity),
    θ̇ = v_hinge,
    v̇ = M(q)⁻¹ (τ(t, ν, v) − c v − h(q, v)).

Quaternions are normalised wherever they are read, so the rotations used are exactly in
SO(3) whatever the integrator does to their norm; the double cover has no singularity
at zero rotation and none at π. The torque program sees ν, the principal rotation
vectors (|v| ≤ π) and hinge angles — the coordinates of :mod:`tflearn.body`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import roma
import torch
from torchdiffeq import odeint, odeint_adjoint

from . import dynamics
from .body import Body

TorqueProgram = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]

#: Calls of :func:`simulate` in this process (a batch counts once); the experiments
#: read it to report how many simulations a method needed.
calls = 0


def n_position(body: Body) -> int:
    """Size of the packed position block: 4 per ball joint, 1 per hinge."""
    return sum(4 if l.joint == "ball" else l.dof for l in body.links)


def pack(body: Body, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Coordinates ν (...×nv) and velocities v (...×nv) → ODE state (...×(n_pos+nv))."""
    batch = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q, v = q.expand(batch + q.shape[-1:]), v.expand(batch + v.shape[-1:])
    parts = []
    for i, link in enumerate(body.links):
        s = q[..., body.slice(i)]
        parts.append(roma.rotvec_to_unitquat(s) if link.joint == "ball" else s)
    return torch.cat(parts + [v], dim=-1)


def unpack(body: Body, y: torch.Tensor):
    """ODE state → (joint rotations list, ν principal coordinates, unit quaternions list, v)."""
    rots, coords, quats, k = [], [], [], 0
    for link in body.links:
        if link.joint == "ball":
            quat = roma.quat_normalize(y[..., k:k + 4])
            quats.append(quat)
            rots.append(roma.unitquat_to_rotmat(quat))
            coords.append(roma.unitquat_to_rotvec(quat, shortest_arc=True))
            k += 4
        else:
            quats.append(None)
            rots.append(None)
            coords.append(y[..., k:k + link.dof])
            k += link.dof
    return rots, torch.cat(coords, dim=-1), quats, y[..., k:]


class SimulationBudget(RuntimeError):
    """A simulation needed more right-hand-side evaluations than its ``max_evals``."""


class ArmODE(torch.nn.Module):
    """Right-hand side dy/dt for :func:`simulate` (an nn.Module so the adjoint can see
    the program's parameters). With ``track_work`` the state carries one more entry,
    W with dW/dt = τ_program · v (the work done by the program's torques). With
    ``max_evals`` it raises :class:`SimulationBudget` on evaluation max_evals + 1."""

    def __init__(self, body: Body, program: TorqueProgram, track_work: bool = False,
                 max_evals: Optional[int] = None):
        super().__init__()
        self.body, self.program, self.track_work = body, program, track_work
        self.max_evals, self.evals = max_evals, 0
        if isinstance(program, torch.nn.Module):
            self.program_module = program

    def forward(self, t, y):
        self.evals += 1
        if self.max_evals is not None and self.evals > self.max_evals:
            raise SimulationBudget(f"simulation: more than {self.max_evals} right-hand-side evaluations")
        body = self.body
        if self.track_work:
            y = y[..., :-1]
        rots, coords, quats, v = unpack(body, y)
        tau = self.program(t, coords, v)
        tau = tau.expand(v.shape) if tau.shape != v.shape else tau
        total = tau - body.damping * v if body.damping else tau
        a = dynamics.forward_dynamics_rot(body, rots, coords, v, total)
        dpos = []
        for i, link in enumerate(body.links):
            vi = v[..., body.slice(i)]
            if link.joint == "ball":
                omega = torch.cat([vi, torch.zeros_like(vi[..., :1])], dim=-1)
                dpos.append(0.5 * roma.quat_product(quats[i], omega))
            else:
                dpos.append(vi)
        out = [*dpos, a]
        if self.track_work:
            out.append((tau * v).sum(-1, keepdim=True))
        return torch.cat(out, dim=-1)


@dataclass
class Trajectory:
    """A simulated path: t (T), q (...×T×nv), v (...×T×nv), work (...×T) or None."""

    t: torch.Tensor
    q: torch.Tensor
    v: torch.Tensor
    work: Optional[torch.Tensor] = None


def zero_program(t, q, v):
    """The torque program τ = 0."""
    return torch.zeros_like(v)


def simulate(body: Body, program: TorqueProgram, q0: torch.Tensor, v0: torch.Tensor,
             t: torch.Tensor, method: str = "dopri5", rtol: float = 1e-7, atol: float = 1e-9,
             options: Optional[dict] = None, adjoint: bool = False,
             track_work: bool = False, max_evals: Optional[int] = None) -> Trajectory:
    """Integrate the body from (q0, v0) at t[0] under ``program(t, ν, v) → τ``.

    Args:
        q0, v0: initial coordinates and velocities (...×nv); any leading batch shape.
        t: increasing sample times (T).
        method, rtol, atol, options: passed to torchdiffeq (``dopri5``, ``dopri8``,
            ``bosh3``, ``rk4``, ...); fixed-step methods need ``options={"step_size": h}``.
        adjoint: backpropagate with the adjoint method (``odeint_adjoint``) instead of
            through the solver's operations.
        track_work: also integrate the work done by the program's torques.
        max_evals: raise :class:`SimulationBudget` past this many right-hand-side
            evaluations (a bound on the whole run; torchdiffeq's ``max_num_steps``
            bounds the steps between two consecutive output times only).
    Returns:
        :class:`Trajectory` with ν and v sampled at t (time on dimension -2).
    """
    if t.ndim != 1 or t.numel() < 2 or not bool((t[1:] > t[:-1]).all()):
        raise ValueError("simulate: t must be a strictly increasing 1-D tensor of >= 2 times")
    global calls
    calls += 1
    func = ArmODE(body, program, track_work, max_evals)
    y0 = pack(body, q0, v0)
    if track_work:
        y0 = torch.cat([y0, torch.zeros_like(y0[..., :1])], dim=-1)
    kwargs = dict(method=method, rtol=rtol, atol=atol, options=options)
    if adjoint:
        params = tuple(p for p in func.parameters() if p.requires_grad)
        ys = odeint_adjoint(func, y0, t, adjoint_params=params, **kwargs)
    else:
        ys = odeint(func, y0, t, **kwargs)
    ys = ys.movedim(0, -2)
    work = None
    if track_work:
        work, ys = ys[..., -1], ys[..., :-1]
    _, coords, _, v = unpack(body, ys)
    return Trajectory(t=t, q=coords, v=v, work=work)
