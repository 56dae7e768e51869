"""The thesis' chapter 4 experiments, each run end to end from ``configs/experiments/NAME.yaml``.

    tflearn experiment NAME [--quick] [key=value ...]  → OUT/results.json, OUT/figures/
    tflearn report                                      → docs/results.md + its figures

:data:`EXPERIMENTS` maps each name to its module — :mod:`.basin` (§4.1), :mod:`.shared`
(§4.2), :mod:`.keyframes` (§4.3), :mod:`.filtering` (§4.5.4), :mod:`.reaches` (§4.5.4 by
class) — each providing
``run(cfg)`` → {"rows", "summary"}, ``figures(cfg, result)`` → paths, ``summary(result)``
(markdown), ``goals(result)`` → [(goal, measured, met)] (the report's "goal: …; measured: … —
(not) met" lines) and ``thesis()`` (the thesis' outcome).
Configs: :mod:`.config`; shared services (guesses, methods, the case runner): :mod:`.common`;
the report: :mod:`.reporting`, its words in text.yaml.
"""
from __future__ import annotations

import importlib
import json
import time
from pathlib import Path

from ..config import dump
from ..io.files import write_text
from .config import NAMES, ExperimentConfig, load_config

__all__ = ["EXPERIMENTS", "ExperimentConfig", "load_config", "run", "report", "text_summary"]


def _module(name: str):
    """A submodule, imported on first use."""
    return importlib.import_module(f"{__name__}.{name}")


def __getattr__(name):
    """``EXPERIMENTS``, the registry name → module, imported on first use (so that a
    config is checked before torch is imported)."""
    if name == "EXPERIMENTS":
        return {n: _module(n) for n in NAMES}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run(cfg: ExperimentConfig) -> dict:
    """Run an experiment end to end: OUT/config.yaml, OUT/results.json, OUT/figures/*.png,
    OUT/tensorboard; returns results.json's content."""
    common = _module("common")
    experiment, out = __getattr__("EXPERIMENTS")[cfg.experiment], Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    dump(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    result = experiment.run(cfg)
    result.update(experiment=cfg.experiment, quick=cfg.quick, config=cfg.model_dump(),
                  elapsed_s=time.perf_counter() - t0)
    paths = experiment.figures(cfg, result)
    result["figures"] = [p.name for p in paths]
    write_text(out / "results.json", json.dumps(result, indent=1, default=float))
    common.log_tensorboard(cfg, result, paths)
    return result


def text_summary(result: dict) -> str:
    """Markdown tables of an experiment's outcome and cost, and its goals."""
    return _module("reporting").outcome(__getattr__("EXPERIMENTS")[result["experiment"]], result)


def report(runs="runs/experiments", out="docs/results.md") -> Path:
    """docs/results.md from the experiments' results under ``runs`` (:mod:`.reporting`)."""
    return _module("reporting").report(__getattr__("EXPERIMENTS"), runs, out)
