"""What a run writes for TensorBoard, read back with TensorBoard's own reader: the tag
layout of tflearn.log, one run folder with its hyper-parameters, steps that only grow
across a resumed run; render's frames as images (no video encoder); the progress bars
and the summary table."""
from __future__ import annotations

import json
import math
import shutil
import sys

import pytest
import torch
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import plugin_data_pb2

from tflearn import render, train
from tflearn.data import gestures
from tflearn.log import RunLog, flat_hparams, summary_table
from tflearn.train.stages import titles

from test_learning import small_config, write_motions

pytestmark = pytest.mark.slow          # every test reads one training run (tb_run)

# One gesture of ~0.5 s, 2 fields at most, 4 candidates, 5 EM steps; success bars at 0 so
# that nothing counts as reproduced and every stage runs (path matching takes its 2
# steps); M fixed at 1, so that reduce tries a field (a motion not reproduced otherwise
# keeps its fields without a trial). Interrupted after 2 checkpoints (the end of "pool")
# and resumed, then run again once finished. A bad file beside the motion is skipped.
# ~10 s on one thread.
TB_OVERRIDES = ["log.tensorboard=true", "solver.each.max_fields=2", "solver.init.candidates=4",
                "solver.em.steps=5", "success.rmse=0", "success.tip=0", "model.fields=1"]
HEADLINE = {"0_overview/M", "0_overview/rmse_rad", "0_overview/worst_tip_cm", "0_overview/torque_cost"}


@pytest.fixture(scope="module")
def tb_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("tb_run")
    data, out = base / "data", base / "run"
    programs = gestures.random_gestures(1, seed=5, ranges={"duration": (0.5, 0.6)})
    write_motions(data, programs)
    (data / "broken.npz").write_bytes(b"not a motion")
    cfg = small_config(data, out, *TB_OVERRIDES)
    with pytest.raises(train.Interrupted):
        train.run(cfg, stop_after=2)
    metrics = train.run(cfg)
    files = sorted((out / "tensorboard").iterdir())
    again = train.run(cfg)                                        # finished: nothing new to log
    return {"out": out, "metrics": metrics, "name": programs[0].name, "duration": programs[0].duration,
            "again": again, "files": files, "broken": data / "broken.npz"}


def events(logdir, purge: bool = True) -> EventAccumulator:
    """Every event of the run folder; ``purge=False``: as written, without the reader's
    clean-up of steps that go back (so that the steps written can be checked)."""
    ea = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "histograms": 0, "images": 0,
                                                      "tensors": 0}, purge_orphaned_data=purge)
    ea.Reload()
    return ea


def test_tag_layout(tb_run):
    ea = events(tb_run["out"] / "tensorboard")
    scalars = set(ea.Tags()["scalars"])
    assert HEADLINE <= scalars
    assert sorted(scalars)[0].startswith("0_overview/")           # the headline group sorts first
    name = tb_run["name"]
    assert {f"motion/{name}/rmse_rad", f"motion/{name}/tip_cm", f"motion/{name}/torque_error_pct"} <= scalars
    # one curve per stage, none joining them; the old single-dot groups are gone
    assert {"torque_cost/each", "torque_cost/reduce", "path/loss", "reduce/removed"} <= scalars
    assert not any(t.startswith(("torque/", "each/", "hparam/", "rmse/", "tip/")) for t in scalars)
    last = {t: max(e.step for e in ea.Scalars(t)) for t in scalars}
    first = {t: min(e.step for e in ea.Scalars(t)) for t in scalars}
    assert last["torque_cost/each"] < first["torque_cost/reduce"] <= last["torque_cost/reduce"] \
        < first["path/loss"]
    assert len(ea.Scalars("torque_cost/reduce")) == 1 and len(ea.Scalars("path/loss")) == 2
    # M at every model change, the last one at the run's last step and equal to metrics.json's;
    # under one tag only
    metrics = json.loads((tb_run["out"] / "metrics.json").read_text())
    M = ea.Scalars("0_overview/M")
    assert len(M) >= 4
    assert M[-1].step == max(last.values()) and M[-1].value == metrics["overall"]["M"]
    assert not any(t.startswith("model/") for t in scalars)
    final = ea.Scalars("0_overview/rmse_rad")[-1]
    assert final.step == max(last.values())
    assert final.value == pytest.approx(metrics["overall"]["rmse"], rel=1e-6)
    # histograms at every model change; path figures at the stage ends
    for tag in ("weights/a", "weights/b", "stiffness/eigenvalues"):
        assert len(ea.Histograms(tag)) > 1
    assert len(ea.Images(f"paths/{name}")) >= 3


