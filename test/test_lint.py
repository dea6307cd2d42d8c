"""Style is part of the test run: ruff (pycodestyle, pyflakes, bugbear, pep257) must be clean."""

import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_python_sources_pass_ruff():
    ruff = shutil.which("ruff")
    assert ruff, "ruff is not installed: run `make test`, which installs the pinned tools"
    result = subprocess.run([ruff, "check", "--no-cache", "sonar_ring", "test", "bench", "launch", "setup.py"],
                            cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
