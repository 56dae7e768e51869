"""The end of a run (stage ``done``): the result (:func:`~tflearn.train.models.final_model`;
with ``model.fields`` 0, without the fields no motion has a weight on) scored by
simulation — one iteration, logged with the paths' figures — and, by rank 0, the
artefacts: ``basis.json`` (:mod:`tflearn.io.basis`), ``metrics.json`` (per motion
and overall scores, error growth, torque resolution, simulations, the history — with
the method ``solver.method: auto`` chose —, the data
files skipped and, for data that carries its generating fields, each matched to a
learned one: :mod:`tflearn.fit.identity`), ``config.yaml``, ``figures/NAME.png``,
``knee.png`` (how the shared basis was chosen: :func:`tflearn.plots.model.knee`),
TensorBoard's hyper-parameters, and the checkpoint of the finished run. A finished run
run again writes them again from its checkpoint, logging nothing.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

from .. import config as config_mod
from .. import parallel
from ..data.loading import generating_bases
from ..fit import identity, impedance, stability
from ..fit.targets import Targets
from ..io import basis as basis_io
from ..io.files import write_text
from ..metrics import Scores, numbers, summarize
from .context import RunContext
from .models import final_model, without_idle
from .state import DONE, RunState


def finish(ctx: RunContext, state: RunState) -> dict:
    """Score the result, write the artefacts (rank 0); metrics.json's dict."""
    tg = ctx.tg
    basis, weights = final_model(state)
    if not ctx.cfg.model.fields:                    # M found, not given: no idle field in it
        basis, weights = without_idle(basis, weights)
    scores, ok = ctx.check(basis, weights, tg)
    if not state.finished:
        step = ctx.tick(state)
        ctx.log.scores(scores, tg, step, figures=True)
        ctx.log.model(basis, weights, step)
    lb = basis_io.LearnedBasis(ctx.body, basis, weights, tg.q0, tg.qd0, tg.rate)
    metrics = summarize(scores, ok, tg, basis.M, ctx.checkpoints.elapsed(state),
                        stability.growth(ctx.body, basis, weights, tg),
                        impedance.path_stiffness(ctx.body, basis, weights, tg),
                        numbers(weights, tg, ctx.body.nv))
    for name, eps in zip(tg.names, ctx.resolution):
        metrics["motions"][name]["torque_resolution"] = eps
    metrics["overall"]["simulations"] = ctx.checkpoints.simulations(state)
    metrics["history"] = state.history.to_dict()
    metrics["skipped"] = ctx.skipped
    generating = generating_bases(ctx.cfg.data, ctx.body, tg.names)
    if generating:
        metrics["identity"] = identity.identify(generating, basis, tg)
    state.stage, state.finished = DONE, True
    if parallel.rank() == 0:
        write(ctx, state, scores, lb, metrics)
    return metrics


def write(ctx: RunContext, state: RunState, scores: Scores, lb: basis_io.LearnedBasis, metrics: dict) -> None:
    """The artefacts of a finished run in OUT, the checkpoint last."""
    cfg, out = ctx.cfg, Path(ctx.cfg.out)
    write_figures(ctx.body, ctx.tg, scores, out, cfg.log.figures)
    pool = state.history.pool
    if pool is not None and pool.selection:
        from ..plots import figures, model
        chosen = pool.selection["kept"]
        figures.save(model.knee(pool.selection["path"], chosen, ctx.tg.N), out / "knee.png")
    config_mod.dump(cfg, out / "config.yaml")
    write_text(out / "metrics.json", json.dumps(metrics, indent=1))
    basis_io.save(lb, out / "basis.json")
    ctx.log.hparams(cfg.model_dump(mode="json"), metrics)
    ctx.checkpoints.write(state)


def write_figures(body, tg: Targets, scores: Scores, out: Path, count: Optional[int] = None) -> None:
    """OUT/figures/NAME.png: the target and simulated paths of the ``count`` motions
    furthest from their paths (None: every motion)."""
    from ..plots import figures as plots
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    for j in scores.worst(count):
        name, k = tg.names[j], int(tg.mask[j].sum())
        paths = {"target": tg.q[j, :k], "simulated": scores.q_sim[j, :k]}
        title = f"{name}: rmse {scores.rmse[j]:.4f} rad, tip {100 * scores.tip[j]:.2f} cm"
        plots.save(plots.motion_sheet(body, tg.t[j, :k], paths, title=title), fig_dir / f"{name}.png")
