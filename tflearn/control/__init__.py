"""Control and perturbation: torque programs that track or play a motion (controllers), pushes
and carried masses (pushes), and the ``perturb`` command with its recovery measures (recovery)."""
