"""The compiled simulator (numba): a field program, the body's dynamics and Dormand–Prince
5(4) with a step size of its own for every member, in one loop per member.

:func:`tflearn.simulation.simulate.simulate` hands a batch to :func:`integrate` when its members are
stepped each alone (``SimOptions(batch="each")``), the program can be
unrolled per member (:meth:`tflearn.model.program.FieldProgram.rows`: field programs, stacks of
them, the gesture library's own-field programs), the tensors are float64 on the CPU and
no gradient is to be carried. Otherwise the torch path runs (:func:`tflearn.simulation.ode.odeint_each`
with :class:`tflearn.simulation.simulate.ArmODE`) — the same maths, the two agree to rounding
(tests/test_simkernel.py):

- the right-hand side of :class:`~tflearn.simulation.simulate.ArmODE`: the state read by
  :func:`tflearn.physics.kernels_state.read_state`, the program's torque

      τ_b(t, ν, v) = Σ_i w_bi(s_b + t) · (−K_gi (d + ζ_g v) exp(−½ dᵀ K_gi d)),  d = ν − η_gi

  (:class:`tflearn.model.program.ProgramRows`; a field whose activation is 0 is skipped),
  the body's joint damping −c v, the articulated-body algorithm
  (:func:`tflearn.physics.kernels.aba`) from a fixed base under the body's gravity or from each
  member's moving base (:class:`tflearn.motions.torso.Bases`, :func:`_base_root`), and the
  position rates (:func:`tflearn.physics.kernels_state.position_rate`); with ``track_work`` one more
  entry, dW/dt = τ · v;
- the solver of :func:`tflearn.simulation.ode.odeint_each`: its tableau, initial step, error norm,
  step-size control, dense output at the sample times, evaluation count and failure codes
  (1 budget, 2 step underflow, 3 non-finite), a failed member's samples NaN from its
  failure on.

Every member (or group of members that share their steps) is integrated from start to
end before the next, so a call costs the sum of its members' own work, without per-step
Python or tensor dispatch (a right-hand side is a few microseconds instead of a fraction
of a millisecond).
"""
from __future__ import annotations

from dataclasses import fields

import numba
import numpy as np
import torch
from numba import njit

from ..physics import kernels, kernels_state
from ..physics.body import Body
from ..physics.configspace import _layout
from ..physics.dynamics import _kernel_root, _kernel_tables
from .ode import _A, _C, _ERROR, _GROW, _MID, _SAFETY, _SHRINK, EachSolution

_FAST = kernels._FAST
_NUMBA_CACHE_DIR = kernels.redirect_cache()          # restored at the end of this module
#: Dormand–Prince's stages (6×6, row s the weights of stages 0..s), nodes, error weights
#: and dense-output weights: tflearn.simulation.ode's, as arrays.
_TABLEAU = (np.array([row + [0.0] * (6 - len(row)) for row in _A]), np.array(_C),
            np.array(_ERROR), np.array(_MID))


def applies(program, y0: torch.Tensor) -> bool:
    """Whether :func:`integrate` can run this simulation: a program that can be unrolled
    per member, float64 on the CPU and nothing that needs a gradient
    (:func:`tflearn.physics.kernels.applies`)."""
    params = list(program.parameters()) if isinstance(program, torch.nn.Module) else []
    return hasattr(program, "rows") and kernels.applies(y0, *params)


