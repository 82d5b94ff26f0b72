"""The package's structure stays as docs/architecture.md draws it: every module sits in a layer, no import points to a
higher layer, and the import graph has no circle. Imports inside functions count as much as those at the top."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "mcsplat"

# Top to bottom, as in docs/architecture.md ("The layers"). A module may import from its own layer and the ones below.
# Keys are the first component of a module's name inside the package ("" is the package's own __init__).
LAYERS = [
    ("interface", {"cli", "__main__"}),
    ("session", {"train", "export"}),
    ("consumers", {"viewer", "report"}),
    ("loop", {"trainer", "subscribers"}),
    ("run", {"run_dir", "state", "evaluation", "events"}),
    ("set-up", {"distributed", "initialization", "schedule", "budget", "config", "config_types"}),
    ("method", {"strategy", "visibility", "metrics", "optim", "mesh", "appearance", "pose_refinement"}),
    ("building blocks", {"render", "data", "losses", "ssim_cpu", "ssim_warp", "io", "capture", "camera_path"}),
    ("model", {"gaussians"}),
    ("foundation", {"geometry", "compute", "camera", "errors", ""}),
]


def module_files() -> dict[str, Path]:
    """'mcsplat.render.binning' -> its file, for every module of the package."""
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
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


def import_graph() -> dict[str, set[str]]:
    files = module_files()
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def layer_of(module: str) -> int:
    inside = module.split(".")[1] if "." in module else ""
    for index, (_, members) in enumerate(LAYERS):
        if inside in members:
            return index
    raise AssertionError(f"{module} is in no layer: add it to LAYERS here and to docs/architecture.md")


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    upward = []
    for module, targets in graph.items():
        for target in targets:
            if layer_of(target) < layer_of(module):
                upward.append(f"{module} ({LAYERS[layer_of(module)][0]}) imports {target} "
                              f"({LAYERS[layer_of(target)][0]})")
    return sorted(upward)


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


def test_every_module_has_a_layer_and_no_import_points_up():
    upward = upward_imports(import_graph())
    assert not upward, "imports that point to a higher layer:\n" + "\n".join(upward)


def test_the_import_graph_has_no_circle():
    circle = find_circle(import_graph())
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_the_checks_see_what_they_guard(tmp_path):
    """Both checks find what they look for when it is planted (a check that cannot fail guards nothing)."""
    (tmp_path / "cameraish.py").write_text("from .trainer import x\n")
    modules = {"mcsplat.camera", "mcsplat.trainer"}
    planted = {"mcsplat.camera": imports_of("mcsplat.camera", tmp_path / "cameraish.py", modules),
               "mcsplat.trainer": {"mcsplat.camera"}}
    assert planted["mcsplat.camera"] == {"mcsplat.trainer"}
    assert upward_imports(planted) == ["mcsplat.camera (foundation) imports mcsplat.trainer (loop)"]
    assert find_circle(planted) == ["mcsplat.camera", "mcsplat.trainer", "mcsplat.camera"]
