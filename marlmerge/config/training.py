"""The one schema of training runs: a shared `RunConfig`, one table per algorithm, and the two
kinds of run built on them (`TrainConfig` here, `marlmerge.config.cotraining.CoTrainConfig`).

A preset (TOML in `trainers/`) names its kind (`kind = "train"` or `"cotrain"`); its keys are the
fields below, the algorithm tables as TOML tables (`[dqn]`, `[td3]`). Every number is validated
where the config is built: finite, and within the `Bounds` declared beside its field
(`marlmerge.config.num`), with an error naming the full key and the value.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

from marlmerge.config.rules import check_values, num, positive, require

PAPER_GAMMA = 0.95
"""The discount factor of the paper's recipe (Sec. IV.B): every default discount."""
ALGORITHMS: tuple[str, ...] = ("quadq", "dqn", "td3")
"""The ego learners `marlmerge train` can train (`TrainConfig.algorithm`)."""
TRAIN_SHIELDS: tuple[str, ...] = ("none", "shield", "shield-left")
"""Gap acceptance's shield in the training loop (`TrainConfig.shield`), as the grid names it."""
PEAK_SHARE_HEADS: tuple[str, ...] = ("abc", "c")
"""The heads of a losing piece of a several-peak Q that `peak_share` reaches: all, or its level."""

JUDGING_KEYS: tuple[str, ...] = ("shield_penalty", "shield_imitation")
"""The `TrainConfig` keys that make the shield judge instead of drive (either > 0)."""

UPDATE_PATHS = ("compiled", "fast", "torchrl")
DEVICE_PATTERN = r"cpu|cuda(:[0-9]+)?|mps"
"""The values `TrainConfig.device` takes (whether the machine has it is checked when a run
starts: `marlmerge.learners.common.resolve_device`)."""

MAX_STEPS = 10**12
"""Step counts and periods are at most this."""
MAX_SEED = 2**63 - 1
"""Seeds are integers in [0, MAX_SEED]."""


