"""pycolmap before numpy breaks numba's compiler: slamkit refuses that order with a clear error.

Measured with pycolmap 4.2.1's wheel, numpy 2 and numba: when ``import pycolmap`` comes before numpy's first
import, the first numba kernel compiled in the process corrupts the heap and the process aborts (SIGABRT,
"malloc assertion failure" or "double free or corruption", no Python traceback), at whatever frame a kernel
first compiles (a fresh machine, or a changed kernel). slamkit imports numpy first; a script that imports
pycolmap first gets an ImportError that says what to do instead of an abort minutes later.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
COMPILE = ("from numba import njit\nimport numpy as np\n@njit\ndef f(a):\n    return a.sum() + 1\n"
           "print(f(np.arange(3.0)))\n")


def _python(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300,
                          cwd=tmp_path)


def test_pycolmap_before_numpy_is_refused_with_what_to_do(tmp_path):
    r = _python("import pycolmap\nimport slamkit\n", tmp_path)
    assert r.returncode == 1 and "ImportError: slamkit: pycolmap was imported before numpy" in r.stderr
    assert "Import slamkit (or numpy) before pycolmap" in r.stderr


def test_the_orders_that_work_import_and_compile(tmp_path):
    for code in ("import slamkit\nimport pycolmap\n", "import numpy\nimport pycolmap\nimport slamkit\n"):
        r = _python(code + COMPILE, tmp_path)
        assert r.returncode == 0 and r.stdout.strip() == "4.0", (code, r.stderr[-2000:])


def _debian_python() -> bool:
    """The interpreter is Debian's system Python (``/usr/bin/python3.*``, itself or behind a venv)."""
    return os.path.realpath(getattr(sys, "_base_executable", sys.executable)).startswith("/usr/bin/python3")


def test_the_hazard_the_guard_is_for(tmp_path):
    """The environment fact itself: pycolmap first, then a numba compile, aborts the process. When a pycolmap
    release fixes it this fails, and the guard in slamkit/__init__.py can go. It depends on the interpreter's
    build: measured with pyenv's CPython 3.11.7 (the machines' Python until 2026-12-05), not with Debian's
    3.11.2 (/usr/bin/python3, the same code prints 4.0), where the guard is only a precaution."""
    r = _python("import pycolmap\n" + COMPILE, tmp_path)
    if r.returncode == 0 and _debian_python():
        pytest.skip("pycolmap before numpy does not abort with Debian's system Python (measured 2026-12-05); "
                    "the hazard was measured with pyenv's CPython 3.11.7 build")
    assert r.returncode == -signal.SIGABRT, (r.returncode, r.stdout, r.stderr[-500:])
