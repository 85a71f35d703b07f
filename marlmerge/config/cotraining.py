"""The schema of a co-training run (`marlmerge cotrain`): the shared `RunConfig` and the
schedule of phases (pretrain the ego, then rounds of adversary and ego phases)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from marlmerge.config.rules import num, positive, require
from marlmerge.config.training import MAX_SEED, MAX_STEPS, RunConfig

PROFILES = {"adversarial": 1.0, "cooperative": -1.0}
PHASES = ("pretrain", "adversary", "ego")
HIGHWAY_ALGORITHMS = ("quadq", "ppo")
"""The highway group's learners: the paper's quadratic Q (off-policy) or PPO (`[ppo]`)."""
HIGHWAY_ACTIONS = ("accel_offset", "desired_speed", "pace_offset")
"""What a learned highway driver chooses (`marlmerge.learners.highway`): an adjustment to its
IDM acceleration, the desired speed its IDM drives towards (PPO only), or an adjustment to the
scripted pacing driver's acceleration."""
HIGHWAY_ENVELOPES = ("none", "safe")
"""What limits a learned highway driver besides its action bounds
(`marlmerge.policies.envelope`): nothing, or a plausible driver's envelope."""
PPO_CRITICS = ("local", "central")
"""IPPO's per-agent critic or MAPPO's centralised one (`marlmerge.learners.ppo`)."""


@dataclass(frozen=True)
class PpoConfig:
    """`[ppo]`: the highway group's PPO learner (`highway_algorithm = "ppo"`), on torchrl's
    `ClipPPOLoss` and GAE. Each collector batch is one rollout: `epochs` passes over it in
    `minibatches` shuffled minibatches, then it is dropped."""

    critic: str = "central"
    """"local" (IPPO: the agent's own observation) or "central" (MAPPO: its own, the ego's and
    every agent's of the world)."""
    lr: float = positive(3.0e-4, 1.0)
    gae_lambda: float = num(0.95, 0.0, 1.0)
    clip_epsilon: float = positive(0.2, 1.0)
    entropy_coeff: float = num(1.0e-3, 0.0, 10.0)
    critic_coeff: float = num(0.5, 0.0, 100.0)
    epochs: int = num(4, 1, 1000)
    minibatches: int = num(4, 1, 100_000)
    max_grad_norm: float = positive(0.5, 1.0e6)
    init_std: float = positive(0.5, 10.0)
    """Initial std of the policy's Gaussian before the tanh squashing (roughly m/s^2 of offset
    near 0, where tanh is linear: the offsets are in +-3 m/s^2)."""

    def __post_init__(self) -> None:
        require(
            [
                (
                    self.critic in PPO_CRITICS,
                    f"ppo.critic must be one of {PPO_CRITICS}, got {self.critic!r}",
                )
            ]
        )


