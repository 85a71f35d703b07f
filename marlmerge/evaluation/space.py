"""The space of traffic conditions a stress test searches (`marlmerge stress`) and the third
held-out set is drawn from: every key `[sample]` draws, each over a range at least as wide as
any preset's.

A point of the space is a dict `{sample key: value}`; `scenario_at` turns it into the scenario a
world runs (exactly what `[sample]` would draw at those values), `unit` / `from_unit` map it to
and from the unit cube [0, 1]^D that the search works in, and `point_preset` / `write_preset`
write a condition as a scenario preset.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.io.files import write_text
from marlmerge.sim.streams import world_changes


@dataclass(frozen=True)
class Dimension:
    """One key of `[sample]` and the range the space spans."""

    key: str
    low: float
    high: float
    unit: str


SPACE: tuple[Dimension, ...] = (
    Dimension("flow_vph_per_lane", 200.0, 2200.0, "veh/h/lane"),
    Dimension("speed_limit_mph", 45.0, 80.0, "mph"),
    Dimension("entry_speed_fraction", 0.55, 1.05, "x limit"),
    Dimension("adversarial_share", 0.0, 1.0, ""),
    Dimension("cooperative_share", 0.0, 1.0, "of the rest"),
    Dimension("adversarial_time_headway_s", 0.3, 1.5, "s"),
    Dimension("adversarial_speed_factor", 0.9, 1.4, "x limit"),
    Dimension("ego_start_speed_mps", 4.0, 26.0, "m/s"),
    Dimension("sensing_range_m", 60.0, 200.0, "m"),
    Dimension("desired_speed_factor", 0.55, 1.3, "x limit"),
    Dimension("time_headway_s", 0.6, 2.4, "s"),
    Dimension("politeness", 0.0, 1.0, ""),
    Dimension("yield_max_brake_mps2", 0.5, 4.0, "m/s^2"),
    Dimension("adversarial_accel_mps2", 1.0, 4.0, "m/s^2"),
    Dimension("ramp_length_m", 30.0, 240.0, "m"),
    Dimension("merge_zone_m", 40.0, 150.0, "m"),
)
"""The dimensions, in `[sample]`'s draw order. Ramp length + merge zone stay under the default
road's 400 m upstream of the merge point."""

