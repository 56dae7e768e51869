"""tflearn on a CUDA device agrees with the CPU: dynamics, simulation, a path-matching
gradient and a whole training run with ``device: cuda`` (skipped where no CUDA device is
present; these tests need no Pinocchio, so they run on a machine with a GPU and the
package's own dependencies only). Where none is present, a run asking for one is refused."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from tflearn import config, train
from tflearn.data import gestures
from tflearn.fit.path import path_loss
from tflearn.fit.targets import prepare, simulate_targets
from tflearn.io import basis as bio
from tflearn.model.weights import MotionWeights
from tflearn.motions.torso import BaseMotion, Bases
from tflearn.physics import body as tb
from tflearn.physics import dynamics as D
from tflearn.simulation.simulate import SimOptions, simulate, zero_program

from conftest import DT
from test_learning import SMALL_GESTURES, small_config, write_motions

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def tensors(x) -> list:
    """Every tensor in a dataclass, a dict or a list, recursively."""
    if isinstance(x, torch.Tensor):
        return [x]
    if dataclasses.is_dataclass(x):
        x = [getattr(x, f.name) for f in dataclasses.fields(x)]
    elif isinstance(x, dict):
        x = list(x.values())
    return [t for v in x for t in tensors(v)] if isinstance(x, (list, tuple)) else []


def test_targets_to_moves_every_tensor_and_its_base():
    """Targets.to puts every tensor, the moving base's too, on the device, values kept."""
    body = tb.arm()
    motion, _ = gestures.generate(body, gestures=[gestures.GESTURES["tuck"]], rate=20.0)[0]
    tg = prepare(body, [motion])
    t = np.linspace(0.0, 3.0, 8)
    still = BaseMotion(t, np.broadcast_to(np.eye(3), (8, 3, 3)), np.zeros((8, 3)))
    tg = dataclasses.replace(tg, base=Bases.of([still]))
    moved = tg.to("meta")
    assert len(tensors(moved)) == len(tensors(tg)) > 10
    assert all(t.device.type == "meta" for t in tensors(moved))
    assert moved.names == tg.names and moved.q.shape == tg.q.shape
    again = tg.to("cpu")
    assert all(torch.equal(a, b) for a, b in zip(tensors(again), tensors(tg)))


@cuda
def test_dynamics_and_simulation_on_cuda(rng):
    """The algorithms and a simulation run on a CUDA device and agree with the CPU."""
    body = tb.arm()
    q, v, a = (torch.as_tensor(rng.normal(size=(4, body.nv)), dtype=DT) for _ in range(3))
    there = [x.cuda() for x in (q, v, a)]
    for f in (D.rnea, D.forward_dynamics):
        assert torch.allclose(f(body, *there).cpu(), f(body, q, v, a), atol=1e-10)
    t = torch.linspace(0, 0.5, 6, dtype=DT)
    opts = SimOptions(rtol=1e-9, atol=1e-9)
    here = simulate(body, zero_program, q, v, t, opts).q
    far = simulate(body, zero_program, there[0], there[1], t.cuda(), opts).q
    assert torch.allclose(far.cpu(), here, atol=1e-6)


@cuda
def test_field_program_path_loss_and_gradient_on_cuda():
    """Two gestures simulated under their field programs through odeint, their path loss
    and its gradient with respect to the weights and the fields: the same on the GPU as
    on the CPU (weights scaled by 1.05 so the loss is not zero)."""
    body = tb.arm()
    chosen = [gestures.GESTURES[g] for g in ("tuck", "planar_line")]
    motions = [m for m, _ in gestures.generate(body, gestures=chosen, rate=50.0)]
    basis, w, _ = gestures.library_model(chosen, body=body)
    results = []
    for device in ("cpu", "cuda"):
        b = copy.deepcopy(basis).to(device)          # Module.to moves in place
        weights = MotionWeights(w.a * 1.05, w.b, w.duration, names=w.names).to(device)
        tg = prepare(body, motions).to(device)
        q_sim, v_sim = simulate_targets(body, b, weights, tg, SimOptions())
        loss = path_loss(body, q_sim, v_sim, tg).sum()
        loss.backward()
        assert q_sim.device.type == device
        results.append([x.detach().cpu().clone() for x in (loss, weights.a_raw.grad, b.eta.grad)])
    (l0, ga0, ge0), (l1, ga1, ge1) = results
    assert l0 > 1e-6 and ge0.abs().max() > 1e-6
    assert torch.allclose(l1, l0, rtol=1e-5)
    assert torch.allclose(ga1, ga0, rtol=1e-4, atol=1e-8 * float(ga0.abs().max()))
    assert torch.allclose(ge1, ge0, rtol=1e-4, atol=1e-8 * float(ge0.abs().max()))


def test_a_device_this_machine_lacks_is_refused_when_the_run_starts(tmp_path):
    """device: cuda validates anywhere (a run's config is read on any machine) but a run
    refuses to start without one; a name torch does not know is refused at once."""
    cfg = config.load(None, ["device=cuda:99", f"out={tmp_path}"])
    with pytest.raises(config.ConfigError, match="'cuda:99'"):
        train.run(cfg)
    assert not (tmp_path / "checkpoint.pt").exists()
    with pytest.raises(config.ConfigError, match="device.*cpu, cuda or cuda:K.*'tpu'"):
        config.load(None, ["device=tpu"])
    assert config.load(None, []).device == "cpu"


def _flat(lb) -> torch.Tensor:
    """A basis file's fields and weights as one vector."""
    w = lb.weights
    return torch.cat([lb.basis.eta.detach().flatten(), lb.basis.K().detach().flatten(),
                      w.a.detach().flatten(), w.b.detach().flatten()])


@cuda
def test_training_on_cuda_learns_the_cpu_basis(tmp_path):
    """The shared small run (2 motions) trained with device: cuda — every stage's tensors
    on the GPU, as its checkpoint shows — takes the same M and reproduces the same motions
    as on the CPU, its basis within 1e-6 of the CPU's (measured on an H200: the bases'
    numbers at most 3.4e-8 apart, the runs' RMSE 1e-10; 90 s there against 9 s on its
    CPU)."""
    programs = gestures.random_gestures(SMALL_GESTURES["count"], seed=SMALL_GESTURES["seed"],
                                        ranges=SMALL_GESTURES["ranges"])
    write_motions(tmp_path / "data", programs)
    runs = {d: train.run(small_config(tmp_path / "data", tmp_path / d, f"device={d}"))
            for d in ("cpu", "cuda")}
    state = torch.load(tmp_path / "cuda" / "checkpoint.pt", weights_only=True)
    assert {t.device.type for t in tensors(state["model"])} == {"cuda"}
    here, there = runs["cpu"], runs["cuda"]
    assert there["overall"]["M"] == here["overall"]["M"] >= 1
    assert [m["success"] for m in there["motions"].values()] == \
        [m["success"] for m in here["motions"].values()]
    a, b = (_flat(bio.load(tmp_path / d / "basis.json")) for d in ("cpu", "cuda"))
    print("largest difference of the bases' numbers:", float((a - b).abs().max()))
    assert torch.allclose(b, a, rtol=1e-6, atol=1e-6)
