"""docs/benchmarks.md: run the benchmarks (or reuse their saved results) and write the page.

    python bench/benchmarks.py --ref 607d0dd --launcher "torchrun --standalone --nproc-per-node 2"
                                                        # run everything (~30 min on 2 cores)
    python bench/benchmarks.py --ref 607d0dd --reuse    # rewrite the page from docs/benchmarks/*.json
    python bench/benchmarks.py --ref 607d0dd --only main_job,scale --variant solver.path.batch=shared
                                                        # rerun two, reuse the others

Runs ``bench/dynamics.py``, ``bench/main_job.py``, ``bench/path_step.py``,
``bench/scale.py`` and ``bench/learn_many.py`` (each in its own process, one after
another), keeps their JSON in docs/benchmarks/ and writes docs/benchmarks.md from it:
every figure with the reference it is a ratio to, measured in the same invocation, and
the machine beside it.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "benchmarks"
PAGE = ROOT / "docs" / "benchmarks.md"


def us(x: float) -> str:
    return f"{x * 1e6:,.2f}" if x < 1e-5 else f"{x * 1e6:,.0f}"


def run(script: str, *args: str) -> None:
    subprocess.run([sys.executable, str(ROOT / "bench" / script), *args], check=True, cwd=ROOT)


def dynamics_section(d: dict) -> list:
    tf, pin = d["tflearn"], d["pinocchio"]
    ref = d.get("reference", {}).get("tflearn")
    m = d["machine"]
    lines = [
        "## Dynamics throughput", "",
        f"The 7-DOF arm, float64, one torch thread ({m['cores']}-core {m['cpu']}, torch "
        f"{m['torch']}, Pinocchio {pin['version']} from PyPI `pin`), random states; µs per "
        "sample (per call ÷ batch). *Pinocchio Python* is one `pin.rnea` / `pin.aba` / "
        "`pin.crba` call from Python; *Pinocchio C++* is its compiled batch loop "
        "(`rneaInParallel`, `abaInParallel`, one thread), the cost of the algorithm "
        "without Python. *ratio* = tflearn ÷ Pinocchio Python call. tflearn's RNEA and "
        "forward dynamics without a gradient to carry run compiled (`tflearn.physics.kernels`); "
        "*with gradient* is the same call with q requiring grad (torch's recursions, the "
        "forward pass only).", "",
        "| batch | RNEA | ratio | Pinocchio C++ | forward dynamics (ABA) | ratio | Pinocchio C++ | "
        "mass matrix | ratio | RNEA with gradient | forward with gradient |"
        + (" RNEA, reference | forward, reference | mass matrix, reference |" if ref else ""),
        "|---" * (11 + (3 if ref else 0)) + "|"]
    grad = tf.get("grad", {"rnea": {}, "forward": {}})
    py = pin["python"]
    for B in tf["rnea"]:
        b = int(B)
        r, f = tf["rnea"][B] / b, tf["forward"][B] / b
        mm = tf["mass"].get(B)
        row = [f"{b:,}", us(r), f"{r / py['rnea']:.2f}", us(pin["batch"]["rnea"][B]),
               us(f), f"{f / py['aba']:.2f}", us(pin["batch"]["aba"][B]),
               us(mm / b) if mm else "–", f"{mm / b / py['crba']:.2f}" if mm else "–"]
        row += [us(grad[k][B] / b) if B in grad[k] else "–" for k in ("rnea", "forward")]
        if ref:
            row += [us(ref[k][B] / b) if B in ref[k] else "–" for k in ("rnea", "forward", "mass")]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", f"A Pinocchio call from Python: RNEA {us(py['rnea'])} µs, ABA {us(py['aba'])} µs, "
              f"CRBA {us(py['crba'])} µs.", ""]
    return lines


def latency_section(d: dict) -> list:
    tf = d["tflearn"]
    ref = d.get("reference", {}).get("tflearn")
    g = tf["gesture"]
    rows = [("one ODE right-hand side, batch 1", tf["rhs_batch1"],
             ref and ref["rhs_batch1"], "≤ 50 µs"),
            (f"a {g['duration_s']:g} s gesture ({g['name']}) simulated, default tolerances "
             f"({g['rhs_evals']} right-hand sides)", g["seconds"],
             ref and ref["gesture"]["seconds"], "≤ 0.1 s")]
    c = tf.get("gesture_compiled")
    if c:
        rows += [(f"one right-hand side inside the compiled simulator (`tflearn.simulation.simkernel`; "
                  f"the gesture's time ÷ its {c['rhs_evals']} right-hand sides, solver included)",
                  c["seconds"] / c["rhs_evals"], ref and ref["rhs_batch1"], "≤ 50 µs"),
                 (f"the same gesture, batch `each`: compiled ({c['rhs_evals']} right-hand sides)",
                  c["seconds"], ref and ref["gesture"]["seconds"], "≤ 0.1 s")]
    lines = ["## Small-batch latency", "",
             "| what | now | " + ("reference | speed-up |" if ref else "") + " goal |",
             "|---|---|" + ("---|---|" if ref else "") + "---|"]
    for what, now, before, goal in rows:
        cells = [what, f"{now * 1e3:.3f} ms" if now >= 1e-4 else f"{now * 1e6:.1f} µs"]
        if ref:
            cells += [f"{before * 1e3:.3f} ms", f"{before / now:.2f}×"]
        lines.append("| " + " | ".join(cells + [goal]) + " |")
    ops = tf.get("aten_ops_batch1")
    if ops:
        before = ref.get("aten_ops_batch1") if ref else None
        lines += ["", "ATen operators dispatched per call at batch 1 (torch.profiler; each costs "
                  "a roughly fixed 0.3–1 µs of dispatch at this size; the compiled loops are not among "
                  "them): "
                  + ", ".join(f"{k} {v}" + (f" (was {before[k]})" if before and k in before else "")
                  for k, v in ops.items()) + "."]
    return lines + [""]


def heading(title: str, intro: str, columns: list) -> list:
    """A section's title, its paragraph and the head of its table."""
    return [f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]