ROAD_KEYS = ("ramp_length_m", "merge_zone_m")
"""The dimensions that are the road's geometry (a batch of worlds shares its road's)."""
HELDOUT3_SEED = 20261202
"""The seed the third held-out set (`envs/heldout3_*`) was drawn with."""
HELDOUT4_SEED = 20261203
"""The seed the fourth held-out set (`envs/heldout4_*`) was drawn with: committed before the
round that added checkpoint selection to the hardened recipe."""
HELDOUT5_SEED = 20261204
"""The seed the fifth held-out set (`envs/heldout5_*`) was drawn with: committed before the
round that added the left-lane watch to the shield (`@shield-left`)."""
HELDOUT6_SEED = 20261205
"""The seed the sixth held-out set (`envs/heldout6_*`) was drawn with: committed before the
round that looked at the collisions behind `@shield-left`."""
HELDOUT7_SEED = 20261206
"""The seed the seventh held-out set (`envs/heldout7_*`) was drawn with: committed before
anyone ran a policy on it, for the round that next changes the drivers' defaults or tunes a
recipe."""
HELDOUT8_SEED = 20261207
"""The seed the eighth held-out set (`envs/heldout8_*`) was drawn with: committed before
anyone ran a policy on it, for the round after the seventh set's check (the drivers' new
default and the recipes tuned on it)."""
HELDOUT9_SEED = 20261214
"""The seed the ninth held-out set (`envs/heldout9_*`) was drawn with: committed before
anyone ran a policy on it, for the round that trains the hardened recipe on the stress space's
roads (`trainers/hardened_roads.toml`)."""
HELDOUT10_SEED = 20261215
"""The seed the tenth held-out set (`envs/heldout10_*`) was drawn with: committed before
anyone ran a policy on it, after the ninth set had judged `hardened_roads`. Costlier
collisions, the variant it was drawn for, failed on its validation roads first; it judged the
hardened recipe trained behind the shield instead (docs/stress.md)."""
HELDOUT11_SEED = 20261216
"""The seed the eleventh held-out set (`envs/heldout11_*`) was drawn with: committed before
anyone ran a policy on it, for the round that trains the hardened recipe bare with the shield's
verdicts as a cost (`TrainConfig.shield_penalty`) or as a teacher (`shield_imitation`), after
the tenth set had judged the recipe trained behind the shield. Both failed on their validation
roads first; it judged the hardened recipe's checkpoint chosen on the stress space's roads
(`select.scenario`) instead (docs/stress.md)."""
HELDOUT12_SEED = 20261217
"""The seed the twelfth held-out set (`envs/heldout12_*`) was drawn with: committed before
anyone ran a policy on it, for the round that trains the hardened recipe with a risk-averse
(expectile) TD loss (`TrainConfig.td_expectile`). That and the next three variants failed on
spent sets first; it judged `trainers/hardened_join.toml` (docs/stress.md, attempt 12)."""
HELDOUT13_SEED = 20261218
"""The seed the thirteenth held-out set (`envs/heldout13_*`) was drawn with: committed before
anyone ran a policy on it, after the twelfth set had judged `trainers/hardened_join.toml`, for
the round that next tunes a recipe. It judged `hardened_join` with collisions at 80
(docs/stress.md, attempt 13)."""
HELDOUT14_SEED = 20261219
"""The seed the fourteenth held-out set (`envs/heldout14_*`) was drawn with: committed before
anyone ran a policy on it, after the thirteenth set had judged attempt 13, for the round that
next tunes a recipe. It judged a Q of three peaks on `trainers/hardened_join.toml` (`peaks = 3`;
docs/stress.md, attempt 14)."""
HELDOUT15_SEED = 20261220
"""The seed the fifteenth held-out set (`envs/heldout15_*`) was drawn with: committed before
anyone ran a policy on it, while the fourteenth set was still unseen, for the round that next
tunes a recipe. No attempt after the fourteenth reached it; it checks whether attempt 14's
lean (`peaks = 3` on `trainers/hardened_join.toml`, against `hardened_join`) holds on a second
set, with the same seeds and nothing retrained (docs/stress.md)."""
HELDOUT16_SEED = 20261221
"""The seed the sixteenth held-out set (`envs/heldout16_*`) was drawn with: committed before
anyone ran a policy on it, while the fifteenth set was still unseen, for the round that next
tunes a recipe."""
HELDOUT17_SEED = 20261222
"""The seed the seventeenth held-out set (`envs/heldout17_*`) was drawn with: committed before
anyone ran a policy on it, while the sixteenth set was still unseen, for the round after the one
the sixteenth judges."""
HELDOUT_SETS = {
    "heldout3": HELDOUT3_SEED,
    "heldout4": HELDOUT4_SEED,
    "heldout5": HELDOUT5_SEED,
    "heldout6": HELDOUT6_SEED,
    "heldout7": HELDOUT7_SEED,
    "heldout8": HELDOUT8_SEED,
    "heldout9": HELDOUT9_SEED,
    "heldout10": HELDOUT10_SEED,
    "heldout11": HELDOUT11_SEED,
    "heldout12": HELDOUT12_SEED,
    "heldout13": HELDOUT13_SEED,
    "heldout14": HELDOUT14_SEED,
    "heldout15": HELDOUT15_SEED,
    "heldout16": HELDOUT16_SEED,
    "heldout17": HELDOUT17_SEED,
}
"""The held-out sets drawn from `SPACE`: file prefix -> seed."""


def unit(point: dict[str, float], space: tuple[Dimension, ...] = SPACE) -> np.ndarray:
    """A point [D] in the unit cube."""
    return np.array([(point[d.key] - d.low) / (d.high - d.low) for d in space])


