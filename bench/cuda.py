"""tflearn on one CUDA device against the same machine's CPU, measured in one invocation.

For the 7-DOF arm in float64:

* inverse dynamics (RNEA), forward dynamics (ABA) and the mass matrix per sample at
  batches 1 … 10⁶: on the GPU torch's recursions (the compiled kernels of
  :mod:`tflearn.physics.kernels` are CPU code), on the CPU the compiled kernels on one thread,
  as ``bench/dynamics.py`` measures them;
* the same two with a gradient (a forward and a backward pass of their sum, q requiring
  grad: what path matching differentiates), torch's recursions on both;
* N motions (the gesture library repeated, weights scaled 1% per copy, as
  ``bench/path_step.py``) simulated without a gradient: on the GPU in one batch (batch
  ``shared``), on the CPU by the compiled simulator, each member stepped alone (batch
  ``each``);
* one path-matching step for N such motions: the batched simulation through
  torchdiffeq's dopri5 and the path loss' gradient by direct backpropagation, on each
  device.

Each section runs on the device and then on the CPU, at most ``--section-timeout`` s
each; a failure or a stop is recorded as data (its traceback) beside what the section
measured before it, so one run says what works on the device, and how far it got.
Timings: the best of three loops of at least ``--min-time`` s for the fast calls, a
single run for a simulation; ``torch.cuda.synchronize`` closes every timed call.
Writes JSON (``--out``).

    python bench/cuda.py --out runs/bench/cuda.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import sys
import time
import traceback
from functools import partial
from pathlib import Path

import path_step
import torch
from dynamics import BATCHES, states
from dynamics import best_time as _best_time


def synced(fn, device):
    """fn, then a wait for the device to finish it."""
    def call():
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return out
    return call


def best_time(fn, device, min_time):
    return _best_time(synced(fn, device), min_time)


def once(fn, device) -> tuple:
    """(seconds of one call after one warm-up call, what that call returned)."""
    call = synced(fn, device)
    call()
    t0 = time.perf_counter()
    out = call()
    return time.perf_counter() - t0, out


def dynamics_section(out, device, max_batch, min_time) -> None:
    from tflearn.physics import dynamics
    from tflearn.physics.body import arm

    body = arm()
    out.update(rnea={}, forward={}, mass={})
    with torch.no_grad():
        for B in (b for b in BATCHES if b <= max_batch):
            q, v, a = (x.to(device) for x in states(body.nv, B))
            out["rnea"][B] = best_time(partial(dynamics.rnea, body, q, v, a), device, min_time) / B
            out["forward"][B] = best_time(partial(dynamics.forward_dynamics, body, q, v, a),
                                          device, min_time) / B
            if B <= max_batch // 10:
                out["mass"][B] = best_time(partial(dynamics.mass_matrix, body, q), device, min_time) / B


def gradient_section(out, device, batches, min_time) -> None:
    from tflearn.physics import dynamics
    from tflearn.physics.body import arm

    body = arm()
    out.update(rnea={}, forward={})
    for B in batches:
        q, v, a = (x.to(device) for x in states(body.nv, B))
        q.requires_grad_()
        for name, f in (("rnea", dynamics.rnea), ("forward", dynamics.forward_dynamics)):
            out[name][B] = best_time(partial(_backward, f, body, q, v, a), device, min_time) / B


def _backward(f, body, q, v, a):
    f(body, q, v, a).sum().backward()
    q.grad = None


def problem(n: int, device):
    """``bench/path_step.py``'s problem of n motions, on ``device``: (body, basis, weights,
    targets)."""
    body, basis, weights, tg = path_step.problem(n)
    return body, basis.to(device), weights.to(device), tg.to(device)


def path_step_section(out, device, sizes) -> None:
    from tflearn.fit.path import path_loss
    from tflearn.fit.targets import simulate_targets
    from tflearn.simulation.simulate import SimOptions

    for n in sizes:                          # one call each: the simulation section warmed up
        body, basis, weights, tg = problem(n, device)
        t0 = time.perf_counter()
        q_sim, v_sim = simulate_targets(body, basis, weights, tg, SimOptions())
        loss = path_loss(body, q_sim, v_sim, tg).sum()
        loss.backward()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        out[n] = {"seconds": time.perf_counter() - t0, "loss": float(loss.detach()),
                  "eta_grad_norm": float(basis.eta.grad.norm())}


def simulation_section(out, device, sizes) -> None:
    from tflearn.fit.targets import simulate_targets
    from tflearn.simulation.simulate import SimOptions

    options = SimOptions(batch="shared" if device.type == "cuda" else "each")
    with torch.no_grad():
        for n in sizes:
            body, basis, weights, tg = problem(n, device)
            seconds, (q, _) = once(partial(simulate_targets, body, basis, weights, tg, options), device)
            out[n] = {"seconds": seconds, "batch": options.batch, "q_sum": float(q.sum())}


class SectionTimeout(Exception):
    pass


def _alarm(signum, frame):
    raise SectionTimeout


def run(name: str, fn, doc: dict, path: Path, limit: int) -> None:
    """doc[name] = the figures fn(figures) filled in, and its failure if it raised or ran
    past ``limit`` seconds (what it measured before is kept); the JSON rewritten after
    every section."""
    t0 = time.perf_counter()
    print(f"{name} …", flush=True)
    doc[name] = {"figures": {}}
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(limit)
    try:
        fn(doc[name]["figures"])
    except SectionTimeout:
        doc[name]["failed"] = f"stopped after {limit} s"
    except Exception:                                  # recorded: what fails on the device
        doc[name]["failed"] = traceback.format_exc()
    finally:
        signal.alarm(0)
    doc[name]["wall_s"] = time.perf_counter() - t0
    print(doc[name].get("failed", "done"), flush=True)
    path.write_text(json.dumps(doc, indent=1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--max-batch", type=int, default=1_000_000)
    p.add_argument("--cpu-max-batch", type=int, default=1_000_000)
    p.add_argument("--grad-batches", default="1000,10000,100000,1000000")
    p.add_argument("--cpu-grad-batches", default="1000,10000,100000")
    p.add_argument("--sim-sizes", default="5,100,1000")
    p.add_argument("--cpu-sim-sizes", default="5,100,1000")
    p.add_argument("--path-sizes", default="5,100")
    p.add_argument("--cpu-path-sizes", default="5")
    p.add_argument("--min-time", type=float, default=0.1)
    p.add_argument("--section-timeout", type=int, default=90,
                   help="seconds one section (one device) may run before it is stopped")
    p.add_argument("--device", default="cuda", help="the device measured against the CPU")
    args = p.parse_args(argv)
    ints = lambda s: [int(x) for x in s.split(",") if x]
    torch.set_num_threads(1)
    cpu, gpu = torch.device("cpu"), torch.device(args.device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                       "python": platform.python_version(), "torch": torch.__version__,
                       "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}}
    sections = (("dynamics", dynamics_section, args.max_batch, args.cpu_max_batch, (args.min_time,)),
                ("gradient", gradient_section, ints(args.grad_batches), ints(args.cpu_grad_batches),
                 (args.min_time,)),
                ("simulation", simulation_section, ints(args.sim_sizes), ints(args.cpu_sim_sizes), ()),
                ("path_step", path_step_section, ints(args.path_sizes), ints(args.cpu_path_sizes), ()))
    for name, fn, there, here, rest in sections:       # the device, then the CPU, each section
        for dev, tag, size in ((gpu, "cuda", there), (cpu, "cpu", here)):
            run(f"{name}_{tag}", lambda out, fn=fn, dev=dev, size=size, rest=rest: fn(out, dev, size, *rest),
                doc, args.out, args.section_timeout)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
