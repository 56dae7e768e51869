"""Dormand–Prince 5(4) with a step size of its own for every member of a batch.

torchdiffeq's adaptive solvers take one step size for a whole batch, chosen from one
RMS error norm over all of its entries: a batch steps as finely as its stiffest member
where that member is stiff, and a member's error is averaged with its mates' — so a
member's path, its accuracy and its cost depend on what else is in the batch, and one
member past the budget stops them all. :func:`odeint_each` integrates each member b
(a row of y, B×D after flattening the leading dimensions) as if alone:

    error e_b = sqrt(mean_d (ê_bd / (atol + rtol·max(|y_bd|, |y'_bd|)))²),
    accepted when e_b ≤ 1,  h_b ← h_b · min(10, max(0.9 e_b^(−1/5), 0.2 if rejected else 1)),

with the Dormand–Prince–Shampine tableau, the initial step of Hairer, Nørsett & Wanner
(§II.4), the fourth-order dense output at the sample times and the safety factors of
torchdiffeq's ``dopri5`` — the same solver, one per member, advanced together so that
every right-hand-side call is one batched evaluation (its time t is per member, the
batch's shape), told which members are still live: a member that has finished or failed
keeps its row but its derivative is not used, so the right-hand side may skip it (the
simulator's does, for the dynamics — the work of a batch then shrinks as its members
finish). Steps are clipped to land on the last sample. A member that fails stops
alone and is reported by code (:data:`FAILURE_CODES`); the others go on.

Members given one group (``groups``) share every step, the error e taken over all
their entries: a group is stepped as one system (the copies of a segment in
multiple shooting, whose differences must be those of one discrete map).

Gradients flow through the accepted steps and the dense output, with the step sizes and
accept/reject decisions held fixed (those of the discrete map that was run). A batch with
a failed member has no usable gradient (its rows hold NaN): drop the member and rerun.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch

#: Why a member stopped: 0 it reached the last sample, or one of these codes.
FAILURE_CODES = {1: "budget", 2: "solver", 3: "nonfinite"}

_A = [[1 / 5],
      [3 / 40, 9 / 40],
      [44 / 45, -56 / 15, 32 / 9],
      [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
      [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
      [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84]]
_C = [1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0]
_ERROR = [35 / 384 - 1951 / 21600, 0, 500 / 1113 - 22642 / 50085, 125 / 192 - 451 / 720,
          -2187 / 6784 + 12231 / 42400, 11 / 84 - 649 / 6300, -1 / 60]
_MID = [6025192743 / 30085553152 / 2, 0, 51252292925 / 65400821598 / 2,
        -2691868925 / 45128329728 / 2, 187940372067 / 1594534317056 / 2,
        -1776094331 / 19743644256 / 2, 11237099 / 235043384 / 2]
_SAFETY, _GROW, _SHRINK = 0.9, 10.0, 0.2


@dataclass
class EachSolution:
    """ys (T×...×D) at the sample times (NaN from a failed member's failure on), failure
    (...: 0 or a :data:`FAILURE_CODES` key), evals (...: right-hand sides each member
    used) and steps (...: its accepted steps)."""

    ys: torch.Tensor
    failure: torch.Tensor
    evals: torch.Tensor
    steps: torch.Tensor


def _pooling(groups: Optional[torch.Tensor], B: int):
    """x (B×D) → the RMS of x over each member's group, per member (B): its own row's
    without ``groups``."""
    if groups is None:
        return lambda x: x.pow(2).mean(-1).sqrt()
    _, gid = torch.unique(groups.reshape(B), return_inverse=True)
    count = torch.bincount(gid)

    def rms(x):
        ms = x.pow(2).mean(-1)
        return (ms.new_zeros(len(count)).index_add(0, gid, ms) / count.to(ms.dtype))[gid].sqrt()
    return rms


def _initial_step(func, t0, y0, f0, rtol, atol, rms):
    """Hairer's starting step per member (B)."""
    scale = atol + y0.abs() * rtol
    d0, d1 = rms(y0 / scale), rms(f0 / scale)
    h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), torch.full_like(d0, 1e-6), 0.01 * d0 / d1)
    f1 = func(t0 + h0, y0 + h0[:, None] * f0, None)
    d2 = rms((f1 - f0) / scale) / h0
    big = torch.maximum(d1, d2)
    h1 = torch.where(big <= 1e-15, torch.clamp(h0 * 1e-3, min=1e-6), (0.01 / big) ** 0.2)
    return torch.minimum(100 * h0, h1)


def _dense(y0, y1, ymid, f0, f1, h, x):
    """torchdiffeq's quartic through y0, y1, y_mid with slopes f0, f1, at x ∈ [0, 1]."""
    a = 2 * h * (f1 - f0) - 8 * (y1 + y0) + 16 * ymid
    b = h * (5 * f0 - 3 * f1) + 18 * y0 + 14 * y1 - 32 * ymid
    c = h * (f1 - 4 * f0) - 11 * y0 - 5 * y1 + 16 * ymid
    return (((a * x + b) * x + c) * x + h * f0) * x + y0


