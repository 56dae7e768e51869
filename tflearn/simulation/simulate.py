"""Simulation of a body under a torque program with torchdiffeq's ``odeint``.

State packing: each ball joint's orientation is a unit quaternion (XYZW, as in roma and
Pinocchio), each hinge an angle, followed by the velocities v (nv). The state is

    y = [quat_1 (4), θ_2 (1), quat_3 (4), ..., v (nv)]       (...×(n_pos + nv))

(a free joint: its quaternion then its translation t, 7 entries) and evolves by
    q̇_ball = ½ q ⊗ (ω, 0)     (ω the child-frame angular velocity),
    θ̇ = v_hinge,
    q̇_free = ½ q ⊗ (ω, 0),  ṫ = R(q) u    (free joint velocity (ω, u), child frame),
    v̇ = M(q)⁻¹ (τ(t, ν, v) − c v − h(q, v))   (the articulated-body algorithm).

Quaternions are normalised wherever they are read, so the rotations used are exactly in
SO(3) whatever the integrator does to their norm; the double cover has no singularity
at zero rotation and none at π. The torque program sees ν, the principal rotation
vectors (|v| ≤ π) and hinge angles — the coordinates of :mod:`tflearn.physics.body`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torchdiffeq import odeint, odeint_adjoint

from ..motions.torso import BaseMotion, Bases
from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import pack, position_rate, unpack
from . import simkernel
from .ode import FAILURE_CODES, odeint_each

TorqueProgram = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]

#: Calls of :func:`simulate` in this process (a batch counts once); the experiments
#: read it to report how many simulations a method needed.
calls = 0


FAILURES = ("budget", "solver", "singular", "nonfinite")


class SimulationFailed(Exception):
    """A simulation that cannot go on. ``reason`` is one of :data:`FAILURES`:
    ``budget`` (more right-hand-side evaluations than ``max_evals``), ``solver`` (the
    integrator gave up, e.g. its step size underflowed), ``singular`` (a joint's
    articulated inertia could not be factorised: the state blew up) or ``nonfinite``
    (NaN or Inf in the state or its derivative). Not a RuntimeError, so that ``except RuntimeError`` never
    hides it and it never hides torch's own errors."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"simulation failed ({reason}): {message}")
        self.reason, self.message = reason, message


@dataclass(frozen=True)
class SimOptions:
    """How to integrate (one object, shared by every command and stage).

    method: a torchdiffeq solver (``dopri5``, ``dopri8``, ``bosh3``, ``rk4`` ...);
    rtol, atol: its tolerances; solver_options: torchdiffeq's own options
    (``{"step_size": h}`` for fixed-step methods, ``{"step_t": t}``); max_evals: fail with
    reason ``budget`` past this many right-hand-side evaluations over the whole run
    (torchdiffeq's ``max_num_steps`` bounds the steps between two output times only);
    adjoint: backpropagate with the adjoint method instead of through the solver;
    batch: how a batch is stepped — ``shared``: torchdiffeq's solver, one step size for
    the whole batch from one error norm over all of it; ``each``: every member its own
    steps and error control (:func:`tflearn.simulation.ode.odeint_each`, Dormand–Prince 5(4) only:
    ``method`` must be ``dopri5``; ``max_evals`` then bounds each member; not with the
    adjoint), the program then called with a time per member (t of the batch's shape)."""

    method: str = "dopri5"
    rtol: float = 1e-7
    atol: float = 1e-9
    max_evals: Optional[int] = 100_000
    adjoint: bool = False
    solver_options: Optional[dict] = None
    batch: str = "shared"

    @property
    def can_step_each(self) -> bool:
        """Whether these options allow batch ``each`` (dopri5, no adjoint, no
        solver_options)."""
        return self.method == "dopri5" and not (self.adjoint or self.solver_options)

    def __post_init__(self):
        if self.batch not in ("shared", "each"):
            raise ValueError(f"SimOptions: batch must be 'shared' or 'each', not {self.batch!r}")
        if self.batch == "each" and not self.can_step_each:
            raise ValueError("SimOptions: batch 'each' steps with its own dopri5: method must be "
                             "'dopri5', without the adjoint or solver_options")


