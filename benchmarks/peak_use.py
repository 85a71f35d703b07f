"""Which piece of a several-peak quadratic Q drives (`TrainConfig.peaks`, docs/learner.md).

For each run (a `policy.pt` of `peaks = K`), drives its greedy policy on a scenario's traffic
(the torchrl view, every world's next ego departing when the last is done) and counts, over all
decisions, how often each piece k is the greedy one (the largest C_k), how often its command is
a brake (below -1 m/s^2), and the mean of each piece's B_k. A share near 1 for one piece means
the envelope collapsed to one quadratic, the paper's network in effect.

    python benchmarks/peak_use.py runs/peaks3/seed_? --scenario hardened_join_mix
"""

from __future__ import annotations

import argparse

import torch

from marlmerge.config.presets import resolve_config
from marlmerge.learners.loading import load_quadq_net
from marlmerge.views.torchrl_env import BatchedMergeEnv

BRAKE_MPS2 = -1.0
"""A greedy command below this (m/s^2) counts as a brake."""


@torch.no_grad()
def peak_use(run: str, scenario: str, worlds: int, decisions: int, seed: int) -> dict:
    """Shares of the greedy decisions per piece [K], the brake share of each piece's greedy
    commands [K] and each piece's mean B [K] (m/s^2), over `worlds` x `decisions` decisions."""
    net = load_quadq_net(run)
    env = BatchedMergeEnv(resolve_config(scenario), num_worlds=worlds, seed=seed)
    k_n = net.peaks
    greedy, brakes, b_sum = torch.zeros(k_n), torch.zeros(k_n), torch.zeros(k_n)
    td = env.reset()
    for _ in range(decisions):
        _, b, c = net(td["observation"].to(torch.float32))  # [W, K] each
        piece = c.argmax(-1)  # [W]
        command = b.gather(-1, piece[:, None])  # [W, 1], m/s^2
        greedy += torch.bincount(piece, minlength=k_n)
        brakes += torch.bincount(piece[command[:, 0] < BRAKE_MPS2], minlength=k_n)
        b_sum += b.sum(0)
        td["action"] = command
        _, td = env.step_and_maybe_reset(td)
    total = float(worlds * decisions)
    return {
        "share": (greedy / total).tolist(),
        "brake_share": (brakes / greedy.clamp(min=1.0)).tolist(),
        "mean_b_mps2": (b_sum / total).tolist(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders or policy files")
    ap.add_argument("--scenario", default="hardened_join_mix")
    ap.add_argument("--worlds", type=int, default=256)
    ap.add_argument("--decisions", type=int, default=300, help="per world")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    print(f"{args.worlds} worlds x {args.decisions} decisions of {args.scenario}, seed {args.seed}")
    print("\n| run | greedy share per piece | of which brakes | mean B per piece m/s² |")
    print("|---|---|---|---|")
    for run in args.runs:
        r = peak_use(run, args.scenario, args.worlds, args.decisions, args.seed)
        cells = [", ".join(f"{v:.3f}" for v in r[key]) for key in ("share", "brake_share")]
        means = ", ".join(f"{v:+.2f}" for v in r["mean_b_mps2"])
        print(f"| {run} | {cells[0]} | {cells[1]} | {means} |")


if __name__ == "__main__":
    main()
