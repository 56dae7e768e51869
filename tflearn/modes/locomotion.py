"""Dynamic locomotion of simple creatures driven by their vibration modes (Kry et al.
2007, §4.1, figure 2, table 1).

The creature of a floating-base modal analysis (:mod:`tflearn.modes.analysis`, ``floating``) is
simulated with its root joint made a 6-DOF free joint (:func:`free_body`), gravity on,
on the ground plane of :mod:`tflearn.physics.contact` (contact points: the link ends,
:func:`contact_points`). A PD controller acts on the joints only (the base is unactuated):

    τ_joints = K_t (θ_set(t) ⊖ θ) − c θ̇,      θ_set(t) = θ₀ ⊕ Σᵢ αᵢ ûᵢ sin(2π f̃ᵢ t + γᵢ)

with K_t the analysis stiffness (:func:`tflearn.modes.analysis.tangent_stiffness`, the closing
spring of a loop included) and the set point of :func:`tflearn.modes.motion.set_point`.
A loop closed by a constraint in the analysis is closed in the simulation by a stiff
spring–damper between the two points (force −k_c Δp − c_c Δṗ on the first, the opposite
on the second, through their point Jacobians).

Measured (:class:`Gait`), over [settle, duration] so that the landing is left out: the
centre of mass's horizontal travel d, the speed d/Δt in body lengths per second (body
length: the largest distance between two contact points at the rest pose θ₀), the
direction of travel (a unit vector in the ground plane) and the cost of transport
W⁺/(m g d) with W⁺ = ∫ Σ_j max(0, τ_j θ̇_j) dt the positive mechanical work of the
joint torques (trapezoidal rule over the output samples).

``tflearn locomotion CONFIG`` (:func:`run`) does this for the creature of a modes config
(configs/modes/linear_creature.yaml, loop_creature.yaml) and writes the measures, the
path and a side-view GIF.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from typing import Optional, Sequence

import numpy as np
import torch

from ..io.files import write_text
from ..motions.motion import Motion
from ..motions.motion import save as save_motion
from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import difference
from ..physics.contact import Ground, with_ground
from ..simulation.simulate import SimOptions, SimulationFailed, Trajectory, simulate
from .analysis import ModalError, Modes, link_index, tangent_stiffness
from .command import analyse_config, constraints_of, drives_of
from .config import ModesConfig
from .motion import Limits, ModeDrive, set_point

N_FREE = 6   # the free joint's coordinates, first in ν: rotation vector, translation


@dataclass(frozen=True)
class LocomotionOptions:
    """duration, settle (s): simulated time and the start of the measurement; rate: output
    samples per second (the work integral's grid); damping: c of the PD controller
    (N·m·s/rad); ground: the contact law; closure_stiffness (N/m), closure_damping
    (N·s/m): the loop-closing spring; lift: the start pose's lowest contact point starts
    this high (m); sim: the integrator (fixed-step RK4 by default: the contact is stiff)."""

    duration: float = 3.0
    settle: float = 0.5
    rate: float = 500.0
    damping: float = 0.005
    ground: Ground = Ground()
    closure_stiffness: float = 2000.0
    closure_damping: float = 2.0
    lift: float = 0.0
    sim: SimOptions = field(default_factory=lambda: SimOptions(
        method="rk4", solver_options={"step_size": 2e-4}, max_evals=None))


@dataclass(frozen=True)
class Gait:
    """A locomotion result: the path of the free body, the centre of mass (T×3), and the
    measured travel (see the module); ``evals`` right-hand-side evaluations."""

    body: Body
    trajectory: Trajectory
    com: np.ndarray
    distance: float
    speed: float
    body_length: float
    direction: np.ndarray
    work: float
    cost_of_transport: float
    evals: int


def free_body(body: Body) -> Body:
    """The body with its root (link 0, a fixed joint at the origin) on a free joint. The
    root's zero orientation moves into the free joint's coordinates
    (:func:`free_start`), so that ν's translation is the root's world position."""
    roots = [i for i, link in enumerate(body.links) if link.parent < 0]
    if roots != [0] or body.links[0].joint != "fixed":
        raise ModalError(f"locomotion: body {body.name!r} needs one root, link 0, on a fixed "
                         f"joint (it becomes the free base)")
    root = replace(body.links[0], joint="free", offset=(0.0, 0.0, 0.0))
    return body.with_(links=(root,) + body.links[1:])


def free_start(body: Body, q_joints) -> torch.Tensor:
    """ν (6 + nv) of the free body with the original root offset as its rotation, the
    root at the origin and the joints at q_joints."""
    rot = torch.as_tensor(body.links[0].offset, dtype=torch.float64)
    return torch.cat([rot, torch.zeros(3, dtype=torch.float64),
                      torch.as_tensor(q_joints, dtype=torch.float64)])


def contact_points(body: Body, q) -> tuple:
    """(links, points P×3): every link's joint origin and every cylinder's far end, with
    the points that coincide at pose q (ν of ``body``, within 1e-9 m) kept once."""
    links, points = [], []
    for i, link in enumerate(body.links):
        links.append(i)
        points.append((0.0, 0.0, 0.0))
        if math.isfinite(link.length):
            links.append(i)
            points.append((0.0, 0.0, -link.length))
    pts = torch.tensor(points, dtype=torch.float64)
    q = torch.as_tensor(q, dtype=torch.float64)
    p, _ = dynamics.points_kinematics_rot(body, dynamics.joint_rotations(body, q), q, links, pts)
    keep = [k for k in range(len(links))
            if not any(float((p[k] - p[j]).norm()) < 1e-9 for j in range(k))]
    return [links[k] for k in keep], pts[keep]


def pd_torques(modes: Modes, drives: Sequence[ModeDrive], limits: Optional[Limits],
               damping: float, t: torch.Tensor, q: torch.Tensor, v: torch.Tensor):
    """τ (...×(6 + nv)) of the PD controller on the free body: zero on the base; t (...)."""
    Kt = torch.as_tensor(tangent_stiffness(modes), dtype=torch.float64)
    target = set_point(modes, drives, t.to(torch.float64), limits)
    qj, vj = q[..., N_FREE:], v[..., N_FREE:]
    err = difference(modes.body, qj, target.expand(qj.shape))
    tau = err @ Kt.T - damping * vj
    return torch.cat([torch.zeros_like(v[..., :N_FREE]), tau], dim=-1)


def closure_torques(body: Body, closures, k: float, c: float, q, v):
    """Σ over closures (a, pa, b, pb) of J_aᵀ f − J_bᵀ f, f = −k Δp − c Δṗ, Δp = p_a − p_b."""
    tau = torch.zeros_like(v)
    rots = dynamics.joint_rotations(body, q)
    for a, pa, b, pb in closures:
        pts = torch.tensor([pa, pb], dtype=torch.float64)
        p, J = dynamics.points_kinematics_rot(body, rots, q, [a, b], pts)
        J = J[..., :3, :]
        pd = (J @ v[..., None, :, None])[..., 0]
        f = -k * (p[..., 0, :] - p[..., 1, :]) - c * (pd[..., 0, :] - pd[..., 1, :])
        tau = tau + ((J[..., 0, :, :] - J[..., 1, :, :]).transpose(-1, -2) @ f[..., None])[..., 0]
    return tau


def closures_of(body: Body, constraints) -> list:
    """(a, point_a, b, point_b) of each loop-closing constraint (:class:`tflearn.modes.analysis.Constraint`
    with a ``other`` link, no weld)."""
    out = []
    for k, con in enumerate(constraints):
        if con.other is None or con.weld:
            raise ModalError(f"constraints[{k}]: locomotion simulates loop closures (two "
                             f"points held together, no weld) only")
        out.append((link_index(body, con.link, f"constraints[{k}].link"), tuple(con.point),
                    link_index(body, con.other, f"constraints[{k}].to"), tuple(con.other_point)))
    return out


def centre_of_mass(body: Body, q: torch.Tensor) -> torch.Tensor:
    """World centre of mass (...×3)."""
    Rw, x = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q), q)
    total, mass = 0.0, 0.0
    for i, link in enumerate(body.links):
        c = torch.as_tensor(link.com, dtype=q.dtype)
        total = total + link.mass * (x[..., i, :] + (Rw[i] @ c))
        mass += link.mass
    return total / mass


def locomote(modes: Modes, drives: Sequence[ModeDrive], constraints=(),
             limits: Optional[Limits] = None,
             options: LocomotionOptions = LocomotionOptions()) -> Gait:
    """Simulate the mode-driven creature on the ground and measure its gait (module)."""
    if not modes.options.floating:
        raise ModalError("locomotion: needs the floating-base analysis (floating: true)")
    body = free_body(modes.body).with_(gravity=(0.0, 0.0, -9.81))
    o = options
    q0 = free_start(modes.body, set_point(modes, drives, torch.zeros(()), limits))
    links, points = contact_points(body, q0)
    p0, _ = dynamics.points_kinematics_rot(body, dynamics.joint_rotations(body, q0), q0,
                                           links, points)
    q0[5] += o.ground.height + o.lift - float(p0[:, 2].min())
    closures = closures_of(body, constraints)
    evals = [0]

    def actuated(t, q, v):
        evals[0] += 1
        tau = pd_torques(modes, drives, limits, o.damping, t.reshape(()), q, v)
        if closures:
            tau = tau + closure_torques(body, closures, o.closure_stiffness, o.closure_damping, q, v)
        return tau

    t = torch.linspace(0.0, o.duration, int(round(o.duration * o.rate)) + 1, dtype=torch.float64)
    traj = simulate(body, with_ground(body, actuated, o.ground, links, points), q0,
                    torch.zeros(body.nv, dtype=torch.float64), t, o.sim)
    with torch.no_grad():
        com = centre_of_mass(body, traj.q).numpy()
        tau = pd_torques(modes, drives, limits, o.damping, t, traj.q, traj.v)
        power = torch.clamp(tau * traj.v, min=0.0).sum(-1).numpy()
    keep = t.numpy() >= o.settle
    tk = t.numpy()[keep]
    step = com[keep][-1, :2] - com[keep][0, :2]
    distance = float(np.linalg.norm(step))
    rest = free_start(modes.body, modes.q0)
    pr, _ = dynamics.points_kinematics_rot(body, dynamics.joint_rotations(body, rest), rest,
                                           links, points)
    length = float(torch.cdist(pr, pr).max())
    mass = sum(link.mass for link in body.links)
    work = float(np.trapezoid(power[keep], tk))
    return Gait(body=body, trajectory=traj, com=com, distance=distance,
                speed=distance / (tk[-1] - tk[0]) / length, body_length=length,
                direction=step / distance if distance > 0 else np.zeros(2), work=work,
                cost_of_transport=work / (mass * 9.81 * distance) if distance > 0 else math.inf,
                evals=evals[0])


def run(cfg: ModesConfig, out=None, duration: float = 3.0, settle: float = 0.5, step: float = 5e-4,
        amplitude: Optional[float] = None) -> dict:
    """``tflearn locomotion CONFIG``: the creature of a floating-base modes config — its
    body, stiffness, loop-closing constraints, ``motion.drives`` (every drive's α replaced
    by ``amplitude`` when given) and ``motion.limits`` — on the ground for ``duration`` s,
    fixed-step RK4 with step ``step`` s, measured from ``settle`` s (:func:`locomote`, the
    rest as :class:`LocomotionOptions`). Writes into ``out`` (default the config's):
    ``locomotion.json`` (the measures of :class:`Gait` and the options), ``locomotion.npz``
    (the free body's path in the Motion format, ν = the free joint's 6 coordinates then
    the joints', at the output rate) and ``locomotion.gif`` (a side view,
    :func:`tflearn.plots.bodies.side_view_gif`). Returns {"locomotion": the JSON document,
    "out": Path, "written": [paths]}."""
    from pathlib import Path

    from ..plots.bodies import side_view_gif
    if not 0 <= settle < duration:
        raise ModalError(f"locomotion: the measurement must start within the run "
                         f"(0 ≤ settle < duration), got settle {settle} s, duration {duration} s")
    if not step > 0:
        raise ModalError(f"locomotion: the RK4 step must be positive, got {step}")
    out = Path(out if out is not None else cfg.out)
    modes = analyse_config(cfg)
    drives = drives_of(cfg)
    if amplitude is not None:
        drives = [replace(d, amplitude=amplitude) for d in drives]
    limits = Limits.from_config(modes.body, cfg.motion.limits, cfg.motion.soft) if cfg.motion.limits else None
    base = LocomotionOptions()
    opts = replace(base, duration=duration, settle=settle,
                   sim=replace(base.sim, solver_options={"step_size": step}))
    try:
        gait = locomote(modes, drives, constraints_of(cfg), limits, opts)
    except SimulationFailed as err:
        raise ModalError(f"locomotion: {err} (a smaller RK4 step may help: {step} s now)") from None
    traj = gait.trajectory
    doc = {"creature": modes.body.name, "drives": [asdict(d) for d in drives],
           "speed_body_lengths_per_s": gait.speed, "distance_m": gait.distance,
           "body_length_m": gait.body_length, "direction_xy": gait.direction.tolist(),
           "positive_joint_work_J": gait.work,
           "cost_of_transport": gait.cost_of_transport if math.isfinite(gait.cost_of_transport) else None,
           "evals": gait.evals,
           "com_height_m": [float(gait.com[:, 2].min()), float(gait.com[:, 2].max())],
           "com_lateral_max_m": float(abs(gait.com[:, 1] - gait.com[0, 1]).max()),
           "options": {"duration": duration, "settle": settle, "step": step, "rate": opts.rate,
                       "damping": opts.damping, "ground": asdict(opts.ground),
                       "closure_stiffness": opts.closure_stiffness,
                       "closure_damping": opts.closure_damping}}
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "locomotion.json", out / "locomotion.npz", out / "locomotion.gif"]
    write_text(written[0], json.dumps(doc, indent=1))
    save_motion(Motion("locomotion", traj.t, traj.q, traj.v, gait.body), written[1])
    side_view_gif(gait.body, traj.t.numpy(), traj.q, written[2], fps=25, title=modes.body.name, com=gait.com)
    return {"locomotion": doc, "out": out, "written": written}
