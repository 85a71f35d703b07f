"""Training presets (TOML in `trainers/`, shipped with the package) and the config of a run that
`--resume` continues."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

from marlmerge import files
from marlmerge.config import from_dict, get_dotted, read_toml, set_dotted, to_dict
from marlmerge.presets import preset_dir
from marlmerge.training.config import FLAT_KEYS, upgrade_flat_keys

PRESET_KINDS = ("train", "cotrain")
"""What a training preset's `kind` key may say: the schema (and command) it belongs to."""

C = TypeVar("C")


def preset_path(path: str | Path) -> Path:
    """A training preset's file: a TOML path, or a name in `trainers/`."""
    path = Path(path)
    if not path.exists():
        known = sorted(p.stem for p in preset_dir("trainers").glob("*.toml"))
        candidate = preset_dir("trainers") / f"{path.stem}.toml"
        if not candidate.exists():
            raise ValueError(f"unknown training preset {str(path)!r} (known: {', '.join(known)})")
        path = candidate
    return path


def preset_kind(path: str | Path) -> str:
    """The schema a training preset names with its `kind` key: "train" or "cotrain"."""
    path = preset_path(path)
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
    path = preset_path(path)
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


def saved_config(cls: type[C], data: dict[str, Any]) -> C:
    """The config stored in a checkpoint (older versions' flat algorithm keys upgraded)."""
    return from_dict(cls, upgrade_flat_keys(data))


def resume_config(cls: type[C], out: Path, requested: C, set_keys: Iterable[str]) -> C:
    """The config of the run in `out` that `--resume` continues. A key given with `--set` must
    agree with it (a resumed run continues that run: nothing is resumable with other values)."""
    saved = saved_config(cls, files.load(out / "checkpoint.pt", "checkpoint")["config"])
    for key in set_keys:
        if get_dotted(saved, key) != get_dotted(requested, key):
            raise ValueError(
                f"--set {key}={get_dotted(requested, key)!r} differs from the run being resumed "
                f"({key} = {get_dotted(saved, key)!r} in {out / 'checkpoint.pt'}): a resumed run "
                "continues with its own config; start a new run with --out to change it"
            )
    return saved


def open_checkpoint(cfg: Any, path: Path, version: int, done: tuple[str, int]) -> dict[str, Any]:
    """The checkpoint `resume` continues: the run of `cfg` (same config, else an error naming
    the keys) and, unless it had finished (`checkpoint[key] >= end` for `done = (key, end)`),
    written in checkpoint layout `version`."""
    if not path.exists():
        raise ValueError(f"--resume: no checkpoint at {path}")
    ckpt = files.load(path, "checkpoint")
    saved = to_dict(saved_config(type(cfg), ckpt["config"]))
    differ = [k for k, v in to_dict(cfg).items() if saved.get(k) != v]
    if differ:
        raise ValueError(
            f"{path}: the run was made with other values of {', '.join(differ)}; resume it with "
            f"its own config (`marlmerge {cfg.KIND} --out RUN --resume`)"
        )
    if ckpt[done[0]] < done[1] and ckpt.get("version") != version:
        raise ValueError(
            f"{path}: written by an older version of marlmerge (checkpoint layout "
            f"{ckpt.get('version', 1)}, this version reads {version}): the run cannot be "
            "resumed exactly; start it again"
        )
    return ckpt
