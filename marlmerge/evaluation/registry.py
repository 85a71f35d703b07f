"""One registry of ego policies: a spec on the command line, in the grid or a video becomes an
`obs [B, F] -> acceleration [B, 1]` function here, and nowhere else.

Specs:
- `hold` (keep speed), `idm` (car following that ignores the merge), `gap` (gap acceptance);
- `[label=]KIND:GLOB` with KIND `quadq`, `dqn` or `td3`: the run folders (or `policy.pt` files)
  GLOB matches, one per training seed; each file must hold a policy of that algorithm;
- a run folder or a `policy.pt` of any algorithm (`policy_from_spec`);
- any of these with `@filter` or `@nofilter` after the kind (`gap@filter`,
  `quadq@nofilter:runs/robust_s*`): with or without the core's safety filter
  (`ego.safety_filter`), whatever the policy was trained with; or with `@shield`
  (`quadq@shield:runs/robust_s*`): its commands judged by gap acceptance
  (`marlmerge.policies.gap_acceptance.GapShield`); or with `@shield-left`: the shield that also
  judges the left-lane drivers predicted to move into the ego's gap (a learned policy trained
  with an extended observation; a rule is given one), caps the ego at IDM behind its leader
  once it has joined, and keeps it rolling where it would stop early on the ramp.

A learned policy drives with the ego-side settings it was trained with (`EGO_SIDE_KEYS`: its
observation layout and its safety filter), whatever the traffic condition it meets: the
condition sets the traffic, the road and the sensors; `scenario_for` puts the two together.

Saved policies are read by `marlmerge.learners.dqn.load_policy` in the one file
format of `marlmerge.io.policy_file`.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import JUDGING_KEYS
from marlmerge.evaluation.rollout import EgoPolicy
from marlmerge.io.files import saved_digest
from marlmerge.io.policy_file import DEFAULT_FILE
from marlmerge.sim.observation import shows_left_lane

if TYPE_CHECKING:
    from marlmerge.policies.gap_acceptance import GapShield

RULE_POLICIES = ("hold", "idm", "gap")
LEARNED_KINDS = ("quadq", "dqn", "td3")
FILTER_MODIFIERS = {"filter": True, "nofilter": False}
SHIELD_MODIFIERS = ("shield", "shield-left")
EGO_SIDE_KEYS = (
    "ego.observation",
    "ego.time_to_merge_cap_s",
    "ego.safety_filter",
    "ego.safety_min_headway_s",
    "ego.safety_min_gap_m",
    "ego.join",
)
"""What belongs to the driver rather than to the traffic: a learned policy keeps these."""


@dataclass(frozen=True)
class PolicySpec:
    """A policy: a rule, or a learned kind with one run folder per training seed."""

    name: str
    kind: str
    runs: tuple[str, ...] = ()
    safety_filter: bool | None = None
    """`@filter` / `@nofilter`: the core's safety filter on / off; None: as trained (rules: off)."""
    shield: bool = False
    """`@shield`: the policy's commands pass through gap acceptance's judgement
    (`marlmerge.policies.gap_acceptance.GapShield`)."""
    shield_left: bool = False
    """`@shield-left`: the shield with `watch_left`, `cap_in_lane` and `keep_rolling` (`shield` is
    true too)."""


