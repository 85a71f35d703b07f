"""Where the scenario presets (`envs/`) and training presets (`trainers/`) are.

In a source checkout (and an editable install) they are the repository's top-level folders; a
wheel ships them inside the package (`marlmerge/_presets/`, see `pyproject.toml`), so `marlmerge
train` and `marlmerge grid` work from any directory after a plain `pip install .`.
"""

from __future__ import annotations

from pathlib import Path

KINDS = ("envs", "trainers")


def preset_dir(kind: str) -> Path:
    """The folder of the `kind` presets ("envs" or "trainers")."""
    if kind not in KINDS:
        raise ValueError(f"preset kind must be one of {KINDS}, got {kind!r}")
    here = Path(__file__).resolve().parent
    shipped = here / "_presets" / kind
    return shipped if shipped.is_dir() else here.parent / kind