@dataclass(frozen=True)
class RunConfig:
    """What every training run has: its name, traffic, seed, worlds, the Q-learning settings
    shared by its learners, logs, checkpoints and the final evaluation. Defaults are the
    paper's recipe (Sec. IV.B, Table 1)."""

    KIND: ClassVar[str] = ""
    """The `kind` a preset of this schema names."""

    name: str = "paper"
    """Run name; outputs go to `runs/<name>` unless `--out` says otherwise."""
    scenario: str = "default"
    """Scenario preset in `envs/` (or a path): the traffic the run trains in."""
    seed: int = num(0, 0, MAX_SEED)
    """Seeds the traffic, the networks, exploration noise and replay sampling."""
    num_worlds: int = num(32, 1, 65_536)
    """B: independent worlds stepped together, each with its own ego, feeding one buffer."""
    env_steps_per_batch: int = num(4, 1, 100_000)
    """Env steps per world in each collector batch; updates follow each batch."""
    batch_size: int = num(32, 1, 65_536)
    """M: minibatch size."""
    gamma: float = num(PAPER_GAMMA, 0.0, 1.0, low_open=True, high_open=True)
    lr: float = positive(1.0e-3, 1.0)
    target_update_period: int = num(500, 1, MAX_STEPS)
    """p: the target network is a copy of the online one, refreshed every p updates."""
    hidden: int = num(64, 1, 4096)
    """Hidden width of the networks (quadq: each of A, B, C, two layers each)."""
    replay_capacity: int = num(200_000, 1, 100_000_000)
    """Transitions kept in each replay buffer (oldest dropped first)."""
    learning_starts: int = num(1_000, 0, MAX_STEPS)
    """No updates until a buffer holds this many transitions (those updates are skipped)."""
    update_path: str = "compiled"
    """"compiled" (torch.compile of the fast path), "fast" (same, eager) or "torchrl" (the
    LossModule loop). The peers compile their gradient steps when "compiled"."""
    updates_per_call: int = num(10, 1, 10_000)
    """Updates fused into one call of the fast path; must divide `target_update_period`."""
    threads: int = num(1, 1, 256)
    """torch threads (tiny networks run fastest on one)."""
    loss_log_every: int = num(5, 1, MAX_STEPS)
    """Log the loss every this many updates (the paper stores it every 5 steps)."""
    checkpoint_every_sim_steps: int = num(200_000, 1, MAX_STEPS)
    """Checkpoint interval; a killed run resumes from its last checkpoint."""
    eval_episodes: int = num(200, 0, 10_000_000)
    """Greedy evaluation after training: this many held-out episodes ..."""
    eval_seed: int = num(1_000_000, 0, MAX_SEED)
    """... on roads seeded from here on (training seeds are small numbers)."""
    eval_worlds: int = num(50, 1, 65_536)
    """Episodes evaluated in parallel (one seed per group of this many)."""
    device: str = "cpu"
    """Where the learners' networks, optimiser state and replays live: "cpu", "cuda", "cuda:N"
    or "mps" (the simulator always runs on the CPU). The random draws (exploration noise,
    minibatch indices) stay on the CPU generators, the same on every device."""

    def _check(self) -> None:
        check_values(self)
        require(
            [
                (
                    self.replay_capacity >= self.batch_size,
                    f"replay_capacity ({self.replay_capacity}) must be >= batch_size "
                    f"({self.batch_size})",
                ),
                (
                    self.update_path in UPDATE_PATHS,
                    f"update_path must be one of {UPDATE_PATHS}, got {self.update_path!r}",
                ),
                (
                    self.target_update_period % self.updates_per_call == 0,
                    f"updates_per_call ({self.updates_per_call}) must divide "
                    f"target_update_period ({self.target_update_period})",
                ),
                (
                    re.fullmatch(DEVICE_PATTERN, self.device) is not None,
                    f"device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got {self.device!r}",
                ),
            ]
        )


@dataclass(frozen=True)
class DqnConfig:
    """`[dqn]`: the DQN peer (torchrl `DQNLoss` over discrete acceleration levels)."""

    hidden_layers: int = num(2, 1, 16)
    """Hidden ReLU layers of width `hidden` in the Q-network."""
    levels: int = num(7, 2, 1001)
    """Acceleration levels evenly spaced over the ego bounds, both ends included."""
    double: bool = False
    """Double DQN target (online argmax, target value); the target is a hard copy every
    `target_update_period` updates."""
    epsilon_start: float = num(1.0, 0.0, 1.0)
    """Epsilon-greedy exploration, epsilon falling linearly from this ..."""
    epsilon_end: float = num(0.05, 0.0, 1.0)
    """... to this over `sigma_decay_fraction` of `total_sim_steps`, then constant."""


@dataclass(frozen=True)
class Td3Config:
    """`[td3]`: the TD3 peer. Its exploration is the Gaussian noise of `sigma_start` /
    `sigma_end`, m/s^2."""

    hidden_layers: int = num(2, 1, 16)
    """Hidden ReLU layers of width `hidden` in the actor and each critic."""
    tau: float = positive(0.005, 1.0)
    """Polyak factor of the target networks (updated with each actor step)."""
    policy_delay: int = num(2, 1, 1000)
    """Critic updates per actor update."""
    target_noise: float = num(0.7, 0.0, 20.0)
    """Std of the target-policy smoothing noise, m/s^2 (TD3's 0.2 x half-range 3.5) ..."""
    target_noise_clip: float = num(1.75, 0.0, 20.0)
    """... clipped to +- this, m/s^2 (TD3's 0.5 x 3.5)."""


LEVEL_SCORES = ("failure", "learnability")
"""What ranks the levels of `[levels]` (`LevelsConfig.score`)."""


