"""A moving base (the performer's torso) and gravity seen from it.

A body's base frame may move in an inertial world (z up): orientation R(t), origin x(t).
The arm's dynamics in the base frame then see (thesis §4.5.3, non-inertial frames)

    ω_b = vec(Rᵀ Ṙ),  ω̇_b,  a_b = Rᵀ ẍ   (base frame)   and gravity g_b = Rᵀ g,

which :func:`tflearn.physics.dynamics.rnea_rot` and :func:`~tflearn.physics.dynamics.forward_dynamics_rot`
take as ``base=(ω_b, ω̇_b, a_b)`` and ``gravity=g_b`` (g the body's gravity, a world
vector). :class:`BaseMotion` splines sampled poses (quintic, exact derivatives:
quaternions through :func:`tflearn.motions.spline.quat_body_motion`, positions directly);
:class:`Bases` holds the splines of a batch's members, one per member, as piecewise
polynomials that torch (:meth:`Bases.terms`) and the compiled simulator
(:mod:`tflearn.simulation.simkernel`) evaluate alike; :func:`tflearn.simulation.simulate.simulate`
takes either as ``base``. The mocap import writes the clip's base as ``torso/NAME.npz`` (t, R, x)
beside the motion (:mod:`tflearn.mocap.clips`); :func:`tflearn.data.loading.torsos` reads those of a
set of motions for training (``torso: moving``).

:func:`gravity_feedforward` is the thesis' gravity-free world made explicit the other
way: with gravity on, the program's torques get the model's own gravity torques g(ν)
added (an internal model, as in Yin et al. 2003), so the fields do the rest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch
from scipy.interpolate import make_interp_spline

from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import align_quaternions
from .motion import MotionFileError
from .spline import quat_body_motion

DTYPE = torch.float64
DEGREE = 5


class BaseMotion:
    """A base pose path through samples t (T), R (T×3×3), x (T×3, metres): a quintic
    interpolating spline (cubic below 6 samples) of the sign-aligned unit quaternions
    and the origin, which :class:`Bases` evaluates (with its derivatives, clamped to
    ``span`` = (t[0], t[-1]))."""

    def __init__(self, t, R, x):
        t = np.asarray(t, dtype=float)
        quat = align_quaternions(roma.rotmat_to_unitquat(torch.tensor(np.array(R, dtype=float))))
        data = np.concatenate([quat.numpy(), np.asarray(x, dtype=float)], axis=1)
        self.spline = make_interp_spline(t, data, k=5 if len(t) >= 6 else 3, axis=0)
        self.span = (float(t[0]), float(t[-1]))

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

    def pieces(self):
        """The spline as polynomials: breaks x (P + 1) and coefficients c (P×6×7), the
        pose (quaternion XYZW, origin) on [x_i, x_{i+1}] being Σ_j c_ij (s − x_i)^(5−j);
        a spline of degree k < 5 (few samples) has its leading coefficients zero."""
        x = np.unique(self.spline.t)
        k = self.spline.k
        c = np.zeros((len(x) - 1, DEGREE + 1, 7))
        for j in range(k + 1):
            c[:, DEGREE - k + j] = self.spline.derivative(k - j)(x[:-1]) / math.factorial(k - j)
        return x, c


@dataclass(frozen=True)
class Bases:
    """The moving bases of a batch's members (B, flattened row order), each a pose path
    of :class:`BaseMotion` as polynomials (:meth:`BaseMotion.pieces`): breaks (B×(P+1)),
    coef (B×P×6×7), pieces (B, member b's own P_b ≤ P; padding repeats its last break
    and holds zeros), start (B): member b at its time t is its base at s = start_b + t,
    clamped to [breaks_b0, breaks_bP_b] (:class:`BaseMotion`'s clamp)."""

    breaks: torch.Tensor
    coef: torch.Tensor
    pieces: torch.Tensor
    start: torch.Tensor

    @classmethod
    def of(cls, motions: list, start=None) -> Bases:
        """One member per :class:`BaseMotion`; ``start`` (B) default zero."""
        parts = [m.pieces() for m in motions]
        P = max(len(x) - 1 for x, _ in parts)
        breaks = np.stack([np.pad(x, (0, P + 1 - len(x)), mode="edge") for x, _ in parts])
        coef = np.stack([np.pad(c, ((0, P - len(c)), (0, 0), (0, 0))) for _, c in parts])
        start = torch.zeros(len(parts), dtype=DTYPE) if start is None else torch.as_tensor(start, dtype=DTYPE)
        return cls(torch.from_numpy(breaks), torch.from_numpy(coef),
                   torch.tensor([len(x) - 1 for x, _ in parts]), start.reshape(len(parts)).clone())

    @property
    def B(self) -> int:
        return len(self.pieces)

    def take(self, idx, shift=None) -> Bases:
        """Members ``idx`` (integer tensor, any shape, flattened), their times shifted
        by ``shift`` (idx's shape, s): member i's base at t is member idx_i's at
        shift_i + t."""
        idx = torch.as_tensor(idx, dtype=torch.long).reshape(-1)
        start = self.start[idx] + (0 if shift is None else torch.as_tensor(shift, dtype=DTYPE).reshape(-1))
        return Bases(self.breaks[idx], self.coef[idx], self.pieces[idx], start)

    def at(self, idx, t) -> Bases:
        """Members ``idx`` (integer tensor, any shape, flattened) as :meth:`take` gives
        them, each cut to the one polynomial piece it is on at its time t (idx's shape):
        the same poses at t, without copying every member's whole path (a batch of many
        members at fixed times, as error-growth Jacobians are, of long clips)."""
        idx = torch.as_tensor(idx, dtype=torch.long).reshape(-1)
        t = torch.as_tensor(t, dtype=DTYPE).reshape(-1)
        i, _ = self._piece(self.breaks[idx], self.pieces[idx], self.start[idx] + t)
        breaks = torch.stack([self.breaks[idx, i], self.breaks[idx, i + 1]], dim=-1)
        return Bases(breaks, self.coef[idx, i].unsqueeze(1), torch.ones_like(i), self.start[idx].clone())

    @staticmethod
    def _piece(breaks, pieces, s):
        """(the piece each member is on at its s, that s clamped to the member's path)."""
        rows = torch.arange(len(pieces))
        s = torch.minimum(torch.maximum(s, breaks[:, 0]), breaks[rows, pieces])
        i = (torch.searchsorted(breaks, s[:, None], right=True)[:, 0] - 1).clamp(
            torch.zeros_like(pieces), pieces - 1)
        return i, s

    def poses(self, t):
        """(p, ṗ, p̈) (B×7 each: the spline's quaternion XYZW and origin) at each
        member's time t (a scalar or B)."""
        t = torch.as_tensor(t, dtype=DTYPE).detach().expand(self.B)
        rows = torch.arange(self.B)
        i, s = self._piece(self.breaks, self.pieces, self.start + t)
        u, c = (s - self.breaks[rows, i])[:, None], self.coef[rows, i]           # B×1, B×6×7
        p = pd = pdd = torch.zeros_like(c[:, 0])
        for j in range(DEGREE + 1):                                              # Horner
            p = p * u + c[:, j]
            if j < DEGREE:
                pd = pd * u + (DEGREE - j) * c[:, j]
            if j < DEGREE - 1:
                pdd = pdd * u + (DEGREE - j) * (DEGREE - j - 1) * c[:, j]
        return p, pd, pdd

    def terms(self, gravity, t):
        """(g_b, (ω_b, ω̇_b, a_b)), B×3 each, at each member's time t (a scalar or B):
        what :func:`tflearn.physics.dynamics.forward_dynamics_rot` takes as ``gravity`` and
        ``base``; ``gravity`` the world's g (3)."""
        p, pd, pdd = self.poses(t)
        w, dw = quat_body_motion(p[:, :4], pd[:, :4], pdd[:, :4])
        R = roma.unitquat_to_rotmat(roma.quat_normalize(p[:, :4]))
        Rt = R.transpose(-1, -2)
        g = torch.as_tensor(gravity, dtype=DTYPE)
        return Rt @ g, (w, dw, (Rt @ pdd[:, 4:, None])[..., 0])


def gravity_feedforward(body: Body, program, base: Bases | None = None):
    """The program with the model's gravity torques added: τ(t, ν, v) + g(ν), with
    g(ν) = RNEA(ν, 0, 0) under the body's gravity (seen from each member's base at t,
    :class:`Bases` of the batch's members, if moving)."""
    def fed(t, q, v):
        zero = torch.zeros_like(q)
        gravity = True if base is None else base.terms(body.gravity, t)[0].reshape(q.shape[:-1] + (3,))
        return program(t, q, v) + dynamics.rnea(body, q, zero, zero, gravity=gravity)
    return fed