def _difference(x: float) -> str:
    return "formats differ" if x == float("inf") else format(x, ".2g")


def main_job_section(d: dict) -> list:
    lines = heading("The main job",
                    f"`train configs/gestures.yaml`, each run a fresh process, one after another "
                    f"in one invocation ({d['cores']} cores).",
                    ["run", "wall time", "speed-up", "M", "gestures reproduced", "worst RMSE (rad)",
                     "worst tip (cm)", "basis.json vs reference (max abs difference, keys both hold)",
                     "basis.json vs the current run"])
    names = {"reference": "reference", "current": "now", "launcher": f"now, `{d.get('launcher')}`"}
    for key, r in d["runs"].items():
        name = names.get(key) or f"now, `{key.removeprefix('variant ')}`"
        lines.append(f"| {name} | {r['wall_s']:.1f} s | {r.get('speedup', 1.0):.2f}× | {r['M']} | "
                     f"{r['reproduced']}/{r['motions']} | {r['worst_rmse_rad']:.4f} | "
                     f"{100 * r['worst_tip_m']:.2f} | "
                     f"{_difference(r['basis_max_difference']) if key != 'reference' else '–'} | "
                     f"{format(r['basis_vs_current'], '.2g') if 'basis_vs_current' in r else '–'} |")
    return lines + [""]


def path_section(d: dict) -> list:
    lines = heading("One path-matching step",
                    "Simulate every motion, the path loss and its gradient (`bench/path_step.py`; "
                    "the gestures repeated with scaled weights, the library's generating model); "
                    "wall time and peak memory of the process.",
                    ["motions", "solver", "gradient", "forward", "forward + backward", "peak memory"])
    for r in d["rows"]:
        mode = "adjoint" if r["adjoint"] else "direct"
        if "step_s" in r:
            lines.append(f"| {r['motions']:,} | {r['method']} | {mode} | {r['forward_s']:.1f} s | "
                         f"{r['step_s']:.1f} s | {r['max_rss_mb'] / 1024:.1f} GiB |")
        else:
            why = f"over {r['timeout_s']:.0f} s" if "timeout_s" in r else r.get("error", "failed")
            lines.append(f"| {r['motions']:,} | {r['method']} | {mode} | {why} | | |")
    return lines + [""]


def exponents(d: dict) -> list:
    """The fitted exponents of a size benchmark (``d["exponents"]``, key ``name_s`` → p),
    as a paragraph after its table; none where fewer than two sizes were measured."""
    if "exponents" not in d:
        return []
    return ["", "Fitted exponents (cost ∝ N^p): " + ", ".join(
        f"{k.removesuffix('_s').replace('_', ' ')} p = {v:.2f}" for k, v in d["exponents"].items()) + "."]


def scale_section(d: dict) -> list:
    lines = heading("Pooled work against the number of motions",
                    "`bench/scale.py`: N random supported programs (made by one batch of per-motion "
                    "steps), the model held at M = 7 fields; one EM step (NNLS weights of every "
                    "motion and one Levenberg–Marquardt step on the shared fields) and one batched "
                    "scoring simulation of all N motions, its batch stepped together (*shared*, "
                    "torchdiffeq's dopri5) and each motion on its own steps (*each*, "
                    "`tflearn.simulation.ode`), at the pipeline's default tolerances.",
                    ["motions N", "samples", "making the motions", "EM step", "scoring, shared",
                     "scoring, each", "peak memory"])
    for r in d["rows"]:
        if "error" in r:
            lines.append(f"| {r['motions']:,} | | not measured: {r['error']} | | | | |")
            continue
        score = {b: (f"{r[f'score_{b}_s']:.1f} s" if f"score_{b}_s" in r else "–")
                 + ("" if not r.get(f"failed_{b}") else f" ({r[f'failed_{b}']} failed)"
                    if isinstance(r[f"failed_{b}"], int) else f" (failed: {r[f'failed_{b}']})")
                 for b in ("shared", "each")}
        lines.append(f"| {r['motions']:,} | {r['samples']:,} | {r['generate_s']:.1f} s | "
                     f"{r['em_step_s']:.2f} s | {score['shared']} | {score['each']} | "
                     f"{r['max_rss_mb'] / 1024:.1f} GiB |")
    return lines + exponents(d) + [""]


