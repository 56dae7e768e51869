"""Experiment 1 (thesis §4.1, figures 4-1 to 4-5): the basin of the search.

Each gesture alone; its generating parameters θ, each times a factor 1 + (r − 1)u,
u ~ U[0, 1], are the initial guess of ``slsqp`` (the thesis' method) and ``local`` (EM,
then path matching); ``pipeline`` (the full search) ignores the guess, so one run per
seed stands for every r. Outcome: the success rate against r per gesture and method,
and the largest r up to which it stays ≥ 90% (:func:`~.common.r90`).
"""
from __future__ import annotations

from . import common
from .config import ExperimentConfig

TEXT = common.text("basin")
#: per gesture, (the largest r the thesis recovered, the first r that failed)
THESIS_R = {g: tuple(v) for g, v in TEXT["thesis_r"].items()}


def thesis() -> str:
    """The thesis' outcome, in words."""
    return "; ".join(f"{g} recovered at r = {a:g}, failed at r = {b:g}"
                     for g, (a, b) in THESIS_R.items()) + " (one trial per r)."


def run(cfg: ExperimentConfig) -> dict:
    """Success rate against r, per gesture alone and method."""
    return common.noise_experiment(cfg, {g: [g] for g in cfg.gestures})


def figures(cfg: ExperimentConfig, result: dict) -> list:
    """Success against r with the thesis' limits, and each gesture's paths."""
    return common.sweep_figures(cfg, result, THESIS_R)


def summary(result: dict) -> str:
    """Per gesture, the success rates of each method at each r."""
    return common.rate_tables(result, THESIS_R)


def goals(result: dict) -> list:
    """(goal, measured, met): the local solver's 90%-success r at least twice the thesis'
    largest recovered r, and the pipeline reproducing every gesture at every r."""
    s, out = result["summary"], []
    for g, ms in s["r90"].items():
        lim = THESIS_R[g][0]
        if "local" in ms:
            r = ms["local"]
            seen = (f"at least 90% up to r = {r:g}" if r > 0 else
                    f"below 90% already at r = {s['rates'][g]['local']['r'][0]:g}")
            out.append((f"{g}: the local solver succeeds at least 90% of the time up to "
                        f"r ≥ {2 * lim:g} (twice the thesis' {lim:g})", seen, r >= 2 * lim))
        if "pipeline" in s["rates"][g]:
            rate = min(s["rates"][g]["pipeline"]["rate"])
            out.append((f"{g}: the full pipeline reproduces the gesture every time, at every r",
                        f"lowest success rate {common.pct(rate)}", rate == 1.0))
    return out
