"""The pure core stays pure, and layers import only downwards (STYLE: allowed import directions)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PURE_DIRS = [ROOT / "service" / "core", ROOT / "service" / "sim"]
FORBIDDEN_MODULES = {
    "fastapi",
    "gi",
    "rtde_receive",
    "rtde_control",
    "ur_rtde",
    "threading",
    "time",
    "asyncio",
    "uvicorn",
    "sqlite3",
    "logging",
    "socket",
    "requests",
    "httpx",
    "os",
    "pathlib",
    "subprocess",
    "api",
    "drivers",
}
FORBIDDEN_CALLS = {"open", "print", "input"}
FORBIDDEN_ATTRS = {"imread", "imwrite", "VideoCapture", "imshow", "waitKey"}


def _py_files(dirs):
    for d in dirs:
        yield from sorted(d.rglob("*.py"))


def _imports(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node, a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node, node.module.split(".")[0]


@pytest.mark.parametrize("path", list(_py_files(PURE_DIRS)), ids=lambda p: str(p.relative_to(ROOT)))
def test_core_module_has_no_io_clock_thread_or_hardware(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    problems = []
    for node, mod in _imports(tree):
        if mod in FORBIDDEN_MODULES:
            problems.append(f"line {node.lineno}: imports {mod}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Name) and f.id in FORBIDDEN_CALLS:
                problems.append(f"line {node.lineno}: calls {f.id}()")
            if isinstance(f, ast.Attribute) and f.attr in FORBIDDEN_ATTRS:
                problems.append(f"line {node.lineno}: calls .{f.attr}()")
    assert not problems, f"{path.name} must stay pure: " + "; ".join(problems)


@pytest.mark.parametrize("path", list(_py_files([ROOT / "service"])), ids=lambda p: str(p.relative_to(ROOT)))
def test_service_never_imports_the_api_or_concrete_drivers(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    # the console script is the composition root: its `serve` verb starts the API (lazily)
    composition_root = path.parent == ROOT / "service" / "cli"
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            m = node.module
            if not composition_root:
                assert not m.startswith("api"), f"{path.name}:{node.lineno} imports the API layer"
            assert not m.startswith(("drivers.camera", "drivers.robot")), (
                f"{path.name}:{node.lineno} imports a concrete driver; go through drivers.registry"
            )


# what each layer of service/ may import of the others (docs/architecture.md): downwards only
LAYERS = {
    "core": set(),  # pure maths: numpy, scipy, opencv, numba
    "sim": {"core"},  # the simulated cell: physics over the core's geometry
    "pipeline": {"core"},  # a frame -> a measured pose
    "store": {"core"},  # files and the database
    "settings": {"store", "drivers"},
    "runtime": {"core", "pipeline", "store", "settings", "sim", "drivers"},  # the running cell
    "workflows": {"core", "pipeline", "store", "settings", "sim"},  # the offline verbs' work
    "plant": {"core", "settings", "runtime"},  # MQTT and OPC UA: the running cell's results into the plant
    "bench": {"core", "pipeline", "store", "settings", "sim", "workflows"},
    "cli": {"core", "pipeline", "store", "settings", "sim", "workflows", "bench", "runtime", "api"},
}


def _layer(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] in ("api", "drivers"):
        return parts[0]
    if parts[0] != "service" or len(parts) == 1:
        return None
    return parts[1].removesuffix(".py")


@pytest.mark.parametrize(
    "path",
    [p for p in _py_files([ROOT / "service"]) if p.parent != ROOT / "service" or p.stem == "settings"],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_layers_import_only_downwards(path):
    rel = path.relative_to(ROOT).with_suffix("")
    own = _layer(".".join(rel.parts))
    assert own in LAYERS, f"{rel} is in no layer; add its folder to LAYERS and docs/architecture.md"
    wrong = []
    for node, _ in _imports(ast.parse(path.read_text(), filename=str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
        for name in names:
            layer = _layer(name)
            if layer is not None and layer != own and layer not in LAYERS[own]:
                wrong.append(f"line {node.lineno}: {name}")
    assert not wrong, f"{rel} ({own}) imports above or beside its layer: " + "; ".join(wrong)


def test_modules_fit_one_sitting():
    too_long = []
    for path in _py_files([ROOT / "service", ROOT / "drivers", ROOT / "api"]):
        n = len(path.read_text().splitlines())
        # ruff format's lines (one argument a line where a call does not fit); STYLE asks for about
        # 600, and a module past 700 is split along a seam of its own
        if n > 700:
            too_long.append(f"{path.relative_to(ROOT)} ({n} lines)")
    assert not too_long, "split these modules: " + ", ".join(too_long)
