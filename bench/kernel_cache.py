"""Whether the compiled kernels give the same numbers freshly compiled as loaded from
numba's on-disk cache: two processes, each with the same empty cache folder
(``NUMBA_CACHE_DIR``), the first compiling and writing it, the second loading it; each
prints a digest of a batched RNEA, a batched forward dynamics and a compiled simulation of
the come_here gesture. Prints both and whether they agree (exit status 1 if not).

    PYTHONPATH=. python bench/kernel_cache.py
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import hashlib, torch
from tflearn.physics import dynamics
from tflearn.data import gestures
from tflearn.model.program import FieldProgram
from tflearn.simulation.simulate import SimOptions, simulate
(m, lb), = gestures.generate(gestures=[gestures.GESTURES["come_here"]])
g = torch.Generator().manual_seed(0)
q, v, tau = (torch.randn(1000, 7, generator=g, dtype=torch.float64) for _ in range(3))
digest = lambda x: hashlib.sha1(x.numpy().tobytes()).hexdigest()[:12]
with torch.no_grad():
    sim = simulate(lb.body, FieldProgram(lb.basis, lb.weights), m.q[:1], m.qd[:1], m.t,
                   SimOptions(batch="each")).q
    print(digest(dynamics.rnea(lb.body, q, v, tau)), digest(dynamics.forward_dynamics(lb.body, q, v, tau)),
          digest(sim))
"""


def main() -> int:
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
        runs = [subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True,
                               check=True).stdout.strip() for _ in range(2)]
    print(f"freshly compiled (rnea, forward dynamics, simulation): {runs[0]}")
    print(f"loaded from the cache:                                 {runs[1]}")
    same = runs[0] == runs[1]
    print("the same" if same else "DIFFERENT")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
