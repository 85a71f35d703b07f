"""One registry of ego policies: a spec on the command line, in the grid or a video becomes an
`obs [B, F] -> acceleration [B, 1]` function here, and nowhere else.

Specs:
- `hold` (keep speed), `idm` (car following that ignores the merge), `gap` (gap acceptance);
- `[label=]KIND:GLOB` with KIND `quadq`, `dqn` or `td3`: the run folders (or `policy.pt` files)
  GLOB matches, one per training seed; each file must hold a policy of that algorithm;
- a run folder or a `policy.pt` of any algorithm (`policy_from_spec`).

Saved policies are read by `marlmerge.learners.baselines_rl.load_policy` in the one file
format of `marlmerge.policy_file`.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

import torch

from marlmerge.config import ScenarioConfig
from marlmerge.evaluate import EgoPolicy

RULE_POLICIES = ("hold", "idm", "gap")
LEARNED_KINDS = ("quadq", "dqn", "td3")


@dataclass(frozen=True)
class PolicySpec:
    """A policy: a rule, or a learned kind with one run folder per training seed."""

    name: str
    kind: str
    runs: tuple[str, ...] = ()


def parse_policy(spec: str) -> PolicySpec:
    """`hold`, `idm`, `gap`, or `[label=]KIND:GLOB` (see the module docstring); every matched
    run must hold a policy file of KIND."""
    label, _, body = spec.rpartition("=")
    kind, _, pattern = body.partition(":")
    if kind in RULE_POLICIES and not pattern:
        return PolicySpec(label or kind, kind)
    if kind in LEARNED_KINDS and pattern:
        from marlmerge.policy_file import read_policy

        found = [m for m in sorted(glob.glob(pattern)) if Path(m).is_dir() or m.endswith(".pt")]
        runs = tuple(found) or (pattern,)
        missing = [r for r in runs if not (r.endswith(".pt") or (Path(r) / "policy.pt").exists())]
        if missing:
            raise ValueError(f"policy {spec!r}: no policy.pt in {missing[0]!r}")
        for run in runs:
            algorithm = read_policy(run, "ego")["algorithm"]
            if algorithm != kind:
                raise ValueError(f"policy {spec!r}: {run!r} holds a {algorithm} policy")
        return PolicySpec(label or kind, kind, runs)
    raise ValueError(
        f"unknown policy {spec!r} (use one of {', '.join(RULE_POLICIES)}, or "
        f"[label=]{'|'.join(LEARNED_KINDS)}:RUN_GLOB)"
    )


def make_policy(spec: PolicySpec, run: str | None, scenario: ScenarioConfig) -> EgoPolicy:
    """The obs [B, F] -> action [B, 1] function of one policy (and one training run)."""
    if spec.kind in LEARNED_KINDS:
        from marlmerge.learners.baselines_rl import load_policy

        return load_policy(run)
    from marlmerge.baselines import GapAcceptancePolicy
    from marlmerge.policies import IdmEgoPolicy, constant_speed_action

    rule = {
        "hold": constant_speed_action,
        "idm": IdmEgoPolicy(scenario),
        "gap": GapAcceptancePolicy(scenario),
    }[spec.kind]
    return lambda obs: torch.as_tensor(rule(obs.numpy()), dtype=torch.float32)


def policy_from_spec(spec: str, scenario: ScenarioConfig) -> EgoPolicy:
    """`hold`, `idm`, `gap`, or a run folder / `policy.pt` of any learner."""
    if spec in RULE_POLICIES:
        return make_policy(PolicySpec(spec, spec), None, scenario)
    path = Path(spec)
    if not (path.suffix == ".pt" and path.exists()) and not (path / "policy.pt").exists():
        raise ValueError(
            f"policy {spec!r}: not one of {', '.join(RULE_POLICIES)} and no policy.pt there"
        )
    from marlmerge.learners.baselines_rl import load_policy

    return load_policy(path)
