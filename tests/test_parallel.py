"""Many processes (tflearn.parallel): the shard of motions per rank, the collectives in a
world of size 1 and of 2 gloo processes, and training under torch.distributed — two
processes started by torchrun give the one-process run's basis.json, and a checkpoint
written by two ranks resumes in one process to the same basis."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from tflearn import parallel, train

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
        parallel.barrier()
    assert parallel.backend("cpu") == "gloo" and parallel.backend("cuda:1") == "nccl"


def test_world_size_without_an_address_is_refused(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    with pytest.raises(RuntimeError, match="MASTER_ADDR"):
        with parallel.group("cpu"):
            pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_main(rank: int, size: int, port: int, data: str, out: str) -> None:
    """One of two gloo ranks: the collectives, then training stopped after its first
    checkpoint (the first round of ``each``: both motions, one per rank)."""
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=size)
    try:
        assert (parallel.rank(), parallel.size(), parallel.mine(5)) == (rank, 2, {0: [0, 2, 4], 1: [1, 3]}[rank])
        assert parallel.all_gather(("r", rank)) == [("r", 0), ("r", 1)]
        assert parallel.broadcast({"from": rank}) == {"from": 0}
        x = parallel.all_reduce_sum(torch.tensor([1.0, 10.0 * rank], dtype=torch.float64))
        assert x.tolist() == [2.0, 10.0]
        assert parallel.gather_motions(5, [f"m{j}" for j in parallel.mine(5)]) == [f"m{j}" for j in range(5)]
        torch.set_num_threads(1)
        try:
            train.run(small_config(data, out), stop_after=1)
        except train.Interrupted:
            pass
        else:
            raise AssertionError("the run was not interrupted")
    finally:
        dist.destroy_process_group()


def test_two_ranks_checkpoint_resumes_in_one_process(run_dir, tmp_path):
    """Two gloo ranks (torch.multiprocessing) fit both motions of the small run in one
    round of ``each`` and stop at its checkpoint (rank 0's); one process resumes it and
    ends with the one-process run's basis.json (to 1e-6)."""
    out = tmp_path / "run"
    mp.spawn(_rank_main, args=(2, _free_port(), str(run_dir["data"]), str(out)), nprocs=2)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert (state["stage"], state["cursor"], len(state["fits"])) == ("each", 2, 2)
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]
    metrics = train.run(small_config(run_dir["data"], out))
    assert_same_basis(out / "basis.json", run_dir["out"] / "basis.json", tol=1e-6)
    ref = json.loads((run_dir["out"] / "metrics.json").read_text())
    assert metrics["overall"]["M"] == ref["overall"]["M"] and metrics["history"] == ref["history"]


def test_torchrun_two_processes_give_the_one_process_basis(run_dir, tmp_path):
    """``torchrun --standalone --nproc-per-node 2 -m tflearn.cli train`` on the small
    run's motions: the one-process run's basis.json (to 1e-6), its M and history, and
    the summary printed once (rank 0)."""
    out = tmp_path / "run2"
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
