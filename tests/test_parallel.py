"""Many processes (tflearn.parallel): the shard of motions per rank, the collectives in a
world of size 1 and of 2 gloo processes, and training under torch.distributed — two
ranks fit a round of ``each`` as one process does, and torchrun's two processes resume a
one-process checkpoint to the one-process run's basis.json."""
from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import tflearn
from tflearn import parallel, train
from tflearn.fit import path as path_fit
from tflearn.fit import select, shooting, targets, torque
from tflearn.fit.shooting import ShootingOptions
from tflearn.fit.targets import prepare
from tflearn.model.fields import FieldBasis
from tflearn.model.program import model_state
from tflearn.model.weights import MotionWeights
from tflearn.motions.motion import Motion
from tflearn.simulation.simulate import SimOptions
from tflearn.train.stages import each

from test_learning import SMALL_OVERRIDES, assert_same_basis, small_config, small_run

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return small_run(tmp_path_factory)       # the one-process run shared with test_learning.py


@pytest.mark.parametrize("n", [0, 1, 2, 5, 17])
@pytest.mark.parametrize("size", [1, 2, 3, 8])
def test_shard_deals_every_index_once(n, size):
    shards = [parallel.shard(n, r, size) for r in range(size)]
    assert sorted(j for s in shards for j in s) == list(range(n))
    for r, s in enumerate(shards):
        assert s == sorted(s) and all(j % size == r for j in s)
        assert parallel.shard(n, r, size) == s                       # deterministic
    assert max(len(s) for s in shards) - min(len(s) for s in shards) <= 1


@pytest.mark.parametrize("rank,size", [(-1, 2), (2, 2), (0, 0)])
def test_shard_refuses_a_rank_outside_the_world(rank, size):
    with pytest.raises(ValueError, match="not one of"):
        parallel.shard(4, rank, size)


def test_a_single_process_is_a_world_of_one(monkeypatch):
    for k in parallel.ENV:
        monkeypatch.delenv(k, raising=False)
    x = torch.tensor([1.0, 2.0], dtype=torch.float64)
    with parallel.group("cpu"):
        assert not dist.is_initialized()
        assert (parallel.rank(), parallel.size(), parallel.mine(3)) == (0, 1, [0, 1, 2])
        assert parallel.all_gather({"a": 1}) == [{"a": 1}]
        assert parallel.broadcast("x") == "x"
        assert parallel.all_reduce_sum(x) is x and x.tolist() == [1.0, 2.0]
        assert parallel.gather_motions(3, ["p", "q", "r"]) == ["p", "q", "r"]
    assert parallel.backend("cpu") == "gloo" and parallel.backend("cuda:1") == "nccl"


def test_rows_sent_to_other_ranks_carry_their_own_elements_only():
    """What a rank pickles for the others (:func:`parallel._cpu`): a row of a matrix,
    a view, pickled as it is carries the whole matrix (measured: 10 rows of a
    1000×100 float64 matrix, 8 MB); sent, it carries its own 100 numbers, unchanged,
    and a tensor that owns its storage is sent as it is."""
    import pickle
    big = torch.arange(100_000, dtype=torch.float64).reshape(1000, 100)
    rows = [big[j] for j in range(0, 1000, 100)]
    sent = parallel._cpu({"rows": rows, "whole": big, "n": 3})
    assert all(torch.equal(a, b) for a, b in zip(sent["rows"], rows)) and sent["n"] == 3
    assert len(pickle.dumps(rows)) > 10 * big.nbytes            # why: each view carries big
    assert len(pickle.dumps(sent["rows"])) < 2 * 10 * rows[0].nbytes
    assert sent["whole"] is big


def test_named_tuples_are_sent_whole():
    """A per-motion fit (a named tuple, :class:`tflearn.train.state.FieldFit`) sent to the
    other ranks comes back the same type with its rows."""
    from tflearn.train.state import FieldFit
    big = torch.arange(20, dtype=torch.float64).reshape(4, 5)
    sent = parallel._cpu([FieldFit(big[1:2], big[2:4], {"a_raw": big[3]})])[0]
    assert isinstance(sent, FieldFit) and torch.equal(sent.eta, big[1:2]) and torch.equal(sent.K, big[2:4])
    assert torch.equal(sent.timing["a_raw"], big[3])


def test_local_device_is_the_ranks_gpu(monkeypatch):
    """Plain cuda is GPU LOCAL_RANK (0 without torchrun); a numbered device stays itself."""
    monkeypatch.delenv("LOCAL_RANK", raising=False)
    assert parallel.local("cuda") == torch.device("cuda", 0)
    monkeypatch.setenv("LOCAL_RANK", "2")
    assert parallel.local("cuda") == torch.device("cuda", 2)
    assert parallel.local("cuda:3") == torch.device("cuda", 3)
    assert parallel.local("cpu") == torch.device("cpu")