def test_one_run_with_hparams(tb_run):
    logdir = tb_run["out"] / "tensorboard"
    assert [p for p in logdir.rglob("*") if p.is_dir()] == []     # no timestamped sub-run
    assert len(list(logdir.glob("events.out.tfevents.*"))) == 2   # the first try and the resumed one
    assert sorted(logdir.iterdir()) == tb_run["files"]            # none from the finished run run again
    ea = events(logdir)
    content = ea.PluginTagToContent("hparams")
    assert {"_hparams_/experiment", "_hparams_/session_start_info"} <= set(content)
    exp = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"]).experiment
    assert {m.name.tag for m in exp.metric_infos} <= set(ea.Tags()["scalars"])
    start = plugin_data_pb2.HParamsPluginData.FromString(
        content["_hparams_/session_start_info"]).session_start_info
    # every key of the run's config, dotted, lists as their JSON text
    cfg = yaml.safe_load((tb_run["out"] / "config.yaml").read_text())
    assert set(start.hparams) == set(flat_hparams(cfg)) and len(start.hparams) > 50
    assert start.hparams["seed"].number_value == 0
    assert start.hparams["model.stiffness"].string_value == "diag"
    assert start.hparams["model.fields"].number_value == 1
    assert start.hparams["solver.em.steps"].number_value == 5
    assert start.hparams["solver.init.candidates"].number_value == 4
    assert start.hparams["log.tensorboard"].number_value == 1           # a bool, as torch writes it
    assert start.hparams["data"].string_value == cfg["data"]
    assert start.hparams["bvh.window"].string_value == "null"
    assert {m.name.tag for m in exp.metric_infos} == HEADLINE


def test_steps_monotone_across_resume(tb_run):
    """As written (no purging by the reader): every tag's steps strictly increase over
    both event files, the resumed run continuing where the checkpoint left off."""
    ea = events(tb_run["out"] / "tensorboard", purge=False)
    tags = ea.Tags()
    series = [ea.Scalars(t) for t in tags["scalars"]] + [ea.Histograms(t) for t in tags["histograms"]]
    series += [ea.Images(t) for t in tags["images"]]
    for s in series:
        steps = [e.step for e in s]
        assert steps == sorted(set(steps)), steps


def test_steps_are_the_global_iteration_count(tb_run):
    """The step of every entry is the run's global iteration count, the checkpoint's
    ``iteration``: the one motion is iteration 1, the pooled model's weights iteration 2,
    the elimination trial comes after its EM steps, the shooting pass, each Adam step and
    each rescue round are one, and the result's scoring is the last; a finished run run
    again logs nothing and counts no iteration."""
    ea = events(tb_run["out"] / "tensorboard")
    state = torch.load(tb_run["out"] / "checkpoint.pt", weights_only=True)
    assert [e.step for e in ea.Scalars("torque_cost/each")] == [1]
    assert [e.step for e in ea.Scalars("torque_cost/pool")] == [2]
    trial, = [e.step for e in ea.Scalars("torque_cost/reduce")]
    path = [e.step for e in ea.Scalars("path/loss")]
    assert trial >= 3 and path == [trial + 2, trial + 3]         # after the shooting pass
    rounds = len(tb_run["metrics"]["history"].get("rescue", []))
    assert [e.step for e in ea.Scalars("0_overview/M")][-1] == path[-1] + rounds + 1 == state["iteration"]
    assert tb_run["again"]["history"] == tb_run["metrics"]["history"]
    assert tb_run["again"]["overall"]["M"] == tb_run["metrics"]["overall"]["M"]


