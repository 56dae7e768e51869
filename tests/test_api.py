"""The public API: every name ``tflearn`` exports resolves, light modules stay light, the
README's library example runs as written, and the code is lint-clean (ruff)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import tflearn

ROOT = Path(__file__).resolve().parents[1]


def test_every_exported_name_resolves():
    for name in tflearn.__all__:
        assert getattr(tflearn, name) is not None, name
    assert set(tflearn.__all__) <= set(dir(tflearn))


def test_config_and_cli_import_without_torch():
    """Argument parsing and config validation need no torch (so that --help and bad
    input answer at once)."""
    code = ("import sys, tflearn, tflearn.config, tflearn.cli, tflearn.errors; "
            "tflearn.config.load(None, ['seed=3']); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.slow
def test_readme_library_example_runs():
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"Library use:\n\n```python\n(.*?)```", readme, re.S)
    assert block, "README has a 'Library use' python block"
    scope: dict = {}
    exec(compile(block.group(1), "README.md", "exec"), scope)
    assert scope["path"].q.shape == (1, 301, 7)


def test_ruff_is_clean():
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "tflearn", "tests", "bench"],
                         cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-3000:]
