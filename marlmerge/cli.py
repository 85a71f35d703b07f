"""Command line: `marlmerge simulate ...`. Run `marlmerge --help` for the commands."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

EGO_RULES = ("hold", "idm", "random")


def _ego_rule(rule: str, cfg, rng: np.random.Generator):
    """An ego policy: observation [7] -> action [1]."""
    from marlmerge.policies import IdmEgoPolicy, constant_speed_action

    if rule == "hold":
        return constant_speed_action
    if rule == "idm":
        return IdmEgoPolicy(cfg)
    lo, hi = cfg.ego.accel_bounds_mps2
    return lambda obs: rng.uniform(lo, hi, size=1).astype(np.float32)


def simulate(args: argparse.Namespace) -> int:
    """Drive ramp vehicles through scripted traffic, print what happened, save a frame."""
    from marlmerge.core import EGO, OUTCOME_NAMES, OUTCOME_NONE
    from marlmerge.env import EGO_AGENT, parallel_env, reward_terms
    from marlmerge.render import render_frame, save_png

    env = parallel_env(args.scenario, render_mode="rgb_array", control="ego")
    cfg = env.cfg
    rng = np.random.default_rng(args.seed)
    policy = _ego_rule(args.ego, cfg, rng)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(
        f"scenario {cfg.name!r}: {cfg.traffic.flow_vph_per_lane:.0f} veh/h/lane, drivers "
        f"coop/neutral/adv = {cfg.driver.mix_cooperative:.2f}/{cfg.driver.mix_neutral:.2f}/"
        f"{cfg.driver.mix_adversarial:.2f}, ego rule {args.ego!r}, seed {args.seed}"
    )
    print(
        f"{'ep':>3} {'outcome':>10} {'time_s':>7} {'reward':>8}  "
        + " ".join(
            f"{k:>12}" for k in ("acceleration", "gap_front", "gap_back", "speed", "collision")
        )
    )
    obs, _ = env.reset(seed=args.seed)
    outcomes: Counter[str] = Counter()
    frame_saved = None
    records = []
    t0 = time.perf_counter()
    steps = 0
    for ep in range(args.episodes):
        totals: Counter[str] = Counter()
        while env.agents:
            obs, _, _, _, info = env.step({EGO_AGENT: policy(obs[EGO_AGENT])})
            steps += 1
            totals.update(reward_terms(info[EGO_AGENT]))
            x_ego = env.core.state.x_m[0, EGO]
            if frame_saved is None and x_ego >= cfg.x_overlap_m - 10.0:
                frame_saved = out / "frame.png"
                save_png(frame_saved, render_frame(env.core, agent_slots=env.agent_slots))
        ego = info[EGO_AGENT]
        outcome = OUTCOME_NAMES[ego["outcome"]]
        outcomes[outcome] += 1
        total = sum(totals.values())
        records.append(
            {
                "episode": ep,
                "outcome": outcome,
                "time_s": ego["ego_time_s"],
                "reward": total,
                **dict(totals),
            }
        )
        print(
            f"{ep:>3} {outcome:>10} {ego['ego_time_s']:>7.1f} {total:>8.2f}  "
            + " ".join(
                f"{totals[k]:>12.2f}"
                for k in ("acceleration", "gap_front", "gap_back", "speed", "collision")
            )
        )
        obs, _ = env.reset()
        assert env.core.state.ego_outcome[0] == OUTCOME_NONE
    wall = time.perf_counter() - t0
    n = args.episodes
    summary = {
        "episodes": n,
        **{f"{k}_rate": outcomes[k] / n for k in ("success", "collision", "truncated")},
        "env_steps": steps,
        "env_steps_per_s": steps / wall,
    }
    print(
        "summary: "
        + ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in summary.items()
        )
    )
    (out / "episodes.json").write_text(
        json.dumps({"summary": summary, "episodes": records}, indent=1)
    )
    print(f"wrote {out / 'episodes.json'}" + (f" and {frame_saved}" if frame_saved else ""))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="marlmerge", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="drive ramp vehicles through scripted traffic")
    s.add_argument("--scenario", default="default", help="preset name in envs/ or a .toml path")
    s.add_argument("--episodes", type=int, default=20)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument(
        "--ego",
        choices=EGO_RULES,
        default="hold",
        help="hold: keep speed; idm: plain car following that ignores the merge; "
        "random: uniform accelerations",
    )
    s.add_argument("--out", default="runs/simulate", help="output folder")
    s.set_defaults(func=simulate)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as err:
        print(f"marlmerge: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
