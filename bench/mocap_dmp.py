"""A kinematic peer on the mocap windows: dynamic movement primitives (PyPI
``movement-primitives``) fitted per window, beside tflearn's shared basis.

    PYTHONPATH=. python bench/mocap_dmp.py [--out runs/mocap_bench] [--weights 10]
        [--window 1.0] [--rate 60] [--run RUN] [--clips TEXT...]
    PYTHONPATH=. python bench/mocap_dmp.py --data DIR --weights 10,20,40 [--run RUN]

With ``--data`` the motions are the .npz files of DIR (whole clips as ``tflearn bvh
import`` writes them, on the body of DIR/body.yaml) instead of the windows, ``--weights``
may list several sizes, and tflearn's parameters are the numbers its run counts per
motion (metrics.json's ``numbers``: non-zero weights, the windows' onsets and durations,
the initial state), simulated as the run simulates.

The windows are bench/mocap_basis.py's (the same import with configs/mocap.yaml's
choices, the busiest windows; give the same --window, --rate and --clips). Per window:
a DMP over the 7 coordinates (ball joints' rotation vectors as plain vectors: the shared
shoulder chart keeps them far from π), ``--weights`` basis functions per dimension,
imitated from the window resampled at 16× its rate on tflearn's quintic spline (the
package's imitation differentiates by finite differences: at 60 Hz they alone cost
~5 cm on a smooth rest-to-rest profile) and replayed open loop from its start (position
and velocity; the windows start and end moving, so the final velocity is allowed);
parameters per motion = 7 × weights + 7 (goal) + 7 (goal velocity) + 1 (duration).
Scores as tflearn's metrics: joint RMSE (configuration difference, rad) and the largest
hand-tip distance (m). Then the start posture is moved by +0.2 rad in every coordinate:
the response is the RMS deviation from the unperturbed replay over the window, and at
its end. With ``--run`` (a run trained on these windows by bench/mocap_basis.py), the
same for tflearn: its program simulated from the window's start and from the moved one.
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from mocap_basis import arguments, prepare_windows  # noqa: E402

from tflearn.motions import motion as motion_mod  # noqa: E402
from tflearn.motions import spline  # noqa: E402
from tflearn.physics import dynamics  # noqa: E402
from tflearn.physics.configspace import difference  # noqa: E402

SHIFT = 0.2
DENSE = 16       # the DMP is imitated and replayed at 16× the window's rate


def scores(body, q_ref: np.ndarray, q: np.ndarray) -> tuple:
    """(joint RMSE rad, max tip distance m) of a path against the reference (T×7 each)."""
    a, b = torch.from_numpy(q_ref), torch.from_numpy(q)
    rmse = float(difference(body, a, b).pow(2).mean().sqrt())
    tip = float((dynamics.tip_position(body, a) - dynamics.tip_position(body, b)).norm(dim=-1).max())
    return rmse, tip


def dmp_row(body, m, n_weights: int) -> dict:
    from movement_primitives.dmp import DMP
    from movement_primitives.dmp._dmp import DMP_STEP_FUNCTIONS, dmp_open_loop
    fine = spline.resample(m, DENSE * m.rate)          # on tflearn's quintic spline
    t, q = fine.t.numpy(), fine.q.numpy()
    dt = float(t[1] - t[0])
    qd = np.gradient(q, dt, axis=0)
    dmp = DMP(n_dims=7, execution_time=float(t[-1]), dt=dt, n_weights_per_dim=n_weights, int_dt=dt)
    dmp.imitate(t, q, allow_final_velocity=True)

    def replay(y0):       # DMP.open_loop starts at rest; the windows start moving
        y = dmp_open_loop(dmp.execution_time_, 0.0, dt, y0, q[-1], dmp.alpha_y, dmp.beta_y,
                          dmp.forcing_term, None, None, dmp.int_dt, DMP_STEP_FUNCTIONS["rk4"],
                          start_yd=qd[0], goal_yd=qd[-1])[1]
        return y[:len(t):DENSE]
    q = m.q.numpy()
    y, y2 = replay(q[0]), replay(q[0] + SHIFT)
    rmse, tip = scores(body, q, y)
    dev = np.linalg.norm(y2 - y, axis=1)
    return {"params": 7 * n_weights + 7 + 7 + 1, "rmse": rmse, "tip": tip,
            "shift_rms": float(np.sqrt((dev ** 2).mean())), "shift_end": float(dev[-1])}


def tflearn_row(run: Path, name: str, m, counted: bool = False) -> dict:
    from tflearn.data.loading import torsos
    from tflearn.evaluate import run_config
    from tflearn.io import basis as basis_io
    from tflearn.model.program import FieldProgram
    from tflearn.simulation.simulate import SimOptions, SimulationFailed, simulate
    lb = basis_io.load(run / "basis.json")
    cfg = run_config(run)[0]
    base = torsos(cfg.data, [m], cfg.torso)                     # the run's torso, if it moves
    j = lb.index(name)
    M, P = lb.basis.M, lb.weights.P
    # per motion: a, b and the window weights c, and the windows' onsets and durations;
    # shared: the centres and the stiffnesses' non-zero lower-triangle entries
    shared = lb.basis.eta.numel() + int((torch.tril(lb.basis.K()) != 0).sum())
    params = f"{M * (2 + P) + 2 * P} + {shared} shared"
    prog = FieldProgram(lb.basis, lb.weights, index=[j])
    opts = SimOptions(rtol=1e-6, atol=1e-8, max_evals=20000)      # the windows' training's options
    if counted:                                                     # as the run counts and simulates
        count = json.loads((run / "metrics.json").read_text())["motions"][name]["numbers"]
        params = f"{count} + {shared} shared"
        opts = replace(cfg.solver.path.options(), batch="shared")
    try:
        with torch.no_grad():
            paths = [simulate(lb.body, prog, lb.q0[j:j + 1] + s, lb.qd0[j:j + 1], m.t, opts, base=base).q[0]
                     .numpy() for s in (0.0, SHIFT)]
    except SimulationFailed as err:
        nan = float("nan")
        return {"params": f"{params} ({err.reason})", "rmse": nan, "tip": nan,
                "shift_rms": nan, "shift_end": nan}
    rmse, tip = scores(lb.body, m.q.numpy(), paths[0])
    dev = np.linalg.norm(paths[1] - paths[0], axis=1)
    return {"params": params, "rmse": rmse, "tip": tip,
            "shift_rms": float(np.sqrt((dev ** 2).mean())), "shift_end": float(dev[-1])}


def main(argv=None) -> int:
    p = arguments(__doc__.split("\n\n")[0])
    p.add_argument("--weights", default="10",
                   help="DMP basis functions per dimension (with --data: sizes, comma-separated)")
    p.add_argument("--run", type=Path, default=None, help="a tflearn run trained on the windows")
    p.add_argument("--data", type=Path, default=None, help="whole motions (.npz) instead of the windows")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    sizes = [int(w) for w in args.weights.split(",")]
    if args.data is not None:
        return whole(args.data, sizes, args.run)
    report, body, windows = prepare_windows(args)
    print("| window | model | parameters | joint RMSE (rad) | max tip error (cm) | "
          f"start +{SHIFT} rad: RMS / end deviation (rad) |")
    print("|---|---|---|---:|---:|---|")
    for c in report["clips"]:
        name = c["file"][:-4]
        m = motion_mod.load(windows / c["file"], body)
        rows = [("DMP", dmp_row(body, m, sizes[0]))]
        if args.run is not None:
            rows.append(("tflearn", tflearn_row(args.run, name, m)))
        for model, r in rows:
            print(f"| {name} | {model} | {r['params']} | {r['rmse']:.4f} | {100 * r['tip']:.2f} | "
                  f"{r['shift_rms']:.3f} / {r['shift_end']:.3f} |")
    return 0


def whole(data: Path, sizes: list, run) -> int:
    """The table for the whole motions of ``data``: a DMP of each size, then tflearn's run."""
    from tflearn.config import read_body
    body = read_body(data / "body.yaml")
    print(f"| clip (s) | model | parameters | joint RMSE (rad) | max tip error (cm) | "
          f"start +{SHIFT} rad: RMS / end deviation (rad) |")
    print("|---|---|---|---:|---:|---|")
    for path in sorted(data.glob("*.npz")):
        m = motion_mod.load(path, body)
        rows = [(f"DMP ({n})", dmp_row(body, m, n)) for n in sizes]
        if run is not None:
            rows.append(("tflearn", tflearn_row(run, path.stem, m, counted=True)))
        for model, r in rows:
            print(f"| {path.stem} ({float(m.t[-1]):.1f}) | {model} | {r['params']} | {r['rmse']:.4f} | "
                  f"{100 * r['tip']:.2f} | {r['shift_rms']:.3f} / {r['shift_end']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
