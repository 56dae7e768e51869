"""A model's torque program and its one state: basis (:mod:`tflearn.model.fields`) and
weights (:mod:`tflearn.model.weights`) together.

:class:`FieldProgram` is τ_j(t, ν, v) = Σ_i w_ji(t) χ_i(ν, v) for each motion j;
:class:`ProgramRows` the same unrolled per batch member for the compiled simulator;
:func:`model_state` / :func:`model_from_state` the exact serialisation of a model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import nn

from .fields import FieldBasis
from .weights import MotionWeights

__all__ = ["FieldProgram", "ProgramRows", "stack_rows", "model_state", "model_from_state",
           "state_to_json"]


class FieldProgram(nn.Module):
    """The torque program of N motions: τ(t, ν, v) = Σ_i w_ji(t) χ_i(ν, v) for each motion j.

    Called as ``program(t, q, v)`` with q, v (...×N×n) — the motion index on the last batch
    dimension — it returns τ (...×N×n). ``index`` restricts it to some motions. ``start``
    (N): each motion's own time at the simulation's t = 0, its program then run at
    start + t (the segments of multiple shooting). t is a scalar, sample times (T, with q
    T×N×n), or a time per member (of q's batch shape, ...×N: the per-member steps of
    :class:`~tflearn.simulation.simulate.SimOptions` batch ``each``).
    """

    def __init__(self, basis: FieldBasis, weights: MotionWeights,
                 index: Optional[Sequence[int]] = None, start: Optional[torch.Tensor] = None):
        super().__init__()
        self.basis, self.weights, self.start = basis, weights, start
        self.index = None if index is None else torch.as_tensor(index, dtype=torch.long)

    def forward(self, t, q, v=None):
        t = torch.as_tensor(t, dtype=q.dtype)
        each = t.ndim > 0 and t.shape == q.shape[:-1]  # a time per member
        if each and self.index is not None:          # ... of the indexed motions
            t = t.new_zeros(t.shape[:-1] + (self.weights.N,)).index_copy(-1, self.index, t)
        if self.start is not None:
            t = self.start + (t if each else t[..., None])
            each = True
        w = self.weights.activation_at(t if each else t[..., None])
        if self.index is not None:
            w = w[..., self.index, :]
        chi = self.basis(q, v)
        return (w.unsqueeze(-1) * chi).sum(-2)

    @torch.no_grad()
    def rows(self, batch: torch.Size) -> Optional[ProgramRows]:
        """The program of every member of a batch of this shape (...×N', N' the motions it
        is called with), row by row in the flattened batch's order, for the compiled
        simulator (:mod:`tflearn.simulation.simkernel`); None when the basis cannot say what its
        fields are (it has no ``tables``)."""
        if not hasattr(self.basis, "tables"):
            return None
        W = self.weights
        motion = torch.arange(W.N) if self.index is None else self.index
        if not batch or batch[-1] != len(motion):
            return None
        motion = motion.repeat(math.prod(batch[:-1]))
        eta, K, zeta, per_motion = self.basis.tables()
        pick = lambda x: x.detach()[motion]
        start = torch.zeros(len(motion), dtype=torch.float64) if self.start is None else pick(self.start)
        return ProgramRows(
            group=motion if per_motion else torch.zeros_like(motion), start=start,
            a=pick(W.a), b=pick(W.b), c=pick(W.c),
            **{k: pick(getattr(W, k)) for k in W.TIMING + W.WINDOWS},
            eta=eta, K=K, damping=torch.full((eta.shape[0],), float(zeta), dtype=torch.float64))


@dataclass
class ProgramRows:
    """A field program unrolled per member b of a flattened batch (B rows), for the
    compiled simulator: member b runs motion time start_b + t and is driven by

        τ_b = Σ_i w_bi χ_gi(ν, v),  g = group_b,
        w_bi = a_bi ψ((t' − so_bi)/sd_bi) + b_bi φ((t' − po_bi)/pd_bi) + Σ_k c_bik φ((t' − wo_bk)/wd_bk)

    with the fields of group g: η (G×M×n), K (G×M×n×n), ζ (G). Per row: group, start
    (B); a, b and the step/pulse onsets and durations (B×M); c (B×M×P); window onsets
    and durations (B×P). :func:`stack_rows` joins several programs' rows."""

    group: torch.Tensor
    start: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    step_onset: torch.Tensor
    step_duration: torch.Tensor
    pulse_onset: torch.Tensor
    pulse_duration: torch.Tensor
    window_onset: torch.Tensor
    window_duration: torch.Tensor
    eta: torch.Tensor
    K: torch.Tensor
    damping: torch.Tensor


def stack_rows(parts: Sequence[ProgramRows]) -> ProgramRows:
    """Several programs' rows one after another (their field groups kept apart), padded to
    the largest M and P with fields and windows of zero weight (durations 1)."""
    M = max(p.a.shape[1] for p in parts)
    P = max(p.c.shape[2] for p in parts)

    def pad(x, dims, value=0.0):                       # dims: [(dimension, new size)]
        size = dict(dims)
        widths = []
        for d in range(x.ndim - 1, min(size) - 1, -1):
            widths += [0, size.get(d, x.shape[d]) - x.shape[d]]
        return nn.functional.pad(x, widths, value=value)
    out, groups = {}, 0
    for p in parts:
        item = {"group": p.group + groups, "start": p.start, "damping": p.damping,
                "a": pad(p.a, [(1, M)]), "b": pad(p.b, [(1, M)]), "c": pad(p.c, [(1, M), (2, P)]),
                "step_onset": pad(p.step_onset, [(1, M)]), "pulse_onset": pad(p.pulse_onset, [(1, M)]),
                "step_duration": pad(p.step_duration, [(1, M)], 1.0),
                "pulse_duration": pad(p.pulse_duration, [(1, M)], 1.0),
                "window_onset": pad(p.window_onset, [(1, P)]),
                "window_duration": pad(p.window_duration, [(1, P)], 1.0),
                "eta": pad(p.eta, [(1, M)]), "K": pad(p.K, [(1, M)])}
        groups += p.eta.shape[0]
        for k, x in item.items():
            out.setdefault(k, []).append(x)
    return ProgramRows(**{k: torch.cat(x) for k, x in out.items()})


# ------------------------------------------------------------------ the model's one state

def model_state(basis: FieldBasis, weights: MotionWeights) -> dict:
    """The exact state of a model (basis + weights) as plain tensors and JSON values: the
    one serialisation used by checkpoints, path matching's best point and experiment rows
    (:func:`state_to_json` for JSON files). :func:`model_from_state` inverts it exactly."""
    return {"basis": {k: v.detach().clone() for k, v in basis.state_dict().items()},
            "weights": {k: v.detach().clone() for k, v in weights.state_dict().items()},
            "kind": basis.kind, "blocks": list(basis.blocks), "damping": basis.damping,
            "names": list(weights.names)}


def model_from_state(state: dict) -> tuple:
    """(FieldBasis, MotionWeights) from :func:`model_state` (tensors or nested lists; a
    state written before field damping and windows existed has ζ = 0 and P = 0)."""
    def tensors(d):
        return {k: v if isinstance(v, torch.Tensor) else torch.tensor(v, dtype=torch.float64)
                for k, v in d.items()}
    b, w = tensors(state["basis"]), tensors(state["weights"])
    M, n = b["eta"].shape
    basis = FieldBasis(torch.zeros(M, n, dtype=torch.float64),
                       torch.eye(n, dtype=torch.float64).expand(M, n, n),
                       kind=state["kind"], blocks=state["blocks"],
                       damping=state.get("damping", 0.0))
    basis.load_state_dict(b)
    N = w["duration"].shape[0]
    none = torch.zeros(N, 0, dtype=torch.float64)       # a state from before windows: P = 0
    w.setdefault("window_onset", none)
    w.setdefault("window_duration", none)
    w.setdefault("c_raw", torch.zeros(N, M, 0, dtype=torch.float64))
    weights = MotionWeights.zeros(M, w["duration"], names=state["names"],
                                  windows=(w["window_onset"], w["window_duration"]))
    weights.load_state_dict(w)
    return basis, weights


def state_to_json(state: dict) -> dict:
    """A :func:`model_state` with every tensor as a nested list (float64 values are kept
    exactly by JSON's shortest round-trip repr)."""
    return {k: ({n: v.tolist() for n, v in x.items()} if k in ("basis", "weights") else x)
            for k, x in state.items()}
