"""tflearn: learn a shared basis of convergent torque fields from limb motions.

Data flows one way: motions → torques → fit → basis → simulate → metrics and plots.
"""
import torch as _torch

__version__ = "0.1.0"

DTYPE = _torch.float64
