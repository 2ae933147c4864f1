"""The pure core stays pure, and layers import only downwards (STYLE: allowed import directions)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PURE_DIRS = [ROOT / "service" / "core", ROOT / "service" / "sim"]
FORBIDDEN_MODULES = {"fastapi", "gi", "rtde_receive", "rtde_control", "ur_rtde", "threading", "time",
                     "asyncio", "uvicorn", "sqlite3", "logging", "socket", "requests", "httpx", "os",
                     "pathlib", "subprocess", "api", "drivers"}
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
    composition_root = path == ROOT / "service" / "cli.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            m = node.module
            if not composition_root:
                assert not m.startswith("api"), f"{path.name}:{node.lineno} imports the API layer"
            assert not m.startswith(("drivers.camera", "drivers.robot")), (
                f"{path.name}:{node.lineno} imports a concrete driver; go through drivers.registry"
            )


def test_modules_fit_one_sitting():
    too_long = []
    for path in _py_files([ROOT / "service", ROOT / "drivers", ROOT / "api"]):
        n = len(path.read_text().splitlines())
        # ruff format's lines (one argument a line where a call does not fit): 800, the 700 of the
        # hand-wrapped code before it; detect, storage, calibrate_camera, aravis and rtde_server are
        # next to be split in the layout redesign
        if n > 800:
            too_long.append(f"{path.relative_to(ROOT)} ({n} lines)")
    assert not too_long, "split these modules: " + ", ".join(too_long)
