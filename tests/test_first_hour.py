"""What a new user meets in the first hour: artefacts readable by colleagues, one run per
output folder, Ctrl-C as one line, progress on the long commands, errors that name the
right file once, and a --help that lists each command once."""
from __future__ import annotations

import os
import re
import select
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tflearn import cli
from tflearn.io import files

ROOT = Path(__file__).resolve().parents[1]
CODE_ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


# ------------------------------------------------------------------ 1. permissions

@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_artefacts_get_the_permissions_of_a_plain_open(tmp_path, umask, mode):
    """A new artefact is 0o666 less the umask, as ``open(path, "w")`` makes it; a
    rewritten one keeps its own permissions."""
    old = os.umask(umask)
    try:
        files.write_text(tmp_path / "new.json", "{}")
        with open(tmp_path / "plain.json", "w") as f:
            f.write("{}")
        (tmp_path / "kept.json").write_text("old")
        os.chmod(tmp_path / "kept.json", 0o640)
        files.write_text(tmp_path / "kept.json", "new")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == mode
    assert stat.S_IMODE((tmp_path / "plain.json").stat().st_mode) == mode
    assert stat.S_IMODE((tmp_path / "kept.json").stat().st_mode) == 0o640
    assert (tmp_path / "kept.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.json", "new.json", "plain.json"]


# ------------------------------------------------------------------ 2. one run per folder

HOLD = ("import sys\nfrom tflearn.io.files import locked\n"
        "with locked(sys.argv[1]):\n    print('held', flush=True)\n    sys.stdin.read()\n")


def _holder(out: Path) -> subprocess.Popen:
    """Another process holding ``out``'s lock until its stdin closes (or it is killed)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env=CODE_ENV)
    assert proc.stdout.readline().strip() == "held"
    return proc


@pytest.mark.slow
def test_a_second_train_into_a_locked_folder_is_refused(tmp_path):
    """While another process writes into OUT, ``train ... out=OUT`` exits with status 2
    and one line naming OUT and the holder's pid, and touches nothing there."""
    out = tmp_path / "run"
    holder = _holder(out)
    try:
        res = subprocess.run([sys.executable, "-m", "tflearn.cli", "train",
                              str(ROOT / "configs" / "gestures.yaml"), f"out={out}", "--quiet"],
                             capture_output=True, text=True, env=CODE_ENV, timeout=120)
        assert sorted(p.name for p in out.iterdir()) == [files.LOCK_FILE]
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert err == (f"tflearn: {out}: another process (pid {holder.pid}) is writing into this folder; "
                   f"wait for it to end, or choose another output folder")
    assert not out.exists()           # the holder made it, and removed it empty


def test_a_killed_runs_lock_is_taken_over(tmp_path):
    """A lock file left behind — by a run killed with SIGKILL, or with any pid in it — does
    not stop the next run: the lock is the operating system's and died with its holder."""
    out = tmp_path / "run"
    holder = _holder(out)
    holder.kill()
    holder.wait(timeout=30)
    assert (out / files.LOCK_FILE).read_text().strip() == str(holder.pid)
    with files.locked(out) as path:
        assert path.read_text() == f"{os.getpid()}\n"
        (out / "basis.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == ["basis.json"]
    # a stale lock file with a pid in it, then train: it gets past the lock to the data
    (out / files.LOCK_FILE).write_text("999999\n")
    assert cli.train_main([str(ROOT / "configs" / "gestures.yaml"), f"out={out}", "--quiet",
                           f"data={tmp_path / 'nowhere'}"]) == 2
    assert sorted(p.name for p in out.iterdir()) == ["basis.json"]


def test_lock_in_the_same_process_and_its_folders(tmp_path):
    """Two locks on one folder exclude each other even within a process; a folder made
    for the lock is removed again when nothing was written into it."""
    out = tmp_path / "a" / "b"
    with files.locked(out):
        with pytest.raises(files.FolderLocked, match=f"pid {os.getpid()}"):
            with files.locked(out):
                pass
    assert not (tmp_path / "a").exists()


# ------------------------------------------------------------------ 3. Ctrl-C

def _interrupt(code: str, marker: str, presses: int = 1, stream: str = "stdout") -> tuple:
    """Run ``code`` (Python) in a subprocess, press Ctrl-C (SIGINT) once ``marker``
    appears on ``stream`` (``presses`` times, 0.3 s apart): (exit status, stderr)."""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=CODE_ENV)
    watched = proc.stdout if stream == "stdout" else proc.stderr
    seen, other = b"", b""
    deadline = time.monotonic() + 120
    while marker.encode() not in seen:
        assert time.monotonic() < deadline and proc.poll() is None, (seen, other)
        ready, _, _ = select.select([watched], [], [], 1.0)
        if ready:
            seen += os.read(watched.fileno(), 65536)
    for k in range(presses):
        time.sleep(0.3 if k else 0.0)
        proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    text = (seen + err if stream == "stderr" else err).decode("utf-8", "replace")
    return proc.returncode, text


