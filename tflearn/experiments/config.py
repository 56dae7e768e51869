"""The experiment config: typed sections (:class:`tflearn.config.Section`) read from
``configs/experiments/NAME.yaml``.

A config is the defaults below ← the file ← (with ``quick``) the file's ``quick:``
section ← dotted ``key=value`` overrides. The file, its ``quick:`` section and every
override are each validated; a failure is a :class:`~tflearn.config.ConfigError` naming
the file and the key (an unknown key with the closest known ones).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator
from pydantic_core import PydanticCustomError

from ..config import (
    Config,
    ConfigError,
    Section,
    SuccessSection,
    layer,
    merge,
    read,
    validate,
)
from ..config import SimulationSection as BaseSimulation

NAMES = ("basin", "shared", "keyframes", "filtering", "reaches")
#: The gesture library's names (``tflearn.data.gestures.GESTURES``, checked by a test), here so
#: that a config is validated without importing torch.
GESTURES = ("come_here", "stiff_elbow_lift", "tuck", "planar_line", "backwards_reach")
METHODS = ("slsqp", "local", "pipeline", "layout")
#: The methods each experiment runs.
SUPPORTED = {"basin": METHODS[:3], "shared": METHODS[:3], "keyframes": ("slsqp", "pipeline", "layout"),
             "filtering": ("pipeline",), "reaches": ("pipeline", "layout")}
#: What an experiment's training config (``train``) has unless its file says otherwise: no
#: TensorBoard, no progress bars of its own, and the simulations of docs/results.md's
#: measurements (a batch stepped together at 1e-6 / 1e-8, not the main job's each at
#: 1e-7 / 1e-9).
_QUIET = {"log": {"tensorboard": False, "progress": False},
          "solver": {"path": {"rtol": 1e-6, "atol": 1e-8, "batch": "shared"}}}


class SlsqpSection(Section):
    """The thesis' method: scipy SLSQP on the torque cost."""

    max_iter: int = Field(200, ge=1)
    ftol: float = Field(1e-12, ge=0)


class LocalSection(Section):
    """tflearn's local solver: EM steps, then path matching only where EM's relative
    torque cost is ≤ ``path_gate``. (Held-out synthesis in ``filtering`` and ``reaches``
    takes ``train.solver.shooting``.)"""

    em_steps: int = Field(300, ge=0)
    em_tol: float = Field(1e-10, ge=0)
    em_max_step: float | None = Field(1.0, gt=0)   # EM's trust region (torque.em max_step)
    # EM starts from the guess' stiffnesses divided by this (1: as guessed): wider fields,
    # whose Gaussians reach the motion from a far centre, so their weights and gradients
    # are not 0; EM then sets the stiffness
    start_wide: float = Field(10.0, ge=1)
    path_steps: int = Field(15, ge=0)
    path_lr: float = Field(0.01, ge=0)
    path_gate: float = Field(1e-3, ge=0)


class SimulationSection(BaseSimulation):
    """How every check, path matching and resimulation integrates; a simulation needing
    more than ``max_evals`` right-hand-side evaluations counts as failed."""

    rtol: float = Field(1e-6, ge=0)
    atol: float = Field(1e-8, ge=0)
    max_evals: int = Field(15000, ge=1)