def learn_many_section(d: dict) -> list:
    shared = (f", their fields drawn from G = {d['library']} shared ones (`--library {d['library']}`)"
              if d.get("library") else ", each with its own fields")
    procs = {r.get("nproc", 1) for r in d["rows"]}
    lines = heading("Many motions learned end to end",
                    "`bench/learn_many.py`: N random supported programs" + shared + " (each stepped "
                    "alone and sampled at the lowest of 100·2ᵏ Hz that resolves it, written as .npz), "
                    "then `train configs/gestures.yaml data=DIR` in a fresh process"
                    + (f" ({', '.join(map(str, sorted(procs)))} processes, torchrun)" if procs != {1} else "")
                    + "; each stage's time from its progress bar"
                    + (f", overrides {' '.join(d['overrides'])}." if d.get("overrides") else "."),
                    ["motions N", "G", "samples", "making them", "training", "each motion alone",
                     "pool and merge", "reduce", "path matching", "M", "reproduced", "worst RMSE (rad)",
                     "worst tip (cm)", "peak memory"])
    stages = ("each motion alone", "pool and merge", "reduce", "path matching")
    for r in d["rows"]:
        head = (f"| {r['motions']:,} | {r.get('G', '–')} | {r['samples']:,} | " if "samples" in r
                else f"| {r['motions']:,} | – | – | ") + f"{r['make_s']:.0f} s | {r['train_s']:.0f} s | "
        if "error" in r:
            lines.append(head + f"{r['error']} |" + " |" * 8)
            continue
        st = r["stages_s"]
        cells = [f"{st[k]:,} s" if k in st else "–" for k in stages]
        lines.append(head
                     + " | ".join(cells) + f" | {r['M']} | {r['reproduced']}/{r['motions']} | "
                     f"{r['worst_rmse_rad']:.4f} | {100 * r['worst_tip_m']:.2f} | "
                     f"{r['max_rss_mb_so_far'] / 1024:.1f} GiB |")
    return lines + exponents(d) + [""]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ref", required=True, help="the revision before the performance work")
    p.add_argument("--reuse", action="store_true", help="only rewrite the page from saved JSON")
    p.add_argument("--launcher", help="passed to bench/main_job.py")
    p.add_argument("--path-sizes", default="5,100,1000")
    p.add_argument("--path-methods", default="dopri5")
    p.add_argument("--path-timeout", default="300")
    p.add_argument("--scale-sizes", default="10,30,100")
    p.add_argument("--learn-sizes", default="5,10")
    p.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                   help="passed to bench/main_job.py")
    p.add_argument("--only", help="rerun only these benchmarks (comma-separated of "
                                  "dynamics,main_job,path_step,scale,learn_many), reusing the "
                                  "others' JSON")
    args = p.parse_args(argv)
    DATA.mkdir(parents=True, exist_ok=True)
    benches = {
        "dynamics": ("--ref", args.ref),
        "main_job": ("--ref", args.ref, *(["--launcher", args.launcher] if args.launcher else []),
                     *(x for v in args.variant for x in ("--variant", v))),
        "path_step": ("--sizes", args.path_sizes, "--methods", args.path_methods,
                      "--timeout", args.path_timeout),
        "scale": ("--sizes", args.scale_sizes),
        "learn_many": ("--sizes", args.learn_sizes)}
    chosen = [] if args.reuse else (args.only.split(",") if args.only else list(benches))
    for name in chosen:
        run(f"{name}.py", *benches[name], "--out", str(DATA / f"{name}.json"))
    dyn = json.loads((DATA / "dynamics.json").read_text())
    lines = ["# Benchmarks", "",
             "Measured by `python bench/benchmarks.py --ref REV`, REV the revision before the "
             "performance work (raw results in [benchmarks/](benchmarks/)); every ratio is against "
             "that reference measured in the same invocation on the same machine — absolute times "
             "vary between machines and with load, ratios much less. Each table is the latest "
             "measurement; the revisions they were measured at, and every earlier measurement, are "
             "in [history.md](history.md#speed-and-scale).", ""]
    lines += dynamics_section(dyn) + latency_section(dyn)
    for name, section in (("main_job.json", main_job_section), ("path_step.json", path_section),
                          ("scale.json", scale_section), ("learn_many.json", learn_many_section)):
        if (DATA / name).exists():
            lines += section(json.loads((DATA / name).read_text()))
    notes = ROOT / "bench" / "benchmarks_notes.md"
    if notes.exists():
        lines += [notes.read_text().rstrip(), ""]
    PAGE.write_text("\n".join(lines))
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
