"""A kernel that calls another module's kernel is recompiled when that one changes.

numba keys a cached kernel on its own file only; :func:`service.pipeline.compile.refresh_stale_caches`
empties the caches of every module of the package when any of them changes. Here a package of two modules
(``a`` calls ``b``) whose ``b`` changes between two fresh interpreters.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

_INIT = """
import os
from pathlib import Path
from service.pipeline.compile import refresh_stale_caches
REFRESHED = None if os.environ.get("NO_REFRESH") else refresh_stale_caches(Path(__file__).resolve().parent, __name__)
"""
_A = "from numba import njit\nfrom kernels_pkg.b import value\n\n@njit(cache=True)\ndef call():\n    return value()\n"
_B = "from numba import njit\n\n@njit(cache=True)\ndef value():\n    return {}\n"


def _run(root: Path, refresh: bool = True) -> tuple[str, str]:
    env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    if not refresh:
        env["NO_REFRESH"] = "1"
    code = "import kernels_pkg, kernels_pkg.a as a; print(kernels_pkg.REFRESHED, a.call())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    refreshed, value = out.stdout.split()
    return refreshed, value


def test_a_change_in_a_called_kernels_module_recompiles_its_callers(tmp_path):
    pkg = tmp_path / "kernels_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(_INIT)
    (pkg / "a.py").write_text(_A)
    (pkg / "b.py").write_text(_B.format(1))
    assert _run(tmp_path) == ("True", "1")  # a new package: recorded, compiled, cached
    assert _run(tmp_path) == ("False", "1")  # unchanged: loaded from the cache, nothing touched
    a_mtime = (pkg / "a.py").stat().st_mtime_ns
    (pkg / "b.py").write_text(_B.format(2))  # only b changes: a's cache still names the old b
    os.utime(pkg / "a.py", ns=(a_mtime, a_mtime))
    assert _run(tmp_path) == ("True", "2")
    assert _run(tmp_path) == ("False", "2")


def test_the_kernel_caches_were_checked_before_the_tests():
    from service.pipeline.compile import KERNEL_PACKAGES, refresh_kernel_caches, refresh_stale_caches

    refresh_kernel_caches()  # conftest's call: recorded, so the second finds nothing to do
    package = KERNEL_PACKAGES[0]
    directory = Path(__import__(package, fromlist=["x"]).__file__).resolve().parent
    assert refresh_stale_caches(directory, package) is False
