"""The presets: where the scenario presets (`envs/`) and training presets (`trainers/`) are, the
one lookup of a preset by name or path (`find_preset`), and their strict loading with dotted-key
overrides.

In a source checkout (and an editable install) they are the repository's top-level folders; a
wheel ships them inside the package (`marlmerge/_presets/`, see `pyproject.toml`), so `marlmerge
train` and `marlmerge grid` work from any directory after a plain `pip install .`.
"""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, TypeVar

from marlmerge.config.codec import from_dict, read_toml, set_dotted
from marlmerge.config.cotraining import CoTrainConfig
from marlmerge.config.scenario import ScenarioConfig, load_scenario, require_ego
from marlmerge.config.training import FLAT_KEYS, TrainConfig

KINDS = ("envs", "trainers")
"""The preset folders: scenarios (`envs/`) and training runs (`trainers/`)."""
PRESET_KINDS = ("train", "cotrain")
"""What a training preset's `kind` key may say: the schema (and command) it belongs to."""
_WHAT = {"envs": "scenario preset", "trainers": "training preset"}
MAX_LISTED = 30  # an unknown preset's error lists them all up to this many

C = TypeVar("C")


def preset_dir(kind: str) -> Path:
    """The folder of the `kind` presets ("envs" or "trainers")."""
    if kind not in KINDS:
        raise ValueError(f"preset kind must be one of {KINDS}, got {kind!r}")
    here = Path(__file__).resolve().parent.parent  # the package folder
    shipped = here / "_presets" / kind
    return shipped if shipped.is_dir() else here.parent / kind


def find_preset(name: str | Path, kind: str = "envs") -> Path:
    """A preset file: a path to an existing file, or a name looked up in the `kind` folder
    ("envs": scenarios, "trainers": training runs); an unknown name is a `ValueError` listing
    the known ones. A path in another folder that does not exist is an error too, not the preset
    of the same name (`envs/NAME.toml` names the preset from any directory)."""
    path = Path(name)
    if path.exists() and (kind == "trainers" or path.suffix == ".toml"):
        return path
    if path.parent != Path(".") and path.parent.name != kind:
        raise ValueError(f"{_WHAT[kind]} file {str(name)!r} does not exist")
    folder = preset_dir(kind)
    candidate = folder / f"{path.stem}.toml"
    if candidate.exists():
        return candidate
    known = sorted(p.stem for p in folder.glob("*.toml")) if folder.exists() else []
    raise ValueError(f"unknown {_WHAT[kind]} {str(name)!r} ({_known(known, path.stem, folder)})")


def _known(known: list[str], stem: str, folder: Path) -> str:
    """The presets an unknown name could have meant: all of them when few, else the closest
    few and where the rest are."""
    if len(known) <= MAX_LISTED:
        return f"known: {', '.join(known) or 'none'}"
    close = difflib.get_close_matches(stem, known, n=5, cutoff=0.5)
    near = f"the closest: {', '.join(close)}; " if close else ""
    return f"{near}{len(known)} presets in {folder}"


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
    """The scenario a training run's `scenario` key names, loaded; an unknown preset, a bad value
    or a scenario its learner cannot train (`ego.join = "chosen"` needs quadq; co-training needs
    an ego, not ramp flow) is a `ValueError` naming the key, raised before the run writes or
    prints anything."""
    try:
        scen = resolve_config(run_cfg.scenario)
    except ValueError as err:
        raise ValueError(f"scenario = {run_cfg.scenario!r}: {err}") from None
    algorithm = getattr(run_cfg, "algorithm", None)  # a co-training run has none
    if scen.ego.chooses_join and algorithm != "quadq":
        raise ValueError(
            f"scenario = {run_cfg.scenario!r} sets ego.join = {scen.ego.join!r}: an action of "
            "two components, which only the quadratic-Q learner (algorithm = 'quadq') takes; "
            f"{'co-training' if algorithm is None else repr(algorithm)} acts on the "
            "acceleration alone"
        )
    if algorithm is None:  # co-training pits highway agents against the one ego
        require_ego(scen, f"co-training: scenario = {run_cfg.scenario!r}")
    return scen


def preset_kind(path: str | Path) -> str:
    """The schema a training preset names with its `kind` key: "train" or "cotrain"."""
    path = find_preset(path, "trainers")
    return _kind_of(path, read_toml(path))


def _kind_of(path: Path, data: dict[str, Any]) -> str:
    kind = data.get("kind")
    if kind not in PRESET_KINDS:
        raise ValueError(
            f"{path}: kind must name the preset's schema, one of {', '.join(PRESET_KINDS)} "
            f'(`kind = "train"` for `marlmerge train`), got {kind!r}'
        )
    return kind


def with_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """`data` with dotted-key overrides (`{"dqn.levels": 9}`); a key of an older version names
    where it lives now."""
    for key in [*data, *overrides]:
        if key in FLAT_KEYS:
            raise ValueError(
                f"config key {key!r} is now {' and '.join(map(repr, FLAT_KEYS[key]))} "
                "(a table per algorithm: `[dqn]` / `[td3]` in a preset, `--set dqn.levels=9`)"
            )
    for key, value in overrides.items():
        set_dotted(data, key, value, create=True)
    return data


def load_preset(cls: type[C], path: str | Path, **overrides: Any) -> C:
    """A preset of the dataclass `cls` (its `KIND` must be the preset's `kind`): a TOML path, or
    a name in `trainers/`; loaded strictly (unknown keys raise), `name` defaulting to the file's
    stem, with dotted-key overrides."""
    path = find_preset(path, "trainers")
    data = read_toml(path)
    kind = _kind_of(path, data)
    if kind != cls.KIND:  # type: ignore[attr-defined]
        raise ValueError(f"{path} is a {kind!r} preset: run it with `marlmerge {kind} {path.stem}`")
    del data["kind"]
    data.setdefault("name", path.stem)
    try:
        preset = from_dict(cls, with_overrides(data, {}))
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    if not overrides:
        return preset
    try:
        return from_dict(cls, with_overrides(data, overrides))
    except ValueError as err:  # the preset alone is valid: the overrides are to blame
        sets = ", ".join(f"{k}={v!r}" for k, v in overrides.items())
        raise ValueError(f"--set {sets} (on {path.name}): {err}") from None


def load_train_config(path: str | Path, **overrides: Any) -> TrainConfig:
    """A training preset (TOML), loaded strictly, with optional (dotted) field overrides."""
    return load_preset(TrainConfig, path, **overrides)


def load_cotrain_config(path: str | Path, **overrides: Any) -> CoTrainConfig:
    """A co-training preset (TOML in `trainers/` or a path), loaded strictly, with overrides."""
    return load_preset(CoTrainConfig, path, **overrides)