def parse_policy(spec: str) -> PolicySpec:
    """`hold`, `idm`, `gap`, or `[label=]KIND:GLOB` (see the module docstring); every matched
    run must hold a policy file of KIND."""
    label, _, body = spec.rpartition("=")
    head, _, pattern = body.partition(":")
    kind, _, modifier = head.partition("@")
    if modifier and modifier not in (*FILTER_MODIFIERS, *SHIELD_MODIFIERS):
        raise ValueError(
            f"policy {spec!r}: unknown modifier @{modifier} "
            "(@filter, @nofilter, @shield or @shield-left)"
        )
    flt = FILTER_MODIFIERS.get(modifier)
    shield, left = modifier in SHIELD_MODIFIERS, modifier == "shield-left"
    if kind in RULE_POLICIES and not pattern:
        return PolicySpec(label or head, kind, safety_filter=flt, shield=shield, shield_left=left)
    if kind in LEARNED_KINDS and pattern:
        from marlmerge.io.policy_file import read_policy

        found = [m for m in sorted(glob.glob(pattern)) if Path(m).is_dir() or m.endswith(".pt")]
        runs = tuple(found) or (pattern,)
        missing = [r for r in runs if not (r.endswith(".pt") or (Path(r) / "policy.pt").exists())]
        if missing:
            raise ValueError(f"policy {spec!r}: no policy.pt in {missing[0]!r}")
        for run in runs:
            algorithm = read_policy(run, "ego")["algorithm"]
            if algorithm != kind:
                raise ValueError(f"policy {spec!r}: {run!r} holds a {algorithm} policy")
        return PolicySpec(label or head, kind, runs, flt, shield, left)
    raise ValueError(
        f"unknown policy {spec!r} (use one of {', '.join(RULE_POLICIES)}, or "
        f"[label=]{'|'.join(LEARNED_KINDS)}:RUN_GLOB)"
    )


def make_policy(spec: PolicySpec, run: str | None, scenario: ScenarioConfig) -> EgoPolicy:
    """The obs [B, F] -> action [B, A] function of one policy (and one training run; A = 2
    with `ego.join = "chosen"`: the rules hold and IDM join at the overlap point)."""
    from marlmerge.policies.gap_acceptance import GapAcceptancePolicy, grid_shield

    if spec.kind in LEARNED_KINDS:
        from marlmerge.learners.loading import load_policy

        policy = load_policy(run)
    else:
        from marlmerge.policies.scripted import (
            IdmEgoPolicy,
            constant_speed_action,
            with_join_at_overlap,
        )

        rule = {
            "hold": with_join_at_overlap(constant_speed_action, scenario),
            "idm": with_join_at_overlap(IdmEgoPolicy(scenario), scenario),
            "gap": GapAcceptancePolicy(scenario),
        }[spec.kind]
        policy = lambda obs: torch.as_tensor(rule(obs.numpy()), dtype=torch.float32)  # noqa: E731
    if not spec.shield:
        return policy
    check_shield_left(spec, scenario)
    return ShieldedPolicy(policy, grid_shield(scenario, spec.shield_left))


class ShieldedPolicy:
    """A policy (obs [B, F] -> action [B, 1]) with its commands through `shield` (`@shield`,
    `@shield-left`); `shield.tally` counts what the shield judged and changed."""

    def __init__(self, policy: EgoPolicy, shield: GapShield) -> None:
        self.policy, self.shield = policy, shield

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(self.shield(obs.cpu().numpy(), self.policy(obs).cpu().numpy()))


def scenario_for(spec: PolicySpec, run: str | None, condition: ScenarioConfig) -> ScenarioConfig:
    """The scenario a policy meets in a traffic condition: the condition, with the ego-side
    settings the (learned) policy was trained with and the filter its spec asks for. A rule
    behind `@shield-left` sees the extended observation where the condition's shows no left
    lane (the rules read the paper's seven features of any layout; the shield reads the rest)."""
    changes = {}
    if run is not None:
        from marlmerge.config import get_dotted
        from marlmerge.learners.loading import load_scenario_of

        trained = load_scenario_of(run)
        changes = {key: get_dotted(trained, key) for key in EGO_SIDE_KEYS}
    elif spec.shield_left and not shows_left_lane(condition):
        changes["ego.observation"] = "extended"
    if spec.safety_filter is not None:
        changes["ego.safety_filter"] = spec.safety_filter
    return condition.replace(**changes) if changes else condition