def integrate(body: Body, program, y0: torch.Tensor, t: torch.Tensor, *, rtol: float, atol: float,
              max_evals, track_work: bool = False, groups: torch.Tensor | None = None, base=None):
    """The states at t (T×...×D) of y0 (...×D) under ``program`` (see the module), as
    :class:`tflearn.simulation.ode.EachSolution`; None when the program cannot be unrolled for this
    batch (run the torch path). ``groups`` (..., integers): members with the same value
    share every step (see :func:`tflearn.simulation.ode.odeint_each`); default: each member alone.
    ``base``: :class:`tflearn.motions.torso.Bases`, one moving base per member (row order), its
    polynomials evaluated in the loop (:func:`_base_root`, the maths of
    :meth:`~tflearn.motions.torso.Bases.terms`); None: a fixed base."""
    batch, D = y0.shape[:-1], y0.shape[-1]
    rows = program.rows(batch)
    if rows is None:
        return None
    B, T = int(np.prod(batch, dtype=np.int64)), t.numel()
    if groups is None:
        order, bounds = np.arange(B, dtype=np.int64), np.arange(B + 1, dtype=np.int64)
    else:
        g = groups.reshape(B).to(torch.int64)
        order = torch.argsort(g, stable=True).numpy().astype(np.int64)
        counts = torch.unique_consecutive(g[order], return_counts=True)[1]
        bounds = np.concatenate([[0], np.cumsum(counts.numpy())]).astype(np.int64)
    layout = _layout(body, y0.device)
    L, n_pos = layout["numpy"], layout["n_pos"]
    ys = np.full((T, B, D), np.nan)
    failure, evals, steps = (np.zeros(B, dtype=np.int64) for _ in range(3))
    arr = lambda x: np.ascontiguousarray(x.detach().to(torch.float64).numpy())
    program_arrays = (rows.group.numpy().astype(np.int64),    # ProgramRows' fields, in order
                      *(arr(getattr(rows, f.name)) for f in fields(rows)[1:]))
    if base is None:
        base_arrays = (np.zeros((0, 2)), np.zeros((0, 1, 6, 7)), np.zeros(0, dtype=np.int64), np.zeros(0))
    else:
        base_arrays = (arr(base.breaks), arr(base.coef), base.pieces.numpy().astype(np.int64),
                       arr(base.start))
    _integrate(arr(t.to(torch.float64)), arr(y0.reshape(B, D)), order, bounds, float(rtol), float(atol),
               -1 if max_evals is None else int(max_evals), bool(track_work),
               _kernel_tables(body), _kernel_root(body, True),
               (*base_arrays, np.asarray(body.gravity, dtype=np.float64)), float(body.damping),
               (L["quat"], L["other"], L["coords"], L["position"]), n_pos, body.nv,
               program_arrays, _TABLEAU, ys, failure, evals, steps)
    as_t = torch.from_numpy
    return EachSolution(as_t(ys).reshape(T, *batch, D), as_t(failure).reshape(batch),
                        as_t(evals).reshape(batch), as_t(steps).reshape(batch))


# ------------------------------------------------------------------ the compiled loops

@njit(cache=True, fastmath=_FAST)
def _step(u):
    """ψ(u) = u − sin(2πu)/2π on [0, 1], 0 before, 1 after."""
    u = min(max(u, 0.0), 1.0)
    return u - np.sin(2 * np.pi * u) / (2 * np.pi)


@njit(cache=True, fastmath=_FAST)
def _pulse(u):
    """φ(u) = ½(1 − cos 2πu) on [0, 1], 0 elsewhere."""
    u = min(max(u, 0.0), 1.0)
    return 0.5 * (1 - np.cos(2 * np.pi * u))


