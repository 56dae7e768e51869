"""``solver.method: auto`` — which model suits a run's motions, decided from the motions.

The pipeline learns a few fields that made the motions; motion no few fields made
(keyframed, recorded) is held on its path by convergent antagonist pairs instead
(:data:`tflearn.config.CONVERGENT`, docs/model.md). What tells them apart is the
pipeline's own first step: a motion searched alone on torques (:func:`tflearn.fit.search.grow`,
``solver.each.max_fields`` fields, no simulation) reaches a small relative torque cost
C_j when a few fields made it (at most 8.4e-4 on the gestures and 100 planted programs)
and stays above it when none did (at least 4.2e-3 on keyframe splines and recorded
windows; docs/model.md, "Which model").
``solver.auto.probes`` motions spread over the data are probed; the pipeline is chosen
when at least half of them reach ``solver.auto.tol``.
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from ..config import CONVERGENT, Config, without
from ..fit import search
from ..fit.targets import Targets
from ..physics.body import Body
from .models import empty_basis, windows

__all__ = ["choose", "probed"]


def probed(cfg: Config, body: Body, tg: Targets) -> dict:
    """{name: C_j} of the probed motions: ``solver.auto.probes`` of them at evenly spaced
    positions in the data, each searched alone on torques (seeded by ``seed`` and its
    position: the same on every rank), stopping at ``solver.auto.tol``."""
    c, count = cfg.solver, min(cfg.solver.auto.probes, tg.N)
    picks = sorted({round(i * (tg.N - 1) / max(count - 1, 1)) for i in range(count)})
    options = search.GrowOptions(max_fields=c.each.max_fields, tol=c.auto.tol, candidates=c.init.candidates,
                                 stiffnesses=tuple(c.init.stiffness_grid), em_steps=c.em.steps,
                                 em_tol=c.em.tol, phases=cfg.model.phases == "variable")
    costs = {}
    for k in picks:
        one = tg.select([k])
        generator = torch.Generator().manual_seed(cfg.seed + k)
        costs[tg.names[k]] = float(search.grow(one, empty_basis(cfg, body), generator, options,
                                               windows=windows(cfg, one))[2][0])
    return costs


def choose(cfg: Config, body: Body, tg: Targets, earlier: Optional[dict] = None) -> tuple:
    """(the config to run, the decision or None): with ``solver.method: auto``, ``cfg``
    with method pipeline when at least half the :func:`probed` motions reach
    ``solver.auto.tol``, else ``cfg`` ← :data:`~tflearn.config.CONVERGENT` but the keys the
    command line gave (:attr:`Config.given <tflearn.config.Config.given>`); the decision
    {"method", "tol", "probes": {name: C_j}} goes into metrics.json (``history.method``).
    ``earlier``: a decision already taken (a resumed run's, from its checkpoint), applied
    as it is, nothing probed. Any other method: (``cfg``, None)."""
    if cfg.solver.method != "auto":
        return cfg, None
    decision = earlier
    if decision is None:
        costs = probed(cfg, body, tg)
        made = sum(cost <= cfg.solver.auto.tol for cost in costs.values())
        decision = {"method": "pipeline" if made >= math.ceil(len(costs) / 2) else "convergent",
                    "tol": cfg.solver.auto.tol, "probes": costs}
    chosen = (cfg.replace(solver={"method": "pipeline"}) if decision["method"] == "pipeline"
              else cfg.replace(**without(CONVERGENT, cfg.given)))
    return chosen, decision
