"""tflearn.config: defaults ← YAML file ← dotted overrides, with every key and value checked."""
from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from tflearn import config
from tflearn.config import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def write(tmp_path, text: str, name: str = "cfg.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_defaults_and_shipped_config():
    cfg = config.load()
    assert cfg == config.Config()
    with pytest.raises(ValidationError):              # frozen: a config is read once
        cfg.seed = 3
    shipped = config.load(ROOT / "configs" / "gestures.yaml")
    assert set(shipped.model_dump()) == set(config.Config.model_fields)
    assert shipped.data == "gestures" and shipped.model.stiffness == "diag"
    assert shipped == cfg                             # the defaults are the main job's
    assert shipped.solver.path.rtol == 1e-7 and shipped.solver.each.tol == 1e-5


def test_file_merges_over_defaults(tmp_path):
    p = write(tmp_path, "seed: 4\nsolver:\n  em:\n    steps: 7\nmodel:\n  stiffness: full\n")
    cfg = config.load(p)
    assert cfg.seed == 4 and cfg.solver.em.steps == 7
    assert cfg.model.stiffness == "full"
    # siblings of the nested keys keep their defaults
    assert cfg.solver.path == config.PathSection()
    assert cfg.model.phases == config.ModelSection().phases
    assert config.load(write(tmp_path, "", "empty.yaml")) == config.Config()


def test_overrides_take_effect(tmp_path):
    data, out = tmp_path / "motions", tmp_path / "run"
    cfg = config.load(None, [f"data={data}", f"out={out}", "seed=17", "solver.em.steps=12",
                             "solver.path.method=rk4", "solver.init.stiffness_grid=[1, 2.5]",
                             "log.progress=false", "success.tip=0.05", "model.phases=variable"])
    assert cfg.data == str(data) and cfg.out == str(out) and cfg.seed == 17
    assert cfg.solver.em.steps == 12 and cfg.solver.path.method == "rk4"
    assert cfg.solver.init.stiffness_grid == [1, 2.5]
    assert cfg.log.progress is False and cfg.log.tensorboard is True
    assert cfg.success.model_dump() == {"rmse": 0.03, "tip": 0.05}
    assert cfg.model.phases == "variable"
    # an override beats the file, the file beats the defaults
    p = write(tmp_path, "seed: 3\nsolver:\n  em:\n    steps: 9\n")
    cfg = config.load(p, ["seed=5"])
    assert cfg.seed == 5 and cfg.solver.em.steps == 9
    # a list of data files
    cfg = config.load(None, ["data=[a.npz, b.npz]"])
    assert cfg.data == ["a.npz", "b.npz"]
    # a float for a float key given as an integer is fine (ints are numbers)
    assert config.load(None, ["success.tip=1"]).success.tip == 1


def test_body_override_replaces_mapping(tmp_path):
    p = write(tmp_path, "body:\n  preset: arm\n  damping: 0.5\n  gravity: [0, 0, -9.81]\n")
    cfg = config.load(p)
    assert cfg.body == {"preset": "arm", "damping": 0.5, "gravity": [0, 0, -9.81]}


@pytest.mark.parametrize("text,key", [
    # unknown keys
    ("bogus: 1\n", "bogus"),
    ("solver:\n  em:\n    stepz: 3\n", "solver.em.stepz"),
    ("model:\n  stifness: diag\n", "model.stifness"),
    ("log:\n  tensorboard: true\n  color: false\n", "log.color"),
    # bad values
    ("solver:\n  em:\n    steps: many\n", "solver.em.steps"),
    ("solver:\n  path:\n    steps: -2\n", "solver.path.steps"),
    ("model:\n  stiffness: spherical\n", "model.stiffness"),
    ("body: [1, 2]\n", "body"),
    ("body: arm\n", "body"),
    ("log: yes-please\n", "log"),
])
def test_bad_key_or_value_in_file_names_key_and_file(tmp_path, text, key):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        config.load(p)
    msg = str(err.value)
    assert repr(key) in msg and str(p) in msg


def test_unknown_key_suggests_close_match(tmp_path):
    with pytest.raises(ConfigError, match=r"did you mean stiffness"):
        config.load(None, ["model.stifness=diag"])


def test_a_moved_key_says_where_it_went():
    with pytest.raises(ConfigError, match=r"solver.layout.rescue is now solver.rescue.enabled"):
        config.load(None, ["solver.layout.rescue=true"])


@pytest.mark.parametrize("override,key", [
    ("bogus=1", "bogus"),
    ("solver.em.stepz=3", "solver.em.stepz"),
    ("solver.nothing.steps=3", "solver.nothing"),
    ("success.speed=1", "success.speed"),
])
def test_unknown_key_in_override(override, key):
    with pytest.raises(ConfigError) as err:
        config.load(None, [override])
    assert repr(key) in str(err.value) and override in str(err.value)


@pytest.mark.parametrize("override,key,what", [
    ("solver.em.steps=abc", "solver.em.steps", "number"),
    ("solver.em.steps=-1", "solver.em.steps", "non-negative"),
    ("solver.path.steps=-3", "solver.path.steps", "non-negative"),
    ("solver.em.steps=1.5", "solver.em.steps", "integer"),
    ("success.rmse=-0.1", "success.rmse", "non-negative"),
    ("success.rmse=true", "success.rmse", "number"),
    ("seed=x", "seed", "number"),
    ("log.progress=maybe", "log.progress", "true or false"),
    ("log.progress=1", "log.progress", "true or false"),
    ("model.stiffness=round", "model.stiffness", "one of"),
    ("model.phases=free", "model.phases", "one of"),
    ("solver.method=sqp", "solver.method", "one of"),
    ("body=3", "body", "mapping"),
    ("solver=3", "solver", "mapping"),
    ("solver.path.method=3", "solver.path.method", "one of"),
    ("solver.path.method=euler5", "solver.path.method", "one of"),
    ("out=3", "out", "str"),
    ("solver.each.max_fields=0", "solver.each.max_fields", "≥ 1"),
    ("data=3", "data", "data"),
    ("solver.init.stiffness_grid=2", "solver.init.stiffness_grid", "list"),
    ("solver.layout.fields=12", "solver.layout", "applies to shape joints, not simplex"),
    ("solver.hold.fields=12", "solver.hold", "applies to shape joints, not pairs"),
])
def test_bad_value_in_override(override, key, what):
    with pytest.raises(ConfigError) as err:
        config.load(None, [override])
    msg = str(err.value)
    assert repr(key) in msg and what in msg


def test_missing_and_unreadable_files(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="cannot read") as err:
        config.load(missing)
    assert str(missing) in str(err.value)
    broken = write(tmp_path, "solver: {em: [1, 2\n", "broken.yaml")
    with pytest.raises(ConfigError, match="not valid YAML") as err:
        config.load(broken)
    assert str(broken) in str(err.value)
    listy = write(tmp_path, "- a\n- b\n", "list.yaml")
    with pytest.raises(ConfigError, match="mapping") as err:
        config.load(listy)
    assert str(listy) in str(err.value)
    with pytest.raises(ConfigError) as err:
        config.load(tmp_path)                    # a folder, not a file
    assert str(tmp_path) in str(err.value)


@pytest.mark.parametrize("override", ["seed", "solver.em.steps", "=3", ""])
def test_override_without_equals_refused(override):
    with pytest.raises(ConfigError, match="key=value"):
        config.load(None, [override])


def test_unparseable_override_value():
    with pytest.raises(ConfigError, match="cannot parse"):
        config.load(None, ["solver.init.stiffness_grid=[1, 2"])


def test_dump_round_trip(tmp_path):
    cfg = config.load(None, ["seed=9", "solver.path.rtol=0.0001", "model.stiffness=block",
                             f"data={tmp_path}"])
    config.dump(cfg, tmp_path / "c.yaml")
    assert config.load(tmp_path / "c.yaml") == cfg


def test_exponent_without_dot_is_a_number(tmp_path):
    assert config.load(None, ["solver.path.rtol=1e-3"]).solver.path.rtol == 1e-3
    assert config.load(write(tmp_path, "solver:\n  each:\n    tol: 1e-5\n")).solver.each.tol == 1e-5


def test_not_utf8_is_refused_naming_the_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("seed: 1  # caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="not UTF-8") as err:
        config.load(p)
    assert str(p) in str(err.value)


def test_replace_validates():
    cfg = config.Config().replace(seed=3, solver={"em": {"steps": 5}})
    assert cfg.seed == 3 and cfg.solver.em.steps == 5 and cfg.solver.path == config.PathSection()
    with pytest.raises(ConfigError, match="'solver.em.steps'"):
        config.Config().replace(solver={"em": {"steps": -5}})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=200))
