"""Figures of motions (figures), of the model (model), of bodies drawn link by link (bodies),
of pushes and recovery (recovery). Matplotlib draws with the Agg
backend (no display needed)."""
import matplotlib

matplotlib.use("Agg")
