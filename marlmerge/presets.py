"""Where the scenario presets (`envs/`) and training presets (`trainers/`) are, and the one
lookup of a scenario preset by name or path.

In a source checkout (and an editable install) they are the repository's top-level folders; a
wheel ships them inside the package (`marlmerge/_presets/`, see `pyproject.toml`), so `marlmerge
train` and `marlmerge grid` work from any directory after a plain `pip install .`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from marlmerge.config import ScenarioConfig, load_scenario

KINDS = ("envs", "trainers")


def preset_dir(kind: str) -> Path:
    """The folder of the `kind` presets ("envs" or "trainers")."""
    if kind not in KINDS:
        raise ValueError(f"preset kind must be one of {KINDS}, got {kind!r}")
    here = Path(__file__).resolve().parent
    shipped = here / "_presets" / kind
    return shipped if shipped.is_dir() else here.parent / kind


def find_preset(name: str | Path) -> Path:
    """A scenario preset file: a path, or a name looked up in the `envs/` folder."""
    path = Path(name)
    if path.suffix == ".toml" and path.exists():
        return path
    envs_dir = preset_dir("envs")
    candidate = envs_dir / f"{path.stem}.toml"
    if candidate.exists():
        return candidate
    known = sorted(p.stem for p in envs_dir.glob("*.toml")) if envs_dir.exists() else []
    raise ValueError(f"unknown scenario preset {str(name)!r} (known: {', '.join(known) or 'none'})")


def resolve_config(config: ScenarioConfig | str | Path | None, **overrides: Any) -> ScenarioConfig:
    """A `ScenarioConfig` from a config, a preset path or name in `envs/`, or the defaults."""
    if config is None:
        cfg = ScenarioConfig()
    elif isinstance(config, ScenarioConfig):
        cfg = config
    else:
        cfg = load_scenario(find_preset(config))
    return cfg.replace(**overrides) if overrides else cfg


def run_scenario(run_cfg: Any) -> ScenarioConfig:
    """The scenario a training run's `scenario` key names, loaded; an unknown preset or a bad
    value is a `ValueError` naming the key, raised before the run writes or prints anything."""
    try:
        return resolve_config(run_cfg.scenario)
    except ValueError as err:
        raise ValueError(f"scenario = {run_cfg.scenario!r}: {err}") from None
