"""Motions: sampled joint trajectories with splines and inverse-dynamics torques (motion) and the
moving base a motion may carry (torso)."""
