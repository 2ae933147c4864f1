"""The code checks run by the test command: ruff's format and lint, and mypy on the pure maths and
the pipeline (configured in pyproject.toml; the versions are pinned in the test extras)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TREES = ["service", "api", "drivers", "tests"]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_format_leaves_every_file_as_it_is():
    r = _run("ruff", "format", "--check", *TREES)
    assert r.returncode == 0, r.stdout + r.stderr


def test_ruff_check_is_clean():
    r = _run("ruff", "check", *TREES)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.slow
def test_mypy_is_clean_on_the_core_and_the_pipeline():
    r = _run("mypy")  # files and options: [tool.mypy] in pyproject.toml
    assert r.returncode == 0, r.stdout + r.stderr