@dataclass(frozen=True)
class CoTrainConfig(RunConfig):
    """One co-training run: the shared run settings (`RunConfig`, used by both groups) and the
    schedule. Learner settings follow the paper's recipe for both groups."""

    KIND: ClassVar[str] = "cotrain"

    name: str = "cotrain"
    loss_log_every: int = 50
    checkpoint_every_sim_steps: int = 400_000
    profile: str = "adversarial"
    """"adversarial" or "cooperative": the sign of the highway agents' interaction term."""
    ego_init: str = ""
    """A trained quadratic-Q ego (`policy.pt` or run folder) to start from; "" = pretrain here."""
    ego_pretrain_sim_steps: int = num(1_600_000, 0, MAX_STEPS)
    """Pretrain phase (skipped with `ego_init`): the paper's recipe against scripted traffic."""
    rounds: int = num(5, 0, 10_000)
    """(adversary, ego) phase pairs after pretraining."""
    adversary_sim_steps: int = num(400_000, 0, MAX_STEPS)
    """Simulator steps (summed over worlds) of each adversary phase; 0 skips them."""
    ego_sim_steps: int = num(400_000, 0, MAX_STEPS)
    """Simulator steps of each ego phase; 0 skips them (e.g. adversaries for a fixed ego)."""
    scripted_fraction: float = num(0.5, 0.0, 1.0)
    """Ego phases: share of egos that meet scripted traffic rather than a pool snapshot."""
    pool_size: int = num(10, 1, 10_000)
    """Adversary snapshots kept (oldest dropped first)."""
    ego_updates_per_sim_step: float = num(1.0, 0.0, 100.0)
    """Ego updates per simulator step of ego experience (paper: 1)."""
    highway_updates_per_sim_step: float = num(0.5, 0.0, 100.0)
    """Highway updates per simulator step of world experience (each step holds up to K agent
    transitions, so ~0.5 updates per stored agent transition)."""
    ego_sigma_start: float = num(1.0, 0.0, 20.0)
    ego_sigma_end: float = num(0.1, 0.0, 20.0)
    """Pretrain exploration, decaying linearly over the first half of the phase (paper)."""
    ego_sigma_cotrain: float = num(0.2, 0.0, 20.0)
    """Exploration noise of the ego in the ego phases (constant), m/s^2."""
    highway_sigma_start: float = num(0.8, 0.0, 20.0)
    highway_sigma_end: float = num(0.1, 0.0, 20.0)
    """Adversary phases: exploration noise decaying linearly over each phase's first half."""
    select_episodes: int = num(200, 0, 10_000_000)
    """After training, every ego of the run (the starting ego and the ego after each ego phase)
    meets scripted traffic and each of the run's own pool snapshots for this many greedy
    episodes; `policy.pt` is the ego with the fewest failures (collisions + truncations), the
    latest on ties. 0 keeps the last ego. The run's own adversaries only: held-out adversaries
    never take part."""
    select_seed: int = num(3_000_000, 0, MAX_SEED)
    """First seed of the selection episodes (apart from `eval_seed` and the grid's seeds)."""
    ego_value_shaping: float = num(0.0, 0.0, 1000.0)
    """Adversary phases: weight w of a potential-based shaping of the highway group's reward
    with the ego's own value estimate (Ng et al., ICML 1999): each acting agent of a world gets
    `sign * w * (V(s) - gamma * (1 - terminated) * V(s'))` per env step, V = max_a Q of the
    ego's network. It pays at once for putting the ego where the ego itself expects to do
    badly and sums to a constant over an episode, so it changes how fast adversaries learn,
    not what is best for them. 0 (default) leaves the reward as the scenario defines it.
    `highway.csv`'s reward per agent step includes it; its term sums do not."""
    highway_algorithm: str = "quadq"
    """The highway group's learner: "quadq" (a residual quadratic Q, `highway_*` settings) or
    "ppo" (IPPO / MAPPO, `[ppo]`; it learns once per collector batch, so
    `highway_updates_per_sim_step` and the highway exploration schedule do not apply)."""
    highway_action: str = "accel_offset"
    """"accel_offset": a learned driver is IDM plus an adjustment in +-3 m/s^2 each step;
    "desired_speed" (PPO only): it picks, each step, the desired speed its IDM drives towards,
    as a factor of the limit in `highway_speed_factor_bounds`. Slower or faster drivers are
    what it can be, never a car that stops dead or brakes out of the blue. "pace_offset": the
    pacing driver (`marlmerge.learners.highway.pacing_accel`: it keeps beside the ramp vehicle
    on the ramp, closes other gaps, lets a waiting ramp vehicle in) plus an adjustment in
    +-3 m/s^2, so that an untrained network drives as that driver does."""
    highway_speed_factor_bounds: tuple[float, float] = num((0.5, 1.1), 0.1, 2.0, ordered=True)
    """"desired_speed": the range of the chosen desired speed, x the speed limit."""
    highway_envelope: str = "none"
    """"safe": every acceleration of a learned driver, in training and wherever its policy file
    drives, stays within a plausible driver's envelope (`marlmerge.policies.envelope`): never
    so fast that it could not stop behind its leader braking as hard as it can, never braking
    harder than the drivers' comfortable `driver.comfort_brake_mps2` unless stopping behind its
    leader asks for it. It can still hang back, drive slowly or speed up into a gap. "none"
    (default): the action bounds only."""
    fairness_worlds: float = num(0.0, 0.0, 0.5)
    """Adversary phases: share of each seed's worlds whose ramp vehicle is driven by gap
    acceptance (`marlmerge.policies.gap_acceptance`, the careful rule driver of the fairness
    test) instead of the ego; the last round(share x `num_worlds`) worlds. In them the rule's
    failures cost the highway group instead of paying it: the failure terms
    (`InteractionConfig`: the ramp vehicle's collisions and stalls) pay nobody, and when the
    rule's ramp vehicle collides or runs out of time every learning agent acting in that world
    loses `fairness_weight` x `w_ego_collision` or `w_ego_stall`. A failure that a careful rule
    driver also suffers is the adversaries', not the ego's. The near-failure terms (hard
    braking, unsafe gaps) still pay. The adversaries cannot tell the two drivers apart, so they
    learn what bites a learned ego without biting the rule. 0 (default): every ramp vehicle is
    the ego."""
    fairness_weight: float = num(1.0, 0.0, 1000.0)
    """In `fairness_worlds`: each acting agent's cost of the rule's failure, x its weight as an
    ego failure."""
    ppo: PpoConfig = field(default_factory=PpoConfig)

    def __post_init__(self) -> None:
        self._check()
        self._check_fairness()
        if self.highway_algorithm not in HIGHWAY_ALGORITHMS:
            raise ValueError(
                f"highway_algorithm must be one of {HIGHWAY_ALGORITHMS}, "
                f"got {self.highway_algorithm!r}"
            )
        if self.highway_action not in HIGHWAY_ACTIONS:
            raise ValueError(
                f"highway_action must be one of {HIGHWAY_ACTIONS}, got {self.highway_action!r}"
            )
        if self.highway_envelope not in HIGHWAY_ENVELOPES:
            raise ValueError(
                f"highway_envelope must be one of {HIGHWAY_ENVELOPES}, "
                f"got {self.highway_envelope!r}"
            )
        if self.highway_action == "desired_speed" and self.highway_algorithm != "ppo":
            raise ValueError(
                'highway_action = "desired_speed" needs highway_algorithm = "ppo", '
                f"got {self.highway_algorithm!r}"
            )
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {tuple(PROFILES)}, got {self.profile!r}")
        if not self.phases():
            raise ValueError("the schedule is empty: every phase has 0 simulator steps")
        if not self.ego_init and self.ego_pretrain_sim_steps == 0 and self.adversary_sim_steps:
            raise ValueError("adversaries need a trained ego: set ego_init or pretrain")

    def rule_worlds(self) -> int:
        """How many of a seed's worlds `fairness_worlds` gives to gap acceptance."""
        return round(self.fairness_worlds * self.num_worlds)

    def _check_fairness(self) -> None:
        if self.fairness_worlds == 0.0:
            return
        n = self.rule_worlds()
        if n < 1:
            raise ValueError(
                f"fairness_worlds = {self.fairness_worlds} of num_worlds = {self.num_worlds} "
                "gives no world to gap acceptance: raise it to at least "
                f"{0.5 / self.num_worlds:.3g}, or set 0"
            )
        if self.profile != "adversarial":
            raise ValueError(
                f"fairness_worlds = {self.fairness_worlds} judges adversaries: it needs "
                f"profile = 'adversarial', got {self.profile!r}"
            )
        if not any(kind == "adversary" for kind, _ in self.phases()):
            raise ValueError(
                f"fairness_worlds = {self.fairness_worlds} acts in adversary phases, and the "
                "schedule has none (rounds = 0 or adversary_sim_steps = 0)"
            )

    def phases(self) -> list[tuple[str, int]]:
        """The schedule: (phase kind, simulator steps) in order."""
        out: list[tuple[str, int]] = []
        if not self.ego_init and self.ego_pretrain_sim_steps > 0:
            out.append(("pretrain", self.ego_pretrain_sim_steps))
        for _ in range(self.rounds):
            if self.adversary_sim_steps > 0:
                out.append(("adversary", self.adversary_sim_steps))
            if self.ego_sim_steps > 0:
                out.append(("ego", self.ego_sim_steps))
        return out
