"""The shared basis chosen among pooled fields (tflearn.fit.select): copies of one field
that differ only where no motion looks are one field, different fields are not, and a
planted library comes back whole and no larger."""
from dataclasses import replace

import pytest
import torch

from tflearn import config
from tflearn.data import gestures as gs
from tflearn.fit import select, torque
from tflearn.fit.targets import prepare
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import MotionWeights
from tflearn.physics import body as tb
from tflearn.train import run

SOFT, STIFF = 6, 0          # the wrist axis of K = diag(1.5, …, 1.5, 1e-3), and a stiff one


def _copies(axis: int, distance: float = 0.3):
    """Four motions of one field with a soft wrist axis, the first made by a copy moved
    ``distance`` rad along ``axis``; the pooled candidates are each motion's own field
    (the copy, then three times the original), with each motion's own weights."""
    body = tb.arm()
    programs = [replace(g, k=((1.5,) * 6 + (1e-3,),)) for g in gs.random_gestures(4, seed=3, library=1)]
    eta = torch.tensor(programs[0].eta[0])
    moved = eta + distance * torch.eye(7, dtype=torch.float64)[axis]
    programs[0] = replace(programs[0], eta=(tuple(moved.tolist()),))
    tg = prepare(body, [m for m, _ in gs.generate_resolved(programs, body)])
    K = torch.diag(torch.tensor(programs[0].k[0], dtype=torch.float64)).expand(4, 7, 7).clone()
    basis = FieldBasis(torch.stack([moved, eta, eta, eta]), K, "diag")
    weights = MotionWeights.zeros(4, tg.duration, tg.names)
    own = torch.eye(4, dtype=torch.bool)
    torque.solve_weights(basis, weights, tg, support=torch.cat([own, own], 1))
    return basis, weights, tg, own


def test_copies_that_differ_along_an_unexcited_direction_are_one_field():
    basis, weights, tg, own = _copies(SOFT)
    assert float((basis.eta[0] - basis.eta[1]).detach().norm()) > 5 * config.MergeSection().distance
    s = select.select(basis, weights, tg, own)
    assert len(s.kept) == 1 and not s.unserved
    assert all(c <= t for c, t in zip(s.costs, s.tolerance))
    dropped = ({0, 1} - set(s.kept)).pop()
    assert [s.kept[0], dropped] in s.merged


def test_fields_that_differ_where_the_motions_look_are_not_merged():
    basis, weights, tg, own = _copies(STIFF)
    s = select.select(basis, weights, tg, own)
    assert sorted(s.kept) == [0, 1] and not s.unserved
    assert sorted(s.merged) == [[1, 2], [1, 3]]              # the exact copies only


def test_the_forward_path_never_costs_more_with_more_fields():
    basis, weights, tg, own = _copies(STIFF)
    path = select.select(basis, weights, tg, own).path
    costs, served = [p[1] for p in path], [p[2] for p in path]
    assert [p[0] for p in path] == list(range(1, len(path) + 1))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(costs, costs[1:]))
    assert served == sorted(served) and served[-1] == tg.N


def test_the_screen_reports_its_blocks_and_the_choice_its_fields():
    """In blocks of two motions the screen tells each block's end, then the choice each
    field that joins; the same two fields are chosen as without the screen."""
    basis, weights, tg, own = _copies(STIFF)
    told = []
    s = select.select(basis, weights, tg, own, select.SelectOptions(block=2),
                      progress=lambda **done: told.append(done))
    assert told == [{"screened": "1/2 blocks"}, {"screened": "2/2 blocks"}, {"chosen": 1}, {"chosen": 2}]
    assert sorted(s.kept) == [0, 1]


