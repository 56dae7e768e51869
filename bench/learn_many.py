"""Many motions learned end to end: N random supported programs
(:func:`tflearn.data.gestures.random_gestures`, each stepped alone by the compiled simulator at
rtol = atol = 1e-12 and sampled at the lowest of 100·2ᵏ Hz that resolves it,
:func:`tflearn.data.gestures.generate_resolved` — the data condition of the supported box —,
written as NAME.npz with its generating program beside it as NAME.json), then the main
job's configuration on them, ``train configs/gestures.yaml data=DIR``, in a fresh process:
the wall time of making them and of training, each stage's share (from the progress
bars), M, how many motions simulation reproduces, the worst joint RMSE and tip error, how
many fields were pooled, how many the selection chose (:mod:`tflearn.fit.select`) and how
many motions got fields of their own back (and how many of those fitted copies), how
many of the G generating fields a learned field
matches (metrics.json's ``identity``, :mod:`tflearn.fit.identity`) and the worst centre
distance and stiffness error |r − 1| among those, the training process' peak memory, and
the fitted exponent of each time (cost ∝ N^p, least squares on log–log). One torch thread.

    python bench/learn_many.py --sizes 5,10 --out runs/bench/learn_many.json
    python bench/learn_many.py --sizes 100 --library 10 --nproc 2 solver.reduce.refit=false
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import revision
from scale import exponent

ROOT = Path(__file__).resolve().parents[1]
_BAR = re.compile(r"\[\d+/\d+\] (.+?): .*?\[(?:(\d+):)?(\d+):(\d+)<")


def make(n: int, seed: int, folder: Path, library: int = 0, stiffness: str = "scalar") -> dict:
    """Write n random programs' motions into ``folder`` (``library`` = G > 0: their fields
    drawn from G shared ones; ``stiffness``: scalar, diag or full fields), each as NAME.npz and
    its generating program as NAME.json (basis format, as ``tflearn gestures --out``
    writes): the seconds it took, the number of motions at each sampling rate, the
    samples in all and the number of generating fields G."""
    import torch

    from tflearn.data import gestures
    from tflearn.io import basis
    from tflearn.motions.motion import save
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rates, samples = {}, 0
    programs = gestures.random_gestures(n, seed=seed, library=library, stiffness=stiffness)
    for motion, generating in gestures.generate_resolved(programs):
        save(motion, folder / f"{motion.name}.npz")
        basis.save(generating, folder / f"{motion.name}.json")
        rates[f"{motion.rate:.0f}"] = rates.get(f"{motion.rate:.0f}", 0) + 1
        samples += motion.T
    G = len({(e, k) for p in programs for e, k in zip(p.eta, p.k)})
    return {"make_s": time.perf_counter() - t0, "motions_at_hz": rates, "samples": samples, "G": G}


def stage_seconds(stderr: str) -> dict:
    """Each stage's elapsed time (s) from the last state of its progress bar."""
    out = {}
    for line in re.split(r"[\r\n]", stderr):
        m = _BAR.search(line)
        if m:
            h, mnt, s = (int(x) if x else 0 for x in m.groups()[1:])
            out[m.group(1)] = 3600 * h + 60 * mnt + s
    return out


def failure(stderr: str) -> str:
    """Why a training process failed: the last exception its error output names (not
    torchrun's own ChildFailedError), else its last line from tflearn's one-line errors,
    else its last line (torchrun ends with a rule of '=', left out)."""
    lines = [x.strip() for x in re.split(r"[\r\n]", stderr) if x.strip() and set(x.strip()) != {"="}]
    raised = [x for x in lines if re.search(r"\b\w*(Error|Exception): ", x) and "ChildFailedError" not in x]
    told = [x for x in lines if re.match(r"(tflearn|train): ", x)]
    return ((raised or told or lines or [""])[-1])[-300:]