def from_unit(u: np.ndarray, space: tuple[Dimension, ...] = SPACE) -> dict[str, float]:
    """The point of a vector [D] in the unit cube (clipped to it)."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    return {d.key: float(d.low + x * (d.high - d.low)) for d, x in zip(space, u, strict=True)}


def latin_hypercube(n: int, dims: int, rng: np.random.Generator) -> np.ndarray:
    """n points [n, dims] in the unit cube, one in each of n strata of every dimension."""
    strata = np.stack([rng.permutation(n) for _ in range(dims)], axis=1)
    return (strata + rng.uniform(size=(n, dims))) / n


def scenario_at(base: ScenarioConfig, point: dict[str, float]) -> ScenarioConfig:
    """The scenario a world runs at `point`: `base` (which draws nothing itself) with what
    `[sample]` draws at those values (keys left out keep `base`'s)."""
    if base.sample.active:
        raise ValueError(f"scenario_at: {base.name!r} draws its traffic ([sample])")
    return base.replace(**world_changes(base, point))


def point_preset(base: ScenarioConfig, point: dict[str, float], name: str) -> dict[str, Any]:
    """A scenario preset of the fixed condition at `point`: the keys that differ from `base`."""
    cfg = dataclasses.replace(scenario_at(base, point), name=name)
    return _diff(to_dict(cfg), to_dict(base)) | {"name": name}


def heldout_points(n: int = 12, seed: int = HELDOUT3_SEED) -> list[dict[str, float]]:
    """n conditions drawn uniformly and independently from `SPACE` by `seed` (not chosen)."""
    rng = np.random.default_rng(seed)
    return [from_unit(rng.uniform(size=len(SPACE))) for _ in range(n)]


def write_heldout3(folder: Path, n: int = 12, seed: int = HELDOUT3_SEED) -> list[Path]:
    """Write the third held-out set, `heldout3_01.toml` ... into `folder`."""
    return write_heldout_set(folder, "heldout3", n, seed)


ORDINALS = (
    "first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth", "ninth", "tenth",
    "eleventh", "twelfth", "thirteenth", "fourteenth", "fifteenth", "sixteenth", "seventeenth",
    "eighteenth", "nineteenth", "twentieth",
)  # fmt: skip


def ordinal_of(prefix: str) -> str:
    """The word for a held-out set's place (heldout11: eleventh); other names unchanged."""
    number = prefix.removeprefix("heldout")
    if number.isdigit() and 1 <= int(number) <= len(ORDINALS):
        return ORDINALS[int(number) - 1]
    return prefix


def write_heldout_set(folder: Path, prefix: str, n: int = 12, seed: int | None = None):
    """Write a held-out set drawn from `SPACE` (`HELDOUT_SETS`), `PREFIX_01.toml` ... into
    `folder`; `seed` defaults to the set's own."""
    seed = HELDOUT_SETS[prefix] if seed is None else seed
    ordinal = ordinal_of(prefix)
    base, paths = ScenarioConfig(), []
    for i, point in enumerate(heldout_points(n, seed), start=1):
        name = f"{prefix}_{i:02d}"
        note = (
            f"The {ordinal} held-out set, condition {i} of {n}: drawn uniformly from the "
            f"stress-test\nspace (marlmerge.evaluation.space.SPACE) by seed {seed}, not chosen "
            "by anyone.\nRemake the set with "
            f"`marlmerge.evaluation.space.write_heldout_set(folder, {prefix!r})`."
        )
        paths.append(write_preset(folder / f"{name}.toml", point_preset(base, point, name), note))
    return paths


def _diff(data: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in data.items():
        if isinstance(v, dict):
            sub = _diff(v, base[k])
            if sub:
                out[k] = sub
        elif v != base[k]:
            out[k] = v
    return out


def write_preset(path: Path, data: dict[str, Any], note: str = "") -> Path:
    """Write a scenario preset (plain values and one level of tables) as TOML."""
    lines = [f"# {line}" for line in note.splitlines()]
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    lines += [f"{k} = {_toml(v)}" for k, v in data.items() if k not in tables]
    for table, values in tables.items():
        lines += ["", f"[{table}]", *(f"{k} = {_toml(v)}" for k, v in values.items())]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, "\n".join(lines) + "\n")
    return path


def _toml(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(v)
