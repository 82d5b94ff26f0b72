"""The package's structure stays as docs/architecture.md draws it: every module sits in a layer, no import points to a
higher layer nor, inside a layer, to a unit on its left, and the import graph has no circle. Imports inside functions
count as much as those at the top."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "src" / "mcsplat"
ARCHITECTURE = ROOT / "docs" / "architecture.md"

# Top to bottom, as in docs/architecture.md ("The layers"). A module may import from the layers below its own and,
# inside its own layer, from the units to the right of its unit (the order of the picture's row: io sits right of
# data, so data may import io and io may not import data). A unit is the first component of a module's name inside the
# package, a subpackage or a top-level module ("" is the package's own __init__); inside a unit imports are free.
LAYERS = [
    ("interface", ("__main__", "cli")),
    ("session", ("blocks", "train", "export")),
    ("consumers", ("viewer", "report")),
    ("loop", ("trainer", "graphed_step", "step", "stopping", "subscribers")),
    ("run", ("run",)),
    ("set-up", ("distributed", "initialization", "partition", "planning", "config", "typed_json")),
    ("method", ("surface_terms", "depth_supervision", "appearance", "pose_refinement", "features",
                "loss_terms", "strategy", "mesh", "visibility", "metrics", "optim")),
    ("building blocks", ("render", "losses", "ssim", "adam_cpu", "capture", "data", "io", "flythrough",
                         "per_image")),
    ("model", ("gaussians",)),
    ("foundation", ("geometry", "compute", "camera", "option_checks", "errors", "")),
]


def module_files(package: Path = PACKAGE) -> dict[str, Path]:
    """'mcsplat.render.bin.warp_kernels' -> its file, for every module of the package."""
    found = {}
    for path in package.rglob("*.py"):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The package's modules that `name` imports (a package itself when the name imported is not a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                if f"{target}.{alias.name}" in modules:
                    found.add(f"{target}.{alias.name}")
                elif target in modules:
                    found.add(target)
        elif isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name in modules}
    found.discard(name)
    return found


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    files = module_files(package)
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def unit_of(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def layer_of(module: str) -> int:
    for index, (_, members) in enumerate(LAYERS):
        if unit_of(module) in members:
            return index
    raise AssertionError(f"{module} is in no layer: add it to LAYERS here and to docs/architecture.md")


def place_in_layer(module: str) -> int:
    """How far right the module's unit stands on its layer's row (0: leftmost)."""
    return LAYERS[layer_of(module)][1].index(unit_of(module))


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    upward = []
    for module, targets in graph.items():
        for target in targets:
            if layer_of(target) < layer_of(module):
                upward.append(f"{module} ({LAYERS[layer_of(module)][0]}) imports {target} "
                              f"({LAYERS[layer_of(target)][0]})")
    return sorted(upward)


def leftward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Imports between two units of one layer that point to the left on its row (as upward as any, only finer)."""
    leftward = []
    for module, targets in graph.items():
        for target in targets:
            if (layer_of(target) == layer_of(module) and unit_of(target) != unit_of(module)
                    and place_in_layer(target) < place_in_layer(module)):
                leftward.append(f"{module} imports {target} ({unit_of(target)} stands left of {unit_of(module)} in "
                                f"{LAYERS[layer_of(module)][0]})")
    return sorted(leftward)


def drawn_rows(text: str) -> list[tuple[str, ...]]:
    """The units of each row of the picture under "## The layers" in docs/architecture.md, left to right."""
    picture = text.split("## The layers", 1)[1].split("```", 2)[1]
    rows = []
    for line in picture.splitlines():
        # A row is " <layer>  <units>  (a comment)"; the "|" lines and the second word of "building blocks" hold none.
        if match := re.match(r" \S+\s+(.*)", line):
            units = tuple(word.rstrip("/") for word in match.group(1).split("(")[0].split() if word != "|")
            if units:
                rows.append(units)
    return rows


def find_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of the graph as a list of modules (the first again at the end), or None."""
    state: dict[str, str] = {}
    stack: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = "open"
        stack.append(module)
        for target in sorted(graph.get(module, ())):
            if state.get(target) == "open":
                return stack[stack.index(target):] + [target]
            if target not in state and (circle := visit(target)):
                return circle
        stack.pop()
        state[module] = "done"
        return None

    for module in sorted(graph):
        if module not in state and (circle := visit(module)):
            return circle
    return None


def circle_inside_a_package(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle among the imports between modules of one unit (render/composite importing render/project importing
    render/composite), which the layers leave free. A package's __init__ importing its own modules to re-export them
    is no circle unless one of them imports the package back."""
    inside = {module: {target for target in targets if unit_of(target) == unit_of(module)}
              for module, targets in graph.items()}
    return find_circle(inside)


def test_every_module_has_a_layer_and_no_import_points_up():
    upward = upward_imports(import_graph())
    assert not upward, "imports that point to a higher layer:\n" + "\n".join(upward)


def test_no_import_points_left_inside_a_layer():
    leftward = leftward_imports(import_graph())
    assert not leftward, ("imports that point to the left inside a layer (move the unit right of what it imports in "
                          "LAYERS and in docs/architecture.md's picture, or the import out):\n" + "\n".join(leftward))


def test_the_picture_has_the_layers_of_the_test():
    """docs/architecture.md draws the layers and the order inside each that the checks here hold the package to."""
    assert drawn_rows(ARCHITECTURE.read_text()) == [tuple(u for u in members if u) for _, members in LAYERS]


def test_the_import_graph_has_no_circle():
    circle = find_circle(import_graph())
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_no_package_imports_itself_in_a_circle():
    circle = circle_inside_a_package(import_graph())
    assert circle is None, "import circle inside a package: " + " -> ".join(circle)


