"""Motions: sampled joint trajectories and their files (motion), splines through them and
their inverse-dynamics torques (spline), and the moving base a motion may carry (torso)."""
