"""The peer learners (DQN over discrete accelerations, TD3) through the same training loop."""

import csv
import json

import pytest
import torch

from marlmerge.config.presets import load_train_config
from marlmerge.config.training import Td3Config, TrainConfig
from marlmerge.io import files
from marlmerge.learners.dqn import DQNLearner, EpsilonGreedy, dqn_action_levels
from marlmerge.learners.loading import load_policy
from marlmerge.learners.quadq import GaussianExploration, QuadraticQNet
from marlmerge.learners.td3 import TD3Learner
from marlmerge.training.train import train

LO, HI = -4.5, 2.5

TINY = dict(
    name="tiny",
    total_sim_steps=4_096,
    num_worlds=8,
    env_steps_per_batch=4,
    learning_starts=256,
    replay_capacity=5_000,
    update_path="fast",  # eager torchrl losses (no compile time in the tests)
    updates_per_sim_step=0.125,
    checkpoint_every_sim_steps=1_024,
    eval_episodes=0,
    hidden=32,
)


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def _packed_rows(n: int, discrete: bool, seed: int = 0) -> torch.Tensor:
    """Random packed transitions [n, 17]: obs, action, reward, terminated, next obs."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.rand(n, 17, generator=g)
    if discrete:
        rows[:, 7] = torch.randint(0, 7, (n,), generator=g).float()
    else:
        rows[:, 7] = LO + (HI - LO) * rows[:, 7]
    rows[:, 8] = -rows[:, 8]
    rows[:, 9] = (rows[:, 9] > 0.8).float()
    return rows


@pytest.mark.parametrize("algorithm", ["dqn", "td3"])
@pytest.mark.slow
def test_tiny_run_end_to_end_and_load_policy(tmp_path, algorithm):
    cfg = TrainConfig(**{**TINY, "algorithm": algorithm, "eval_episodes": 4, "eval_worlds": 4})
    rng_before = torch.get_rng_state()
    result = train(cfg, tmp_path, progress=False)
    assert torch.equal(rng_before, torch.get_rng_state()), "train() touched the global RNG"
    for name in ("loss.csv", "egos.csv", "checkpoint.pt", "policy.pt", "evaluation.json"):
        assert (tmp_path / name).exists(), name
    assert (tmp_path / "fig3_loss.png").exists()
    assert result.sim_steps == 4_096 and result.updates == 4_096 // 8
    loss = _rows(tmp_path / "loss.csv")
    assert loss[0] == ["update", "sim_step", "loss"] and len(loss) > 10
    assert all(torch.isfinite(torch.tensor(float(r[2]))) for r in loss[1:])
    assert len(_rows(tmp_path / "egos.csv")) - 1 == result.egos > 0
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert ev["episodes"] == 4
    saved = files.load(tmp_path / "checkpoint.pt")
    assert saved["algorithm"] == algorithm and "learner" in saved["group"]

    policy = load_policy(tmp_path)  # a run folder or its policy.pt
    obs = torch.rand(16, 7, generator=torch.Generator().manual_seed(1)) * 2
    action = policy(obs)
    assert action.shape == (16, 1) and action.dtype == torch.float32
    assert (action >= LO).all() and (action <= HI).all()
    assert not action.requires_grad
    if algorithm == "dqn":  # only the levels can come out
        levels = dqn_action_levels(cfg.dqn.levels, LO, HI)
        assert torch.isin(action, levels).all()


@pytest.mark.parametrize("algorithm", ["dqn", "td3"])
@pytest.mark.slow
def test_killed_run_resumes_bit_exact(tmp_path, algorithm):
    cfg = TrainConfig(**{**TINY, "algorithm": algorithm})
    straight = train(cfg, tmp_path / "a", progress=False)
    # killed after 2,560 steps; its last checkpoint is at 2,048 and its logs run past it
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=2_560)
    saved = files.load(tmp_path / "b" / "checkpoint.pt")
    assert saved["sim_steps"] == 2_048
    resumed = train(cfg, tmp_path / "b", resume=True, progress=False)
    assert resumed.sim_steps == straight.sim_steps and resumed.updates == straight.updates
    assert _rows(tmp_path / "a" / "egos.csv") == _rows(tmp_path / "b" / "egos.csv")
    assert _rows(tmp_path / "a" / "loss.csv") == _rows(tmp_path / "b" / "loss.csv")
    wa = files.load(tmp_path / "a" / "policy.pt")["policy_state"]["net"]
    wb = files.load(tmp_path / "b" / "policy.pt")["policy_state"]["net"]
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    ca = files.load(tmp_path / "a" / "checkpoint.pt")["group"]["learner"]["loss"]
    cb = files.load(tmp_path / "b" / "checkpoint.pt")["group"]["learner"]["loss"]
    assert all(torch.equal(ca[k], cb[k]) for k in ca)  # online and target networks


def test_dqn_levels_map_to_accelerations():
    levels = dqn_action_levels(7, LO, HI)
    expected = [-4.5, -4.5 + 7 / 6, -4.5 + 14 / 6, -1.0, -4.5 + 28 / 6, -4.5 + 35 / 6, 2.5]
    assert torch.allclose(levels, torch.tensor(expected))
    assert torch.equal(dqn_action_levels(8, LO, HI), torch.arange(8.0) - 4.5)
    with pytest.raises(ValueError):
        dqn_action_levels(1, LO, HI)

    learner = DQNLearner(levels, hidden=16, exploration=EpsilonGreedy(1.0, 1.0, 1, 7), seed=3)
    obs = torch.rand(64, 7, generator=torch.Generator().manual_seed(0))
    # greedy: the level of the arg-max Q-value
    q = learner.q_mlp(obs)
    assert torch.equal(learner.greedy(obs), levels[q.argmax(-1)].unsqueeze(-1))
    # exploring (epsilon = 1): the env gets levels[index], the replay keeps the index
    from tensordict import TensorDict

    from marlmerge.training.loop import GroupPolicy, LearningGroup

    gen = torch.Generator().manual_seed(0)
    group = LearningGroup("ego", learner, None, gen, gen, 1.0, 32, 0, 5)  # type: ignore[arg-type]
    policy = GroupPolicy(group)

    td = policy(TensorDict({"observation": obs}, batch_size=[64]))
    index = td["action_index"]
    assert index.dtype == torch.int64 and index.shape == (64,)
    assert len(index.unique()) > 3  # random levels, not the greedy one
    assert torch.equal(td["action"], levels[index].unsqueeze(-1))
    assert torch.equal(learner.replay_action(td), index.float().unsqueeze(-1))


def test_epsilon_greedy_schedule_and_seeding():
    eps = EpsilonGreedy(1.0, 0.1, 100, 5)
    assert eps.epsilon(0) == 1.0 and eps.epsilon(50) == pytest.approx(0.55)
    assert eps.epsilon(10_000) == pytest.approx(0.1)
    greedy = torch.zeros(1000, dtype=torch.int64)
    a = eps(greedy, 10_000, torch.Generator().manual_seed(5))
    b = eps(greedy, 10_000, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    assert 0.05 < (a != 0).float().mean() < 0.12  # ~ 0.1 * 4/5 take another level


@pytest.mark.parametrize("double_dqn", [False, True])
def test_dqn_updates_and_hard_target_copy(double_dqn):
    learner = DQNLearner(
        dqn_action_levels(7, LO, HI),
        hidden=16,
        target_update_period=4,
        double_dqn=double_dqn,
        exploration=EpsilonGreedy(1.0, 0.05, 10, 7),
        seed=0,
    )
    rows = _packed_rows(6 * 32, discrete=True).view(6, 32, 17)
    before = learner.loss.target_value_network_params.clone()
    for i in range(4):
        assert torch.isfinite(learner.update(rows[i]))
        if i < 3:  # the target changes only on the 4th update (period 4)
            assert (before == learner.loss.target_value_network_params).all()
    after = learner.loss.target_value_network_params
    assert (after == learner.loss.value_network_params.data).all()
    assert learner.num_updates == 4


def test_td3_learner_is_seeded_and_leaves_the_global_rng_alone():
    def run() -> dict:
        learner = TD3Learner(
            LO, HI, hidden=16, exploration=GaussianExploration(1.0, 0.1, 10, LO, HI), seed=7
        )
        rows = _packed_rows(8 * 32, discrete=False).view(8, 32, 17)
        for i in range(8):
            learner.update(rows[i])
        assert learner.num_updates == 8
        return learner.state_dict()

    state = torch.get_rng_state()
    a = run()
    assert torch.equal(state, torch.get_rng_state())
    torch.manual_seed(123)  # a different global state changes nothing
    b = run()
    assert all(torch.equal(a["loss"][k], b["loss"][k]) for k in a["loss"])
    # the actor is squashed inside the bounds and explores inside them too
    learner = TD3Learner(LO, HI, hidden=16, exploration=GaussianExploration(5.0, 5.0, 1, LO, HI))
    obs = torch.rand(256, 7, generator=torch.Generator().manual_seed(0)) * 10
    act = learner.act(obs, 0, torch.Generator().manual_seed(0))["action"]
    assert act.shape == (256, 1) and (act >= LO).all() and (act <= HI).all()


def test_load_policy_reads_quadq_policies(tmp_path):
    net = QuadraticQNet(7, 16, generator=torch.Generator().manual_seed(0))
    from marlmerge.config import ScenarioConfig, to_dict

    old_format = {"config": {"hidden": 16}, "scenario": to_dict(ScenarioConfig()), "net": net}
    old_format["net"] = net.state_dict()
    torch.save(old_format, tmp_path / "policy.pt")
    policy = load_policy(tmp_path / "policy.pt")
    obs = torch.rand(10, 7, generator=torch.Generator().manual_seed(0))
    assert torch.equal(policy(obs), net.greedy(obs).detach())
    with pytest.raises(ValueError, match="no saved ego policy"):
        load_policy(tmp_path / "missing")


def test_bad_algorithm_is_rejected_by_name():
    with pytest.raises(ValueError, match="'ppo'"):
        TrainConfig(algorithm="ppo")
    with pytest.raises(ValueError, match="td3.policy_delay"):
        TrainConfig(algorithm="td3", td3=Td3Config(policy_delay=0))


def test_algorithm_tables_take_dotted_overrides_and_old_flat_keys_say_where_they_went(tmp_path):
    cfg = load_train_config("dqn", **{"dqn.levels": 9, "td3.tau": 0.01})
    assert cfg.dqn.levels == 9 and cfg.td3.tau == 0.01 and cfg.dqn.double is False
    with pytest.raises(ValueError, match="'dqn_levels' is now 'dqn.levels'"):
        load_train_config("dqn", dqn_levels=9)
    old = tmp_path / "old.toml"
    old.write_text('kind = "train"\nalgorithm = "td3"\ntd3_tau = 0.01\n')
    with pytest.raises(ValueError, match=r"old.toml: .*'td3_tau' is now 'td3.tau'"):
        load_train_config(old)
    with pytest.raises(ValueError, match="dqn.levels"):
        load_train_config("dqn", **{"dqn.levels": 1})
    with pytest.raises(ValueError, match="unknown config key 'dqn.level'"):
        load_train_config("dqn", **{"dqn.level": 3})


def test_presets():
    for name, algorithm in (("dqn", "dqn"), ("td3", "td3")):
        full = load_train_config(name)
        quick = load_train_config(f"{name}_quick")
        assert full.algorithm == quick.algorithm == algorithm
        assert full.total_sim_steps == load_train_config("paper").total_sim_steps
        assert quick.total_sim_steps == load_train_config("quick").total_sim_steps
