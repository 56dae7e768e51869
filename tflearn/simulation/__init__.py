"""Simulation: the Dormand–Prince solver (ode), the compiled simulator (simkernel), and
:func:`~tflearn.simulation.simulate.simulate` with its options and its failure (simulate)."""