def learn(data: Path, out: Path, overrides=(), nproc: int = 1) -> dict:
    """``train configs/gestures.yaml data=DATA`` in a fresh process (``nproc`` > 1: that
    many under ``torchrun --standalone``); what it found."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    launch = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}"]
              if nproc > 1 else [sys.executable])
    cmd = [*launch, "-m", "tflearn.cli", "train", "configs/gestures.yaml", f"data={data}",
           f"out={out}", "log.progress=true", *overrides]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    (out.parent / "train.log").write_text(proc.stderr)
    if not (out / "metrics.json").exists():        # exit 1 alone means: not all reproduced
        return {"train_s": wall, "error": f"train exited {proc.returncode}: {failure(proc.stderr)}",
                "log": str(out.parent / "train.log")}
    m = json.loads((out / "metrics.json").read_text())
    motions, each = m["motions"].values(), m["history"].get("each", {})
    identity = m.get("identity", {})
    chosen = (m["history"].get("pool") or {}).get("selection") or {}
    matched = [f for f in identity.get("fields", []) if f["matched"]]
    return {"train_s": wall, "stages_s": stage_seconds(proc.stderr), "M": m["overall"]["M"],
            "pooled": chosen.get("pooled"), "selected": chosen.get("kept"),
            "shared": len(m["history"].get("pool", {}).get("shared") or []),
            "restored": len(m["history"].get("pool", {}).get("restored") or []),
            "copied": len(m["history"].get("pool", {}).get("copied") or []),
            "reproduced": sum(bool(x["success"]) for x in motions),
            "worst_rmse_rad": max(x["rmse"] for x in motions),
            "worst_tip_m": max(x["tip"] for x in motions), "fields_matched": identity.get("matched"),
            "generating_fields": identity.get("G"),
            "worst_matched_centre_rad": max((f["centre_distance_rad"] for f in matched), default=None),
            "worst_matched_stiffness": max((abs(f["stiffness_ratio"] - 1) for f in matched
                                            if f["stiffness_ratio"] is not None), default=None),
            "max_rss_mb_so_far": peak,
            "reproduced_alone": sum(each.get("reproduced", [])), "reused": len(each.get("reused", [])),
            "declined": each.get("declined", {})}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="5,10")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--library", type=int, default=0,
                   help="G > 0: the programs' fields drawn from G shared ones (0: each its own)")
    p.add_argument("--stiffness", choices=("scalar", "diag", "full"), default="scalar",
                   help="the programs' fields: K = k·I, seven independent diagonal entries, or "
                        "full with seven eigenvalues about random axes")
    p.add_argument("--nproc", type=int, default=1, help="training processes (torchrun)")
    p.add_argument("--out", type=Path)
    p.add_argument("--keep", type=Path, help="keep each size's data, run folder and train.log in "
                   "KEEP/N (default: a temporary folder, removed)")
    p.add_argument("overrides", nargs="*", help="config overrides for train (KEY=VALUE)")
    args = p.parse_args(argv)
    commit = revision.head()                  # the code this process runs
    rows = []
    for n in (int(x) for x in args.sizes.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            where = Path(tmp) if args.keep is None else args.keep / str(n)
            data, out = where / "data", where / "run"
            data.mkdir(parents=True)
            row = {"motions": n, "nproc": args.nproc, "stiffness": args.stiffness,
                   **make(n, args.seed, data, args.library, args.stiffness)}
            row.update(learn(data, out, args.overrides, args.nproc))
        rows.append(row)
        print(json.dumps(row), flush=True)
        write(args.out, commit, args.overrides, rows, args.library)   # after every size
    return 0


def write(path: Path | None, commit: str, overrides: list, rows: list, library: int = 0) -> None:
    doc = {"commit": commit, "overrides": overrides, "library": library, "rows": rows}
    done = [r for r in rows if "error" not in r]
    if len(done) > 1:
        doc["exponents"] = {k: exponent(done, k) for k in ("make_s", "train_s")}
    revision.write_json(path, doc)


if __name__ == "__main__":
    sys.exit(main())
