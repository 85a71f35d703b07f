"""How much could importance sampling of a sampled scenario's traffic parameters gain at best?

For a scenario with `[sample]` ranges (each world draws its traffic: flow, speed limit, driver
bands, mix, ...), this runs plain Monte Carlo over fresh roads, then fits, to the episodes that
ended in the event, the best proposal of the product family that `marlmerge.sim.proposal` uses
(one Beta per sampled key, by moments, optionally mixed with the natural uniform) and computes
what that proposal's estimate would cost: with q the proposal density and y the event,
E_q[(y p/q)^2] = E_p[y p/q], so the variance, and the efficiency against Monte Carlo
(rate (1 - rate) / variance), follow from the Monte Carlo sample itself. The proposal is
fitted to the same sample it is judged on, so the number is an upper bound of what
cross-entropy fitting of that family can reach (before counting its fitting rounds).

    python benchmarks/proposal_bound.py [--policy gap] [--scenario hardened_mix]
        [--episodes 20000] [--seed 0]

Prints one JSON line per event (collision, failure) with the rate, the events and the
efficiency at a few defensive mixture weights.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.registry import policy_for_evaluation
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_TRUNCATED
from marlmerge.sim.proposal import BETA_RANGE, beta_log_pdf
from marlmerge.sim.streams import (
    DRAWN_AFTER_MIX,
    DRAWN_BEFORE_MIX,
    SCENARIO_STREAM,
    draw_world_values,
)
from marlmerge.views.torchrl_env import BatchedMergeEnv

DEFENSIVE = (0.0, 0.1, 0.3)
"""Weights of the natural uniform mixed into the fitted proposal."""


def drawn_units(
    cfg: ScenarioConfig, seeds: list[np.random.SeedSequence], keys: list[str]
) -> np.ndarray:
    """[E, K] each episode's sampled values, as positions in their ranges. An env's reset sends
    the second ego of a fresh road, and with `resample_every_egos = 1` that ego drives the
    second traffic its world drew."""
    draws = 2 if cfg.sample.resample_every_egos == 1 else 1
    units = np.zeros((len(seeds), len(keys)))
    for e, seq in enumerate(seeds):
        fresh = np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key)
        g = np.random.default_rng(fresh.spawn(SCENARIO_STREAM + 1)[SCENARIO_STREAM])
        for _ in range(draws):
            values, _ = draw_world_values(cfg, g)
        for j, key in enumerate(keys):
            lo, hi = getattr(cfg.sample, key)
            units[e, j] = (values[key] - lo) / (hi - lo)
    return units


def check_units(
    cfg: ScenarioConfig,
    seeds: list[np.random.SeedSequence],
    keys: list[str],
    units: np.ndarray,
    n: int = 4,
) -> None:
    """The replayed draws are the traffic the env's egos drove (first `n` episodes)."""
    env = BatchedMergeEnv(cfg, num_worlds=n, seed=list(seeds[:n]))
    env.reset()
    for b in range(n):
        world = env.core.world_scenario(b)
        flow = world.traffic.flow_vph_per_lane
        if "flow_vph_per_lane" in keys:
            lo, hi = cfg.sample.flow_vph_per_lane
            assert math.isclose(flow, lo + units[b, keys.index("flow_vph_per_lane")] * (hi - lo))


def bound(event: np.ndarray, units: np.ndarray, keys: list[str]) -> dict:
    rate = float(event.mean())
    out: dict = {"rate": rate, "events": int(event.sum()), "episodes": int(event.size)}
    if event.sum() < 5:
        return out | {"efficiency": None}
    log_q = np.zeros(event.size)
    fitted = {}
    for j, key in enumerate(keys):
        y = np.clip(units[event, j], 1e-6, 1 - 1e-6)
        m, v = float(y.mean()), float(y.var())
        common = max(m * (1 - m) / max(v, 1e-9) - 1, 1e-3)
        a = float(np.clip(m * common, *BETA_RANGE))
        b = float(np.clip((1 - m) * common, *BETA_RANGE))
        fitted[key] = [round(a, 2), round(b, 2)]
        log_q += beta_log_pdf(np.clip(units[:, j], 1e-9, 1 - 1e-9), a, b)
    eff = {}
    for mix in DEFENSIVE:
        q = (1 - mix) * np.exp(log_q) + mix
        variance = float(np.mean(event / q)) - rate * rate
        eff[str(mix)] = rate * (1 - rate) / variance if variance > 0 else math.inf
    return out | {"efficiency": eff, "beta": fitted}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", default="gap")
    ap.add_argument("--scenario", default="hardened_mix")
    ap.add_argument("--episodes", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    policy, cfg = policy_for_evaluation(args.policy, resolve_config(args.scenario))
    if not cfg.sample.active:
        raise SystemExit(f"--scenario {args.scenario}: no [sample] ranges to tilt")
    keys = [k for k in DRAWN_BEFORE_MIX + DRAWN_AFTER_MIX if getattr(cfg.sample, k) is not None]
    seeds = [np.random.SeedSequence(args.seed, spawn_key=(e,)) for e in range(args.episodes)]
    units = drawn_units(cfg, seeds, keys)
    check_units(cfg, seeds, keys, units)
    rec, _ = rollout_first_egos(policy, cfg, args.episodes, 0, 500, road_seeds=seeds)
    collision = rec["outcome"] == OUTCOME_COLLISION
    failure = collision | (rec["outcome"] == OUTCOME_TRUNCATED)
    for name, event in (("collision", collision), ("failure", failure)):
        row = {"policy": args.policy, "scenario": args.scenario, "event": name}
        print(json.dumps(row | bound(event, units, keys)))


if __name__ == "__main__":
    main()