class ArmODE(torch.nn.Module):
    """Right-hand side dy/dt for :func:`simulate` (an nn.Module so the adjoint can see
    the program's parameters). With ``track_work`` the state carries one more entry,
    W with dW/dt = τ_program · v (the work done by the program's torques). Raises
    :class:`SimulationFailed` on evaluation max_evals + 1, and for a non-finite state
    unless ``strict`` is off (the per-member integrator checks each member itself)."""

    def __init__(self, body: Body, program: TorqueProgram, track_work: bool = False,
                 max_evals: Optional[int] = None, base=None, strict: bool = True):
        super().__init__()
        self.body, self.program, self.track_work, self.base = body, program, track_work, base
        self.strict = strict
        self.max_evals, self.evals = max_evals, 0
        if isinstance(program, torch.nn.Module):
            self.program_module = program

    def forward(self, t, y, live=None):
        """dy/dt at t, y (...×D); ``live`` (... bool, from the per-member integrator):
        the members whose derivative is wanted — the program still sees the whole batch
        (its shape is its motion index), the dynamics only these rows, the others get 0."""
        self.evals += 1
        if self.max_evals is not None and self.evals > self.max_evals:
            raise SimulationFailed("budget", f"more than {self.max_evals} right-hand-side evaluations")
        if self.strict and not bool(torch.isfinite(y).all()):
            raise SimulationFailed("nonfinite", f"NaN or Inf in the state at t = {float(t.detach()):.4g} s")
        body = self.body
        if self.track_work:
            y = y[..., :-1]
        rots, coords, quats, v = unpack(body, y)
        tau = self.program(t, coords, v)
        tau = tau.expand(v.shape) if tau.shape != v.shape else tau
        state = (rots, coords, quats, v, tau)
        if live is None:
            return self._rate(t, *state, base=self.base)
        rows = live.reshape(-1).nonzero().squeeze(-1)
        t = t.reshape(-1)[rows] if t.ndim else t
        out = self._rate(t, *_rows(state, v.shape[:-1], rows),
                         base=None if self.base is None else self.base.take(rows))
        return out.new_zeros(live.numel(), out.shape[-1]).index_copy(0, rows, out).reshape(
            live.shape + out.shape[-1:])

    def _rate(self, t, rots, coords, quats, v, tau, base=None):
        body = self.body
        total = tau - body.damping * v if body.damping else tau
        moving = {} if base is None else dict(zip(("gravity", "base"), _moving(body, base, t, v.shape[:-1])))
        try:
            a = dynamics.forward_dynamics_rot(body, rots, coords, v, total, **moving)
        except torch.linalg.LinAlgError:
            raise SimulationFailed("singular", f"an articulated inertia cannot be factorised at "
                                               f"t = {float(t.detach()):.4g} s") from None
        out = [position_rate(body, rots, quats, v), a]
        if self.track_work:
            out.append((tau * v).sum(-1, keepdim=True))
        return torch.cat(out, dim=-1)


def _moving(body: Body, base: Bases, t, batch: torch.Size):
    """(g_b, (ω_b, ω̇_b, a_b)) of the batch's members (batch×3 each) at t (a scalar or
    one time per member)."""
    t = t.reshape(-1) if torch.is_tensor(t) and t.ndim else t
    g, terms = base.terms(body.gravity, t)
    shape = lambda x: x.reshape(batch + (3,))
    return shape(g), tuple(shape(x) for x in terms)


def _rows(state: tuple, batch: torch.Size, rows: torch.Tensor) -> tuple:
    """The rows (R) of the flattened batch of every tensor in ``state`` (lists entry by
    entry, None kept): ...×X → R×X."""
    def take(x):
        if isinstance(x, list):
            return [take(e) for e in x]
        return None if x is None else x.reshape(batch.numel(), *x.shape[len(batch):])[rows]
    return tuple(take(x) for x in state)


@dataclass
class Trajectory:
    """A simulated path: t (T), q (...×T×nv), v (...×T×nv), work (...×T) or None, and
    failure: per member (a list in the batch's row order, flattened) None or why its
    simulation stopped — only with ``throw=False``; that member's path is then NaN."""

    t: torch.Tensor
    q: torch.Tensor
    v: torch.Tensor
    work: Optional[torch.Tensor] = None
    failure: Optional[list] = None


def zero_program(t, q, v):
    """The torque program τ = 0."""
    return torch.zeros_like(v)


