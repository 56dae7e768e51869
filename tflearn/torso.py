"""A moving base (the performer's torso) and gravity seen from it.

A body's base frame may move in an inertial world (z up): orientation R(t), origin x(t).
The arm's dynamics in the base frame then see (thesis §4.5.3, non-inertial frames)

    ω_b = vec(Rᵀ Ṙ),  ω̇_b,  a_b = Rᵀ ẍ   (base frame)   and gravity g_b = Rᵀ g,

which :func:`tflearn.dynamics.rnea_rot` and :func:`~tflearn.dynamics.forward_dynamics_rot`
take as ``base=(ω_b, ω̇_b, a_b)`` and ``gravity=g_b`` (g the body's gravity, a world
vector). :class:`BaseMotion` splines sampled poses (quintic, exact derivatives:
quaternions through :func:`tflearn.motion.quat_body_motion`, positions directly) and is
what :func:`tflearn.simulate.simulate` takes as ``base``. The mocap import writes the
clip's base as ``torso/NAME.npz`` (t, R, x) beside the motion (:mod:`tflearn.mocap`).

:func:`gravity_feedforward` is the thesis' gravity-free world made explicit the other
way: with gravity on, the program's torques get the model's own gravity torques g(ν)
added (an internal model, as in Yin et al. 2003), so the fields do the rest.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import roma
import torch
from scipy.interpolate import make_interp_spline

from . import dynamics
from .body import Body
from .configspace import align_quaternions
from .motion import MotionFileError, quat_body_motion
from .simulate import base_terms

DTYPE = torch.float64


class BaseMotion:
    """A base pose path through samples t (T), R (T×3×3), x (T×3, metres).

    Calling it at a time t (a scalar, within [t[0], t[-1]]; clamped) returns
    (R, ω_b, ω̇_b, a_b): the orientation (3×3) and, in the base frame, the angular
    velocity, angular acceleration and the origin's acceleration (3 each), float64.
    """

    def __init__(self, t, R, x):
        t = np.asarray(t, dtype=float)
        quat = align_quaternions(roma.rotmat_to_unitquat(torch.tensor(np.array(R, dtype=float))))
        data = np.concatenate([quat.numpy(), np.asarray(x, dtype=float)], axis=1)
        self.t0, self.t1 = float(t[0]), float(t[-1])
        self.spline = make_interp_spline(t, data, k=5 if len(t) >= 6 else 3, axis=0)
        self.d1, self.d2 = self.spline.derivative(1), self.spline.derivative(2)

    @classmethod
    def load(cls, path) -> BaseMotion:
        """Read a torso file (arrays t, R, x); :class:`MotionFileError` names the file."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                t, R, x = f["t"], f["R"], f["x"]
        except (OSError, KeyError, ValueError) as err:
            raise MotionFileError(str(path), f"not a torso file with arrays t, R, x ({err})") from None
        T = len(t)
        if t.ndim != 1 or R.shape != (T, 3, 3) or x.shape != (T, 3) or T < 4:
            raise MotionFileError(str(path), f"torso arrays have shapes t {t.shape}, R {R.shape}, "
                                             f"x {x.shape}; expected (T,), (T, 3, 3), (T, 3), T ≥ 4")
        return cls(t, R, x)

    def __call__(self, t):
        s = float(np.clip(float(t), self.t0, self.t1))
        p, pd, pdd = (torch.from_numpy(np.ascontiguousarray(f(s))) for f in (self.spline, self.d1, self.d2))
        w, dw = quat_body_motion(p[:4], pd[:4], pdd[:4])
        R = roma.unitquat_to_rotmat(roma.quat_normalize(p[:4]))
        return R, w, dw, R.T @ pdd[4:]


def gravity_feedforward(body: Body, program, base=None):
    """The program with the model's gravity torques added: τ(t, ν, v) + g(ν), with
    g(ν) = RNEA(ν, 0, 0) under the body's gravity (seen from the base at t, if moving)."""
    def fed(t, q, v):
        zero = torch.zeros_like(q)
        if base is None:
            g = dynamics.rnea(body, q, zero, zero)
        else:
            g = dynamics.rnea(body, q, zero, zero, gravity=base_terms(body, base, t, q.dtype)[0])
        return program(t, q, v) + g
    return fed
