"""Layers only point down: no module imports one from a higher layer (runtime imports included)."""

import ast
import pathlib

SRC = pathlib.Path(__file__).resolve().parents[1] / "src" / "hairwarp"

# Lowest first. A module may import its own layer or any below it.
LAYERS = [
    {"_validate", "_warp", "config", "runtime", "kernels"},
    {"ops"},
    {"energy", "metrics", "torch_reference"},
    {"scene", "models", "solvers"},
    {"io", "render"},
    {"methods", "training", "builder", "bench"},
    {"evaluation", "api"},
    {"commands", "cli", "__init__"},
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _top(module: str) -> str:
    return module.split(".")[1] if module.count(".") else "__init__"


def _imports(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hairwarp"):
            if node.module == "hairwarp":
                yield from (f"hairwarp.{a.name}" for a in node.names)
            else:
                yield node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.startswith("hairwarp."))


def test_every_module_has_a_layer():
    tops = {p.relative_to(SRC).parts[0].removesuffix(".py") for p in SRC.iterdir()
            if p.suffix == ".py" or (p.is_dir() and (p / "__init__.py").exists())}
    assert tops - set(RANK) == set()


def test_imports_point_down():
    upward = []
    for path in SRC.rglob("*.py"):
        own = path.relative_to(SRC).parts[0].removesuffix(".py")
        for module in _imports(path):
            target = _top(module)
            if target in RANK and RANK[target] > RANK[own]:
                upward.append(f"{path.relative_to(SRC)} imports {module}")
    assert upward == []


def test_kernels_are_device_code_only():
    """kernels/ imports Warp, the standard library, its own modules and the config constants; never torch."""
    kernels = SRC.parents[1] / "kernels"
    bad = []
    for path in kernels.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            for name in names:
                if name.split(".")[0] in ("torch", "numpy") or (
                        name.startswith("hairwarp") and not name.startswith(("hairwarp.kernels", "hairwarp.config"))):
                    bad.append(f"{path.name} imports {name}")
    assert bad == []


def test_bridges_launch_and_wrap_through_the_one_helper():
    """Every launch goes through `_warp.launch` (overloads resolved once, launches replayed) and
    every tensor view through `_warp.as_warp`, except where those helpers live and for the
    vec4 views of the CPU grid, which `as_warp` does not make."""
    launches, views = [], []
    for path in SRC.rglob("*.py"):
        if path.name == "_warp.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if "wp.launch(" in line and "_warp.launch(" not in line:
                launches.append(f"{path.relative_to(SRC)}:{number}")
            if "wp.from_torch(" in line and "dtype=wp.vec4" not in line:
                views.append(f"{path.relative_to(SRC)}:{number}")
    assert launches == []
    assert views == []