def simulate(body: Body, program: TorqueProgram, q0: torch.Tensor, v0: torch.Tensor,
             t: torch.Tensor, options: SimOptions = SimOptions(), *,
             track_work: bool = False, base=None, throw: bool = True,
             groups: Optional[torch.Tensor] = None) -> Trajectory:
    """Integrate the body from (q0, v0) at t[0] under ``program(t, ν, v) → τ``.

    Args:
        q0, v0: initial coordinates and velocities (...×nv); any leading batch shape.
        t: increasing sample times (T).
        options: :class:`SimOptions` (solver, tolerances, budget, adjoint, batch stepping).
        track_work: also integrate the work done by the program's torques.
        base: a moving base, :class:`tflearn.motions.torso.BaseMotion` (the whole batch's)
            or :class:`tflearn.motions.torso.Bases` (one per member of q0's batch, in row
            order); the body's gravity is then a world vector, seen from the base as
            Rᵀ g. None: the base is fixed (inertial).
        throw: raise when the simulation fails. ``False`` (batch ``each`` only): return
            the members that failed in ``Trajectory.failure``, the others' paths intact.
        groups: (batch ``each`` only) an integer per member (q0's batch shape): members
            with the same value share every step, one error norm over all of them
            (copies of a system whose differences must come from one discrete map);
            default: every member alone.
    Returns:
        :class:`Trajectory` with ν and v sampled at t (time on dimension -2).
    Raises:
        SimulationFailed: the integration cannot go on (see its ``reason``); with batch
        ``shared`` a batch fails as a whole (score its members one by one to tell which),
        with ``each`` the first failed member is named.
    """
    if t.ndim != 1 or t.numel() < 2 or not bool((t[1:] > t[:-1]).all()):
        raise ValueError("simulate: t must be a strictly increasing 1-D tensor of >= 2 times")
    each = options.batch == "each"
    if isinstance(base, BaseMotion):
        base = Bases.of([base]).take(torch.zeros(q0.shape[:-1].numel(), dtype=torch.long))
    if base is not None and base.B != q0.shape[:-1].numel():
        raise ValueError(f"simulate: {base.B} moving bases for a batch of {q0.shape[:-1].numel()}")
    if not (throw or each) or (groups is not None and not each):
        raise ValueError("simulate: throw=False and groups need SimOptions(batch='each')")
    global calls
    calls += 1
    y0 = pack(body, q0, v0)
    if track_work:
        y0 = torch.cat([y0, torch.zeros_like(y0[..., :1])], dim=-1)
    failure = None
    if each:
        ys, failure = _integrate_each(body, program, track_work, y0, t, options, throw, groups, base)
    else:
        ys = _integrate_shared(ArmODE(body, program, track_work, options.max_evals, base), y0, t, options)
    ys = ys.movedim(0, -2)
    work = None
    if track_work:
        work, ys = ys[..., -1], ys[..., :-1]
    _, coords, _, v = unpack(body, ys)
    return Trajectory(t=t, q=coords, v=v, work=work, failure=failure)


def _integrate_shared(func: ArmODE, y0, t, options: SimOptions) -> torch.Tensor:
    """torchdiffeq's ``odeint`` (or the adjoint): the states at t (T×...×D)."""
    kwargs = dict(method=options.method, rtol=options.rtol, atol=options.atol,
                  options=options.solver_options)
    try:
        if options.adjoint:
            params = tuple(p for p in func.parameters() if p.requires_grad and p.numel())
            ys = odeint_adjoint(func, y0, t, adjoint_params=params, **kwargs)
        else:
            ys = odeint(func, y0, t, **kwargs)
    except AssertionError as err:            # torchdiffeq's way of giving up
        raise SimulationFailed("solver", str(err) or "the integrator gave up") from None
    if not bool(torch.isfinite(ys).all()):
        raise SimulationFailed("nonfinite", "NaN or Inf in the simulated path")
    return ys


_WHY = {"budget": "more than {} right-hand-side evaluations", "solver": "its step size underflowed",
        "nonfinite": "NaN or Inf in its state"}


def _integrate_each(body: Body, program, track_work: bool, y0, t, options: SimOptions, throw: bool,
                    groups=None, base=None):
    """Every member stepped alone: compiled (:func:`tflearn.simulation.simkernel.integrate`) where it
    applies, else :func:`tflearn.simulation.ode.odeint_each` with :class:`ArmODE`. The states at t
    (T×...×D) and each member's failure (None or a message; members in row order),
    raising the first with ``throw``."""
    tol = dict(rtol=options.rtol, atol=options.atol, max_evals=options.max_evals, groups=groups)
    sol = None
    if simkernel.applies(program, y0):
        sol = simkernel.integrate(body, program, y0, t, track_work=track_work, base=base, **tol)
    if sol is None:
        sol = odeint_each(ArmODE(body, program, track_work, base=base, strict=False), y0, t, **tol)
    errors = [None if not c else SimulationFailed(FAILURE_CODES[c], f"batch member {b}: "
                                                  + _WHY[FAILURE_CODES[c]].format(options.max_evals))
              for b, c in enumerate(sol.failure.reshape(-1).tolist())]
    first = next((e for e in errors if e), None)
    if throw and first:
        raise first
    return sol.ys, [e and str(e) for e in errors]
