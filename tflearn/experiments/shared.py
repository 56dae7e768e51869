"""Experiment 2 (thesis §4.2, figures 4-6 to 4-8): one basis for several motions.

The gestures together (come-here, tuck and backwards reach) with one basis of their
generating fields: ``slsqp`` and ``local`` from the fields and all weights noised by r
(θ · (1 + (r − 1)u)), the ``pipeline`` learning ``train.model.fields`` = 4 fields from no
guess. Outcome: each motion's success rate against r; the fits' cost histories are kept
for the learning curves.
"""
from __future__ import annotations

from ..io import basis as basis_io
from ..plots import figures as plots
from ..plots import model as model_plots
from . import common
from .config import ExperimentConfig

TEXT = common.text("shared")


def thesis() -> str:
    """The thesis' outcome, in words."""
    return TEXT["thesis"]


def run(cfg: ExperimentConfig) -> dict:
    """Success rates against r of one shared basis for all the gestures."""
    return common.noise_experiment(cfg, {"+".join(cfg.gestures): cfg.gestures}, keep_history=True)


def figures(cfg: ExperimentConfig, result: dict) -> list:
    """Success against r per motion, the paths, the pipeline's weights per motion and the
    guess-based fits' learning curves (seed ``seed0``)."""
    out = common.sweep_figures(cfg, result, {}, per_motion=True)
    fig_dir = common.figure_dir(cfg)
    for group in result["summary"]["rates"]:
        run_dir = common.pipeline_run(cfg, group)
        if (run_dir / "basis.json").exists():
            lb = basis_io.load(run_dir / "basis.json")
            out.append(fig_dir / "weights.png")
            plots.save(model_plots.weights_bars(lb.names, lb.weights.a.detach(), lb.weights.b.detach(),
                                                title="pipeline (M = 4): weights per motion"), out[-1])
    curves = {f"{x['method']} r={x['r']:g}": x["history"] for x in result["rows"]
              if x["seed"] == cfg.seed0 and "history" in x}
    if curves:
        out.append(fig_dir / "learning_curves.png")
        plots.save(model_plots.learning_curves(curves, title="torque cost per iteration (seed 0)"), out[-1])
    return out


def summary(result: dict) -> str:
    """Per method, each motion's success rate and all motions' at each r."""
    return common.rate_tables(result, {}, per_motion=True)


def goals(result: dict) -> list:
    """(goal, measured, met): every method reproducing every motion at every r."""
    return [(f"{m}: every motion reproduced every time, at every r",
             f"lowest success rate {common.pct(min(v['rate']))}", min(v["rate"]) == 1.0)
            for ms in result["summary"]["rates"].values() for m, v in ms.items()]