@dataclass(frozen=True)
class LevelsConfig:
    """`[levels]`: prioritised replay of the traffic where the ego fails
    (`marlmerge.training.levels`, as in PLR); needs a scenario with `[sample]`."""

    replay_fraction: float = num(0.0, 0.0, 1.0)
    """Share of new roads that replay a level from the buffer; 0: off (the plain `[sample]`
    draws, bit for bit)."""
    capacity: int = num(1000, 1, 1_000_000)
    """Levels kept; a full buffer drops its lowest-scored level for a fresh draw."""
    min_levels: int = num(64, 1, 1_000_000)
    """Replay starts once this many levels have a finished ego."""
    temperature: float = positive(0.3, 100.0)
    """Rank prioritisation: P ~ (1 / rank) ** (1 / temperature) (lower: greedier)."""
    staleness: float = num(0.1, 0.0, 1.0)
    """Weight of the staleness term (levels not chosen for long come back)."""
    seed_presets: tuple[str, ...] = ()
    """Scenario presets (paths or names) whose traffic starts in the buffer, e.g. the failure
    regions `marlmerge stress` writes (`regions/region_KK.toml`): `seed_levels` levels drawn
    from each preset's `[sample]` ranges (and its road), each starting with the score of one
    failed ego, so that training replays them early."""
    seed_levels: int = num(16, 1, 100_000)
    """Levels drawn from each of `seed_presets`."""
    replay_roads: bool = False
    """True: a level is one road (its traffic and the seed of its vehicles' draws), replayed
    as it was; False: a traffic condition, replayed on a new road each time."""
    score: str = "failure"
    """What ranks the levels: "failure", the failure rate `(failures + 1/2) / (episodes + 1)`
    (PLR's prioritisation by how badly the ego does), or "learnability", p (1 - p) with
    p = (failures + m) / (episodes + 1) and m the buffer's failure rate (Rutherford et al.,
    NeurIPS 2024): levels the ego sometimes fails come first, and one it always fails or
    never fails falls back. Unscored levels rank first under it (they are kept)."""


@dataclass(frozen=True)
class SelectConfig:
    """`[select]`: keep the best greedy policy of the run, not the last. Q-learning's returns
    spike (the paper's Fig. 4): an ego that was fine can be broken by the next few hundred
    thousand updates and repaired after them, so the last weights are a draw from that cycle.
    From `start_fraction` of the run on, every `every_sim_steps` and at the end, the greedy
    policy drives `episodes` roads of the training scenario (or `scenario`) seeded from `seed`
    (apart from the evaluation's and every held-out set's); `policy.pt` is the one with the
    fewest failures (collisions + truncations), the latest on ties, and `policy_last.pt` the
    last."""

    every_sim_steps: int = num(0, 0, MAX_STEPS)
    """0: off (`policy.pt` is the last policy, as in the paper)."""
    episodes: int = num(400, 1, 10_000_000)
    seed: int = num(5_000_000, 0, MAX_SEED)
    start_fraction: float = num(0.5, 0.0, 1.0)
    """Candidates from this fraction of `total_sim_steps` on (by default once the exploration
    noise has decayed)."""
    scenario: str = ""
    """The scenario preset (or path) of the validation roads; "": the training scenario."""


