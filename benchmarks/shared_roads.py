"""Replay the roads where most of a learned policy's seeds collide, beside gap acceptance.

    python benchmarks/shared_roads.py runs/patient_grid/episodes.csv --policy hardened \
        --min-seeds 4 [--root-seed 2000000]

A grid drives every policy on the same roads (`marlmerge.evaluation.grid.road_seeds`: keyed by
the root seed, the preset and the episode), so any of its roads can be driven again, alone, with
each policy's trajectory recorded. For every road where at least `--min-seeds` of the policy's
seeds collided in the grid, this drives each of those seeds and gap acceptance there again,
checks the outcome is the grid's, and prints per road and policy: the outcome, who hit whom
(the ego into the gap-front vehicle, the gap-back vehicle into the ego), where (the ego's x
against the join point), and the ego's speed, lead and lag gaps (bumper, m) and lag time gap
(s) as its front bumper passed the join point, and the episode's return (with `--reward
PRESET`, under that preset's reward: the reward changes no motion). Then the same pooled over
the roads, and the returns by outcome. `--trace` prints one road decision by decision.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np

from marlmerge.config import to_dict
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.grid import road_seeds
from marlmerge.evaluation.metrics import EpisodeTrajectory
from marlmerge.evaluation.registry import make_policy, parse_policy, scenario_for
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED

OUTCOMES = {
    OUTCOME_SUCCESS: "success",
    OUTCOME_COLLISION: "collision",
    OUTCOME_TRUNCATED: "truncation",
}
"""Outcome codes in the words of a grid's episodes.csv."""


def shared_roads(path: str, policy: str, min_seeds: int) -> tuple[dict, dict]:
    """(condition, episode) -> the runs of `policy` that collided there, for the roads where at
    least `min_seeds` did; and (condition, episode) -> gap acceptance's outcome there."""
    hits: dict[tuple[str, int], list[str]] = defaultdict(list)
    gap: dict[tuple[str, int], str] = {}
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            key = (r["condition"], int(r["episode"]))
            if r["policy"] == policy and float(r["collision"]) > 0:
                hits[key].append(r["run"])
            elif r["policy"] == "gap":
                gap[key] = next(k for k in OUTCOMES.values() if float(r[k]) > 0)
    return {k: sorted(v) for k, v in hits.items() if len(v) >= min_seeds}, gap


def drive(
    spec: str, run: str | None, preset: str, episode: int, root: int, reward: dict | None = None
) -> tuple[EpisodeTrajectory, float]:
    """One road of a grid condition driven again by one policy (one training run): its
    trajectory and its episode's total reward, under the condition's reward or, with `reward`
    (dotted `reward.*` overrides), another one (the reward changes no draw and no motion)."""
    p = parse_policy(spec)
    scen = scenario_for(p, run, resolve_config(preset)).replace(**(reward or {}))
    seeds = road_seeds(root, scen.name, episode + 1)[episode:]
    rec, traces = rollout_first_egos(
        make_policy(p, run, scen), scen, 1, 0, 1, record=True, road_seeds=seeds
    )
    return traces[0], float(rec["reward"][0])


def reward_of(preset: str | None) -> dict | None:
    """A preset's reward as dotted overrides (None: keep each condition's)."""
    if preset is None:
        return None
    return {f"reward.{k}": v for k, v in to_dict(resolve_config(preset).reward).items()}


def at_join(tr: EpisodeTrajectory, x_join_m: float) -> dict[str, float]:
    """The ego's state at the first sample at or past the join point (nan where never)."""
    idx = np.nonzero(np.asarray(tr.x_m) >= x_join_m)[0]
    if idx.size == 0:
        return {"v": np.nan, "lead": np.nan, "lag": np.nan, "lag_s": np.nan, "t": np.nan}
    k = int(idx[0])
    v_back = float(tr.v_back_mps[k])
    lag = float(tr.d_back_m[k])
    return {
        "v": float(tr.v_mps[k]),
        "lead": float(tr.d_front_m[k]),
        "lag": lag,
        "lag_s": lag / v_back if v_back > 0.1 else np.inf,
        "t": float(tr.t_s[k]),
    }