def test_the_check_inside_a_package_sees_what_it_guards(tmp_path):
    """Planted as files: a package whose __init__ re-exports its modules passes; a loop between two of its
    subpackages (relative imports, through a subpackage's __init__) is found, and only that loop."""
    render = tmp_path / "mcsplat" / "render"
    for folder in ("composite", "project"):
        (render / folder).mkdir(parents=True)
    (tmp_path / "mcsplat" / "__init__.py").write_text("")
    (render / "__init__.py").write_text("from .composite import composite\nfrom .project.kernel import project\n")
    (render / "constants.py").write_text("")
    (render / "composite" / "__init__.py").write_text("from .function import composite\n")
    (render / "composite" / "function.py").write_text("from ..constants import TILE\n")
    (render / "project" / "__init__.py").write_text("")
    (render / "project" / "kernel.py").write_text("from .. import constants\n")
    assert circle_inside_a_package(import_graph(tmp_path / "mcsplat")) is None

    (render / "composite" / "function.py").write_text("from ..constants import TILE\nfrom ..project import kernel\n")
    (render / "project" / "kernel.py").write_text("def project():\n    from ..composite import composite\n")
    graph = import_graph(tmp_path / "mcsplat")
    assert circle_inside_a_package(graph) == ["mcsplat.render.composite", "mcsplat.render.composite.function",
                                              "mcsplat.render.project.kernel", "mcsplat.render.composite"]
    assert upward_imports(graph) == [] and leftward_imports(graph) == []  # the layers alone let it pass


def test_the_checks_see_what_they_guard(tmp_path):
    """Both checks find what they look for when it is planted (a check that cannot fail guards nothing)."""
    (tmp_path / "cameraish.py").write_text("from .trainer import x\n")
    modules = {"mcsplat.camera", "mcsplat.trainer"}
    planted = {"mcsplat.camera": imports_of("mcsplat.camera", tmp_path / "cameraish.py", modules),
               "mcsplat.trainer": {"mcsplat.camera"}}
    assert planted["mcsplat.camera"] == {"mcsplat.trainer"}
    assert upward_imports(planted) == ["mcsplat.camera (foundation) imports mcsplat.trainer (loop)"]
    assert find_circle(planted) == ["mcsplat.camera", "mcsplat.trainer", "mcsplat.camera"]


def test_the_check_inside_a_layer_sees_what_it_guards(tmp_path):
    """An import between two packages of one layer is caught when it points left (io/transforms.py once imported
    data/ for View) and passes when it points right (data/ writes through io/); inside a package imports are free."""
    (tmp_path / "transforms.py").write_text("from ..data import View\n")
    modules = {"mcsplat.io.transforms", "mcsplat.io.atomic", "mcsplat.data", "mcsplat.data.undistort"}
    planted = {"mcsplat.io.transforms": imports_of("mcsplat.io.transforms", tmp_path / "transforms.py", modules),
               "mcsplat.data.undistort": {"mcsplat.io.atomic", "mcsplat.data"},
               "mcsplat.io.atomic": set(), "mcsplat.data": set()}
    assert planted["mcsplat.io.transforms"] == {"mcsplat.data"}
    assert upward_imports(planted) == []
    assert leftward_imports(planted) == ["mcsplat.io.transforms imports mcsplat.data (data stands left of io in "
                                         "building blocks)"]


def test_the_trainer_holds_the_step_and_the_loop_only():
    """trainer.py is the loop; the step (step.py), setting a run up (run/setup.py), planning it (planning/), stopping
    it (stopping.py) and metrics.json's layout (run/metrics.py) live in modules of their own, and keep it short."""
    lines = (PACKAGE / "trainer.py").read_text().splitlines()
    assert len(lines) <= 300, f"trainer.py has {len(lines)} lines: move what is not the step or the loop out"


def families_at_the_top(package: Path = PACKAGE) -> dict[str, list[str]]:
    """The package's top-level modules and subpackages grouped by the word before their name's first underscore,
    for the groups of two or more: run_dir.py beside run_scene.py, or ssim_cpu.py beside an ssim/ package."""
    names = [path.stem for path in package.glob("*.py") if not path.stem.startswith("__")]
    names += [path.name for path in package.iterdir() if (path / "__init__.py").is_file()]
    groups: dict[str, list[str]] = {}
    for name in names:
        groups.setdefault(name.split("_")[0], []).append(name)
    return {word: sorted(members) for word, members in sorted(groups.items()) if len(members) > 1}


def test_modules_of_one_family_form_a_package():
    """The layers check imports between units and leave those inside a package free, so a flat top level gets finer
    checks for free and invites the next run_*.py beside the others. A family of modules (one first word) is a package
    instead, its members named without the prefix (run/folder.py, ssim/cpu.py); the package's circles are still
    checked (test_no_package_imports_itself_in_a_circle)."""
    families = families_at_the_top()
    assert not families, "modules that share a first word; make each family a package: " + "; ".join(
        f"{word}: {', '.join(members)}" for word, members in families.items())


def test_the_family_check_sees_what_it_guards(tmp_path):
    for name in ("run_dir.py", "run_scene.py", "trainer.py", "train.py", "ssim_cpu.py", "__main__.py"):
        (tmp_path / name).write_text("")
    (tmp_path / "ssim").mkdir()
    (tmp_path / "ssim" / "__init__.py").write_text("")
    assert families_at_the_top(tmp_path) == {"run": ["run_dir", "run_scene"], "ssim": ["ssim", "ssim_cpu"]}