@njit(cache=True, fastmath=_FAST)
def _torque(m, t, q, v, program, tau, d, Kd, win):
    """τ (nv) of member m at its program's time t from ν = q, v (the module's formula)."""
    group, start, a, b, c, so, sd, po, pd, wo, wd, eta, K, zeta = program
    g, n, M, P = group[m], q.shape[0], a.shape[1], c.shape[2]
    tt = start[m] + t
    tau[:] = 0.0
    for k in range(P):
        win[k] = _pulse((tt - wo[m, k]) / wd[m, k])
    for i in range(M):
        w = a[m, i] * _step((tt - so[m, i]) / sd[m, i]) + b[m, i] * _pulse((tt - po[m, i]) / pd[m, i])
        for k in range(P):
            w += c[m, i, k] * win[k]
        if w == 0.0:
            continue
        quad = 0.0
        for k in range(n):
            d[k] = q[k] - eta[g, i, k]
        for k in range(n):
            acc = 0.0
            for j in range(n):
                acc += K[g, i, k, j] * (d[j] + zeta[g] * v[j])
            Kd[k] = acc
            if zeta[g] != 0.0:                      # dᵀKd without the damping term
                acc = 0.0
                for j in range(n):
                    acc += K[g, i, k, j] * d[j]
            quad += d[k] * acc
        e = w * np.exp(-0.5 * quad)
        for k in range(n):
            tau[k] -= e * Kd[k]


@njit(cache=True, fastmath=_FAST)
def _base_root(m, t, base, V0, A0, pose):
    """V_0 = (ω_b, 0) and A_0 = (ω̇_b, a_b − g_b) (1×6 each, in place) of member m's
    moving base at its time t: its pose polynomial (p, ṗ, p̈ into the rows of ``pose``,
    3×7; quaternion XYZW and origin) by Horner, then ω = 2 vec(p̄ ṗ)/|p|², ω̇ = 2 vec(p̄ p̈)/|p|² − ω 2(p·ṗ)/|p|²,
    a_b = Rᵀ ẍ, g_b = Rᵀ g (:meth:`tflearn.motions.torso.Bases.terms`)."""
    breaks, coef, pieces, start, g = base
    P = pieces[m]
    s = min(max(start[m] + t, breaks[m, 0]), breaks[m, P])
    lo, hi = 0, P - 1                                   # the last piece i with breaks[i] <= s
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if breaks[m, mid] <= s:
            lo = mid
        else:
            hi = mid - 1
    u = s - breaks[m, lo]
    p, pd, pdd = pose[0], pose[1], pose[2]
    deg = coef.shape[2] - 1
    for c in range(7):
        a0, a1, a2 = 0.0, 0.0, 0.0
        for j in range(deg + 1):
            cj = coef[m, lo, j, c]
            a0 = a0 * u + cj
            if j < deg:
                a1 = a1 * u + (deg - j) * cj
            if j < deg - 1:
                a2 = a2 * u + (deg - j) * (deg - j - 1) * cj
        p[c], pd[c], pdd[c] = a0, a1, a2
    n2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2] + p[3] * p[3]
    dot = 2 * (p[0] * pd[0] + p[1] * pd[1] + p[2] * pd[2] + p[3] * pd[3])
    x, y, z, w = p[0], p[1], p[2], p[3]
    for k in range(3):                                  # vec(p̄ ⊗ d) = w d_v − d_w p_v − p_v × d_v
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        wk = w * pd[k] - pd[3] * p[k] - (p[k1] * pd[k2] - p[k2] * pd[k1])
        ak = w * pdd[k] - pdd[3] * p[k] - (p[k1] * pdd[k2] - p[k2] * pdd[k1])
        V0[0, k] = 2 * wk / n2
        A0[0, k] = 2 * ak / n2 - V0[0, k] * dot / n2
        V0[0, 3 + k] = 0.0
    r = np.sqrt(n2)
    R = kernels._quat_rotmat(x / r, y / r, z / r, w / r)
    for k in range(3):                                  # Rᵀ(ẍ − g): column k of R
        acc = 0.0
        for j in range(3):
            acc += R[3 * j + k] * (pdd[4 + j] - g[j])
        A0[0, 3 + k] = acc


