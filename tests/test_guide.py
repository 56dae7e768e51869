"""docs/guide.md runs as written: its ```python blocks are exec'd in one namespace and its
```bash blocks run in a shell, in order, in an empty folder; after each block the files
its ``<!-- creates: ... -->`` comment names must exist.

In bash blocks ``train`` and ``tflearn`` at the start of a command become
``python -m tflearn.cli train`` / ``python -m tflearn.cli`` with this checkout first on
PYTHONPATH (the console scripts may belong to another install). About 50 s of CPU on the
2-core test machine (75 s wall while other jobs ran).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide.md"

BLOCK = re.compile(r"^```(python|bash)\n(.*?)^```\n(?:\s*<!-- creates: (.*?) -->)?", re.S | re.M)
COMMAND = re.compile(r"^(\s*)(train|tflearn)\b", re.M)


def steps(text: str) -> list:
    """(language, code, files it creates) of each runnable block, in order."""
    return [(lang, code, (creates or "").split()) for lang, code, creates in BLOCK.findall(text)]


def shell(code: str) -> str:
    """A bash block with the CLI run as ``python -m tflearn.cli`` from this checkout."""
    py = sys.executable

    def sub(m):
        return f"{m.group(1)}{py} -m tflearn.cli" + (" train" if m.group(2) == "train" else "")
    return COMMAND.sub(sub, code)


def test_guide_parses():
    found = steps(GUIDE.read_text())
    langs = [lang for lang, _, _ in found]
    assert "python" in langs and "bash" in langs
    bash = "\n".join(code for lang, code, _ in found if lang == "bash")
    for command in ("train ", "tflearn evaluate", "tflearn render", "tflearn simulate"):
        assert command in bash, command
    assert "--data" in bash
    assert shell("train x.yaml\ntflearn evaluate r").count("-m tflearn.cli") == 2
    assert "docs/guide.md" in (ROOT / "README.md").read_text()


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::UserWarning")
def test_guide_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()          # the guide sets one thread; restored below
    env = dict(os.environ, MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    scope: dict = {"__name__": "guide"}
    for i, (lang, code, creates) in enumerate(steps(GUIDE.read_text())):
        where = f"docs/guide.md block {i + 1} ({lang})"
        if lang == "python":
            exec(compile(code, where, "exec"), scope)
        else:
            out = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", shell(code)], cwd=tmp_path,
                                 env=env, capture_output=True, text=True, timeout=300)
            assert out.returncode == 0, f"{where} failed:\n{code}\n{out.stdout}\n{out.stderr}"
        for name in creates:
            assert (tmp_path / name).is_file(), f"{where} did not create {name}"
    torch.set_num_threads(threads)


# a commit hash: 7 to 40 hex digits with a letter and a digit
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def test_docs_state_current_figures():
    """The README and docs/ name no commits (each figure is stated as last measured, with
    its command); docs/history.md alone keeps the revisions and earlier measurements."""
    pages = [ROOT / "README.md", ROOT / "bench" / "benchmarks_notes.md",
             *sorted((ROOT / "docs").glob("*.md"))]
    for page in pages:
        if page.name != "history.md":
            hit = COMMIT.search(page.read_text())
            assert hit is None, f"{page.relative_to(ROOT)} names {hit.group(0)}: move it to docs/history.md"
    assert COMMIT.search((ROOT / "docs" / "history.md").read_text())