class ExperimentConfig(Section):
    """One experiment (``tflearn experiment NAME``); see configs/experiments/."""

    experiment: Literal[NAMES] = "basin"
    out: str = "runs/experiments/basin"
    gestures: list[str] = list(GESTURES)         # basin / shared / keyframes / filtering
    r: list[float] = [1.2, 1.4, 1.8, 2.2, 2.6, 3.0, 4.2, 6.0, 8.0, 10.0]
    seeds: int = Field(20, ge=1)
    seed0: int = Field(0, ge=0)
    methods: list[Literal[METHODS]] = list(METHODS[:3])   # unset: SUPPORTED[experiment]
    straight_reach: bool = True                  # keyframes: add the straight-line reach
    jobs: int = Field(1, ge=1)
    slsqp: SlsqpSection = SlsqpSection()
    local: LocalSection = LocalSection()
    simulation: SimulationSection = SimulationSection()
    success: SuccessSection = SuccessSection()
    # the pipeline's training config, over _QUIET; a training run that is not one of many
    # cases shows its own progress bars (common.fit_pipeline_case)
    train: Config = validate(_QUIET, Config)
    # the layout method's training config: ``train`` with these keys over it and
    # solver.method layout, e.g. {model: {windows: 4}, solver: {layout: {shape: simplex}}}
    layout: dict = {}
    quick: bool = False                          # set by load_config(quick=True)

    @field_validator("gestures")
    @classmethod
    def _known_gestures(cls, names: list) -> list:
        unknown = [g for g in names if g not in GESTURES]
        if unknown:
            raise PydanticCustomError("unknown_gesture", "unknown gestures {unknown} (known: {known})",
                                      {"unknown": str(unknown), "known": ", ".join(GESTURES)})
        return names

    @model_validator(mode="before")
    @classmethod
    def _default_methods(cls, doc):
        if isinstance(doc, dict) and "methods" not in doc:
            return {**doc, "methods": list(SUPPORTED.get(doc.get("experiment"), METHODS[:3]))}
        return doc

    @field_validator("methods")
    @classmethod
    def _supported(cls, methods: list, info: ValidationInfo) -> list:
        ok = SUPPORTED.get(info.data.get("experiment"), METHODS)
        if set(methods) - set(ok):
            raise PydanticCustomError("unsupported_method", "{experiment} runs {ok}, not {bad}", {
                "experiment": info.data["experiment"], "ok": ", ".join(ok),
                "bad": ", ".join(m for m in methods if m not in ok)})
        return methods

    @field_validator("train", mode="before")
    @classmethod
    def _quiet(cls, doc):
        return merge(_QUIET, doc) if isinstance(doc, dict) else doc

    @field_validator("layout")
    @classmethod
    def _layout_config(cls, doc: dict, info: ValidationInfo) -> dict:
        if "train" in info.data:                 # else train's own error is reported
            try:
                layout_config(info.data["train"], doc)
            except ConfigError as err:
                raise PydanticCustomError("layout", "{problem}", {"problem": str(err)}) from None
        return doc

    def training(self, method: str) -> Config:
        """The training config of ``method``: ``train`` with solver.method pipeline for the
        pipeline (not decided from the data: the experiments compare the methods),
        ``train`` ← ``layout`` with solver.method layout for the layout."""
        if method == "layout":
            return layout_config(self.train, self.layout)
        return self.train.replace(solver={"method": "pipeline"})


def layout_config(train: Config, layout: dict) -> Config:
    """``train`` with the keys of ``layout`` over it and ``solver.method: layout``."""
    return validate(merge(merge(train.model_dump(), layout), {"solver": {"method": "layout"}}),
                    Config)


class ExperimentFile(ExperimentConfig):
    """A config file: the config and its ``quick:`` section (each key validated alone)."""

    quick: ExperimentConfig = ExperimentConfig()


def load_config(path, quick: bool = False, overrides=()) -> ExperimentConfig:
    """The experiment config of the file at ``path``, with its ``quick:`` section applied
    if ``quick``, then the dotted ``overrides``; raises :class:`ConfigError` naming the
    file and the key."""
    doc = read(path)
    quick_doc = doc.pop("quick", None) or {}
    validate({**doc, "quick": quick_doc}, ExperimentFile, str(path))
    doc = merge(merge(doc, quick_doc) if quick else doc, {"quick": quick})
    validate(doc, ExperimentConfig, str(path))
    try:
        doc = layer(doc, overrides, ExperimentConfig)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return validate(doc, ExperimentConfig, str(path))