def test_a_field_only_a_motion_not_required_needs_is_not_chosen():
    """Motion 0 alone needs field 0 (it differs where the motions look): not required
    (its own fit did not reproduce it), it adds no field, and draws on the one chosen for
    the others, unserved but not listed as such; the others are served as before."""
    basis, weights, tg, own = _copies(STIFF)
    s = select.select(basis, weights, tg, own, required=[False, True, True, True])
    assert s.kept == [1] and not s.unserved and s.support[0] == [1]
    assert s.costs[0] > s.tolerance[0] and all(c <= t for c, t in zip(s.costs[1:], s.tolerance[1:]))
    assert sorted(select.select(basis, weights, tg, own, select.SelectOptions(block=2),
                                required=[False, True, True, True]).kept) == [1]


def test_a_floor_under_the_own_fits_cost_lets_a_near_field_serve():
    """Motion 0's own field (a copy 0.3 rad off along a stiff axis) fits it better than
    the others' field; with its bar raised to its cost on that field (the floor a
    simpler own fit that simulation reproduces would set) the others' field serves it
    too, and one field is chosen."""
    basis, weights, tg, own = _copies(STIFF)
    alone = weights.select_motions([0]).select_fields([1])
    on_theirs = float(torque.solve_weights(basis.select([1]), alone, tg.select([0]))[0])
    s = select.select(basis, weights, tg, own, floor=[on_theirs, 0.0, 0.0, 0.0])
    assert s.kept == [1] and not s.unserved
    assert s.tolerance[0] == pytest.approx(on_theirs + select.SelectOptions().tol)


def test_the_reproducing_cost_is_that_of_the_fewest_fields_simulation_takes():
    """:func:`select.reproducing_cost`: the fields join greedily by cost (motion 1's own
    field first, then the moved copy); the cost at the first size the check accepts, or
    on all of them."""
    basis, weights, tg, own = _copies(STIFF)
    both = MotionWeights.zeros(4, tg.duration, tg.names)
    sizes = []

    def accept_at(k):
        return lambda b, w: sizes.append(b.M) or b.M >= k
    first = select.reproducing_cost(basis, both, tg, 1, [0, 1], accept_at(1))
    alone = float(torque.solve_weights(basis.select([1]), both.select_motions([1]).select_fields([1]),
                                       tg.select([1]))[0])
    assert first == pytest.approx(alone, rel=1e-9) and sizes == [1]
    sizes.clear()
    whole = select.reproducing_cost(basis, both, tg, 1, [0, 1], accept_at(3))
    pair = float(torque.solve_weights(basis.select([0, 1]), both.select_motions([1]).select_fields([0, 1]),
                                      tg.select([1]))[0])
    assert whole == pytest.approx(pair, rel=1e-9) and whole <= first and sizes == [1]


def test_each_motion_gets_its_fewest_chosen_fields_that_serve_it():
    basis, weights, tg, own = _copies(STIFF)
    s = select.select(basis, weights, tg, own)
    assert sorted(s.kept) == [0, 1]
    assert s.support == [[0], [1], [1], [1]]                 # each its own field alone
    assert all(c <= t for c, t in zip(s.costs, s.tolerance))


def test_an_own_fit_whose_torques_are_no_motions_is_judged_by_its_fields():
    """An own fit whose torques are no motion's (weights ten times too large, C_j > 1, as
    path shooting with free fields can leave one) is held to its own fields' NNLS bar —
    the bar of the fit with its exact weights —, not served by no field at all."""
    basis, weights, tg, own = _copies(STIFF)
    exact = select.select(basis, weights, tg, own)
    weights.set_flat(("a_raw", "b_raw"), 10 * weights.flat(("a_raw", "b_raw")), list(range(4)))
    assert all(c > 1 for c in torque.torque_costs(basis, weights, tg).tolist())
    s = select.select(basis, weights, tg, own)
    assert s.tolerance == pytest.approx(exact.tolerance, rel=1e-6) and max(s.tolerance) < 0.01
    assert sorted(s.kept) == sorted(exact.kept) and s.support == exact.support and not s.unserved
    bare, alone = own.clone(), MotionWeights.zeros(4, tg.duration, tg.names)
    bare[0] = False                                          # no field of its own, no torque: C = 1
    s = select.select(basis, alone, tg, bare)
    assert s.tolerance[0] == pytest.approx(1 - select.SelectOptions().tol) and len(s.support[0]) == 1


