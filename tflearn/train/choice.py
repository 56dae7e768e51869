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

The fields' stiffness kind is decided with it: the probes search fields of the run's
``model.stiffness`` first; when some probe does not reach the bar, they are searched again
with ``full`` K (a symmetric K couples the coordinates, as fields made with one do), and
the kind that brings more probes within the bar is the pipeline's (the run's own on a
tie). Not when ``model.stiffness`` is given on the command line or is ``full`` already.
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
    with method pipeline (and the stiffness kind decided, module docstring) when at least
    half the :func:`probed` motions reach ``solver.auto.tol``, else ``cfg`` ←
    :data:`~tflearn.config.CONVERGENT` but the keys the command line gave
    (:attr:`Config.given <tflearn.config.Config.given>`); the decision {"method",
    "stiffness" (the pipeline's kind; None for the pairs), "tol", "probes": {kind: {name:
    C_j}}} goes into metrics.json (``history.method``).
    ``earlier``: a decision already taken (a resumed run's, from its checkpoint), applied
    as it is, nothing probed. Any other method: (``cfg``, None)."""
    if cfg.solver.method != "auto":
        return cfg, None
    decision = _decide(cfg, body, tg) if earlier is None else _earlier(earlier, cfg.model.stiffness)
    if decision["method"] == "pipeline":
        kind = {"stiffness": decision["stiffness"]}
        return cfg.replace(solver={"method": "pipeline"}, model=kind), decision
    return cfg.replace(**without(CONVERGENT, cfg.given)), decision


def _earlier(decision: dict, kind: str) -> dict:
    """A checkpoint's decision; one written before the kind was decided (probes by name
    alone) probed the run's own kind."""
    if "stiffness" in decision:
        return decision
    pipeline = decision["method"] == "pipeline"
    return dict(decision, stiffness=kind if pipeline else None, probes={kind: decision["probes"]})


def _decide(cfg: Config, body: Body, tg: Targets) -> dict:
    """The decision of :func:`choose`, from the probes (module docstring)."""
    kind, tol = cfg.model.stiffness, cfg.solver.auto.tol
    probes = {kind: probed(cfg, body, tg)}
    made = {kind: sum(c <= tol for c in probes[kind].values())}
    if made[kind] < len(probes[kind]) and kind != "full" and "stiffness" not in cfg.given.get("model", {}):
        probes["full"] = probed(cfg.replace(model={"stiffness": "full"}), body, tg)
        made["full"] = sum(c <= tol for c in probes["full"].values())
    best = max(made, key=lambda k: (made[k], k == kind))
    pipeline = made[best] >= math.ceil(len(probes[kind]) / 2)
    return {"method": "pipeline" if pipeline else "convergent", "stiffness": best if pipeline else None,
            "tol": tol, "probes": probes}
