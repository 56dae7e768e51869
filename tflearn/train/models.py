"""The models the stages start from: an empty basis of the config's kind, the spanning
layout of :mod:`tflearn.fit.layout`, and the weights a motion may use (its support)."""
from __future__ import annotations

from typing import Optional

import torch

from ..config import Config
from ..fit import layout
from ..fit.targets import Targets, submovement_windows
from ..model.fields import FieldBasis
from ..model.program import model_from_state
from ..model.weights import MotionWeights


def weight_support(fields: Optional[list], P: int) -> Optional[torch.Tensor]:
    """The weights (N×M(2+P) bools, [a | b | c]) of the fields each motion may use
    (N×M lists of bools, :attr:`RunState.support`); None: every weight free."""
    if fields is None:
        return None
    f = torch.tensor(fields, dtype=torch.bool).reshape(len(fields), -1)
    return torch.cat([f, f, f.repeat_interleave(P, dim=1)], dim=1)


def empty_basis(cfg: Config, body) -> FieldBasis:
    """An empty basis of the config's stiffness kind and field damping on the body's blocks."""
    m = cfg.model
    return FieldBasis.empty(body.nv, m.stiffness, body.blocks, m.field_damping)


def layout_basis(cfg: Config, body, tg: Targets, c=None) -> FieldBasis:
    """The spanning basis (:func:`tflearn.fit.layout.spanning_basis`) of ``c``'s shape,
    radius and stiffness (by default ``solver.layout``) around the motions of ``tg``."""
    c = c or cfg.solver.layout
    fields = c.fields if c.shape == "joints" else None          # rescue's shapes have no budget
    return layout.spanning_basis(body, tg, empty_basis(cfg, body), c.radius, c.stiffness, c.shape, fields)


def windows(cfg: Config, tg: Targets) -> tuple:
    """Each motion's sub-movement windows (onsets, durations: N×P) as the config asks:
    ``model.windows`` of them, each motion using as many as its length asks at
    ``model.window_rate`` (:func:`~tflearn.fit.targets.submovement_windows`)."""
    return submovement_windows(tg, cfg.model.windows, rate=cfg.model.window_rate)


def layout_model(cfg: Config, body, tg: Targets) -> tuple:
    """The ``layout`` stage's model before NNLS: :func:`layout_basis` and zero weights on
    each motion's ``model.windows`` sub-movement windows."""
    basis = layout_basis(cfg, body, tg)
    return basis, MotionWeights.zeros(basis.M, tg.duration, tg.names, windows(cfg, tg))


def final_model(state) -> tuple:
    """The run's result (basis, weights): the current model, or path matching's best point."""
    best = state.path.best if state.path is not None else None
    return model_from_state(best["model"] if best is not None else state.model)


def without_idle(basis, weights) -> tuple:
    """(basis, weights) without the fields on which no motion has a weight (a, b or c):
    their torque is zero on every motion, so every motion's program is unchanged (path
    matching can leave unused a field that elimination kept)."""
    used = weights.used().any(0)
    if bool(used.all()) or not bool(used.any()):
        return basis, weights
    keep = used.nonzero().flatten().tolist()
    return basis.select(keep), weights.select_fields(keep)
