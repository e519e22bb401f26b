"""Other Python interpreters than the one running the tests, for
``tests/test_python_versions.py`` and ``make test-versions``.

:func:`find` ``(version) -> (path, named)``: the interpreter of ``version`` ("3.12") to test:
the first of ``CNNPS_TEST_PYTHONS`` (paths separated by ``os.pathsep``; ``named`` is then
True), ``python<version>`` on ``PATH``, pyenv's builds
(``$PYENV_ROOT/versions/<version>.*/bin/python<version>``, ``~/.pyenv`` by default) that
runs and reports that version; ``(None, False)`` when there is none.

``python -m tests.support.pythons DIR VERSION...`` (network: PyPI) makes, for each version
found, a virtual environment ``DIR/py<version>`` holding the core requirements of
``pyproject.toml`` except torch and dvc (what the torch-free modules need to import;
reinstalled only when that list changes), and prints the interpreters, ``os.pathsep``
separated, for ``CNNPS_TEST_PYTHONS``. Nothing here installs torch.
"""

from __future__ import annotations

import glob
import hashlib
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ENV_VAR = "CNNPS_TEST_PYTHONS"
LEFT_OUT = {"torch", "dvc"}  # torch: a multi-GB build; dvc: a large tree no torch-free module imports


def version_of(exe: str) -> str | None:
    """``"3.12"`` for an interpreter that runs, else None (a pyenv shim of a version
    that is not selected exits non-zero)."""
    try:
        res = subprocess.run([exe, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout.strip() if res.returncode == 0 else None


def _candidates(version: str) -> list[str]:
    found = [shutil.which(f"python{version}")]
    root = os.environ.get("PYENV_ROOT") or os.path.expanduser("~/.pyenv")
    found += sorted(glob.glob(os.path.join(root, "versions", f"{version}.*", "bin", f"python{version}")), reverse=True)
    return [p for p in found if p]


def named() -> list[str]:
    return [p for p in os.environ.get(ENV_VAR, "").split(os.pathsep) if p]


def find(version: str) -> tuple[str | None, bool]:
    for exe in named():
        if version_of(exe) == version:
            return exe, True
    for exe in _candidates(version):
        if version_of(exe) == version:
            return exe, False
    return None, False


def requirements() -> list[str]:
    """The core requirements of pyproject.toml except :data:`LEFT_OUT`."""
    import re

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    return [d for d in deps if re.split(r"[\s<>=!~;\[]", d, maxsplit=1)[0].lower() not in LEFT_OUT]


def make_venv(base: Path, version: str) -> str | None:
    """``base/py<version>`` with :func:`requirements` installed; its interpreter, or None
    when no interpreter of ``version`` is found."""
    exe = next((p for p in _candidates(version) if version_of(p) == version), None)
    if exe is None:
        print(f"python{version}: not found on PATH or under pyenv, not tested", file=sys.stderr)
        return None
    venv = base.resolve() / f"py{version}"
    py = venv / "bin" / "python"
    reqs = requirements()
    stamp = venv / ".requirements"
    digest = hashlib.sha256("\n".join(reqs).encode()).hexdigest()
    if py.exists() and stamp.is_file() and stamp.read_text() == digest:
        return str(py)
    if not py.exists():
        subprocess.run([exe, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", *reqs], check=True)
    stamp.write_text(digest)
    return str(py)


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    base = Path(argv[0])
    made = [p for p in (make_venv(base, v) for v in argv[1:]) if p]
    print(os.pathsep.join(made))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