def test_random_bytes_give_a_config_error_or_a_config(tmp_path, data):
    p = tmp_path / "fuzz.yaml"
    p.write_bytes(data)
    try:
        cfg = config.load(p)
    except ConfigError as err:
        assert str(err).startswith(str(p))
    else:
        assert isinstance(cfg, config.Config)


YAML_VALUES = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                           lambda x: (st.lists(x, max_size=3)
                                      | st.dictionaries(st.text(max_size=8), x, max_size=3)),
                           max_leaves=6)
KEYS = ["seed", "data", "out", "strict", "model.fields", "model.stiffness", "solver.em.steps",
        "solver.path.rtol", "solver.path.method", "solver.init.stiffness_grid", "success.tip",
        "log.progress", "solver.merge", "body", "nonsense.key"]


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(KEYS), YAML_VALUES)
def test_any_value_at_any_key_is_validated(key, value):
    """Every value at every key either validates to the schema's type or is refused
    with a ConfigError naming the key (or its first unknown part)."""
    doc: dict = {}
    cur = doc
    parts = key.split(".")
    for k in parts[:-1]:
        cur = cur.setdefault(k, {})
    cur[parts[-1]] = value
    try:
        cfg = config.validate(doc)
    except ConfigError as err:
        assert parts[0] in str(err)
    else:
        assert isinstance(cfg, config.Config)


