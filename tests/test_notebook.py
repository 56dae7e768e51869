"""notebooks/analysis.ipynb: committed without outputs, and executed end to end (nbclient,
the ``python3`` kernel of the interpreter running the tests) on the small run shared with
test_learning.py and test_cli.py (measured on the 2-core test machine: 15 s to train it
when this module runs alone, 9 s to execute the notebook)."""
from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import ipykernel  # noqa: F401  (test dependencies: a missing one is an error, not a skip)
import nbclient
import nbformat
import pytest

from test_learning import small_run

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "analysis.ipynb"

# Appended to the executed copy only: the notebook's own results, for the checks below.
PROBE = """
import json
print("PROBE " + json.dumps({"name": name, "rmse": sim.rmse[0], "tip": sim.tip[0],
                             "end_shift": end_shift, "tip_shift": tip_shift}))
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return small_run(tmp_path_factory)       # the run shared with test_learning.py


def test_notebook_is_committed_clean():
    """No outputs or execution counts in the repository; the first code cell is the
    parameters cell reading TFLEARN_RUN."""
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    for cell in code:
        assert cell.outputs == [] and cell.execution_count is None, cell.source[:60]
    assert "parameters" in code[0].metadata.get("tags", [])
    assert 'os.environ.get("TFLEARN_RUN", "runs/gestures")' in code[0].source
    assert nb.metadata["kernelspec"]["name"] == "python3"


def _outputs(nb) -> dict:
    """Markdown, text and decoded PNG outputs of an executed notebook, in order."""
    out = {"markdown": [], "text": [], "png": []}
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            assert o.output_type != "error", "".join(o.get("traceback", []))
            if o.output_type == "stream":
                out["text"].append(o.text)
            elif o.output_type in ("display_data", "execute_result"):
                data = o.get("data", {})
                if "image/png" in data:
                    out["png"].append(base64.b64decode(data["image/png"]))
                elif "text/markdown" in data:
                    out["markdown"].append(data["text/markdown"])
                elif "text/plain" in data:
                    out["text"].append(data["text/plain"])
    return out


@pytest.mark.slow
def test_notebook_executes(run_dir, monkeypatch):
    """The notebook runs without error on a run given by a path relative to the
    repository root (the kernel starts in notebooks/); it shows the fields and weights
    tables, a figure per field plus the weights, trajectories, hand paths and edited
    hand paths; its re-simulation of the first motion matches metrics.json, the
    edited program (a × 1.5) moves the end posture, and its table of the fields' modes
    has the frequencies of tflearn.modes.analysis.field_modes on basis.json."""
    run = run_dir["out"]
    lb = json.loads((run / "basis.json").read_text())
    ref = json.loads((run / "metrics.json").read_text())
    M, names = len(lb["fields"]), [m["name"] for m in lb["motions"]]
    monkeypatch.setenv("TFLEARN_RUN", os.path.relpath(run, ROOT))
    monkeypatch.delenv("TFLEARN_MOTION", raising=False)

    nb = nbformat.read(NOTEBOOK, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(PROBE))
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=300,
                                     resources={"metadata": {"path": str(NOTEBOOK.parent)}})
    client.execute()
    out = _outputs(nb)

    fields = [t for t in out["markdown"] if t.startswith("| field |")]
    assert len(fields) == 1
    assert [line.split("|")[1].strip() for line in fields[0].splitlines()[2:]] == \
        [str(i) for i in range(M)]
    weights = [t for t in out["markdown"] if t.startswith("| motion |")]
    assert len(weights) == 1
    rows = weights[0].splitlines()[2:]
    assert [r.split("|")[1].strip() for r in rows] == names
    for row, name in zip(rows, names):
        assert f"| {ref['motions'][name]['rmse']:.4f} |" in row

    modes = [t for t in out["markdown"] if t.startswith("| modes of field |")]
    assert len(modes) == 1
    from tflearn.modes import analysis as md
    from tflearn.physics.body import from_dict
    want = md.field_modes(from_dict(lb["body"]), [f["eta"] for f in lb["fields"]],
                          [f["K"] for f in lb["fields"]])
    for line, fm in zip(modes[0].splitlines()[2:], want, strict=True):
        assert line.split("|")[2].strip() == " ".join(f"{f:.2f}" for f in fm.frequencies[:4])

    assert len(out["png"]) >= M + 4     # fields, weights, trajectories, hand paths, edited
    assert all(png.startswith(b"\x89PNG") for png in out["png"])

    text = "".join(out["text"])
    assert f"M = {M} fields" in text and "end posture moved" in text
    probe = json.loads(text.split("PROBE ", 1)[1].splitlines()[0])
    assert probe["name"] == names[0]
    row = ref["motions"][names[0]]
    assert abs(probe["rmse"] - row["rmse"]) <= 1e-6 and abs(probe["tip"] - row["tip"]) <= 1e-6
    assert probe["tip_shift"] > 1e-3 and max(probe["end_shift"].values()) > 1e-3
