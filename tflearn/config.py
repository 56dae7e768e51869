"""Training configuration: YAML files plus dotted ``key=value`` overrides.

A config is a nested mapping validated against :data:`DEFAULTS`: every key must exist
there (unknown keys are refused, naming the key and the closest known ones) and values
must have the default's type. Overrides use dotted keys (``solver.em.steps=200``); the
shorthands ``data=``, ``out=`` and ``seed=`` address the top-level keys. Values are parsed
as YAML scalars (``1e-3``, ``true``, ``[1, 2]``).
"""
from __future__ import annotations

import copy
import difflib
import re
from pathlib import Path

import yaml

DEFAULTS: dict = {
    # A folder of .npz motions, a list of .npz files, or "gestures" (the built-in library).
    "data": "gestures",
    "out": "runs/gestures",
    "seed": 0,
    "body": {"preset": "arm"},
    "model": {
        "fields": 0,             # M; 0 = the smallest M that still reproduces every motion
        "stiffness": "diag",     # scalar | diag | block | full
        "phases": "fixed",       # fixed (onset 0, duration λ) | variable (learned onsets/durations)
    },
    "solver": {
        # pipeline (below) | slsqp: the thesis' baseline, SLSQP with numerical derivatives
        # on the torque cost from a seeded random guess (needs model.fields ≥ 1, diag K)
        "method": "pipeline",
        "init": {
            "candidates": 48,    # multi-start candidates per field added
            "stiffness_grid": [0.25, 0.5, 1.0, 2.0, 4.0, 8.0],
        },
        "each": {"max_fields": 3, "tol": 1e-5},   # per-motion growth: fields, relative torque cost
        # Levenberg–Marquardt steps per EM refinement; stop when a step gains < tol (relative)
        "em": {"steps": 100, "tol": 1e-6},
        "path": {
            "steps": 20, "lr": 0.003,
            "method": "dopri5", "rtol": 1e-6, "atol": 1e-8,
            "max_evals": 20000,  # right-hand-side evaluations per simulation; past it: failed
            "adjoint": False,
            "velocity_weight": 0.1,
        },
        "merge": {"distance": 0.05},   # merge pooled fields closer than this (rad, and relative K)
        "slsqp": {"max_iter": 200},    # iterations of the baseline (solver.method: slsqp)
    },
    "success": {"rmse": 0.03, "tip": 0.02},
    "log": {"tensorboard": True, "progress": True},
}


class ConfigError(ValueError):
    """A bad config key or value; the message names it."""


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2 floats such as 1e-3 (YAML 1.1 wants 1.0e-3)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)?(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)$|^[-+]?[0-9][0-9_]*\.[0-9_]*$"""),
    list("-+0123456789."))


def check(cfg: dict, ref: dict, where: str = "") -> None:
    """Validate ``cfg`` against the reference mapping ``ref`` (keys, types, choices);
    raises :class:`ConfigError` naming the first bad key (prefixed by ``where``)."""
    for key, val in cfg.items():
        path = f"{where}{key}"
        if key not in ref:
            close = difflib.get_close_matches(key, list(ref), n=3)
            hint = f" (did you mean {', '.join(close)}?)" if close else f" (known: {', '.join(ref)})"
            raise ConfigError(f"unknown config key {path!r}{hint}")
        default = ref[key]
        if isinstance(default, dict):
            if key == "body":
                if not isinstance(val, dict):
                    raise ConfigError(f"config key 'body' must be a mapping, got {val!r}")
                continue
            if not isinstance(val, dict):
                raise ConfigError(f"config key {path!r} must be a mapping, got {val!r}")
            check(val, default, path + ".")
        elif key == "data":
            if not isinstance(val, (str, list)):
                raise ConfigError(f"config key 'data' must be a folder, a list of .npz files or "
                                  f"'gestures', got {val!r}")
        elif isinstance(default, bool):
            if not isinstance(val, bool):
                raise ConfigError(f"config key {path!r} must be true or false, got {val!r}")
        elif isinstance(default, (int, float)):
            if isinstance(val, bool) or not isinstance(val, (int, float)):
                raise ConfigError(f"config key {path!r} must be a number, got {val!r}")
            if isinstance(default, int) and not isinstance(val, int):
                raise ConfigError(f"config key {path!r} must be an integer, got {val!r}")
            if val < 0:
                raise ConfigError(f"config key {path!r} must be non-negative, got {val!r}")
        elif not isinstance(val, type(default)):
            raise ConfigError(f"config key {path!r} must be a {type(default).__name__}, got {val!r}")
    choices = {"model.stiffness": ("scalar", "diag", "block", "full"),
               "model.phases": ("fixed", "variable"),
               "solver.method": ("pipeline", "slsqp")}
    for path, allowed in choices.items():
        head, _, leaf = path.partition(".")
        if where.endswith(head + ".") and leaf in cfg and cfg[leaf] not in allowed:
            raise ConfigError(f"config key {path!r} must be one of {allowed}, got {cfg[leaf]!r}")


def parse_override(text: str) -> tuple:
    """``a.b.c=value`` → (["a", "b", "c"], parsed value)."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise ConfigError(f"override {text!r} is not of the form key=value")
    try:
        value = yaml.load(raw, Loader=_Loader) if raw != "" else ""
    except yaml.YAMLError as err:
        raise ConfigError(f"override {text!r}: cannot parse value ({err})") from None
    return key.split("."), value


def read(path) -> dict:
    """The mapping in a YAML file (not validated); errors name the file."""
    path = Path(path)
    try:
        doc = yaml.load(path.read_text(), Loader=_Loader) or {}
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: a config must be a mapping of keys to values")
    return doc


def merge(base: dict, new: dict) -> dict:
    """``base`` updated recursively by ``new`` (copies; "body" is replaced whole)."""
    out = copy.deepcopy(base)
    for key, val in new.items():
        if isinstance(val, dict) and isinstance(out.get(key), dict) and key != "body":
            out[key] = merge(out[key], val)
        else:
            out[key] = copy.deepcopy(val)
    return out


def load(path=None, overrides=(), defaults: dict = DEFAULTS) -> dict:
    """``defaults`` ← YAML file ← overrides, validated against ``defaults`` (the training
    config's by default). Raises :class:`ConfigError`."""
    cfg = copy.deepcopy(defaults)
    if path is not None:
        doc = read(path)
        try:
            check(doc, defaults)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
        cfg = merge(cfg, doc)
    for text in overrides:
        keys, value = parse_override(text)
        node = {}
        cur = node
        for k in keys[:-1]:
            cur = cur.setdefault(k, {})
        cur[keys[-1]] = value
        try:
            check(node, defaults)
        except ConfigError as err:
            raise ConfigError(f"override {text!r}: {err}") from None
        cfg = merge(cfg, node)
    return cfg


def dump(cfg: dict, path) -> None:
    Path(path).write_text(yaml.safe_dump(cfg, sort_keys=False))