def test_a_motion_needs_one_of_two_copies_and_each_different_field():
    """:func:`select.needed`: of a field, a copy of it and a field the motion has no use
    for, the motion needs the field alone; of two fields that differ where it looks, it
    needs the one its weights are on."""
    basis, weights, tg, own = _copies(STIFF)
    both = MotionWeights.zeros(4, tg.duration, tg.names)
    torque.solve_weights(basis, both, tg)                    # every motion on every field
    assert select.needed(basis, both, tg, 1, [1, 2, 3], 1e-4) == [1]
    assert select.needed(basis, weights, tg, 0, [0, 1], 1e-4) == [0]
    assert select.needed(basis, weights, tg, 1, [0, 1], 1e-4) == [1]
    assert select.needed(basis, weights, tg, 1, [], 1e-4) == []


def test_exact_copies_are_one_candidate():
    basis, weights, tg, own = _copies(STIFF)                 # fields 1, 2, 3: one field thrice
    s = select.select(basis, weights, tg, own)
    assert all(2 not in c and 3 not in c for c in s.candidates)
    assert all(1 in c for c in s.candidates[1:])


def test_reach_is_relative_to_the_motions_own_fields():
    """A copy of a motion's own field is its candidate however weak both are on its path:
    with reach 0.9, an absolute bar would leave motion 1 its own copy alone."""
    basis, weights, tg, own = _copies(STIFF, distance=1e-6)
    peak = basis.gaussians(tg.q[1][tg.mask[1]]).max(0).values
    assert float(peak[1]) < 0.9
    s = select.select(basis, weights, tg, own, select.SelectOptions(reach=0.9))
    assert 0 in s.candidates[1] and len(s.kept) == 1


@pytest.mark.parametrize("axis", [SOFT, STIFF])
def test_a_screen_by_blocks_chooses_what_the_whole_selection_does(axis):
    """Blocks of two motions, each choosing among its own motions' fields, then every
    motion among the blocks' choices: the same fields and supports as one selection
    over all candidates, each motion seeing no more candidates than there — and not a
    pooled field that is no motion's own (here a copy of field 1 moved 1e-3 rad), which
    no block chooses."""
    basis, weights, tg, own = _copies(axis)
    basis = basis.extend(basis.eta.detach()[1:2] + 1e-3, basis.K().detach()[1:2])
    weights, own = weights.extend_fields(1), torch.cat([own, torch.zeros(4, 1, dtype=torch.bool)], 1)
    whole = select.select(basis, weights, tg, own, select.SelectOptions(block=0))
    screened = select.select(basis, weights, tg, own, select.SelectOptions(block=2))
    assert sorted(screened.kept) == sorted(whole.kept) and screened.support == whole.support
    assert screened.costs == pytest.approx(whole.costs, rel=1e-9) and not screened.unserved
    assert all(set(a) <= set(b) for a, b in zip(screened.candidates, whole.candidates))
    assert any(4 in c for c in whole.candidates) and not any(4 in c for c in screened.candidates)


@pytest.mark.slow
def test_a_planted_library_of_three_fields_in_twelve_motions_gives_back_three(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    from tflearn.io import basis as basis_io
    from tflearn.motions.motion import save
    for motion, generating in gs.generate_resolved(gs.random_gestures(12, seed=5, library=3)):
        save(motion, data / f"{motion.name}.npz")
        basis_io.save(generating, data / f"{motion.name}.json")
    cfg = config.load("configs/gestures.yaml", [f"data={data}", f"out={tmp_path / 'run'}",
                                                 "log.tensorboard=false", "log.progress=false"])
    metrics = run(cfg)
    assert metrics["overall"]["M"] == 3
    assert all(m["success"] for m in metrics["motions"].values())
    assert metrics["identity"]["matched"] == metrics["identity"]["G"] == 3
    chosen = metrics["history"]["pool"]["selection"]
    assert chosen["kept"] == 3 and chosen["pooled"] > 3
    assert (tmp_path / "run" / "knee.png").stat().st_size > 0
