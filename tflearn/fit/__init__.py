"""Fitting torque fields to motions.

* :mod:`.targets` — motions prepared for fitting: padded samples, velocities, torques,
* :mod:`.nnls` — batched non-negative least squares (exact weight solves),
* :mod:`.torque` — torque matching (thesis eq. 3.10/3.11), EM alternation, joint descent,
* :mod:`.impedance` — weights that also give a stiffness about the path; equilibria,
* :mod:`.layout` — fields laid out around the motions (spanning polytopes, convergent pairs),
* :mod:`.path` — path matching through ``odeint`` simulation, metrics,
* :mod:`.shooting` — path matching by multiple shooting and Levenberg–Marquardt,
* :mod:`.receding` — the same window by window, for long motions,
* :mod:`.stability` — local error growth along a path,
* :mod:`.slsqp` — the thesis' SQP baseline (scipy SLSQP, numerical derivatives),
* :mod:`.search` — global search: data-driven centres, multi-start, greedy growth of M,
* :mod:`.select` — the shared basis chosen among pooled fields by the motions,
* :mod:`.identity` — generating fields matched to learned ones along the directions
  their motions excite.
"""
