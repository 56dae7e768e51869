"""Perturbations of a controlled limb and how it responds (Yin, Cline & Pai 2003).

A :class:`Push` is an external force f(t) = F φ((t − t₀)/D) on a named point of the body,
in the body's base frame (the world's on a fixed base; on a moving torso the chest's: the
push moves with the performer), with φ the C¹ cosine pulse of :func:`tflearn.model.weights.pulse_profile`
(φ(u) = ½(1 − cos 2πu) on [0, 1], zero elsewhere), so its impulse is ∫f dt = F D/2
(:meth:`Push.from_impulse` for a given impulse). It acts on the joints as τ = J_pᵀ f
(:func:`tflearn.physics.dynamics.point_jacobian`, linear rows), added to the controller's torque.
F may carry leading batch dimensions (B×3) to push a batch of simulations differently.
Points: ``hand`` (the body's tip), a link name (that link's joint origin) or a joint name
of :data:`tflearn.physics.body.JOINT_NAMES` (``elbow`` is the forearm's origin).

A carried object is a point mass at a named point (:func:`carry`): a new Body whose
link mass, centre of mass and inertia include it, driven by controllers built for the
nominal body.

:func:`respond` simulates a controller under a :class:`Perturbation`; :func:`measure`
compares a perturbed response with the unperturbed one and the target:

* ``max_joint_dev`` (rad): max over t of ‖ν_p(t) ⊖ ν₀(t)‖;
* ``max_hand_dev`` (m): max over t of ‖x_p(t) − x₀(t)‖ (hand tip);
* ``recovery_s``: time from the push's end until the hand is back within ``tol``
  (1 cm) of its unperturbed path and stays there to the end (0 if it never left;
  None if it is still off at the end);
* ``final_joint_error`` (rad), ``final_hand_error`` (m): ‖ν_p(T) ⊖ ν_d(T)‖ and the hand's
  distance from the target's hand at the last sample;
* ``peak_torque`` (N·m): the largest |τ_k| of the controller (not the push) over the
  samples; ``push_work`` (J): ∫ f·ẋ_p dt by the trapezoidal rule.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..model.weights import pulse_profile
from ..physics import dynamics
from ..physics.body import JOINT_NAMES, Body
from ..physics.configspace import difference
from ..simulation.simulate import SimOptions, Trajectory, simulate


class PerturbationError(InputError):
    """A perturbation that cannot be applied (unknown point, bad window or mass)."""


def point_on(body: Body, name: str) -> tuple:
    """(link index, point in the link frame (3,)) of a named point: ``hand`` is the tip,
    a link or joint name (:data:`~tflearn.physics.body.JOINT_NAMES`) that link's joint origin."""
    if name == "hand":
        return body.tip_link % len(body.links), tuple(body.tip_point)
    links = {link.name: i for i, link in enumerate(body.links)}
    links.update({JOINT_NAMES[n]: i for n, i in list(links.items()) if n in JOINT_NAMES})
    if name not in links:
        raise PerturbationError(f"no point {name!r} on the {body.name} body "
                                f"(expected hand or one of {', '.join(links)})")
    return links[name], (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Push:
    """Force F (N, base frame, 3 or B×3) at ``point`` with profile φ((t − onset)/duration)."""

    force: tuple
    onset: float
    duration: float
    point: str = "hand"

    def __post_init__(self):
        if not self.duration > 0 or not self.onset >= 0:
            raise PerturbationError(f"a push needs onset >= 0 and duration > 0, got "
                                    f"onset {self.onset}, duration {self.duration}")

    @classmethod
    def from_impulse(cls, impulse, onset: float, duration: float, point: str = "hand") -> Push:
        """The push of this impulse (N·s, 3 or B×3) over the window: F = 2 impulse / D."""
        return cls(tuple(np.asarray(impulse, dtype=float) * 2.0 / duration), onset, duration, point)

    @property
    def end(self) -> float:
        return self.onset + self.duration

    def impulse(self) -> torch.Tensor:
        """∫ f dt = F D / 2 (N·s)."""
        return torch.as_tensor(self.force, dtype=torch.float64) * self.duration / 2

    def force_at(self, t) -> torch.Tensor:
        """f(t) (3 or B×3)."""
        t = torch.as_tensor(t, dtype=torch.float64)
        F = torch.as_tensor(np.asarray(self.force, dtype=float))
        return F * pulse_profile((t - self.onset) / self.duration)

    def torque(self, body: Body, t, q: torch.Tensor) -> torch.Tensor:
        """τ = J_pᵀ f(t) (...×nv) at coordinates q (...×nv)."""
        link, point = point_on(body, self.point)
        J = dynamics.point_jacobian(body, q, link, point)[..., :3, :]
        return torch.einsum("...in,...i->...n", J, self.force_at(t).to(q))


def carry(body: Body, mass: float, point: str = "hand") -> Body:
    """The body holding a point mass ``mass`` (kg) at ``point``: that link's mass
    m' = m + m_p, centre c' = (m c + m_p p)/m' and inertia about c' by the parallel-axis
    theorem, I' = I + m (|d|² 1 − d dᵀ) + m_p (|e|² 1 − e eᵀ), d = c − c', e = p − c'."""
    if not mass > 0:
        raise PerturbationError(f"a carried mass must be positive, got {mass}")
    i, p = point_on(body, point)
    link = body.links[i]
    m, c, p = link.mass, np.asarray(link.com, dtype=float), np.asarray(p, dtype=float)
    m2 = m + mass
    c2 = (m * c + mass * p) / m2

    def shift(w, r):
        return w * ((r @ r) * np.eye(3) - np.outer(r, r))
    inertia = np.asarray(link.inertia, dtype=float) + shift(m, c - c2) + shift(mass, p - c2)
    new = replace(link, mass=m2, com=tuple(c2), inertia=tuple(map(tuple, inertia)))
    return body.with_(links=body.links[:i] + (new,) + body.links[i + 1:])


@dataclass(frozen=True)
class Perturbation:
    """Pushes applied together, and a carried mass (kg) at ``carry_point`` (0: none)."""

    pushes: tuple = ()
    carry: float = 0.0
    carry_point: str = "hand"

    def body(self, body: Body) -> Body:
        """The body the controller actually drives."""
        return carry(body, self.carry, self.carry_point) if self.carry else body

    def window(self) -> Optional[tuple]:
        """(first onset, last end) of the pushes, None without pushes."""
        if not self.pushes:
            return None
        return min(p.onset for p in self.pushes), max(p.end for p in self.pushes)


class Pushed(torch.nn.Module):
    """The program τ = controller(t, ν, v) + Σ_pushes J_pᵀ f(t)."""

    def __init__(self, body: Body, controller, pushes: tuple):
        super().__init__()
        self.body, self.controller, self.pushes = body, controller, pushes

    def forward(self, t, q, v):
        tau = self.controller(t, q, v)
        for push in self.pushes:
            tau = tau + push.torque(self.body, t, q)
        return tau


@dataclass
class Response:
    """A simulated response: t (T); q, v and the controller's torque tau (...×T×nv); the
    hand tip (...×T×3); push_work (...): ∫ Σ f·ẋ_p dt over the samples (trapezoidal); work
    (...×T): the simulator's integral of (controller + push torque)·v."""

    t: torch.Tensor
    q: torch.Tensor
    v: torch.Tensor
    tau: torch.Tensor
    hand: torch.Tensor
    push_work: torch.Tensor
    work: torch.Tensor


def _options(options: SimOptions, perturbation: Perturbation) -> SimOptions:
    """``options`` with every push's onset and end as forced step times (so that an
    adaptive step cannot jump over a short push)."""
    if not perturbation.pushes:
        return options
    times = sorted({x for p in perturbation.pushes for x in (p.onset, p.end)})
    so = dict(options.solver_options or {})
    so["step_t"] = torch.tensor(times, dtype=torch.float64)
    return replace(options, solver_options=so)


def respond(body: Body, controller, perturbation: Perturbation, q0: torch.Tensor,
            v0: torch.Tensor, t: torch.Tensor, options: SimOptions = SimOptions(),
            base=None) -> Response:
    """Simulate ``controller`` on the perturbed body from (q0, v0) (B×nv) over t (T), on
    a moving ``base`` (a one-member :class:`tflearn.motions.torso.Bases`, every member of
    the batch on it; the pushes' forces and the hand then in its frame) or a fixed one.

    Raises :class:`tflearn.simulation.simulate.SimulationFailed` as :func:`simulate` does."""
    plant = perturbation.body(body)
    program = Pushed(plant, controller, perturbation.pushes)
    if base is not None:
        base = base.take(torch.zeros(q0.shape[:-1].numel(), dtype=torch.long))
    with torch.no_grad():
        tr: Trajectory = simulate(plant, program, q0, v0, t, _options(options, perturbation),
                                  track_work=True, base=base)
        tau = torch.stack([controller(t[k], tr.q[..., k, :], tr.v[..., k, :])
                           for k in range(len(t))], dim=-2)
        hand = dynamics.tip_position(plant, tr.q)
        power = torch.zeros(tr.q.shape[:-1], dtype=torch.float64)
        for push in perturbation.pushes:
            link, point = point_on(plant, push.point)
            J = dynamics.point_jacobian(plant, tr.q, link, point)[..., :3, :]
            xdot = torch.einsum("...in,...n->...i", J, tr.v)
            f = torch.stack([push.force_at(tk) for tk in t], dim=-2)
            power = power + (f * xdot).sum(-1)
        push_work = torch.trapezoid(power, t, dim=-1)
    return Response(t, tr.q, tr.v, tau, hand, push_work, tr.work)


def measure(body: Body, base: Response, pushed: Response, target_q: torch.Tensor,
            window: Optional[tuple], tol: float = 0.01) -> dict:
    """The figures of the module docstring for one perturbed response (no batch) against
    the unperturbed ``base`` of the same controller and the target ν_d (T×nv) at the same
    samples; ``window`` the push's (onset, end)."""
    t = pushed.t.numpy()
    jdev = difference(body, base.q, pushed.q).norm(dim=-1)
    hdev = (pushed.hand - base.hand).norm(dim=-1).numpy()
    end = window[1] if window else float(t[0])
    off = np.nonzero(hdev >= tol)[0]
    if not len(off):
        recovery = 0.0
    elif off[-1] == len(t) - 1:
        recovery = None
    else:
        recovery = max(0.0, float(t[off[-1] + 1]) - end)
    target_hand = dynamics.tip_position(body, target_q[-1])
    return {"max_joint_dev": float(jdev.max()), "max_hand_dev": float(hdev.max()),
            "recovery_s": recovery,
            "final_joint_error": float(difference(body, target_q[-1], pushed.q[-1]).norm()),
            "final_hand_error": float((pushed.hand[-1] - target_hand).norm()),
            "peak_torque": float(pushed.tau.abs().max()),
            "push_work": float(pushed.push_work)}


def tracking_rmse(body: Body, response: Response, target_q: torch.Tensor) -> float:
    """Joint RMSE (rad) of a response against the target ν_d (T×nv): √(mean_t ‖ν ⊖ ν_d‖²/nv)."""
    d = difference(body, target_q, response.q)
    return float(d.pow(2).mean().sqrt())
