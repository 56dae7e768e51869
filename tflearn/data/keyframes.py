"""Motions not made by torque fields (thesis §4.3, §4.5.4): eased keyframe splines and
straight-line hand reaches.

* :func:`keyframe_motion` — keyframe postures ν_k at times t_k joined by a quintic
  spline with zero velocity and acceleration at the first and last key (eased in and
  out, as a motion from and to rest starts and stops; C⁴ between). Ball joints are
  splined on their sign-aligned unit quaternions, renormalised, hinges on their angles;
  the result is a :class:`~tflearn.motions.motion.Motion` sampled at ``rate``.
* :func:`random_keyframes` — such animations through random postures (seeded), the
  test data of motion no field made.
* :func:`straight_reach` — the hand tip moves along the straight segment p₀ → p₁ with the
  minimum-jerk timing s(u) = 10u³ − 15u⁴ + 6u⁵; the coordinates come from damped
  least-squares inverse kinematics, each sample started from the previous one:
      ν ← ν + Jᵀ(J Jᵀ + μ² I)⁻¹ (p(t) − tip(ν)),   J = ∂tip/∂ν (3×nv),
  the minimum-norm step over the moving coordinates, so the arm makes no motion the
  path does not ask for.
"""
from __future__ import annotations

import numpy as np
import roma
import torch
from scipy.interpolate import make_interp_spline

from ..motions.motion import Motion
from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import align_quaternions

F64 = torch.float64


def _eased_spline(times: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Quintic spline through (times, values K×d) with zero velocity and acceleration at
    both ends, at t; two keys give the minimum-jerk ease between them."""
    if len(times) == 2:
        s = minimum_jerk(torch.from_numpy((t - times[0]) / (times[-1] - times[0]))).numpy()
        return values[0] + s[:, None] * (values[-1] - values[0])
    zero = np.zeros(values.shape[1])
    bc = ([(1, zero), (2, zero)], [(1, zero), (2, zero)])
    return make_interp_spline(times, values, k=5, bc_type=bc)(t)


def keyframe_motion(name: str, body: Body, keys, times, rate: float = 100.0) -> Motion:
    """An eased spline animation through keyframe postures.

    Args:
        keys: K×nv keyframe coordinates ν (K ≥ 2).
        times: K increasing key times (s); the motion runs from times[0] to times[-1].
    """
    keys = torch.as_tensor(keys, dtype=F64)
    times = np.asarray(times, dtype=float)
    if keys.ndim != 2 or keys.shape[0] != len(times) or len(times) < 2:
        raise ValueError(f"keyframe_motion {name!r}: need K ≥ 2 keys (K×{body.nv}) and K times")
    steps = int(round((times[-1] - times[0]) * rate))
    t = times[0] + np.arange(steps + 1) / rate
    parts = []
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint == "ball":
            quat = align_quaternions(roma.rotvec_to_unitquat(keys[:, s]))
            p = torch.from_numpy(_eased_spline(times, quat.numpy(), t))
            parts.append(roma.unitquat_to_rotvec(p / p.norm(dim=-1, keepdim=True)))
        elif link.dof:
            parts.append(torch.from_numpy(_eased_spline(times, keys[:, s].numpy(), t)))
    return Motion(name, torch.from_numpy(t - t[0]), torch.cat(parts, dim=-1), body=body)


def random_keyframes(body: Body, n: int, seed: int, keys: int = 3, spread: float = 0.8,
                     durations: tuple = (0.6, 1.2), rate: float = 100.0) -> list:
    """``n`` eased keyframe animations (:func:`keyframe_motion`) named ``keys{seed}_{i}``,
    each through ``keys`` random postures: every coordinate uniform in ±``spread`` rad
    about rest, hinges flexed (uniform in [−2 spread − 0.2, −0.2]: the preset arm's elbow
    bends that way), each segment's duration uniform in ``durations`` (s)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        q = (2 * torch.rand(keys, body.nv, generator=g, dtype=F64) - 1) * spread
        for k, link in enumerate(body.links):
            if link.joint == "hinge":
                q[:, body.slice(k)] = -0.2 - 2 * spread * torch.rand(keys, 1, generator=g, dtype=F64)
        lo, hi = durations
        steps = lo + (hi - lo) * torch.rand(keys - 1, generator=g, dtype=F64)
        times = np.concatenate([[0.0], np.cumsum(steps.numpy())])
        out.append(keyframe_motion(f"keys{seed}_{i}", body, q, times, rate))
    return out


def minimum_jerk(u: torch.Tensor) -> torch.Tensor:
    """s(u) = 10u³ − 15u⁴ + 6u⁵ on [0, 1] (zero velocity and acceleration at both ends)."""
    u = u.clamp(0, 1)
    return u ** 3 * (10 - 15 * u + 6 * u ** 2)


def straight_reach(name: str, body: Body, q_start, p_end, duration: float, rate: float = 100.0,
                   damping: float = 1e-3, iterations: int = 20, tol: float = 1e-10,
                   moving=None) -> Motion:
    """The hand tip along the straight line from tip(q_start) to ``p_end`` (3), by damped
    least-squares IK from sample to sample over the coordinates ``moving`` (nv bools;
    default: every joint but the last, so the arm reaches with shoulder and elbow and the
    hand keeps its start rotation). Raises ValueError if the line leaves the arm's reach
    (a sample misses its point by more than 1 mm)."""
    if moving is None:
        moving = torch.ones(body.nv, dtype=torch.bool)
        moving[body.slice(len(body.links) - 1)] = False
    moving = torch.as_tensor(moving, dtype=F64)
    q = torch.as_tensor(q_start, dtype=F64).clone()
    p_end = torch.as_tensor(p_end, dtype=F64)
    p0 = dynamics.tip_position(body, q)
    t = torch.arange(int(round(duration * rate)) + 1, dtype=F64) / rate
    path = p0 + minimum_jerk(t / duration)[:, None] * (p_end - p0)
    out = []
    for target in path:
        for _ in range(iterations):
            err = target - dynamics.tip_position(body, q)
            if float(err.norm()) < tol:
                break
            J = torch.autograd.functional.jacobian(lambda x: dynamics.tip_position(body, x), q) * moving
            A = J @ J.T + damping ** 2 * torch.eye(3, dtype=F64)
            q = q + J.T @ torch.linalg.solve(A, err)
        miss = float((target - dynamics.tip_position(body, q)).norm())
        if miss > 1e-3:
            raise ValueError(f"straight_reach {name!r}: the line leaves the arm's reach "
                             f"(misses a point by {100 * miss:.1f} cm)")
        out.append(q.clone())
    return Motion(name, t, torch.stack(out), body=body)
