"""The main job, `train configs/gestures.yaml`, timed now and at an earlier revision in one
invocation (same machine, same moment), with what each run found: M, how many gestures
were reproduced, the worst joint RMSE and tip error, and whether the two basis.json files
agree.

Each run is a fresh process in its own output folder (progress bars off); the earlier
revision runs from a temporary git worktree with that tree first on the Python path.
``--launcher`` prefixes the current tree's command (e.g. ``"torchrun --nproc-per-node 2"``
for a distributed run, when the package supports it) and adds that as a third run;
each ``--variant KEY=VALUE`` adds a run of the current tree with that config override.

    python bench/main_job.py --ref 607d0dd --out runs/bench/main_job.json
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import revision

ROOT = Path(__file__).resolve().parents[1]


def run_train(tree: Path, out: Path, prefix=(), overrides=()) -> dict:
    """Run the main job of ``tree`` into ``out`` (with config ``overrides``); wall time
    and the run's metrics."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    cmd = [*prefix, "-m", "tflearn.cli"] if prefix else [sys.executable, "-m", "tflearn.cli"]
    cmd += ["train", "configs/gestures.yaml", f"out={out}", "log.progress=false", *overrides]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, cwd=tree, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    m = json.loads((out / "metrics.json").read_text())
    motions = m["motions"]
    return {"wall_s": wall, "M": m["overall"]["M"],
            "reproduced": sum(bool(x["success"]) for x in motions.values()),
            "motions": len(motions),
            "worst_rmse_rad": max(x["rmse"] for x in motions.values()),
            "worst_tip_m": max(x["tip"] for x in motions.values()),
            "basis": json.loads((out / "basis.json").read_text())}


def max_difference(a, b) -> float:
    """The largest absolute difference between two JSON documents' numbers, over the keys
    both hold (a later basis format adds keys; inf where lists differ in length or a value
    in type)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return max((max_difference(a[k], b[k]) for k in a.keys() & b.keys()), default=0.0)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return float("inf")
        return max((max_difference(x, y) for x, y in zip(a, b)), default=0.0)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return abs(float(a) - float(b))
    return 0.0 if a == b else float("inf")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ref", required=True, help="the earlier git revision")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--launcher", help="a command prefix for a third run of the current tree")
    p.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                   help="one more run of the current tree with this config override (repeatable)")
    args = p.parse_args(argv)
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ref_tree = tmp / "ref"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(ref_tree), args.ref],
                       check=True, capture_output=True)
        try:
            runs["reference"] = run_train(ref_tree, tmp / "run-ref")
            runs["current"] = run_train(ROOT, tmp / "run-now")
            if args.launcher:
                runs["launcher"] = run_train(ROOT, tmp / "run-launcher", shlex.split(args.launcher))
            for i, v in enumerate(args.variant):
                runs[f"variant {v}"] = run_train(ROOT, tmp / f"run-variant{i}", overrides=[v])
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(ref_tree)],
                           check=True, capture_output=True)
    bases = {name: r.pop("basis") for name, r in runs.items()}
    for name, r in runs.items():
        if name != "reference":
            r["basis_max_difference"] = max_difference(bases["reference"], bases[name])
            r["speedup"] = runs["reference"]["wall_s"] / r["wall_s"]
        if name not in ("reference", "current"):
            r["basis_vs_current"] = max_difference(bases["current"], bases[name])
    doc = {"ref": args.ref, "commit": revision.head(), "launcher": args.launcher, "runs": runs,
           "cores": os.cpu_count()}
    revision.write_json(args.out, doc)
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
