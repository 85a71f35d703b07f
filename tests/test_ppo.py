"""PPO for the highway group (IPPO / MAPPO): the learner on constructed rollouts, the collector
on the multi-agent view, and co-training runs at a tiny budget (learning, resume, policy files)."""

import csv

import pytest
import torch
from test_cotrain import TINY as COTRAIN_TINY
from torch.distributions import Normal
from torchrl.envs.utils import check_env_specs

from marlmerge.io import files
from marlmerge.learners.highway import load_highway_policy
from marlmerge.learners.ppo import PPOHighwayLearner, critic_observation, critic_size
from marlmerge.training.cotrain import JointPolicy, cotrain, load_cotrain_config
from marlmerge.training.loop import make_replay
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv

GAMMA, LMBDA = 0.9, 0.8


def _learner(critic_dim=12, seed=0, **kw):
    settings = dict(
        gamma=GAMMA, lmbda=LMBDA, lr=1e-3, clip_epsilon=0.2, entropy_coeff=1e-3,
        critic_coeff=0.5, epochs=2, minibatches=3, max_grad_norm=0.5, init_std=0.5, seed=seed,
    )  # fmt: skip
    return PPOHighwayLearner(12, critic_dim, 16, -3.0, 3.0, **{**settings, **kw})


def _constant_critic(learner, v0):
    with torch.no_grad():
        for p in learner.critic_net.parameters():
            p.zero_()
        list(learner.critic_net.parameters())[-1].fill_(v0)


def test_gae_per_agent_matches_the_recursion_by_hand():
    """One world, T = 4 steps, K = 2 agents, constant reward r and value v0: agent 0 drives the
    whole batch (cut at its end: bootstrapped), agent 1 is towed away after step 1 (terminal)
    and absent after it. Absent steps give no rows and leak nothing into the others."""
    learner = _learner()
    r, v0, t_len = 1.0, 2.0, 4
    _constant_critic(learner, v0)
    obs = torch.randn(1, t_len, 2, 12)
    valid = torch.tensor([[[True, True], [True, True], [True, False], [True, False]]])
    terminated = torch.zeros(1, t_len, 2, dtype=torch.bool)
    terminated[0, 1, 1] = True
    end = terminated.clone()
    rows = learner.rollout_rows(
        obs, obs, torch.zeros(1, t_len, 2, 1), torch.full((1, t_len, 2, 1), r), obs,
        valid, end, terminated, torch.zeros_like(end),
    )  # fmt: skip
    assert rows.shape == (6, 12 + 12 + 4)
    adv, target = rows[:, -2], rows[:, -1]
    # rows come in [B, T, K] order of the valid steps: (0,0) (0,1) (1,0) (1,1) (2,0) (3,0)
    delta_cut, delta_end = r + GAMMA * v0 - v0, r - v0
    agent0 = [sum((GAMMA * LMBDA) ** i * delta_cut for i in range(t_len - t)) for t in range(4)]
    agent1 = [delta_cut + GAMMA * LMBDA * delta_end, delta_end]
    expected = [agent0[0], agent1[0], agent0[1], agent1[1], agent0[2], agent0[3]]
    assert torch.allclose(adv, torch.tensor(expected), atol=1e-5)
    assert torch.allclose(target, adv + v0, atol=1e-5)


def test_an_agent_driving_off_the_road_is_bootstrapped_from_its_own_value():
    """Leaving downstream is cut, not absorbing: its advantage is r + gamma V(s) - V(s), never the
    terminal r - V(s) that would pay a driver with negative rewards to leave early."""
    learner = _learner()
    obs, nxt = torch.randn(1, 1, 1, 12), torch.zeros(1, 1, 1, 12)
    yes = torch.ones(1, 1, 1, dtype=torch.bool)
    no = ~yes
    reward = torch.full((1, 1, 1, 1), -1.0)
    rows = learner.rollout_rows(obs, obs, torch.zeros(1, 1, 1, 1), reward, nxt, yes, yes, no, yes)
    v = learner.value(obs).item()
    assert rows[0, -2].item() == pytest.approx(-1.0 + GAMMA * v - v, abs=1e-5)


def test_sampling_is_seeded_squashed_into_the_bounds_and_never_touches_the_global_rng():
    learner = _learner()
    obs, rows = torch.randn(64, 4, 12), torch.randn(50, 12 + 12 + 4)
    before = torch.get_rng_state()
    a = learner.act(obs, 0, torch.Generator().manual_seed(5))
    b = learner.act(obs, 0, torch.Generator().manual_seed(5))
    assert torch.equal(a["action"], b["action"]) and torch.equal(a["z"], b["z"])
    assert a["action"].abs().max() <= 3.0
    assert torch.allclose(a["action"], 3.0 * torch.tanh(a["z"]))
    loc, scale = learner.actor_net(obs)
    expected = Normal(loc, scale).log_prob(a["z"])
    assert torch.allclose(learner.log_prob(obs, a["z"]), expected, atol=1e-5)
    assert torch.equal(learner.greedy(obs), 3.0 * torch.tanh(loc.detach()))
    replay = make_replay(1000, torch.Generator().manual_seed(0))
    replay.extend(rows)
    losses = learner.learn(replay, 0, 0)
    assert losses.shape == (2 * 3,) and len(replay) == 0  # epochs x minibatches, then emptied
    assert torch.equal(torch.get_rng_state(), before)


