"""Resuming training: interrupted in-process and killed (SIGKILL) as a real process at
several moments, a re-run of the same command ends with the uninterrupted run's
basis.json; checkpoints are plain tensors (``weights_only``) and refuse another version
or another config; artefacts are never half written."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tflearn import train

from test_learning import SMALL_OVERRIDES, assert_same_basis, small_config, small_run


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return small_run(tmp_path_factory)       # the run shared with test_learning.py


@pytest.mark.slow
def test_resume_after_interrupt(run_dir, tmp_path):
    """Interrupted after 1 checkpoint (inside stage "each"), then after 2 more (at the end
    of "pool"), then after 2 more (inside "reduce"), then resumed to the end: basis.json
    equals the uninterrupted run's (measured: identical, max |Δ| = 0); the simulations
    counted over the resumes are the uninterrupted run's, plus at most one per resume:
    elimination checks a window of trials in one batch (``solver.path.batch: each``), and
    a run stopped inside the window simulates the rest of it again (measured: 158
    against 157)."""
    out = tmp_path / "resumed"
    cfg = small_config(run_dir["data"], out)
    stops = []
    for k in (1, 2, 2):
        with pytest.raises(train.Interrupted):
            train.run(cfg, stop_after=k)
        state = torch.load(out / "checkpoint.pt", weights_only=True)
        stops.append((state["stage"], state["cursor"]))
        assert not (out / "basis.json").exists()
    assert stops[0] == ("each", 1)
    assert stops[1] == ("reduce", 0)
    assert stops[2][0] == "reduce" and stops[2][1] == 2
    metrics = train.run(cfg)
    assert_same_basis(out / "basis.json", run_dir["out"] / "basis.json")
    ref = json.loads((run_dir["out"] / "metrics.json").read_text())
    for name, row in ref["motions"].items():
        for key in ("rmse", "tip", "torque_rel_rms"):
            assert abs(metrics["motions"][name][key] - row[key]) <= 1e-12
    assert metrics["overall"]["M"] == ref["overall"]["M"]
    assert metrics["history"] == ref["history"]
    # cost over the four processes: each simulation counted once, a window's batch redone
    one, resumed = ref["overall"]["simulations"], metrics["overall"]["simulations"]
    assert 0 < one <= resumed <= one + 3


def _train_command(config: Path, data: Path, out: Path) -> list:
    return [sys.executable, "-m", "tflearn.cli", "train", str(config), f"data={data}",
            f"out={out}", *SMALL_OVERRIDES]


def _wait_for(predicate, proc, timeout=120.0):
    """Poll until ``predicate()`` holds (True) or the process ends (False)."""
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.02)
    raise TimeoutError("the training process made no progress")


def _checkpoint_stage(out: Path):
    try:
        return torch.load(out / "checkpoint.pt", weights_only=True)["stage"]
    except Exception:
        return None


@pytest.mark.slow
def test_sigkill_at_several_moments_then_rerun(run_dir, tmp_path):
    """A real ``tflearn train`` process killed with SIGKILL while it fits the first
    motion (no checkpoint yet), right after the first checkpoint, once it reaches the
    reduce stage, and while it writes its artefacts; after each kill every file in the
    output folder is whole (the checkpoint loads, no stray temporary file is taken for
    an artefact), and re-running the same command ends with the uninterrupted run's
    basis.json (fields and weights to 1e-6; measured: identical)."""
    cfg_file = tmp_path / "empty.yaml"
    cfg_file.write_text("")
    out = tmp_path / "killed"
    cmd = _train_command(cfg_file, run_dir["data"], out)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    moments = [
        ("before any checkpoint", lambda: out.exists()),
        ("after the first checkpoint", lambda: (out / "checkpoint.pt").exists()),
        ("in the reduce stage", lambda: _checkpoint_stage(out) in ("reduce", "path", "done")),
        ("while writing artefacts", lambda: (out / "figures").exists()),
    ]
    killed = []
    for what, reached in moments:
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            if _wait_for(reached, proc):
                proc.send_signal(signal.SIGKILL)
                killed.append(what)
        finally:
            proc.wait(timeout=60)
        if (out / "checkpoint.pt").exists():
            torch.load(out / "checkpoint.pt", weights_only=True)    # whole, never half written
        for name in ("basis.json", "metrics.json"):
            if (out / name).exists():
                json.loads((out / name).read_text())
    assert len(killed) >= 3, killed
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert_same_basis(out / "basis.json", run_dir["out"] / "basis.json", tol=1e-6)
    assert not list(out.rglob(".*.tmp*"))


@pytest.mark.slow
def test_checkpoint_is_plain_data(run_dir):
    """The checkpoint loads with ``weights_only=True`` (no pickled objects)."""
    state = torch.load(run_dir["out"] / "checkpoint.pt", weights_only=True)
    assert state["format"] == train.CHECKPOINT_FORMAT and state["stage"] == "done"


@pytest.mark.slow
def test_checkpoint_of_other_config_refused(run_dir):
    out = run_dir["out"]
    before = (out / "checkpoint.pt").read_bytes()
    cfg = small_config(run_dir["data"], out, "seed=1", "solver.em.tol=1e-7")
    with pytest.raises(train.CheckpointError, match=r"\(seed, solver\.em\.tol differ\)") as err:
        train.run(cfg)
    assert str(out / "checkpoint.pt") in str(err.value)
    assert (out / "checkpoint.pt").read_bytes() == before


@pytest.mark.slow
def test_a_run_resumes_whatever_its_log_settings(run_dir):
    """log.* says how a run shows its progress, not what it computes: a finished run run
    again with other log settings is the same run, its basis unchanged."""
    before = (run_dir["out"] / "basis.json").read_bytes()
    finished = json.loads((run_dir["out"] / "metrics.json").read_text())
    cfg = small_config(run_dir["data"], run_dir["out"], "log.progress=true", "log.figures=1")
    metrics = train.run(cfg)
    assert metrics["overall"]["M"] == finished["overall"]["M"]
    assert metrics["history"] == finished["history"]
    assert (run_dir["out"] / "basis.json").read_bytes() == before


@pytest.mark.slow
def test_checkpoint_from_before_a_config_key_resumes(run_dir, tmp_path):
    """A checkpoint written before a config key existed (its config lacks the key) ran as
    the key's default does: it resumes under the default, and is refused, naming the key,
    under another value."""
    import shutil
    out = tmp_path / "run"
    shutil.copytree(run_dir["out"], out)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    state["config"]["out"] = str(out)
    del state["config"]["device"], state["config"]["solver"]["shooting"]["tip_weight"]
    torch.save(state, out / "checkpoint.pt")
    metrics = train.run(small_config(run_dir["data"], out))
    before = json.loads((run_dir["out"] / "metrics.json").read_text())
    assert metrics["overall"]["M"] == before["overall"]["M"]
    assert_same_basis(out / "basis.json", run_dir["out"] / "basis.json", tol=0.0)
    with pytest.raises(train.CheckpointError, match=r"\(solver\.shooting\.tip_weight differ\)"):
        train.run(small_config(run_dir["data"], out, "solver.shooting.tip_weight=5"))


def test_config_changes_names_dotted_keys():
    old = {"seed": 0, "solver": {"em": {"tol": 1e-6, "steps": 30}}, "body": {"preset": "arm"}}
    new = {"seed": 0, "solver": {"em": {"tol": 1e-6, "steps": 40}}, "body": {"preset": "leg"},
           "device": "cuda"}
    assert train.config_changes(old, new) == ["body", "device", "solver.em.steps"]
    assert train.config_changes(old, old) == []


@pytest.mark.slow
@pytest.mark.parametrize("content,problem", [
    ({"format": "tflearn-checkpoint/1", "stage": "each"}, "another tflearn version"),
    ({"stage": "each", "cursor": 0}, "another tflearn version"),
    ({"format": train.CHECKPOINT_FORMAT, "stage": "each"}, "not a complete checkpoint"),
    (b"\x00garbage", "not a readable checkpoint"),
])
def test_bad_checkpoints_refused(run_dir, tmp_path, content, problem):
    """A checkpoint of another version, an incomplete one, or random bytes: a
    CheckpointError naming the file, nothing written."""
    out = tmp_path / "run"
    out.mkdir()
    ckpt = out / "checkpoint.pt"
    if isinstance(content, bytes):
        ckpt.write_bytes(content)
    else:
        torch.save(content, ckpt)
    with pytest.raises(train.CheckpointError, match=problem) as err:
        train.run(small_config(run_dir["data"], out))
    assert str(ckpt) in str(err.value)
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]


@pytest.mark.slow
def test_pickled_checkpoint_is_not_loaded(run_dir, tmp_path):
    """A checkpoint that would need pickle (an arbitrary object) is refused, not run."""
    out = tmp_path / "run"
    out.mkdir()
    torch.save({"format": train.CHECKPOINT_FORMAT, "payload": Path("x")}, out / "checkpoint.pt")
    with pytest.raises(train.CheckpointError, match="not a readable checkpoint"):
        train.run(small_config(run_dir["data"], out))