# a long wait made of short sleeps: a signal that the kernel hands to another thread of
# the process (torch starts some) is acted on by the main thread between two calls, so
# one time.sleep(60) would hold a Ctrl-C up to a minute (seen once, 64 s in a fresh clone)
SLOW = """import sys, time
from tflearn import cli
from tflearn.data import gestures
def wait(seconds):
    for _ in range(int(seconds * 10)):
        time.sleep(0.1)
def slow(*args, **kw):
{body}
gestures.write = slow
sys.exit(cli.main(["gestures", "--out", sys.argv[1] if len(sys.argv) > 1 else "unused"]))
"""


@pytest.mark.parametrize("case", ["plain", "turned into another error", "pressed twice"])
def test_ctrl_c_is_one_line_and_status_130(case):
    """Ctrl-C: exit status 130 and one line, never a traceback — also when a library
    turns the KeyboardInterrupt into another exception (as drawing a figure did), and
    when a second Ctrl-C comes while the first one unwinds."""
    body = {"plain": "    print('started', flush=True)\n    wait(60)",
            "turned into another error": ("    try:\n        print('started', flush=True)\n"
                                          "        wait(60)\n"
                                          "    except KeyboardInterrupt:\n"
                                          "        raise RuntimeError('the figure was not drawn')"),
            "pressed twice": ("    try:\n        print('started', flush=True)\n        wait(60)\n"
                              "    finally:\n        wait(60)")}[case]
    code, err = _interrupt(SLOW.format(body=body), "started", presses=2 if case == "pressed twice" else 1)
    assert code == 130
    assert err == "tflearn: interrupted\n"


@pytest.mark.slow
def test_ctrl_c_during_training(tmp_path):
    """``tflearn train`` interrupted while it fits: one line saying that re-running
    resumes, exit status 130, the checkpoint kept, the folder's lock released."""
    out = tmp_path / "run"
    code = (f"import sys\nfrom tflearn import cli\nsys.exit(cli.main(['train', "
            f"{str(ROOT / 'configs' / 'gestures.yaml')!r}, 'out={out}', 'log.tensorboard=false']))")
    status, err = _interrupt(code, "motions [", stream="stderr")
    assert status == 130, err
    assert "Traceback" not in err and "bug" not in err
    assert err.rstrip().splitlines()[-1] == "tflearn: interrupted, re-run to resume"
    assert not (out / files.LOCK_FILE).exists()


# ------------------------------------------------------------------ 4. progress