def crash(tr: EpisodeTrajectory) -> str:
    """Who hit whom at the last sample: `front` (the ego into the gap-front vehicle: its bumper
    gap at most 0.5 m and not larger than the back one), `back` (the gap-back vehicle into the
    ego) or `side` (neither gap closed); `-` without a collision."""
    if tr.outcome != OUTCOME_COLLISION:
        return "-"
    df, db = float(tr.d_front_m[-1]), float(tr.d_back_m[-1])
    if df <= 0.5 and df <= db:
        return "front"
    if db <= 0.5:
        return "back"
    return "side"


def decisions(spec: str, run: str | None, preset: str, episode: int, root: int) -> list[dict]:
    """One grid road driven again, decision by decision: the ego's position and speed, its
    command, its time to the join point and the paper's gap (the gap vehicles' bumper gaps now,
    and extrapolated to the ego's arrival at the join point at constant speeds, as the
    `"extended_join"` layout computes them but without its time cap and clipping, from the
    paper's seven features, so for any layout; m, s, m/s, m/s^2)."""
    import torch

    from marlmerge.sim.observation import EGO_SCALE
    from marlmerge.views.torchrl_env import BatchedMergeEnv

    p = parse_policy(spec)
    scen = scenario_for(p, run, resolve_config(preset))
    policy = make_policy(p, run, scen)
    seeds = road_seeds(root, scen.name, episode + 1)[episode:]
    env = BatchedMergeEnv(scen, num_worlds=1, seed=seeds)
    td, rows, length = env.reset(), [], scen.vehicle.length_m
    step_s = scen.sim.dt_s * scen.sim.action_repeat
    for k in range(int(scen.ego.max_episode_s / step_s) + 1):
        obs = td["observation"]
        v, x, v_f, x_f, v_b, x_b, _ = (obs[0, :7].numpy() * EGO_SCALE).tolist()
        t_join = max(scen.x_overlap_m - x, 0.0) / max(v, 0.1)
        action = policy(obs)
        rows.append({
            "t": k * step_s, "x": x, "v": v, "cmd": float(action[0, 0]),
            "t_join": t_join, "lead": x_f - x - length, "lag": x - x_b - length,
            "lead_at_join": x_f - x + (v_f - v) * t_join - length,
            "lag_at_join": x - x_b + (v - v_b) * t_join - length, "v_back": v_b,
        })  # fmt: skip
        td["action"] = torch.as_tensor(action, dtype=torch.float32).reshape(1, -1)
        td = env.step(td)["next"]
        if bool(td["done"].any()):
            rows[-1]["outcome"] = OUTCOMES.get(int(td["outcome"].reshape(-1)[0]), "running")
            break
    return rows