def odeint_each(func: Callable, y0: torch.Tensor, t: torch.Tensor, *, rtol: float = 1e-7,
                atol: float = 1e-9, max_evals: Optional[int] = None,
                groups: Optional[torch.Tensor] = None) -> EachSolution:
    """Integrate dy/dt = func(t, y) from y0 (...×D) at t[0], each member with its own steps.

    ``func(t, y, live)`` gets t (...) — every member's own time —, y (...×D) and live
    (... bool, or None for all): the members whose derivative will be used; the rows of
    the others may hold anything, finite or not. ``t``: the
    increasing sample times (T), shared. ``max_evals``: a member that needs more
    right-hand sides than this stops with code 1 (budget). A member stops with code 2
    when its step underflows (t + h = t) and code 3 when its state or derivative is not
    finite. See the module for the error control. ``groups`` (..., integers): members with
    the same value share every step — one step size, and one error norm e over all their
    entries (a group is stepped as one system; a non-finite member stops its group);
    default: every member alone."""
    shape, D = y0.shape[:-1], y0.shape[-1]
    y = y0.reshape(-1, D)
    B, T, dev, dt = y.shape[0], t.numel(), y.device, y.dtype
    rms = _pooling(groups, B)
    t = t.to(dt)
    def call(tb, yb, live):
        live = None if live is None or bool(live.all()) else live.reshape(shape)
        return func(tb.reshape(shape), yb.reshape(*shape, D), live).reshape(B, D)
    tb = t[0].expand(B).clone()
    f = call(tb, y, None)
    h = _initial_step(call, tb, y.detach(), f.detach(), rtol, atol, rms).detach()
    failure = torch.zeros(B, dtype=torch.long, device=dev)
    failure[~torch.isfinite(rms(f) + rms(y))] = 3
    evals = torch.full((B,), 2, dtype=torch.long, device=dev)
    steps = torch.zeros(B, dtype=torch.long, device=dev)
    nxt = torch.ones(B, dtype=torch.long, device=dev)        # next sample to fill
    pieces = [(torch.arange(B, device=dev), torch.zeros(B, dtype=torch.long, device=dev), y)]
    end = t[-1]
    while True:
        live = (failure == 0) & (nxt < T)
        if not bool(live.any()):
            break
        h = torch.where(live, torch.minimum(h, end - tb), torch.zeros_like(h))
        k = [f]
        for c, a in zip(_C, _A):
            ys = y + h[:, None] * sum(ai * ki for ai, ki in zip(a, k) if ai)
            k.append(call(tb + c * h, ys, live))
        y1 = ys                                         # the last stage is the 5th-order solution
        err = h[:, None] * sum(e * ki for e, ki in zip(_ERROR, k) if e)
        ratio = rms(err / (atol + rtol * torch.maximum(y.abs(), y1.abs()))).detach()
        finite = torch.isfinite(rms(y1.detach()) + rms(k[-1].detach())) & torch.isfinite(ratio)
        evals = evals + 6 * live
        acc = live & finite & (ratio <= 1)
        t1 = torch.where(acc, tb + h, tb)
        nxt = _emit(pieces, t, nxt, acc, tb, t1, h, y, y1, k)
        steps = steps + acc
        y = torch.where(acc[:, None], y1, y)
        f = torch.where(acc[:, None], k[-1], f)
        safe = torch.where(finite, ratio, torch.full_like(ratio, 1e6))
        factor = torch.clamp(_SAFETY * safe.clamp(min=1e-10) ** -0.2, max=_GROW)
        factor = torch.where(acc, factor.clamp(min=1.0), factor.clamp(min=_SHRINK))
        h_new = h * factor
        tb = t1
        stop = torch.where(live & ~finite, 3, 0)              # a state that blew up
        stop = torch.where(live & ~acc & (h_new <= 1e-14 * (1 + tb.abs())), 2, stop)
        if max_evals is not None:
            stop = torch.where(live & (evals > max_evals) & (nxt < T), 1, stop)
        failure = torch.where(stop > 0, stop, failure)
        h = torch.where(live, h_new, h)
    return EachSolution(_assemble(pieces, B, T, D, y0).reshape(T, *shape, D),
                        failure.reshape(shape), evals.reshape(shape), steps.reshape(shape))


def _emit(pieces: list, t, nxt, acc, tb, t1, h, y, y1, k) -> torch.Tensor:
    """Append the dense output of the accepted steps (tb → t1) at every sample they pass
    to ``pieces`` as (members, sample indices, states); the next sample of each member."""
    T = t.numel()
    ymid = y + h[:, None] * sum(m * ki for m, ki in zip(_MID, k) if m)
    rows = torch.arange(y.shape[0], device=y.device)
    while True:
        emit = acc & (nxt < T) & (t[nxt.clamp(max=T - 1)] <= t1 + 1e-12 * (1 + t1.abs()))
        if not bool(emit.any()):
            return nxt
        b, j = rows[emit], nxt[emit]
        x = ((t[j] - tb[b]) / h[b]).clamp(0, 1)[:, None]
        pieces.append((b, j, _dense(y[b], y1[b], ymid[b], k[0][b], k[-1][b], h[b, None], x)))
        nxt = nxt + emit


def _assemble(pieces, B, T, D, like):
    """The samples written by the steps, NaN where none was (T×B×D)."""
    b = torch.cat([p[0] for p in pieces])
    j = torch.cat([p[1] for p in pieces])
    vals = torch.cat([p[2] for p in pieces])
    out = like.new_full((T * B, D), float("nan"))
    return out.index_put((j * B + b,), vals).reshape(T, B, D)
