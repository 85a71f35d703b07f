"""What gap acceptance's shield does to a policy's commands under ramp flow, printed as JSON.

Runs `marlmerge rampflow POLICY` (a policy behind `@shield` or `@shield-left`) and records every
call of the shield: for each ramp vehicle that the shield judged (on the ramp, before its join,
the settling time included), its position, speed, the command asked and the command driven.
Prints the ramp-flow result's flow, delay and collisions, the share of commands the shield
changed, and the same by 25 m of ramp, so that one sees where a policy drives differently from
gap acceptance and where the shield steps in. (`marlmerge rampflow` itself reports the share
over the measurement window, `shield_changed_share`; this script adds where on the ramp.)

    python benchmarks/shield_overrides.py "gap@shield-left"
    python benchmarks/shield_overrides.py "quadq@shield-left:runs/ramp_flow_shielded_s0"
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.ramp_flow import run_ramp_flow
from marlmerge.policies import gap_acceptance
from marlmerge.policies.gap_acceptance import CHANGED_MPS2
from marlmerge.sim.observation import EGO_FEATURES, EGO_SCALE, feature_index

BIN_M = 25.0


class Recorder:
    """Wraps `GapShield.__call__`: keeps (x m, v m/s, asked, driven m/s^2) of every judged row."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.call = gap_acceptance.GapShield.__call__
        x, v = (feature_index(EGO_FEATURES, n) for n in ("ego_position", "ego_speed"))

        def recorded(shield, obs: np.ndarray, cmd: np.ndarray) -> np.ndarray:
            out = self.call(shield, obs, cmd)
            o = np.asarray(obs, dtype=np.float64)
            live = np.any(o != 0.0, axis=-1)  # free agent columns are all zeros
            raw = o[live][:, : len(EGO_FEATURES)] * EGO_SCALE
            asked = np.asarray(cmd, dtype=np.float64).reshape(-1)[live]
            driven = np.asarray(out, dtype=np.float64).reshape(-1)[live]
            self.rows.append(np.stack([raw[:, x], raw[:, v], asked, driven], -1))
            return out

        gap_acceptance.GapShield.__call__ = recorded  # type: ignore[method-assign]

    def close(self) -> None:
        gap_acceptance.GapShield.__call__ = self.call  # type: ignore[method-assign]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("policy", help='a policy behind a shield, e.g. "quadq@shield-left:RUN"')
    p.add_argument("--scenario", default="ramp_flow")
    p.add_argument("--hours", type=float, default=1.0)
    p.add_argument("--worlds", type=int, default=4)
    p.add_argument("--seed", type=int, default=100)
    args = p.parse_args()
    if "@shield" not in args.policy:
        raise SystemExit(f"policy {args.policy!r}: give it behind @shield or @shield-left")
    recorder = Recorder()
    try:
        result = run_ramp_flow(
            resolve_config(args.scenario), args.policy, args.hours, args.worlds, args.seed
        )
    finally:
        recorder.close()
    x, v, asked, driven = np.concatenate(recorder.rows).T
    changed = np.abs(asked - driven) > CHANGED_MPS2
    bins = []
    for lo in np.arange(np.floor(x.min() / BIN_M) * BIN_M, x.max(), BIN_M):
        m = (x >= lo) & (x < lo + BIN_M)
        if m.sum() >= 20:
            bins.append(
                {
                    "x_m": [float(lo), float(lo + BIN_M)],
                    "commands": int(m.sum()),
                    "speed_mps": float(v[m].mean()),
                    "asked_mps2": float(asked[m].mean()),
                    "driven_mps2": float(driven[m].mean()),
                    "changed_share": float(changed[m].mean()),
                }
            )
    out = {
        "policy": args.policy,
        "seed": args.seed,
        "merged_vph": result.merged_vph,
        "ramp_delay_s": result.ramp_delay_s,
        "ramp_collisions_per_1000": result.ramp_collisions_per_1000,
        "commands": int(x.size),
        "changed_share": float(changed.mean()),
        "by_position": bins,
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
