"""Every compiled kernel the product calls has a reference test here (issue: one NumPy reference per kernel).

The kernels are the ``@njit`` functions of ``service/core/_kernels/*.py`` that code outside
``_kernels`` imports, by name (``from service.core._kernels.x import k``) or through its module
(``from service.core._kernels import x`` ... ``x.k``). Each must be named in the code (not only
a comment) of one of the ``tests/core/kernels/test_*.py`` files, so a new kernel without a
reference test fails here.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
KERNELS = ROOT / "service" / "core" / "_kernels"
PACKAGE = "service.core._kernels"
CALLERS = [ROOT / "service", ROOT / "drivers", ROOT / "api"]
TESTS = Path(__file__).resolve().parent


def _is_njit(decorator: ast.expr) -> bool:
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    return (isinstance(target, ast.Name) and target.id == "njit") or (
        isinstance(target, ast.Attribute) and target.attr == "njit"
    )


def njit_functions() -> dict[str, set[str]]:
    """Module name -> the names of the @njit functions it defines."""
    out = {}
    for path in sorted(KERNELS.glob("*.py")):
        tree = ast.parse(path.read_text())
        out[path.stem] = {
            node.name
            for node in tree.body
            if isinstance(node, ast.FunctionDef) and any(_is_njit(d) for d in node.decorator_list)
        }
    return out


def kernels_used_outside() -> set[tuple[str, str]]:
    """(module, function) of every name of a kernel module used by code outside ``_kernels``."""
    used = set()
    for path in (p for d in CALLERS for p in sorted(d.rglob("*.py"))):
        if KERNELS in path.parents:
            continue
        tree = ast.parse(path.read_text())
        aliases = {}  # local name -> kernel module, for attribute access
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.startswith(PACKAGE + "."):
                    used |= {(node.module.rsplit(".", 1)[1], a.name) for a in node.names}
                elif node.module == PACKAGE:
                    aliases |= {a.asname or a.name: a.name for a in node.names}
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith(PACKAGE + "."):
                        aliases[a.asname or a.name] = a.name.rsplit(".", 1)[1]
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute):
                owner = ast.unparse(node.value)
                if owner in aliases:
                    used.add((aliases[owner], node.attr))
    return used


def names_in_tests() -> set[str]:
    """Every identifier the reference tests use in code: names, attributes, imported names."""
    names = set()
    for path in sorted(TESTS.glob("test_*.py")):
        if path.name == Path(__file__).name:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Name):
                names.add(node.id)
            elif isinstance(node, ast.Attribute):
                names.add(node.attr)
            elif isinstance(node, ast.alias):
                names.add(node.name)
    return names


@cache
def public_kernels() -> tuple[str, ...]:
    defined = njit_functions()
    return tuple(sorted(f"{mod}.{name}" for mod, name in kernels_used_outside() if name in defined.get(mod, set())))


def test_the_kernel_list_is_found():
    # the parse itself: a known kernel of each way of importing, so an empty list cannot pass
    found = public_kernels()
    for known in (
        "contour_kernel.contour_stats_kernel",  # from service.core._kernels.contour_kernel import ...
        "decode_kernel.read_rings_kernel",  # from service.core._kernels import decode_kernel; decode_kernel.x
        "roi_kernel.window_half_size_kernel",
        "resection_kernel.resect_kernel",
    ):
        assert known in found
    assert len(found) >= 20


def test_every_kernel_used_outside_kernels_has_a_reference_test():
    named = names_in_tests()
    missing = [k for k in public_kernels() if k.split(".")[1] not in named]
    assert not missing, "kernels without a reference test in tests/core/kernels/: " + ", ".join(missing)