def test_progress_bars_of_modes(tmp_path, capsys):
    """``tflearn modes``: a bar over its steps (each animated mode, the combined motion,
    each figure) on stderr; none with --quiet."""
    cfg = ROOT / "configs" / "modes" / "linear_creature.yaml"
    argv = ["modes", str(cfg), "animation.modes=1", "log.tensorboard=false", "--out", str(tmp_path / "m")]
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert re.search(r"modes: 100%\|.*\| 3/3 steps", err), err
    assert cli.main([*argv, "--quiet"]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.slow
def test_progress_bars_of_render_and_perturb(tiny_run, tmp_path, capsys):
    """``render``: a bar over the frames; ``perturb``: over the simulations (the
    unperturbed one and one per case, per controller) and each motion's figures."""
    run, name = tiny_run["run"], tiny_run["programs"][0].name
    assert cli.main(["render", str(run), "--motion", name, "--fps", "10", "--no-tensorboard",
                     "--out", str(tmp_path / "a.gif")]) == 0
    err = capsys.readouterr().err
    assert re.search(rf"render {name}: 100%\|.*\| (\d+)/\1 frames", err), err
    assert cli.main(["perturb", str(run), "--motion", name, "--controller", "fields", "--force", "1,0,0",
                     "--at", "0.1", "--no-animation", "--out", str(tmp_path / "p")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"perturb: 100%\|.*\| 3/3 steps", err), err      # unperturbed, the push, figures
    assert cli.main(["perturb", str(run), "--motion", name, "--controller", "fields", "--quiet",
                     "--no-animation", "--out", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().err == ""


def test_progress_bar_of_an_experiments_cases(tmp_path, monkeypatch, capsys):
    """The case runner counts the cases (those cached from an earlier run as done)."""
    from tflearn.experiments import common
    from tflearn.experiments.config import ExperimentConfig
    cfg = ExperimentConfig(experiment="basin", out=str(tmp_path), jobs=1)
    cases = [("noised", "tuck", 1.2, s) for s in range(3)]
    common.case_file(cfg, cases[0]).parent.mkdir(parents=True)
    files.write_text(common.case_file(cfg, cases[0]), "[]")
    row = {"method": "slsqp", "success": [True]}
    monkeypatch.setattr(common, "run_case", lambda case: [row])
    assert common.run_cases(cfg, cases) == [row, row]
    err = capsys.readouterr().err
    assert re.search(r"basin: 100%\|.*\| 3/3 cases", err) and "slsqp 1/1" in err, err


# ------------------------------------------------------------------ 6., 7. errors once, the right file

SMALL_TRUNCATED = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 3 Xposition Yposition Zposition
  End Site
  {
    OFFSET 0 -5 0
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3
"""


def test_bvh_import_of_a_truncated_clip(tmp_path, capsys):
    """One line naming the file and the problem, no "created" line, no folder."""
    clip = tmp_path / "clip.bvh"
    clip.write_text(SMALL_TRUNCATED)
    out = tmp_path / "imported"
    assert cli.main(["bvh", "import", str(clip), "--out", str(out)]) == 2
    printed = capsys.readouterr()
    assert printed.err == f"tflearn: {clip}: truncated: 'Frames: 2' but only 1 frame lines " \
                          f"(the file ends at line 14)\n"
    assert printed.out == "" and not out.exists()


def test_bvh_import_that_writes_nothing_leaves_no_folder(mocap, tmp_path, capsys):
    """A window no clip is as long as: one error line, no "created", no folder."""
    out = tmp_path / "imported"
    clip = mocap / "dataset-1_guide_normal_001.bvh"
    with pytest.warns(UserWarning, match="ends after the clip"):
        assert cli.main(["bvh", "import", str(clip), "--out", str(out), "--window", "0", "1000"]) == 2
    printed = capsys.readouterr()
    assert printed.err == f"tflearn: {out}: no clip is as long as the window [0.0, 1000.0] s\n"
    assert printed.out == "" and not out.exists()


def test_evaluate_names_the_missing_run(tmp_path, capsys, monkeypatch):
    """``tflearn evaluate runs/nope``: one line naming runs/nope (or RUN/basis.json for a
    folder without one), exit 2, no folder made."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(["evaluate", "runs/nope"]) == 2
    assert capsys.readouterr().err == "tflearn: runs/nope: no such run folder or basis.json\n"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "runs" / "empty").mkdir(parents=True)
    for command in (["evaluate", "runs/empty"], ["render", "runs/empty", "--motion", "a"],
                    ["simulate", "runs/empty", "--motion", "a", "--out", "x/a.npz"]):
        assert cli.main(command) == 2
        err = capsys.readouterr().err
        assert err == ("tflearn: runs/empty/basis.json: no such file (is runs/empty a run folder "
                       "written by train?)\n"), command
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["empty", "runs"]


# ------------------------------------------------------------------ 8. help

def test_help_lists_each_command_once(capsys):
    """``tflearn --help``: every command exactly once, with its help; ``experiment
    --help`` names every registered experiment."""
    from tflearn.experiments import NAMES
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    text = capsys.readouterr().out
    parser = cli.build_parser()
    commands = parser._subparsers._group_actions[0].choices
    assert len(commands) >= 10
    for name in commands:
        assert len(re.findall(rf"^  {re.escape(name)} ", text, re.M)) == 1, (name, text)
    assert len(re.findall(r"^  \S", text.split("options:")[0], re.M)) == len(commands)
    with pytest.raises(SystemExit):
        cli.main(["experiment", "--help"])
    text = capsys.readouterr().out
    assert text.startswith("usage: tflearn experiment ")
    assert set(NAMES) >= {"basin", "shared", "keyframes", "filtering", "reaches"}
    for name in NAMES:
        assert name in text, name