def check_shield_left(spec: PolicySpec, scenario: ScenarioConfig) -> None:
    """`@shield-left` reads the left-lane features: refuse it, naming the policy and the
    scenario, where the policy's observation has none."""
    if spec.shield_left and not shows_left_lane(scenario):
        raise ValueError(
            f"policy {spec.name!r} on {scenario.name!r}: @shield-left reads the left lane, which "
            f"ego.observation = {scenario.ego.observation!r} does not show (a policy trained "
            "with 'extended', 'extended_accel' or 'extended_join' does)"
        )


def policy_for_evaluation(
    spec: str, scenario: ScenarioConfig | None
) -> tuple[EgoPolicy, ScenarioConfig]:
    """The policy `evaluate` runs and the scenario it meets: a rule, a run folder or
    `policy.pt`, or one policy in the grid's notation (`gap@shield`, `quadq@filter:RUN`, one
    run). `scenario` None: the learned policy's own scenario (rules: the default)."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.learners.loading import load_scenario_of

    def own(run: str | None) -> ScenarioConfig:
        return resolve_config("default") if run is None else load_scenario_of(run)

    if spec in RULE_POLICIES:
        scenario = scenario or own(None)
        return policy_from_spec(spec, scenario), scenario
    if Path(spec).exists():  # a run folder or policy.pt: its ego-side settings in any scenario
        scenario = scenario_for(PolicySpec(spec, "run"), spec, scenario or own(spec))
        return policy_from_spec(spec, scenario), scenario
    parsed = parse_policy(spec)
    if len(parsed.runs) > 1:
        raise ValueError(f"policy {spec!r} names {len(parsed.runs)} runs; evaluate takes one")
    run = parsed.runs[0] if parsed.runs else None
    scenario = scenario_for(parsed, run, scenario or own(run))
    return make_policy(parsed, run, scenario), scenario


def saved_files_of(spec: str) -> str:
    """A digest of the saved policy files a policy spec drives (`io.files.saved_digest`, one per
    run, comma-separated; "" for a rule)."""
    if spec in RULE_POLICIES:
        return ""
    if Path(spec).exists():
        return saved_digest(spec, DEFAULT_FILE["ego"])
    return ",".join(saved_digest(run, DEFAULT_FILE["ego"]) for run in parse_policy(spec).runs)


def bare_shield_note(spec: str) -> str | None:
    """A note for a policy spec that drives a run trained behind gap acceptance's shield
    (`TrainConfig.shield`) without it, saying how to drive it as trained; None otherwise (rules,
    mixes, specs with a shield, runs trained bare or with a judging shield: `shield_penalty`,
    `shield_imitation`)."""
    from marlmerge.io.policy_file import read_policy

    if Path(spec).exists():
        kind, runs = "", (spec,)
    else:
        try:
            parsed = parse_policy(spec)
        except ValueError:
            return None
        if parsed.shield or not parsed.runs:
            return None
        kind, runs = parsed.kind, parsed.runs
    for run in runs:
        saved = read_policy(run, "ego")
        shield = saved["config"].get("shield", "none")
        judging = any(saved["config"].get(key, 0.0) > 0.0 for key in JUDGING_KEYS)
        if shield != "none" and not judging:
            algorithm = kind or saved["algorithm"]
            return (
                f"note: {run} was trained behind the shield ({shield}) and drives here without "
                f"it; as trained: {algorithm}@{shield}:{run}"
            )
    return None


def policy_from_spec(spec: str, scenario: ScenarioConfig) -> EgoPolicy:
    """`hold`, `idm`, `gap`, or a run folder / `policy.pt` of any learner."""
    if spec in RULE_POLICIES:
        return make_policy(PolicySpec(spec, spec), None, scenario)
    path = Path(spec)
    if not (path.suffix == ".pt" and path.exists()) and not (path / "policy.pt").exists():
        raise ValueError(
            f"policy {spec!r}: not one of {', '.join(RULE_POLICIES)} and no policy.pt there"
        )
    from marlmerge.learners.loading import load_policy

    return load_policy(path)