def print_trace(args: argparse.Namespace) -> None:
    cond, ep, run = args.trace.split(",")
    spec, run = ("gap", None) if run == "gap" else (f"{args.kind}:{run}", run)
    print(
        "| t s | x m | v m/s | command m/s² | time to join s | lead m | lag m "
        "| lead at join m | lag at join m | back's speed m/s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in decisions(spec, run, cond.replace(" ", "_"), int(ep), args.root_seed):
        print(
            f"| {r['t']:.1f} | {r['x']:.1f} | {r['v']:.1f} | {r['cmd']:+.2f} | {r['t_join']:.1f}"
            f" | {r['lead']:.1f} | {r['lag']:.1f} | {r['lead_at_join']:.1f}"
            f" | {r['lag_at_join']:.1f} | {r['v_back']:.1f} |"
            + (f" {r['outcome']}" if "outcome" in r else "")
        )


def print_roads(args: argparse.Namespace) -> dict[str, list[dict]]:
    """The per-road table; returns its rows by `learned` / `gap`."""
    roads, gap_outcome = shared_roads(args.episodes_csv, args.policy, args.min_seeds)
    reward = reward_of(args.reward)
    print(f"{len(roads)} roads where at least {args.min_seeds} seeds of {args.policy} collided\n")
    print(
        "| condition | episode | policy | outcome | crash | x at end m | v at end m/s "
        "| v at join m/s | lead m | lag m | lag s | t at join s | return |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    pooled: dict[str, list[dict]] = defaultdict(list)
    mismatches = 0
    for (cond, ep), runs in sorted(roads.items()):
        preset = cond.replace(" ", "_")
        x_join = resolve_config(preset).x_overlap_m
        rows = [(f"{args.kind}:{r}", r, "learned") for r in runs] + [("gap", None, "gap")]
        for spec, run, who in rows:
            tr, ret = drive(spec, run, preset, ep, args.root_seed, reward)
            want = "collision" if who == "learned" else gap_outcome.get((cond, ep), "?")
            got = OUTCOMES.get(tr.outcome, "running")
            mismatches += got != want
            j = at_join(tr, x_join)
            row = {"who": who, "crash": crash(tr), "x_end": float(tr.x_m[-1]) - x_join, **j}
            row |= {"outcome": got, "return": ret}
            pooled[who].append(row)
            note = "" if got == want else f" (grid: {want})"
            print(
                f"| {cond} | {ep} | {run or 'gap'} | {got}{note} | {row['crash']}"
                f" | {row['x_end']:+.1f} | {float(tr.v_mps[-1]):.1f} | {j['v']:.1f}"
                f" | {j['lead']:.1f} | {j['lag']:.1f} | {j['lag_s']:.2f} | {j['t']:.1f}"
                f" | {ret:.1f} |"
            )
    print(f"\noutcomes differing from the grid's: {mismatches}\n")
    return pooled


def print_pooled(pooled: dict[str, list[dict]], reward: str | None) -> None:
    """Who hit whom and where, the state at the join, and the episodes' returns, pooled."""
    print(
        "| policy | episodes | crash front / back / side | of them within 3 m past the join "
        "| x at end past join m (median) | v at join (median) | lead m (median) "
        "| lag m (median) | lag s (median) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for who, rs in pooled.items():
        c = {k: sum(r["crash"] == k for r in rs) for k in ("front", "back", "side")}
        near = sum(r["crash"] != "-" and r["x_end"] <= 3.0 for r in rs)

        def med(k: str, rs: list[dict] = rs) -> float:
            return float(np.nanmedian([r[k] for r in rs]))

        print(
            f"| {who} | {len(rs)} | {c['front']} / {c['back']} / {c['side']} | {near}"
            f" | {med('x_end'):+.1f}"
            f" | {med('v'):.1f} | {med('lead'):.1f} | {med('lag'):.1f} | {med('lag_s'):.2f} |"
        )
    print(f"\nEpisode returns under {reward or 'each condition'}'s reward:\n")
    print("| policy | outcome | episodes | median | mean |")
    print("|---|---|---|---|---|")
    for who, rs in pooled.items():
        for outcome in ("all", *OUTCOMES.values()):
            r = [x["return"] for x in rs if outcome in ("all", x["outcome"])]
            if r:
                print(f"| {who} | {outcome} | {len(r)} | {np.median(r):.1f} | {np.mean(r):.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("episodes_csv")
    ap.add_argument("--policy", default="hardened")
    ap.add_argument("--kind", default="quadq", help="the learned policy's kind")
    ap.add_argument("--min-seeds", type=int, default=4)
    ap.add_argument("--root-seed", type=int, default=2_000_000)
    ap.add_argument(
        "--reward",
        metavar="PRESET",
        help="score the episodes with this preset's reward (e.g. the recipe's training traffic)",
    )
    ap.add_argument(
        "--trace",
        metavar="CONDITION,EPISODE,RUN",
        help="instead, one road decision by decision (RUN: a run folder, or gap)",
    )
    args = ap.parse_args()
    if args.trace:
        print_trace(args)
        return
    print_pooled(print_roads(args), args.reward)


if __name__ == "__main__":
    main()