def test_the_central_critic_sees_its_agent_the_ego_and_the_whole_group():
    hw, ego = torch.randn(5, 3, 4, 12), torch.randn(5, 3, 7)  # [B, T, K, 12], [B, T, 7]
    assert torch.equal(critic_observation(hw, ego, "local"), hw)
    central = critic_observation(hw, ego, "central")
    assert central.shape == (5, 3, 4, critic_size(12, 7, 4, "central")) == (5, 3, 4, 67)
    assert torch.equal(central[..., 2, :12], hw[..., 2, :])
    assert torch.equal(central[..., 1, 12:19], ego)
    assert torch.equal(central[..., 3, 19:].reshape(5, 3, 4, 12), hw)


def test_a_learner_restored_from_its_saved_state_continues_bit_for_bit(tmp_path):
    rows = torch.randn(3, 40, 12 + 12 + 4)
    a, b = _learner(seed=3), _learner(seed=9)

    def learn(learner, chunk):
        replay = make_replay(100, torch.Generator().manual_seed(0))
        replay.extend(chunk)
        return learner.learn(replay, 0, 0)

    learn(a, rows[0])
    files.save(a.state_dict(), tmp_path / "state.pt")
    b.load_state_dict(files.load(tmp_path / "state.pt"))
    for chunk in rows[1:]:
        assert torch.equal(learn(a, chunk), learn(b, chunk))
    for k, v in a.actor_net.state_dict().items():
        assert torch.equal(v, b.actor_net.state_dict()[k]), k


def test_the_multi_agent_view_passes_check_env_specs_and_collects_ppo_samples():
    env = MultiAgentMergeEnv("default", num_worlds=3, seed=0)
    check_env_specs(env, seed=0)
    env.set_opponent_mix(1, 0.0)
    learner, gen = _learner(), torch.Generator().manual_seed(1)
    policy = JointPolicy(lambda o: torch.zeros(o.shape[0], 1), [lambda o: learner.act(o, 0, gen)])
    rollout = env.rollout(20, policy, break_when_any_done=False)
    z, action = rollout.get((GROUP, "z")), rollout.get((GROUP, "action"))
    assert z.shape == action.shape == (3, 20, env.n_agents, 1)
    assert torch.allclose(action, 3.0 * torch.tanh(z))  # the offset acts as the acceleration here


TINY = {
    **COTRAIN_TINY,
    "ego_pretrain_sim_steps": 2_048,
    "rounds": 1,
    "adversary_sim_steps": 6_144,
    "ego_sim_steps": 2_048,
    "highway_algorithm": "ppo",
}


@pytest.mark.slow
@pytest.mark.parametrize("critic", ["central", "local"])
def test_a_killed_ppo_run_resumes_to_the_same_adversary_and_ego(tmp_path, critic):
    cfg = load_cotrain_config("cotrain", **TINY, **{"ppo.critic": critic})
    full, cut = tmp_path / "full", tmp_path / "cut"
    cotrain(cfg, full, progress=False)
    cotrain(cfg, cut, progress=False, stop_after_sim_steps=5_000)  # inside the adversary phase
    assert files.load(cut / "checkpoint.pt")["phase_index"] == 1
    cotrain(cfg, cut, resume=True, progress=False)
    for name in ("policy.pt", "highway_policy.pt", "pool/adversary_1.pt"):
        a, b = (files.load(d / name)["policy_state"]["net"] for d in (full, cut))
        assert all(torch.equal(a[k], b[k]) for k in a), name
    assert (full / "loss.csv").read_text() == (cut / "loss.csv").read_text()
    saved = files.load(full / "highway_policy.pt")
    assert saved["algorithm"] == "ppo-residual"
    hw = load_highway_policy(full)
    assert hw(torch.zeros(2, 4, 12)).shape == (2, 4, 1)


@pytest.mark.slow
def test_ppo_adversaries_raise_their_own_return_at_a_tiny_budget(tmp_path):
    """100k simulator steps against the paper's ego stand-in (a fixed ego pretrained briefly):
    the highway group's mean reward per agent step over the last fifth of the phase beats the
    first fifth's, by more than the batch-to-batch noise."""
    longer = dict(adversary_sim_steps=100_000, ego_sim_steps=0, select_episodes=0, num_worlds=32)
    cfg = load_cotrain_config(
        "cotrain",
        **{**TINY, **longer},
        env_steps_per_batch=32,
        **{"ppo.lr": 1e-3, "ppo.epochs": 8},
    )
    cotrain(cfg, tmp_path, progress=False)
    with open(tmp_path / "highway.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["phase"] == "adversary"]
    per_batch = torch.tensor([float(r["reward_per_agent_step"]) for r in rows])
    fifth = len(per_batch) // 5
    first, last = per_batch[:fifth], per_batch[-fifth:]
    noise = (first.std() ** 2 / fifth + last.std() ** 2 / fifth).sqrt()
    assert last.mean() - first.mean() > 3 * noise, (first.mean(), last.mean(), noise)
