"""Lint: ruff with the docstring rules of pyproject.toml over the library and its kernels."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_ruff_passes_on_the_library_and_kernels():
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "src", "kernels"], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
