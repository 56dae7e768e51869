"""What the benchmarks record: the checked-out commit of this tree, and their JSON
written (imported by the scripts beside it, which run as ``python bench/NAME.py`` with
this folder on the path)."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True,
                              text=True).stdout.strip()
    except OSError:                                  # no git here
        return ""


def head() -> str:
    """The short hash of HEAD ("" where git cannot tell)."""
    return _git("rev-parse", "--short", "HEAD")


def dirty() -> bool:
    """Whether tflearn/ has uncommitted changes."""
    return bool(_git("status", "--porcelain", "--", "tflearn"))


def write_json(path: Path | str | None, doc) -> None:
    """``doc`` as indented JSON at ``path``, its folder made; nothing where ``path`` is None."""
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))
