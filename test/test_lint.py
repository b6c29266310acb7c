"""The code base passes ruff with the project's settings (ruff.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def ruff_command() -> list[str]:
    """Ruff of this interpreter's environment: ``python -m ruff``, or the script beside it."""
    try:
        import ruff  # noqa: F401
        return [sys.executable, '-m', 'ruff']
    except ImportError:
        pass
    beside = Path(sys.executable).with_name('ruff')
    found = str(beside) if beside.exists() else shutil.which('ruff')
    if not found:
        # package.xml declares it (test_depend python3-ruff-pip): a missing ruff is a
        # broken test environment, never a reason to pass the lint quietly.
        pytest.fail('ruff is not installed, although package.xml declares it as a test '
                    'dependency: rosdep install --from-paths src --ignore-src -y '
                    '(rosdep key python3-ruff-pip), or pip install ruff')
    return [found]


def ruff_check(*paths: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*ruff_command(), 'check', '--no-cache', '--config', str(ROOT / 'ruff.toml'),
         '--output-format', 'concise', *paths], cwd=ROOT, capture_output=True, text=True,
        timeout=60, input=stdin)


def test_ruff_check():
    result = ruff_check('vfd_ros2', 'test', 'launch', 'bench', 'scripts')
    assert result.returncode == 0, f'ruff check failed:\n{result.stdout}\n{result.stderr}'


def test_the_project_rules_are_in_force():
    """Double quotes and an upward-looking docstring are findings: the config is read."""
    result = ruff_check('--stdin-filename', 'vfd_ros2/example.py',
                        stdin='"""The module."""\n\nNAME = "double"\n')
    assert result.returncode == 1 and 'Q000' in result.stdout, result.stdout
