"""A virtual environment for a test's subprocess that sees the packages of the interpreter running
the tests, whether that interpreter is a system Python or itself a virtual environment (as when a
user follows the README inside `python -m venv venv`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def child_venv(path: Path, with_pip: bool = True, python: str = sys.executable) -> Path:
    """A venv at `path` whose site-packages come first and whose fallbacks are the site-packages
    of `python` (not of the base interpreter, which `--system-site-packages` would give from
    inside a venv). The fallbacks' own `.pth` hooks (an editable install's import finder) are not
    run, so a package installed into the child is the one it imports. Returns its interpreter."""
    args = [python, "-m", "venv", str(path)] + ([] if with_pip else ["--without-pip"])
    subprocess.run(args, check=True, timeout=600)
    probe = "import sys; print('\\n'.join(p for p in sys.path if p.endswith('site-packages')))"
    parent = subprocess.run(
        [python, "-c", probe], capture_output=True, text=True, check=True
    ).stdout.split()
    py = path / "bin" / "python"
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    Path(site, "_parent_site_packages.pth").write_text("\n".join(parent) + "\n")
    return py