def test_a_skipped_file_is_reported(tb_run):
    """The bad file beside the motion is skipped: metrics.json and the summary name it
    and why."""
    skipped, = json.loads((tb_run["out"] / "metrics.json").read_text())["skipped"]
    assert skipped["file"] == str(tb_run["broken"]) and skipped["reason"]
    assert f"skipped {tb_run['broken']}: {skipped['reason']}" in summary_table(tb_run["metrics"]).splitlines()


def test_render_logs_images(tb_run, tmp_path, monkeypatch):
    """render's TensorBoard output is images (frames at steps, a contact sheet), with no
    video encoder: importing moviepy fails here."""
    run = tmp_path / "run"
    shutil.copytree(tb_run["out"], run, ignore=shutil.ignore_patterns("tensorboard"))
    monkeypatch.setitem(sys.modules, "moviepy", None)
    monkeypatch.setitem(sys.modules, "moviepy.editor", None)
    messages = []
    name = tb_run["name"]
    render.render(run, name, out=tmp_path / "a.gif", fps=10, log=messages.append)
    ea = events(run / "tensorboard")
    frames = ea.Images(f"render/{name}/frames")
    count = math.floor(tb_run["duration"] * 10 + 1e-9) + 1             # one per 1/fps over [0, λ]
    assert [e.step for e in frames] == list(range(count))
    assert frames[0].width > 100 and frames[0].height > 100
    strip, = ea.Images(f"render/{name}/strip")
    assert strip.width >= 2 * frames[0].width
    assert f"render/{name}/frames" in messages[0]


def test_progress_and_summary(tb_run, capsys):
    """The bars name the stage with its total; summary_table lists every motion and
    where the artefacts are."""
    log = RunLog(tb_run["out"], tensorboard=False, progress=True,
                 stages=titles(("each", "pool", "reduce", "path")))
    log.open()
    log.stage("each", 3)
    log.status(motion="a", M=2, cost=1e-4)
    log.close()
    err = capsys.readouterr().err
    assert "[1/4] each motion alone" in err and "1/3 motions" in err and "M=2" in err
    table = summary_table(tb_run["metrics"], tb_run["out"])
    lines = table.splitlines()
    assert lines[0].split()[:3] == ["motion", "rmse", "(rad)"]
    row = next(line for line in lines if line.startswith(tb_run["name"]))
    efolds = tb_run["metrics"]["motions"][tb_run["name"]]["growth_efolds"]
    assert row.split()[4] == f"{efolds:.2f}" and "growth (e-folds)" in lines[0]
    o = tb_run["metrics"]["overall"]
    assert f"M = {o['M']} fields" in table and f"at most {o['numbers_per_s']:.0f} numbers per second" in table
    assert o["numbers_per_s"] == max(m["numbers_per_s"] for m in tb_run["metrics"]["motions"].values()) > 0
    assert str(tb_run["out"]) in lines[-1] and "tensorboard/" in lines[-1]


def test_the_summary_says_why_a_motion_is_not_reproduced():
    """A motion not reproduced reads "simulation failed" where its simulation did, "nor by
    its own fit" where its own per-motion fit (history.each) failed it as well, and plain
    "no" where only the shared basis loses it."""
    def motion(success, failure=None):
        m = {"rmse": 0.01 if success else 0.2, "tip": 0.01, "torque_rel_rms": 0.1, "growth_efolds": 3.0,
             "success": success, "numbers_per_s": 20.0}
        return {**m, "failure": failure} if failure else m
    metrics = {"motions": {"a": motion(True), "b": motion(False), "c": motion(False),
                           "d": motion(False, "simulation failed (budget)")},
               "overall": {"rmse": 0.1, "tip": 0.01, "torque_rel_rms": 0.1, "growth_efolds": 3.0,
                           "success": False, "M": 2, "numbers_per_s": 20.0, "wall_time_s": 5.0},
               "history": {"each": {"reproduced": [True, True, False, False]}}}
    cells = {line.split()[0]: line.split(None, 5)[5] for line in summary_table(metrics).splitlines()
             if line[:1] in "abcd" and len(line.split()) > 5}
    assert cells == {"a": "yes", "b": "no", "c": "no: nor by its own fit", "d": "no: simulation failed"}
    del metrics["history"]
    assert "nor by its own fit" not in summary_table(metrics)
