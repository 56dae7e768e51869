"""docs/results.md: every experiment's set-up, the thesis' outcome, ours and its figures.

The words come from text.yaml (:func:`~.common.text`); the numbers from each
experiment's OUT/results.json, through its module's ``summary`` and ``goals``.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from ..io.files import write_text
from ..physics.body import arm
from ..plots import figures as plots
from ..plots import model as model_plots
from . import common


def outcome(experiment, result: dict) -> str:
    """Markdown of an experiment's outcome: its own tables, the cost table and its goals."""
    parts = [experiment.summary(result), common.cost_table(result["summary"]["costs"])]
    goals = experiment.goals(result)
    if goals:
        parts.append("Goals:\n\n" + "\n".join(goal_line(*g) for g in goals))
    return "\n\n".join(parts)


def goal_line(goal: str, measured: str, met: bool) -> str:
    """One goal as a markdown item: "goal: …; measured: … — met" (or **not met**)."""
    return f"- goal: {goal}; measured: {measured} — {'met' if met else '**not met**'}"


def _model_section(fig_root: Path) -> list:
    """The model's figures (torque fields, profiles), drawn into ``fig_root``."""
    words = common.text("report")
    plots.save(model_plots.fields_gallery(arm()), fig_root / "fields.png")
    plots.save(model_plots.profiles_figure(), fig_root / "profiles.png")
    return ["## The model", "", words["model"], "", "![fields](results/fields.png)", "",
            words["profiles"], "", "![profiles](results/profiles.png)", ""]


def _results(runs: Path, name: str):
    """(folder, results.json content) of an experiment's run under ``runs``, the full
    size preferred over ``-quick``; (None, None) if neither ran."""
    for folder in (runs / name, runs / f"{name}-quick"):
        if (folder / "results.json").exists():
            return folder, json.loads((folder / "results.json").read_text())
    return None, None


def _section(name: str, experiment, runs: Path, fig_root: Path) -> list:
    """An experiment's section; its figures copied to ``fig_root``/NAME."""
    words = common.text(name)
    doc = [f"## {words['title']}", "", f"**Set-up:** {words['setup']}", "",
           f"**Thesis:** {experiment.thesis()}", ""]
    folder, result = _results(runs, name)
    if result is None:
        return doc + [f"Not run yet: `tflearn experiment {name}`.", ""]
    size, flag = (" (quick size)", " --quick") if result["quick"] else ("", "")
    compute = sum(v["wall_s"] for v in result["summary"]["costs"].values())
    doc += [f"**Ours**{size}: `tflearn experiment {name}{flag}` (the fits took {compute / 60:.0f} "
            f"min of single-threaded compute in all; cases are cached, so a re-run only "
            f"redraws).", "", outcome(experiment, result), ""]
    if "notes" in words:
        doc += [f"**Notes:** {words['notes']}", ""]
    dest = fig_root / name
    dest.mkdir(exist_ok=True)
    for fig in result["figures"]:
        shutil.copy(folder / "figures" / fig, dest / fig)
        doc += [f"![{Path(fig).stem}](results/{name}/{fig})", ""]
    return doc


def report(experiments: dict, runs="runs/experiments", out="docs/results.md") -> Path:
    """Write ``out`` (and its figures in results/ beside it): for every experiment of
    ``experiments`` (name → module) with a results.json under ``runs``, the thesis'
    outcome, ours, the figures and the command that regenerates it."""
    runs, out = Path(runs), Path(out)
    fig_root = out.parent / "results"
    fig_root.mkdir(parents=True, exist_ok=True)
    words = common.text("report")
    doc = [f"# {words['title']}", "", words["intro"], "", words["see_also"], "",
           *_model_section(fig_root)]
    for name, experiment in experiments.items():
        doc += _section(name, experiment, runs, fig_root)
    write_text(out, "\n".join(doc))
    return out
