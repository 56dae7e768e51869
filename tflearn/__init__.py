"""tflearn: learn a shared basis of convergent torque fields from limb motions.

Data flows one way: motions → torques → fit → basis → simulate → metrics and plots.

The public API (imported lazily, so that ``import tflearn.config`` stays light):

* bodies — :class:`Body`, :class:`Link`, :func:`arm`, :func:`chain`, :func:`body_from_config`;
* motions — :class:`Motion`, :func:`load_motion`, :func:`save_motion`, :func:`load_motions`;
  recordings of joint angles: :func:`read_csv` (a CSV file), :func:`from_euler` (arrays);
* the model — :class:`FieldBasis` (shared fields), :class:`MotionWeights` (per-motion
  weights), :class:`FieldProgram` (their torque program);
* simulation — :class:`SimOptions`, :class:`Trajectory`, :class:`SimulationFailed`
  (the integrator itself is :func:`tflearn.simulation.simulate.simulate`);
* scores — :func:`score`, :class:`Scores`;
* learning — :class:`Config`, :func:`load_config`, :func:`learn` (``train CONFIG``);
* trained bases — :class:`LearnedBasis`, :func:`load_basis`, :func:`save_basis`,
  :func:`evaluate_run`, :func:`synthesize`;
* errors — :class:`InputError`, the base of every bad-input error.
"""
import importlib

__version__ = "0.1.0"

_API = {
    "Body": "physics.body", "Link": "physics.body", "arm": "physics.body", "chain": "physics.body",
    "body_from_config": ("physics.body", "from_config"),
    "Motion": "motions.motion", "load_motion": ("motions.motion", "load"),
    "save_motion": ("motions.motion", "save"),
    "load_motions": "data.loading", "read_csv": "motions.motion", "from_euler": "motions.motion",
    "FieldBasis": "model.fields", "MotionWeights": "model.weights", "FieldProgram": "model.program",
    "SimOptions": "simulation.simulate", "Trajectory": "simulation.simulate",
    "SimulationFailed": "simulation.simulate",
    "score": "metrics", "Scores": "metrics",
    "Config": "config", "load_config": ("config", "load"), "learn": ("train", "run"),
    "LearnedBasis": "io.basis", "load_basis": ("io.basis", "load"), "save_basis": ("io.basis", "save"),
    "evaluate_run": "evaluate", "synthesize": "evaluate",
    "InputError": "errors",
}
__all__ = sorted(_API)


def __getattr__(name):
    if name not in _API:
        raise AttributeError(f"module 'tflearn' has no attribute {name!r}")
    module, attr = _API[name] if isinstance(_API[name], tuple) else (_API[name], name)
    return getattr(importlib.import_module(f"tflearn.{module}"), attr)


def __dir__():
    return __all__ + ["__version__"]