@njit(cache=True, fastmath=_FAST)
def _rate(m, t, y, out, work, tables, root, base, damping, orders, n_pos, program, s):
    """dy/dt (D) of member m at time t and state y (D) into ``out``; s: scratch arrays."""
    quat, other, coords_order, position_order = orders
    Y, coords, quats, R, v, tau, total, qdd, pos, d, Kd, win, V0, A0, pose = s
    nv = coords.shape[1]
    for k in range(y.shape[0]):
        Y[0, k] = y[k]
    kernels_state.read_state(Y, quat, other, coords_order, coords, quats, R)
    for k in range(nv):
        v[0, k] = y[n_pos + k]
    _torque(m, t, coords[0], v[0], program, tau, d, Kd, win)
    for k in range(nv):
        total[0, k] = tau[k] - damping * v[0, k]
    kind, rot, R0, origin, axis, offset, parent, inertia = tables
    if base[2].shape[0]:
        _base_root(m, t, base, V0, A0, pose)
        kernels.aba(kind, rot, R0, origin, axis, offset, parent, inertia, R, coords, V0, A0, v, total, qdd)
    else:
        kernels.aba(kind, rot, R0, origin, axis, offset, parent, inertia, R, coords, root[0], root[1],
                    v, total, qdd)
    kernels_state.position_rate(kind, rot, offset, R, quats, v, position_order, pos)
    for k in range(n_pos):
        out[k] = pos[0, k]
    for k in range(nv):
        out[n_pos + k] = qdd[0, k]
    if work:
        acc = 0.0
        for k in range(nv):
            acc += tau[k] * v[0, k]
        out[n_pos + nv] = acc


@njit(cache=True, fastmath=_FAST)
def _rms(x, scale):
    acc = 0.0
    for k in range(x.shape[0]):
        acc += (x[k] / scale[k]) ** 2
    return np.sqrt(acc / x.shape[0])


@njit(cache=True, fastmath=_FAST)
def _flat(x):
    """A contiguous array as one vector (a view)."""
    return x.reshape(x.size)


@njit(cache=True, fastmath=_FAST)
def _finite(x):
    for k in range(x.shape[0]):
        if not np.isfinite(x[k]):
            return False
    return True


@njit(cache=True, fastmath=_FAST)
def _rates(members, t, Y, out, work, tables, root, base, damping, orders, n_pos, program, s):
    """dy/dt of every member of a group (rows of Y, m×D) at time t into ``out`` (m×D)."""
    for i in range(members.shape[0]):
        _rate(members[i], t, Y[i], out[i], work, tables, root, base, damping, orders, n_pos, program, s)


