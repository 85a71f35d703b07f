"""The checkpoint a `--resume` continues: the run's saved config (older layouts upgraded), checked
against the requested one."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

from marlmerge.config import from_dict, get_dotted, to_dict
from marlmerge.config.training import upgrade_flat_keys
from marlmerge.io import files

C = TypeVar("C")

PLACE_KEYS = ("device",)
"""Keys that say where a run computes, not what it computes: a resumed run may change them
(`--resume --set device=cpu` continues a run trained on an accelerator on a machine without)."""


def saved_config(cls: type[C], data: dict[str, Any]) -> C:
    """The config stored in a checkpoint (older versions' flat algorithm keys upgraded)."""
    return from_dict(cls, upgrade_flat_keys(data))


def resume_config(
    cls: type[C],
    out: Path,
    requested: C,
    set_keys: Iterable[str],
    name: str = "checkpoint.pt",
    named: bool = False,
) -> C:
    """The config of the run in `out` (checkpoint `name`) that `--resume` continues. A key given
    with `--set` must agree with it (a resumed run continues that run: nothing is resumable
    with other values), except the `PLACE_KEYS`, which the request sets; a preset `named` on
    the command line must be the run's (its `name`)."""
    saved = saved_config(cls, files.load(out / name, "checkpoint")["config"])
    run_name, asked = saved.name, requested.name
    if named and "name" not in set_keys and run_name != asked:
        raise ValueError(
            f"--resume: the run in {out} was trained from preset {run_name!r}, not {asked!r}; "
            f"resume it with its own config (`marlmerge {cls.KIND} {run_name} --out {out} "
            "--resume`) or start a new run with another --out"
        )
    place = {k: getattr(requested, k) for k in PLACE_KEYS if k in set_keys}
    saved = dataclasses.replace(saved, **place)  # type: ignore[type-var]
    for key in set_keys:
        if get_dotted(saved, key) != get_dotted(requested, key):
            raise ValueError(
                f"--set {key}={get_dotted(requested, key)!r} differs from the run being resumed "
                f"({key} = {get_dotted(saved, key)!r} in {out / name}): a resumed run "
                "continues with its own config; start a new run with --out to change it"
            )
    return saved


def refuse_to_overwrite(ckpt_path: Path, resume: bool) -> None:
    """A run of several seeds does not start over a checkpoint it was not asked to resume."""
    if ckpt_path.exists() and not resume:
        raise ValueError(f"{ckpt_path.parent} already holds a run: pass --resume to continue it")


def open_checkpoint(
    cfg: Any, path: Path, version: int, done: tuple[str, int], seeds: list[int] | None = None
) -> dict[str, Any]:
    """The checkpoint `resume` continues: the run of `cfg` (same config, else an error naming
    the keys) and, unless it had finished (`checkpoint[key] >= end` for `done = (key, end)`),
    written in checkpoint layout `version`. With `seeds`, a run of several seeds in one
    process (`--seeds`): the run of those seeds (its config is the first seed's)."""
    if not path.exists():
        raise ValueError(f"--resume: no checkpoint at {path}")
    ckpt = files.load(path, "checkpoint")
    if seeds is not None:
        if ckpt.get("seeds") != seeds:
            verb = "co-trains" if cfg.KIND == "cotrain" else "trains"
            raise ValueError(
                f"{path}: the run {verb} seeds {ckpt.get('seeds')}, not {seeds}; resume it "
                f"with --seeds {','.join(map(str, ckpt.get('seeds') or []))}"
            )
        cfg = dataclasses.replace(cfg, seed=seeds[0])
    saved = to_dict(saved_config(type(cfg), ckpt["config"]))
    differ = [k for k, v in to_dict(cfg).items() if saved.get(k) != v and k not in PLACE_KEYS]
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