def test_world_size_without_an_address_is_refused(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    with pytest.raises(RuntimeError, match="MASTER_ADDR"):
        with parallel.group("cpu"):
            pass


class _Threads:
    """A world of ``size`` ranks as threads: :func:`parallel.rank`, :func:`parallel.size`
    and :func:`parallel.all_gather` (a barrier) for the test of code above them."""
    def __init__(self, monkeypatch, size: int):
        self.local, self.barrier, self.box = threading.local(), threading.Barrier(size), [None] * size
        monkeypatch.setattr(parallel, "rank", lambda: self.local.rank)
        monkeypatch.setattr(parallel, "size", lambda: size)
        monkeypatch.setattr(parallel, "all_gather", self.all_gather)

    def all_gather(self, obj) -> list:
        self.box[self.local.rank] = obj
        self.barrier.wait()
        out = list(self.box)
        self.barrier.wait()
        return out

    def run(self, f) -> list:
        """f() on every rank, its results by rank."""
        results = [None] * len(self.box)

        def main(r):
            self.local.rank = r
            results[r] = f()
        threads = [threading.Thread(target=main, args=(r,)) for r in range(len(self.box))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return results


@pytest.mark.parametrize("library", [None, "fields"])
def test_each_deals_the_declined_motions_searches_to_the_ranks_in_turn(monkeypatch, tmp_path, library):
    """:func:`each.fits` on two ranks: the motions of a block (10 … 17) are tried on
    the library by one rank each (rank = position mod 2), and the three it declines
    (11, 12, 15) are searched in turn — 11 and 15 by rank 0, 12 by rank 1, where the
    motions' own ranks would give two to rank 1 — each with its seed and told why it was
    declined; both ranks get every fit in motion order. Without a library every motion
    is searched, dealt the same way."""
    world, calls = _Threads(monkeypatch, 2), []
    ctx = train.new_context(small_config("gestures", tmp_path / "run"), None)

    def reuse(ctx, lib, tg, k):
        calls.append(("try", parallel.rank(), k))
        taken = each.MotionFit(k, 0.0, 1, True, reused=True)
        return (None, f"why {k}") if k in (11, 12, 15) else (taken, None)

    def fit_one(ctx, tg, k, seed):
        calls.append(("search", parallel.rank(), k))
        return each.MotionFit(k, float(seed), 1, False)            # its seed as its cost
    monkeypatch.setattr(each, "reuse", reuse)
    monkeypatch.setattr(each, "fit_one", fit_one)
    batch, seeds = list(range(10, 18)), [100 + k for k in range(20)]
    fits = world.run(lambda: each.fits(ctx, library, None, batch, seeds))
    assert fits[0] == fits[1]
    if library is None:
        assert fits[0] == [each.MotionFit(k, 100.0 + k, 1, False) for k in batch]
        assert sorted(calls) == sorted(("search", i % 2, k) for i, k in enumerate(batch))
        return
    assert fits[0] == [each.MotionFit(k, 100.0 + k, 1, False, declined=f"why {k}") if k in (11, 12, 15)
                       else each.MotionFit(k, 0.0, 1, True, reused=True) for k in batch]
    assert sorted(c for c in calls if c[0] == "try") == sorted(("try", i % 2, k) for i, k in enumerate(batch))
    assert sorted(c for c in calls if c[0] == "search") == [("search", 0, 11), ("search", 0, 15),
                                                          ("search", 1, 12)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _path_problem():
    """Three short made-up motions (0.04 s, 5 samples) and a two-field model, simulated
    by fixed-step rk4 (so that a batch gives each motion what it gets alone)."""
    body = tflearn.arm()
    t = torch.linspace(0, 0.04, 5, dtype=torch.float64)
    motions = []
    for j in range(3):
        phase = torch.arange(7, dtype=torch.float64) + j
        q = 0.2 * (j + 1) * torch.sin(3 * t[:, None] + phase)
        motions.append(Motion(f"m{j}", t, q, 0.6 * (j + 1) * torch.cos(3 * t[:, None] + phase)))
    tg = prepare(body, motions)
    eye = torch.eye(7, dtype=torch.float64)
    basis = FieldBasis(torch.stack([0.3 * torch.ones(7), -0.2 * torch.ones(7)]).double(),
                       torch.stack([1.5 * eye, 0.7 * eye]), kind="diag", blocks=body.blocks)
    weights = MotionWeights(torch.tensor([[1.0, 2.0], [0.5, 1.5], [2.0, 0.3]], dtype=torch.float64),
                            torch.tensor([[0.4, 0.1], [0.2, 0.9], [0.6, 0.5]], dtype=torch.float64),
                            tg.duration, names=tg.names)
    return body, basis, weights, tg


def _path_steps(distributed: bool) -> dict:
    """Two path-matching steps (the second from the first's Adam state) on
    :func:`_path_problem`, three iterations of shooting its fields (moved by 0.05) and
    weights, and 6 EM steps towards its model from centres moved by 0.1,
    the three motions in one chunk ("em": every rank runs EM whole) and in a chunk each
    ("em_chunks", ``targets.CHUNK_BYTES`` 1: the ranks share the chunks)."""
    body, basis, weights, tg = _path_problem()
    options = SimOptions(method="rk4", solver_options={"step_size": 0.01})
    first = path_fit.path_step(body, basis, weights, tg, 0.01, options=options, distributed=distributed)
    second = path_fit.path_step(body, basis, weights, tg, first.lr, first.best, first.optimizer,
                                options=options, distributed=distributed)
    out = {"loss": [first.loss, second.loss], "model": model_state(basis, weights)}
    _, basis, weights, tg = _path_problem()                # the fields shared by the three motions' paths
    with torch.no_grad():
        basis.eta += 0.05
    res = shooting.shooting_match(body, basis, weights, tg, sim=options, distributed=distributed,
                                  options=ShootingOptions(fields=True, iterations=3))
    out["shooting"], out["shooting_model"] = res.loss, model_state(basis, weights)
    for key, chunk_bytes in (("em", targets.CHUNK_BYTES), ("em_chunks", 1)):
        _, basis, weights, tg = _path_problem()               # EM from off the model that made tg.tau
        x = torch.cat([weights.a, weights.b], -1)
        tau = (torque.design(basis, weights, tg) @ x[:, None, :, None]).squeeze(-1)
        tg = dataclasses.replace(tg, tau=tau)
        with torch.no_grad():
            basis.eta += 0.1
        saved, targets.CHUNK_BYTES = targets.CHUNK_BYTES, chunk_bytes
        try:
            out[key] = torque.em(basis, weights, tg, steps=6, distributed=distributed)
        finally:
            targets.CHUNK_BYTES = saved
        out[f"{key}_model"] = model_state(basis, weights)
    return out


def _path_shooting_start() -> list:
    """The three motions' path losses at :func:`_path_steps`' shooting start."""
    body, basis, weights, tg = _path_problem()
    with torch.no_grad():
        basis.eta += 0.05
    options = SimOptions(method="rk4", solver_options={"step_size": 0.01})
    return shooting.shooting_match(body, basis, weights, tg, sim=options,
                                   options=ShootingOptions(fields=True, iterations=0)).loss


def _screened_selection(distributed: bool) -> dict:
    """The selection of four motions' fields (tests/test_select.py's copies) screened in
    blocks of two, as a dict: the blocks shared by the ranks, the choice made on rank 0."""
    from test_select import STIFF, _copies
    basis, weights, tg, own = _copies(STIFF)
    return dataclasses.asdict(select.select(basis, weights, tg, own, select.SelectOptions(block=2),
                                            distributed=distributed))


def _rank_main(rank: int, size: int, port: int, data: str, out: str, steps: str) -> None:
    """One of two gloo ranks: the collectives, two distributed path-matching steps (rank 0
    saves them to ``steps``), then training stopped after its first checkpoint (the first
    round of ``each``: both motions, one per rank)."""
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=size)
    try:
        assert (parallel.rank(), parallel.size()) == (rank, 2)
        assert parallel.mine(5) == {0: [0, 2, 4], 1: [1, 3]}[rank]
        assert parallel.all_gather(("r", rank)) == [("r", 0), ("r", 1)]
        assert parallel.broadcast({"from": rank}) == {"from": 0}
        x = parallel.all_reduce_sum(torch.tensor([1.0, 10.0 * rank], dtype=torch.float64))
        assert x.tolist() == [2.0, 10.0]
        assert parallel.gather_motions(5, [f"m{j}" for j in parallel.mine(5)]) == [f"m{j}" for j in range(5)]
        torch.set_num_threads(1)
        result = _path_steps(distributed=True)
        result["selection"] = _screened_selection(distributed=True)
        if rank == 0:
            torch.save(result, steps)
        try:
            train.run(small_config(data, out), stop_after=1)
        except train.Interrupted:
            pass
        else:
            raise AssertionError("the run was not interrupted")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_ranks_share_path_steps_em_and_a_round_of_each(run_dir, tmp_path):
    """Two gloo ranks (torch.multiprocessing): two path-matching steps on three motions
    (two on rank 0, one on rank 1; losses gathered, gradients all-reduced) end where one
    process's do, to rounding (the ranks' gradients are summed in another grouping); EM
    takes one process's steps to the last bit, in one chunk (run whole by every rank) or
    in three (shared: each chunk's weights solved and its terms of JᵀJ and Jᵀr formed by
    one rank, every rank adding them in chunk order); multiple shooting of fields shared by
    the three motions, each rank simulating its share of the segments, ends where one
    process does, to the last bit; the selection screened in blocks, a block per rank,
    chooses what one process does;
    then both ranks fit the two motions of the small run in one round of ``each`` and
    stop at its checkpoint, written by rank 0 alone: the fits are those of one process
    stopped after the same two motions (each motion's search has its own seeded
    generator; a finished run's checkpoint holds no fits, dropped once pooled)."""
    out, steps = tmp_path / "run", tmp_path / "steps.pt"
    mp.spawn(_rank_main, args=(2, _free_port(), str(run_dir["data"]), str(out), str(steps)), nprocs=2)
    shared, alone = torch.load(steps, weights_only=True), _path_steps(distributed=False)
    assert alone["loss"][1] < alone["loss"][0]                  # the steps did something
    assert shared["loss"] == pytest.approx(alone["loss"], rel=1e-12)
    assert sum(alone["shooting"]) < 0.5 * sum(_path_shooting_start())      # the fields moved to the paths
    assert shared["shooting"] == alone["shooting"]
    assert shared["selection"] == _screened_selection(distributed=False)     # a block per rank
    for em in ("em", "em_chunks", "shooting"):
        if em != "shooting":
            assert alone[em][-1] < 0.9 * alone[em][0] and shared[em] == alone[em]  # EM moved; the same steps
        for part in ("basis", "weights"):
            for key, value in alone[f"{em}_model"][part].items():
                assert torch.equal(shared[f"{em}_model"][part][key], value), key
    for part in ("basis", "weights"):
        for key, value in alone["model"][part].items():
            assert torch.allclose(shared["model"][part][key], value, rtol=1e-10, atol=1e-12), key
    for model in ("model", "em_model", "em_chunks_model", "shooting_model"):
        assert not torch.equal(alone[model]["basis"]["eta"], _path_problem()[1].eta.detach())
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]
    with pytest.raises(train.Interrupted):
        train.run(small_config(run_dir["data"], tmp_path / "one"), stop_after=2)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    ref = torch.load(tmp_path / "one" / "checkpoint.pt", weights_only=True)
    assert (state["stage"], state["cursor"], state["iteration"]) == ("each", 2, 2)
    assert torch.load(run_dir["out"] / "checkpoint.pt", weights_only=True)["fits"] == []
    assert len(state["fits"]) == len(ref["fits"]) == 2
    for (eta, K, timing), (eta0, K0, timing0) in zip(state["fits"], ref["fits"]):
        assert torch.equal(eta, eta0) and torch.equal(K, K0)
        assert timing.keys() == timing0.keys() and all(torch.equal(timing[k], timing0[k]) for k in timing)


@pytest.mark.slow
def test_torchrun_resumes_a_one_process_checkpoint(run_dir, tmp_path):
    """One process fits the first motion and stops at that checkpoint; ``torchrun
    --standalone --nproc-per-node 2 -m tflearn.cli train`` resumes it to the end: the
    one-process run's basis.json (to 1e-6), M and history, and the summary printed once
    (by rank 0)."""
    out = tmp_path / "run"
    with pytest.raises(train.Interrupted):
        train.run(small_config(run_dir["data"], out), stop_after=1)
    config = tmp_path / "small.yaml"
    config.write_text("seed: 0\n")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "tflearn.cli", "train", str(config), f"data={run_dir['data']}", f"out={out}",
           *SMALL_OVERRIDES]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("artefacts in") == 1, done.stdout
    assert_same_basis(out / "basis.json", run_dir["out"] / "basis.json", tol=1e-6)
    ref = json.loads((run_dir["out"] / "metrics.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["overall"]["M"] == ref["overall"]["M"] and metrics["history"] == ref["history"]
    for name, row in ref["motions"].items():
        assert abs(metrics["motions"][name]["rmse"] - row["rmse"]) <= 1e-6


@pytest.mark.slow
def test_ranks_leave_the_group_together(tmp_path):
    """Rank 1 leaves the ``group`` body at once with exit status 1 (as ``train`` does when
    a motion is not reproduced), rank 0 only after writing a file 2 s later: torchrun,
    which stops every rank once one exits non-zero, still lets rank 0 finish (the
    barrier at the end of the body), so the file exists."""
    script = tmp_path / "ranks.py"
    script.write_text(f"""import pathlib, sys, time
from tflearn import parallel
with parallel.group("cpu"):
    rank = parallel.rank()
    if rank == 0:
        time.sleep(2)
        pathlib.Path({str(tmp_path / "written")!r}).write_text("rank 0")
sys.exit(rank)
""")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           str(script)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr[-2000:]
    assert (tmp_path / "written").read_text() == "rank 0"

