"""The package's rooms import only from the rooms below them (README, "Layout"): data flows
one way, motions → torques → fit → basis → simulate → metrics and plots."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tflearn"

#: The rooms from the bottom up, as README's layout lists them.
ROOMS = ("errors", "parallel", "physics", "model", "io", "motions", "simulation", "plots", "data",
         "fit", "metrics", "synthesis", "config", "log", "mocap", "evaluate", "render", "modes",
         "control", "train", "experiments", "cli")


def room(module: str) -> str:
    """The room of a dotted module name inside tflearn ('tflearn.fit.torque' → 'fit')."""
    return module.split(".")[1]


def imported(path: Path) -> set:
    """Every tflearn module a file imports, at module level or inside a function."""
    parts = ("tflearn",) + path.relative_to(PACKAGE).with_suffix("").parts
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            if not target.startswith("tflearn"):
                continue
            if target == "tflearn":              # from . import a, b: the modules a, b
                names |= {f"tflearn.{a.name}" for a in node.names
                          if (PACKAGE / f"{a.name}.py").exists() or (PACKAGE / a.name).is_dir()}
            else:
                names.add(target)
        elif isinstance(node, ast.Import):
            names |= {a.name for a in node.names if a.name.startswith("tflearn.")}
    return {n for n in names if n != "tflearn" and n.count(".") >= 1}


def modules():
    return sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def test_every_module_lives_in_a_listed_room():
    assert {room("tflearn." + ".".join(p.relative_to(PACKAGE).with_suffix("").parts))
            for p in modules()} == set(ROOMS)


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path):
    own = room("tflearn." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
    up = sorted(m for m in imported(path) if ROOMS.index(room(m)) > ROOMS.index(own))
    assert not up, f"{path.relative_to(PACKAGE)} ({own}) imports from rooms above it: {up}"


def test_readme_layout_lists_the_rooms_in_order():
    """README's "Layout" tree names every room once, bottom up, in the order checked here."""
    text = (PACKAGE.parent / "README.md").read_text()
    tree = text[text.index("## Layout"):].split("```")[1]
    names = []
    for line in tree.splitlines():
        if line.startswith(("├── ", "└── ")):
            entry = line[4:].split("  ")[0]
            names += [n.strip().removesuffix("/").removesuffix(".py") for n in entry.split(",")]
    assert tuple(names) == ROOMS