@dataclass(frozen=True)
class TrainConfig(RunConfig):
    """One run training the ego against scripted traffic (`marlmerge train`)."""

    KIND: ClassVar[str] = "train"

    total_sim_steps: int = num(1_600_000, 1, MAX_STEPS)
    """N: simulator steps of ego experience, summed over all worlds (paper: 1.6 M)."""
    updates_per_sim_step: float = num(1.0, 0.0, 100.0)
    """Gradient updates per simulator step of experience (paper: 1, i.e. k per transition)."""
    sigma_start: float = num(1.0, 0.0, 20.0)
    """Exploration (quadq, td3): std of the Gaussian noise on the greedy action at the start,
    m/s^2 ..."""
    sigma_end: float = num(0.1, 0.0, 20.0)
    """... decaying linearly to this ..."""
    sigma_decay_fraction: float = num(0.5, 0.0, 1.0)
    """... over this fraction of `total_sim_steps`, then constant (dqn: epsilon likewise)."""
    algorithm: str = "quadq"
    """Learner: "quadq" (the paper's quadratic Q), "dqn" (discrete levels, `[dqn]`) or "td3"
    (`[td3]`). All use the shared settings above."""
    shield: str = "none"
    """With "shield" or "shield-left": while collecting, the ego's commands (every merging
    vehicle's, under ramp flow) pass through gap acceptance's judgement (`GapShield`, the grid's
    `@shield` and `@shield-left`), the replay keeps the commands driven, and `evaluation.json`
    measures the policy behind that shield: a run meant to be deployed as `quadq@shield:RUN`.
    quadq and td3 only ("none": no shield)."""
    shield_penalty: float = num(0.0, 0.0, 1000.0)
    """0: the `shield` drives, as above. > 0: the shield only judges. The ego drives its own
    command, and the reward the replay keeps for each env step loses `shield_penalty` x |command
    - what the shield would let through| (per m/s^2; the logged rewards stay the env's), so the
    learner pays for the commands gap acceptance would overrule and sees where they lead;
    `evaluation.json` measures the policy bare, as it is meant to drive. Needs a `shield`; any
    algorithm."""
    shield_imitation: float = num(0.0, 0.0, 1000.0)
    """> 0: the shield only judges (as with `shield_penalty`) and teaches. The ego drives its own
    command; before each update the shield judges the greedy command B(s) of every replayed
    state, and where it would overrule it, the loss gains `shield_imitation` x (B(s) - the
    shield's command)^2 (`FastQuadQUpdater.imitate`). `evaluation.json` measures the policy
    bare. Needs a `shield`; quadq on the fast or compiled path."""
    td_expectile: float = num(0.5, 0.05, 0.95)
    """tau of the quadratic Q's TD loss: each squared TD error weighs 2 tau where the target
    is above Q(s, a) and 2 (1 - tau) where it is below (expectile regression). Below 0.5, Q
    fits a low expectile of the return, so outcomes worse than expected (a collision after a
    gap that usually holds) weigh more: a risk-averse critic, and B(s) moves away from the
    commands whose returns spread downwards. 0.5: the paper's squared error. quadq on the
    fast or compiled path."""
    lr_end_fraction: float = num(1.0, 0.001, 1.0)
    """The quadratic Q's learning rate falls linearly from `lr` to `lr` x this over the run's
    updates (`total_sim_steps` x `updates_per_sim_step`), so the last updates move the weights
    less and the checkpoints late in a run differ less from each other. 1: the paper's constant
    rate. quadq on the fast or compiled path."""
    flush_denormals: bool = False
    """The quadratic Q's updates run with subnormal floats flushed to zero (only the update's
    call: `marlmerge.learners.compiling.denormals_flushed`). Dead units' Adam moments decay into
    the subnormal range, where the CPU's arithmetic is many times slower: on one host the
    update of 8 seeds in one process took 37 s instead of 58 s (200,000 steps), with the same
    bits in every run checked (`docs/scale-out.md`). Off by default, as it changes the
    arithmetic wherever a subnormal arises. quadq on the fast or compiled path."""
    peaks: int = num(1, 1, 8)
    """K quadratic pieces of the quadratic Q, which is then the largest of them: Q(s, a) =
    max_k A_k(s) (B_k(s) - a)^2 + C_k(s), acting with the B of the largest C
    (`marlmerge.learners.quadq.QuadraticQNet`). Several pieces can hold several good commands
    at once (brake and let a vehicle pass, or go), where one quadratic holds one. 1: the
    paper's network. quadq with one action component, no `shield_imitation`."""
    peak_share: float = num(0.0, 0.0, 1.0)
    """With `peaks` > 1: the weight of each losing piece's own squared TD error at the replayed
    command. The envelope's error reaches only the piece that is largest there, so a piece
    that never wins never learns and the envelope can collapse to one piece; with a share, every
    piece follows the returns and can come back. 0: the envelope's error alone. quadq with
    `peaks` > 1 on the fast or compiled path."""
    peak_share_heads: str = "abc"
    """The heads of a losing piece that `peak_share` reaches: "abc" its A, B and C (the piece
    follows the returns wherever it loses, and can drift onto the winner's command); "c" its
    level C alone, so a piece that lost everywhere rises back at its own command B_k and is
    shaped only where it wins."""
    peak_bands: bool = False
    """With `peaks` = K > 1: piece k's greedy command B_k lies in the k-th of K equal bands of
    the command range (hard braking, ..., accelerating), so the pieces cannot drift onto one
    command: every state keeps K separate candidates, each valued by its own C_k. Needs
    `peak_share` > 0, or a piece that never wins would never learn its band."""
    dqn: DqnConfig = field(default_factory=DqnConfig)
    td3: Td3Config = field(default_factory=Td3Config)
    levels: LevelsConfig = field(default_factory=LevelsConfig)
    select: SelectConfig = field(default_factory=SelectConfig)

    @property
    def shield_drives(self) -> bool:
        """The vehicles drive what the shield lets through (a `shield` and no `JUDGING_KEYS`)."""
        return self.shield != "none" and all(getattr(self, key) == 0.0 for key in JUDGING_KEYS)

    def __post_init__(self) -> None:
        self._check()
        require(
            [
                *self._shield_checks(),
                *self._fast_path_checks(),
                *self._peak_checks(),
                (
                    not self.shield_drives or self.algorithm != "dqn",
                    f"shield = {self.shield!r} replaces the commands driven, which dqn's discrete "
                    "levels cannot store: use algorithm = 'quadq' or 'td3' (or shield_penalty > 0)",
                ),
                *self._level_checks(),
            ]
        )
        self._check_named_presets()

    def _shield_checks(self) -> list[tuple[bool, str]]:
        return [
            (
                self.algorithm in ALGORITHMS,
                f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}",
            ),
            (
                self.shield in TRAIN_SHIELDS,
                f"shield must be one of {TRAIN_SHIELDS}, got {self.shield!r}",
            ),
            (
                self.shield_penalty == 0.0 or self.shield != "none",
                f"shield_penalty = {self.shield_penalty} needs a shield to judge the "
                "commands: set shield = 'shield' or 'shield-left'",
            ),
            (
                self.shield_imitation == 0.0 or self.shield != "none",
                f"shield_imitation = {self.shield_imitation} needs a shield to teach: set "
                "shield = 'shield' or 'shield-left'",
            ),
        ]

    def _fast_path_checks(self) -> list[tuple[bool, str]]:
        """Options of the quadratic Q's fast path, refused on any other update."""
        fast = self.algorithm == "quadq" and self.update_path != "torchrl"
        needs = (
            "algorithm = 'quadq' with update_path 'fast' or 'compiled', got "
            f"{self.algorithm!r} on {self.update_path!r}"
        )
        return [
            (
                self.shield_imitation == 0.0 or fast,
                f"shield_imitation = {self.shield_imitation} trains the quadratic Q's fast "
                f"path: {needs}",
            ),
            (
                self.td_expectile == 0.5 or fast,
                f"td_expectile = {self.td_expectile} weighs the quadratic Q's fast-path "
                f"loss: {needs}",
            ),
            (
                self.lr_end_fraction == 1.0 or fast,
                f"lr_end_fraction = {self.lr_end_fraction} schedules the quadratic Q's "
                f"fast-path Adam: {needs}",
            ),
            (
                not self.flush_denormals or fast,
                f"flush_denormals = true flushes the quadratic Q's fast-path updates: {needs}",
            ),
        ]

    def _peak_checks(self) -> list[tuple[bool, str]]:
        return [
            (
                self.peaks == 1 or (self.algorithm == "quadq" and self.shield_imitation == 0.0),
                f"peaks = {self.peaks} shapes the quadratic Q without imitation: algorithm "
                f"= 'quadq' and shield_imitation = 0, got {self.algorithm!r} and "
                f"{self.shield_imitation}",
            ),
            (
                self.peak_share == 0.0 or (self.peaks > 1 and self.update_path != "torchrl"),
                f"peak_share = {self.peak_share} weighs the losing pieces of a quadratic Q "
                f"of several peaks on the fast path: peaks > 1 with update_path 'fast' or "
                f"'compiled', got peaks = {self.peaks} on {self.update_path!r}",
            ),
            (
                self.peak_share_heads in PEAK_SHARE_HEADS,
                f"peak_share_heads must be one of {PEAK_SHARE_HEADS}, got "
                f"{self.peak_share_heads!r}",
            ),
            (
                not self.peak_bands or self.peak_share > 0.0,
                f"peak_bands = true keeps each piece in its band of commands: it needs "
                f"peak_share > 0 (a piece that never wins learns only through it), got "
                f"peak_share = {self.peak_share} with peaks = {self.peaks}",
            ),
        ]

    def _level_checks(self) -> list[tuple[bool, str]]:
        return [
            (
                not self.levels.seed_presets or self.levels.replay_fraction > 0.0,
                "levels.seed_presets needs levels.replay_fraction > 0 (nothing replays them)",
            ),
            (
                self.levels.score in LEVEL_SCORES,
                f"levels.score must be one of {LEVEL_SCORES}, got {self.levels.score!r}",
            ),
            (
                not self.levels.replay_roads or self.levels.replay_fraction > 0.0,
                "levels.replay_roads = true needs levels.replay_fraction > 0 (nothing "
                "replays the roads)",
            ),
        ]

    def _check_named_presets(self) -> None:
        """The presets the run names (levels to seed, the scenario a policy is chosen on)
        resolve, and the choice is not made on a held-out set."""
        from marlmerge.config.presets import resolve_config  # presets imports this module

        for i, preset in enumerate(self.levels.seed_presets):
            try:
                resolve_config(preset)
            except (ValueError, OSError) as e:
                raise ValueError(f"levels.seed_presets[{i}] = {preset!r}: {e}") from None
        if not self.select.scenario:
            return
        try:
            chosen_on = resolve_config(self.select.scenario).name
        except (ValueError, OSError) as e:
            raise ValueError(f"select.scenario = {self.select.scenario!r}: {e}") from None
        require(
            [
                (
                    not chosen_on.startswith(("heldout", "lapses_heldout")),
                    f"select.scenario = {self.select.scenario!r} is a held-out set "
                    f"({chosen_on}): choosing a policy on it would tune on the test",
                )
            ]
        )


FLAT_KEYS = {
    "mlp_hidden_layers": ("dqn.hidden_layers", "td3.hidden_layers"),
    "dqn_levels": ("dqn.levels",),
    "dqn_double": ("dqn.double",),
    "epsilon_start": ("dqn.epsilon_start",),
    "epsilon_end": ("dqn.epsilon_end",),
    "td3_tau": ("td3.tau",),
    "td3_policy_delay": ("td3.policy_delay",),
    "td3_target_noise": ("td3.target_noise",),
    "td3_target_noise_clip": ("td3.target_noise_clip",),
}
"""Keys of version-0.3 configs (flat) and where they live now (the algorithm tables)."""


def upgrade_flat_keys(data: dict[str, Any]) -> dict[str, Any]:
    """A saved `TrainConfig` dict of an older version (flat algorithm keys) in today's layout."""
    out = {k: v for k, v in data.items() if k not in FLAT_KEYS}
    for old, new_keys in FLAT_KEYS.items():
        if old in data:
            for dotted in new_keys:
                table, key = dotted.split(".")
                out.setdefault(table, {})[key] = data[old]
    return out