@njit(cache=True, fastmath=_FAST)
def _integrate(t, y0, order, bounds, rtol, atol, max_evals, work, tables, root, base, damping, orders,
               n_pos, nv, program, tableau, ys, failure, evals, steps):
    """Every group of members (rows ``order[bounds[g]:bounds[g+1]]`` of y0, B×D) from t[0]
    to t[-1], its samples into ys (T×B×D, NaN-filled), its failure code, right-hand sides
    and accepted steps into the others: :func:`tflearn.simulation.ode.odeint_each` group by group
    (a group of one member is a member stepped alone)."""
    A, C, E, MID = tableau
    D = y0.shape[1]
    T, P, nr = t.shape[0], program[4].shape[2], orders[0].shape[0]
    s = (np.zeros((1, D)), np.zeros((1, nv)), np.zeros((1, nr, 4)), np.zeros((1, nr, 3, 3)),
         np.zeros((1, nv)), np.zeros(nv), np.zeros((1, nv)), np.zeros((1, nv)),
         np.zeros((1, n_pos)), np.zeros(nv), np.zeros(nv), np.zeros(max(P, 1)), np.zeros((1, 6)),
         np.zeros((1, 6)), np.zeros((3, 7)))
    end = t[-1]
    for g in range(bounds.shape[0] - 1):
        members = order[bounds[g]:bounds[g + 1]]
        m = members.shape[0]
        k = np.zeros((7, m, D))
        y, y1, f = np.zeros((m, D)), np.zeros((m, D)), np.zeros((m, D))
        stage, scale, err = np.zeros((m, D)), np.zeros((m, D)), np.zeros((m, D))
        for i in range(m):
            y[i] = y0[members[i]]
        tb = t[0]
        _rates(members, tb, y, f, work, tables, root, base, damping, orders, n_pos, program, s)
        scale[:] = atol + np.abs(y) * rtol                   # Hairer's initial step
        d0, d1 = _rms(_flat(y), _flat(scale)), _rms(_flat(f), _flat(scale))
        h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
        stage[:] = y + h0 * f
        _rates(members, tb + h0, stage, k[1], work, tables, root, base, damping, orders, n_pos, program, s)
        err[:] = k[1] - f
        d2 = _rms(_flat(err), _flat(scale)) / h0
        big = max(d1, d2)
        h1 = max(h0 * 1e-3, 1e-6) if big <= 1e-15 else (0.01 / big) ** 0.2
        h = min(100 * h0, h1)
        code = 0 if (_finite(_flat(f)) and _finite(_flat(y))) else 3
        count, accepted, nxt = 2, 0, 1
        for i in range(m):
            ys[0, members[i], :] = y[i]
        while code == 0 and nxt < T:
            h = min(h, end - tb)
            k[0] = f
            for st in range(6):
                for i in range(m):
                    for j in range(D):
                        acc = 0.0
                        for r in range(st + 1):
                            if A[st, r] != 0.0:
                                acc += A[st, r] * k[r, i, j]
                        stage[i, j] = y[i, j] + h * acc
                _rates(members, tb + C[st] * h, stage, k[st + 1], work, tables, root, base, damping,
                       orders, n_pos, program, s)
            for i in range(m):
                for j in range(D):
                    y1[i, j] = stage[i, j]
                    acc = 0.0
                    for r in range(7):
                        if E[r] != 0.0:
                            acc += E[r] * k[r, i, j]
                    err[i, j] = h * acc
                    scale[i, j] = atol + rtol * max(abs(y[i, j]), abs(y1[i, j]))
            ratio = _rms(_flat(err), _flat(scale))
            finite = _finite(_flat(y1)) and _finite(_flat(k[6])) and np.isfinite(ratio)
            count += 6
            ok = finite and ratio <= 1
            t1 = tb + h if ok else tb
            if ok:
                while nxt < T and t[nxt] <= t1 + 1e-12 * (1 + abs(t1)):
                    x = min(max((t[nxt] - tb) / h, 0.0), 1.0)
                    for i in range(m):
                        for j in range(D):
                            acc = 0.0
                            for r in range(7):
                                if MID[r] != 0.0:
                                    acc += MID[r] * k[r, i, j]
                            mid = y[i, j] + h * acc
                            k0, k6, ya, yb = k[0, i, j], k[6, i, j], y[i, j], y1[i, j]
                            qa = 2 * h * (k6 - k0) - 8 * (yb + ya) + 16 * mid
                            qb = h * (5 * k0 - 3 * k6) + 18 * ya + 14 * yb - 32 * mid
                            qc = h * (k6 - 4 * k0) - 11 * ya - 5 * yb + 16 * mid
                            ys[nxt, members[i], j] = (((qa * x + qb) * x + qc) * x + h * k0) * x + ya
                    nxt += 1
                accepted += 1
                y[:] = y1
                f[:] = k[6]
            safe = ratio if finite else 1e6
            factor = min(_SAFETY * max(safe, 1e-10) ** -0.2, _GROW)
            factor = max(factor, 1.0) if ok else max(factor, _SHRINK)
            h_new = h * factor
            tb = t1
            if not finite:
                code = 3
            if not ok and h_new <= 1e-14 * (1 + abs(tb)):
                code = 2
            if max_evals >= 0 and count > max_evals and nxt < T:
                code = 1
            h = h_new
        for i in range(m):
            failure[members[i]], evals[members[i]], steps[members[i]] = code, count, accepted


numba.config.CACHE_DIR = _NUMBA_CACHE_DIR
