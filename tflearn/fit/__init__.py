"""Fitting torque fields to motions.

* :mod:`.nnls` — batched non-negative least squares (exact weight solves),
* :mod:`.torque` — torque matching (thesis eq. 3.10/3.11), EM alternation, joint descent,
* :mod:`.path` — path matching through ``odeint`` simulation, metrics,
* :mod:`.slsqp` — the thesis' SQP baseline (scipy SLSQP, numerical derivatives),
* :mod:`.search` — global search: data-driven centres, multi-start, greedy growth of M,
* :mod:`.identity` — generating fields matched to learned ones along the directions
  their motions excite.
"""