# the settings for many motions of one shared basis (docs/config.md, configs/many.yaml)
MANY = ["solver.each.reuse=8", "solver.reduce.refit=false", "solver.path.motions=unreproduced",
        "solver.path.steps=0", "solver.shooting.broyden=true", "solver.pool.sharing=own",
        "solver.pool.min_gain=1e-7", "solver.reduce.reach=1e-6", "solver.reduce.chunk=2",
        "solver.shooting.used=true", "solver.each.reuse_tol=1e-4"]


def _schema(path: Path):
    """The schema a shipped config is read with: perturb batches, mode analyses, the rest
    train configs (experiments have their own loader)."""
    from tflearn.modes.config import ModesConfig
    if path.parent.name == "modes":
        return ModesConfig
    return config.PerturbConfig if path.stem.startswith("perturb") else config.Config


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml"))
                         + sorted((ROOT / "configs" / "modes").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_loads(path):
    """Every config in configs/ (and configs/modes/) validates with its schema, and every
    top-level one says in a header comment what it is for."""
    schema = _schema(path)
    cfg = config.load(path, (), schema)
    assert isinstance(cfg, schema)
    if path.parent.name == "configs":
        assert path.read_text().startswith("# "), f"{path.name} has no header comment"


def test_many_is_the_main_job_with_the_settings_for_many_motions():
    """configs/many.yaml is configs/gestures.yaml with the settings for many motions and
    nothing else changed but the data and the output folder."""
    many = config.load(ROOT / "configs" / "many.yaml")
    assert many == config.load(ROOT / "configs" / "gestures.yaml", MANY + ["data=motions", "out=runs/many"])
    s = many.solver
    assert (s.each.reuse, s.each.reuse_tol) == (8, 1e-4)
    assert (s.reduce.refit, s.reduce.reach, s.reduce.chunk) == (False, 1e-6, 2)
    assert (s.path.motions, s.path.steps, s.pool.sharing, s.pool.min_gain) == ("unreproduced", 0, "own", 1e-7)
    assert s.shooting.broyden and s.shooting.used
    assert config.load(ROOT / "configs" / "many.yaml", ["data=elsewhere"]).data == "elsewhere"


def test_mocap_config_is_for_recorded_motion():
    """configs/mocap.yaml: the spanning layout on the performer's moving torso, its header
    saying it is for recorded (or keyframed) motion."""
    path = ROOT / "configs" / "mocap.yaml"
    cfg = config.load(path)
    assert cfg.solver.method == "layout" and cfg.torso == "moving" and cfg.model.windows == 16
    assert "recorded" in path.read_text().split("\ndata:")[0]


def _leaves(schema, prefix=""):
    """(dotted key, field) of every leaf of a config schema (nested sections recursed)."""
    for name, field in schema.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, config.Section):
            yield from _leaves(ann, f"{prefix}{name}.")
        else:
            yield prefix + name, field


@pytest.mark.parametrize("schema", [config.Config, config.PerturbConfig], ids=lambda s: s.__name__)
def test_config_reference_lists_every_key_with_its_default(schema):
    """docs/config.md has a row `key` | `default` | meaning for every key of the training
    config (before its perturbation section) and of the perturbation config (in it), the
    default as tflearn.config has it."""
    import re

    import yaml
    train, _, perturb = (ROOT / "docs" / "config.md").read_text().partition("\n## Perturbation batches")
    text = perturb.partition("\n## ")[0] if schema is config.PerturbConfig else train
    rows = dict(re.findall(r"^\| `([^`]+)` \| (`[^`]*`|\(required\)) \|", text, re.M))
    for key, field in _leaves(schema):
        assert key in rows, f"docs/config.md has no row for {key}"
        if field.is_required():
            assert rows[key] == "(required)", key
        else:
            documented = yaml.load(rows[key].strip("`"), Loader=config._Loader)
            assert documented == field.default, (key, rows[key], field.default)


def test_without_drops_the_given_keys_only():
    """``without``: a key given is dropped, a section given in part loses only those keys
    (and goes when none is left), ``body`` counts as one key; ``given`` is the overrides'."""
    doc = {"model": {"fields": 0, "windows": 16}, "solver": {"layout": {"radius": 2.0}},
           "body": {"preset": "arm"}}
    assert config.without(doc, {"model": {"windows": 4}, "solver": {"layout": {"radius": 1.0}},
                                "body": {"preset": "chain"}}) == {"model": {"fields": 0}}
    assert config.without(doc, {}) == doc and config.without(doc, {"model": 1}) == {
        "solver": {"layout": {"radius": 2.0}}, "body": {"preset": "arm"}}
    cfg = config.load(None, ["model.windows=4", "solver.em.steps=7", "model.fields=2"])
    assert cfg.given == {"model": {"windows": 4, "fields": 2}, "solver": {"em": {"steps": 7}}}
    assert cfg.replace(seed=3).given == cfg.given and config.Config().given == {}
