"""Print the physics validation figures quoted in docs/model.md ("Validation of the physics").

    python bench/validate_physics.py

* largest relative error of RNEA, mass matrix and forward dynamics against Pinocchio
  (PyPI ``pin``) on random states (rotations up to π), with and without gravity;
* relative kinetic-energy drift over 3 s with zero torque, gravity and damping
  (dopri8, rtol = atol = 1e-12, stepping onto every sample time).
"""
import numpy as np
import pinocchio as pin
import torch

from tflearn.physics import body as tb
from tflearn.physics import dynamics
from tflearn.simulation import simulate

torch.set_num_threads(1)


def rel(x: torch.Tensor, ref: np.ndarray) -> float:
    """max |x − ref| / max |ref|."""
    return float(np.abs(x.numpy() - ref).max() / np.abs(ref).max())


def to_pin(body):
    model, ids = pin.Model(), []
    for l in body.links:
        parent = 0 if l.parent < 0 else ids[l.parent]
        place = pin.SE3(pin.exp3(np.array(l.offset)), np.array(l.origin))
        jm = (pin.JointModelSpherical() if l.joint == "ball"
              else pin.JointModelRevoluteUnaligned(np.array(l.axis)))
        jid = model.addJoint(parent, jm, place, l.name)
        inertia = pin.Inertia(l.mass, np.array(l.com), np.array(l.inertia))
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        ids.append(jid)
    model.gravity.linear = np.array(body.gravity)
    return model


def q_pin(body, q):
    out = []
    for i, l in enumerate(body.links):
        s = q[body.slice(i)]
        out.extend(pin.Quaternion(pin.exp3(s)).coeffs() if l.joint == "ball" else s)
    return np.array(out)


def main():
    rng = np.random.default_rng(0)
    worst = {"rnea": 0.0, "mass": 0.0, "aba": 0.0}
    for gravity in [(0, 0, 0), (0, 0, -9.81)]:
        body = tb.arm(gravity=gravity, offsets=[[0.3, -0.2, 0.1], [0, 0, 0], [0, 0.5, 0]])
        model = to_pin(body)
        data = model.createData()
        for _ in range(200):
            q = rng.normal(size=7)
            for s in (slice(0, 3), slice(4, 7)):
                q[s] *= rng.uniform(0, np.pi) / np.linalg.norm(q[s])
            v, a = rng.normal(size=7), rng.normal(size=7)
            qp = q_pin(body, q)
            tau = pin.rnea(model, data, qp, v, a)
            t = torch.tensor
            worst["rnea"] = max(worst["rnea"], rel(dynamics.rnea(body, t(q), t(v), t(a)), tau))
            M = pin.crba(model, data, qp)
            M = np.triu(M) + np.triu(M, 1).T
            worst["mass"] = max(worst["mass"], rel(dynamics.mass_matrix(body, t(q)), M))
            acc = pin.aba(model, data, qp, v, tau)
            worst["aba"] = max(worst["aba"], rel(dynamics.forward_dynamics(body, t(q), t(v), t(tau)), acc))
    for k, e in worst.items():
        print(f"max relative error vs Pinocchio, {k}: {e:.2e}")
    arm = tb.arm()
    g = torch.Generator().manual_seed(0)
    q0 = torch.randn(2, 7, generator=g, dtype=torch.float64)
    v0 = torch.randn(2, 7, generator=g, dtype=torch.float64)
    t = torch.linspace(0, 3, 31, dtype=torch.float64)
    tr = simulate.simulate(arm, simulate.zero_program, q0, v0, t,
                           simulate.SimOptions(method="dopri8", rtol=1e-12, atol=1e-12,
                                               solver_options={"step_t": t[1:]}))
    ke = dynamics.kinetic_energy(arm, tr.q, tr.v)
    print(f"kinetic energy drift over 3 s: {float(((ke - ke[:, :1]).abs() / ke[:, :1]).max()):.2e}")


if __name__ == "__main__":
    main()
