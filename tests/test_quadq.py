"""Tests of the quadratic-in-action Q-learner (marlmerge.learners.quadq)."""

from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict

import marlmerge.learners.quadq as qq
import marlmerge.learners.quadq_fast as qf
from marlmerge.learners.packed_replay import TransitionReplay
from marlmerge.learners.quadq_flat import TEACHER_CHANGED

LOW, HIGH = qq.DEFAULT_ACTION_BOUNDS
OBS_DIM = 7


@pytest.fixture(autouse=True)
def _quiet_torchrl_target_warning():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No target network updater")
        yield


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _net(seed: int = 0, **kw) -> qq.QuadraticQNet:
    return qq.QuadraticQNet(OBS_DIM, kw.pop("hidden", 16), generator=_gen(seed), **kw)


def _batch(
    n: int, g: torch.Generator, terminated: torch.Tensor | None = None, join: bool = False
) -> TensorDict:
    if terminated is None:
        terminated = torch.rand(n, 1, generator=g) < 0.3
    action = torch.rand(n, 1, generator=g) * (HIGH - LOW) + LOW
    if join:  # a second component in [-1, 1] (ego.join = "chosen")
        action = torch.cat([action, torch.rand(n, 1, generator=g) * 2.0 - 1.0], -1)
    return TensorDict(
        {
            "observation": torch.randn(n, OBS_DIM, generator=g),
            "action": action,
            ("next", "reward"): torch.randn(n, 1, generator=g),
            ("next", "terminated"): terminated,
            ("next", "observation"): torch.randn(n, OBS_DIM, generator=g),
        },
        batch_size=[n],
    )


def _perturb_target(loss: qq.QuadraticQLoss, g: torch.Generator) -> None:
    with torch.no_grad():
        for t in loss.target_value_network_params.values(True, True):
            t.add_(0.05 * torch.randn(t.shape, generator=g))


def _filled_replay(n: int, g: torch.Generator, join: bool = False) -> TransitionReplay:
    rep = TransitionReplay(2 * n, OBS_DIM, action_dim=2 if join else 1)
    rep.extend_tensordict(_batch(n, g, join=join))
    return rep


# --- network ---------------------------------------------------------------------------------


def test_argmax_over_action_grid_is_b_and_q_at_b_is_c():
    net = _net()
    obs = torch.randn(64, OBS_DIM, generator=_gen(1)) * 3.0
    grid = torch.linspace(LOW, HIGH, 7001)  # spacing 1e-3 m/s^2
    with torch.no_grad():
        a, b, c = net(obs)
        q = net.q(obs.unsqueeze(1), grid.view(1, -1, 1)).squeeze(-1)  # [64, 7001]
        best = grid[q.argmax(dim=1)].unsqueeze(-1)
        assert torch.all((b > LOW) & (b < HIGH))
        torch.testing.assert_close(best, b, atol=1e-3, rtol=0)
        torch.testing.assert_close(net.greedy(obs), b)
        torch.testing.assert_close(net.q(obs, b), c, atol=1e-6, rtol=0)
        torch.testing.assert_close(net.max_value(obs), c)
        assert torch.all(q.max(dim=1).values.unsqueeze(-1) <= c + 1e-5)


@pytest.mark.parametrize("scale", [1.0, 1e3, 1e6, -1e6])
def test_curvature_is_finite_negative_and_bounded(scale: float):
    net = _net(a_min=1e-3, a_max=5.0)
    obs = torch.randn(256, OBS_DIM, generator=_gen(2)) * scale
    with torch.no_grad():
        a, b, c = net(obs)
    for t in (a, b, c):
        assert torch.isfinite(t).all()
    assert torch.all(a < 0)
    assert torch.all(a <= -1e-3) and torch.all(a >= -5.0)
    assert torch.all((b >= LOW) & (b <= HIGH))


def test_extreme_observations_give_finite_loss_and_grads():
    net = _net()
    loss = qq.QuadraticQLoss(net)
    td = _batch(32, _gen(3))
    td["observation"] = td["observation"] * 1e6
    td["next", "observation"] = td["next", "observation"] * 1e6
    out = loss(td)
    out["loss_value"].backward()
    assert torch.isfinite(out["loss_value"])
    assert all(torch.isfinite(p.grad).all() for p in net.parameters())


def test_initial_curvature():
    net = _net(a_init=0.1)
    with torch.no_grad():
        a = net(torch.zeros(1, OBS_DIM))[0]
    # zero input -> hidden = relu(bias); head A = <h, w> + bias, so |A| is near a_init
    assert 0.02 < -a.item() < 0.5


# --- loss ------------------------------------------------------------------------------------


def test_gradients_reach_online_params_never_target():
    net = _net()
    loss = qq.QuadraticQLoss(net)
    _perturb_target(loss, _gen(4))
    out = loss(_batch(32, _gen(5), terminated=torch.zeros(32, 1, dtype=torch.bool)))
    out["loss_value"].backward()
    online = list(loss.value_network_params.values(True, True))
    assert all(p.requires_grad and p.grad is not None for p in online)
    assert all(p.grad.abs().sum() > 0 for p in online)
    targets = list(loss.target_value_network_params.values(True, True))
    assert all((not t.requires_grad) and t.grad is None for t in targets)
    # optimiser over loss.parameters() sees only the online parameters
    ids = {id(p) for p in loss.parameters()}
    assert ids == {id(p) for p in net.parameters()}
    assert not ids & {id(t) for t in targets}
    for key in ("td_error", "pred_value", "target_value", "A_mean", "B_mean", "C_mean"):
        assert not out[key].requires_grad and out[key].shape == ()
    assert out["A_mean"] < 0


def test_loss_matches_manual_formula():
    net = _net()
    loss = qq.QuadraticQLoss(net, gamma=0.9)
    _perturb_target(loss, _gen(6))
    td = _batch(16, _gen(7))
    out = loss(td)
    target_net = _net()
    with torch.no_grad():
        for key, t in loss.target_value_network_params.items(True, True):
            target_net.get_parameter(".".join(key) if isinstance(key, tuple) else key).copy_(t)
        y = (
            td["next", "reward"]
            + 0.9 * (~td["next", "terminated"]).float() * target_net(td["next", "observation"])[2]
        )
        expected = (net.q(td["observation"], td["action"]) - y).pow(2).mean()
    torch.testing.assert_close(out["loss_value"].detach(), expected)
    assert td["td_error"].shape == (16, 1)  # priority written back, |delta|


def test_terminal_transitions_are_not_bootstrapped():
    loss = qq.QuadraticQLoss(_net(), gamma=0.95)
    g = _gen(8)
    td = _batch(8, g, terminated=torch.ones(8, 1, dtype=torch.bool))
    y1 = loss.td_target(td)
    torch.testing.assert_close(y1, td["next", "reward"])
    td["next", "observation"] = torch.randn(8, OBS_DIM, generator=g) * 10
    torch.testing.assert_close(loss.td_target(td), td["next", "reward"])
    # not terminated: target moves with the next-state value, by gamma * C_target(s')
    td["next", "terminated"] = torch.zeros(8, 1, dtype=torch.bool)
    y2 = loss.td_target(td)
    with torch.no_grad():
        c_next = loss.value_network.max_value(td["next", "observation"])  # target == online now
    torch.testing.assert_close(y2, td["next", "reward"] + 0.95 * c_next)
    td["next", "observation"] = torch.randn(8, OBS_DIM, generator=g) * 10
    assert not torch.allclose(loss.td_target(td), y2)


def test_truncation_still_bootstraps():
    loss = qq.QuadraticQLoss(_net(), gamma=0.95)
    td = _batch(8, _gen(9), terminated=torch.zeros(8, 1, dtype=torch.bool))
    td["next", "truncated"] = torch.ones(8, 1, dtype=torch.bool)
    td["next", "done"] = torch.ones(8, 1, dtype=torch.bool)
    with torch.no_grad():
        c_next = loss.value_network.max_value(td["next", "observation"])
    torch.testing.assert_close(loss.td_target(td), td["next", "reward"] + 0.95 * c_next)
    assert not torch.allclose(loss.td_target(td), td["next", "reward"])


def test_set_keys_remaps_inputs():
    g = _gen(10)
    plain = _batch(16, g)
    loss = qq.QuadraticQLoss(_net())
    ref = loss(plain.clone())["loss_value"]
    loss.set_keys(
        observation=("agents", "obs"),
        action=("agents", "accel"),
        reward="r",
        terminated="term",
        priority="prio",
    )
    assert ("next", "agents", "obs") in loss.in_keys and ("next", "r") in loss.in_keys
    remapped = TensorDict(
        {
            ("agents", "obs"): plain["observation"],
            ("agents", "accel"): plain["action"],
            ("next", "r"): plain["next", "reward"],
            ("next", "term"): plain["next", "terminated"],
            ("next", "agents", "obs"): plain["next", "observation"],
        },
        batch_size=[16],
    )
    out = loss(remapped)
    torch.testing.assert_close(out["loss_value"], ref)
    assert "prio" in remapped.keys()
    with pytest.raises(KeyError):
        loss(plain.clone())
    with pytest.raises(ValueError):
        loss.set_keys(not_a_key="x")


def test_kwargs_call():
    loss = qq.QuadraticQLoss(_net())
    td = _batch(4, _gen(11))
    vals = loss(
        observation=td["observation"],
        action=td["action"],
        next_reward=td["next", "reward"],
        next_terminated=td["next", "terminated"],
        next_observation=td["next", "observation"],
    )
    torch.testing.assert_close(vals[0], loss(td)["loss_value"])


# --- target updates --------------------------------------------------------------------------


def _same(a: TensorDict, b: TensorDict) -> bool:
    return all(torch.equal(x, b.get(k)) for k, x in a.items(True, True))


def test_periodic_hard_update_copies_every_p_updates():
    p = 5
    net = _net()
    loss = qq.QuadraticQLoss(net)
    updater = qq.PeriodicHardUpdate(loss, period=p)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-2)
    g = _gen(12)
    tgt, online = loss.target_value_network_params, loss.value_network_params
    initial = tgt.detach().clone()
    for i in range(1, 2 * p + 1):
        opt.zero_grad()
        loss(_batch(32, g))["loss_value"].backward()
        opt.step()
        updater.step()
        if i % p == 0:
            assert _same(tgt, online), f"no copy after update {i}"
        elif i < p:
            assert _same(tgt, initial), f"copied too early, update {i}"
        else:
            assert not _same(tgt, online), f"copied too early, update {i}"


def test_fast_updater_copies_target_every_p_updates():
    p, k = 6, 2
    loss = qq.QuadraticQLoss(_net())
    rep = _filled_replay(200, _gen(13))
    fast = qf.FastQuadQUpdater(
        loss, rep, generator=_gen(14), updates_per_call=k, target_update_period=p, lr=1e-2
    )
    tgt = loss.target_value_network_params
    initial = tgt.detach().clone()
    for _ in range(p // k - 1):
        fast.step()
        assert _same(tgt, initial)
    fast.step()
    assert fast.num_updates == p
    assert _same(tgt, loss.value_network_params)
    fast.step()
    assert not _same(tgt, loss.value_network_params)
    with pytest.raises(ValueError):
        qf.FastQuadQUpdater(
            loss, rep, generator=_gen(0), updates_per_call=4, target_update_period=6
        )


# --- fast path -------------------------------------------------------------------------------


def _fast_vs_reference(k: int, compile: bool = False, join: bool = False, peaks: int = 1) -> None:
    g = _gen(15)
    rep = _filled_replay(500, g, join)
    rows = rep.sample((k, 32), g)
    pair = []
    extra = ((-1.0, 1.0),) if join else ()
    for _ in range(2):
        net = _net(hidden=64, extra_bounds=extra, peaks=peaks)
        loss = qq.QuadraticQLoss(net, gamma=0.95)
        _perturb_target(loss, _gen(16))
        pair.append(loss)
    fast_loss, ref_loss = pair
    fast = qf.FastQuadQUpdater(
        fast_loss,
        rep,
        generator=_gen(17),
        updates_per_call=k,
        target_update_period=100 * k,
        compile=compile,
    )
    opt = torch.optim.Adam(ref_loss.parameters(), lr=1e-3)
    # same batch, same parameters: the fast loss equals the LossModule loss
    first = rep.to_tensordict(rows[0])
    lm = fast_loss(first.clone())["loss_value"].detach()
    ref_values = []
    for i in range(k):
        out = ref_loss(rep.to_tensordict(rows[i]))
        ref_values.append(out["loss_value"].detach())
        opt.zero_grad()
        out["loss_value"].backward()
        opt.step()
    fast_values = fast.step(rows)
    torch.testing.assert_close(fast_values[0], lm, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(fast_values, torch.stack(ref_values), rtol=1e-5, atol=1e-6)
    # the hand-written gradients + flat Adam track autograd + torch.optim.Adam
    for (name, p_fast), p_ref in zip(
        fast_loss.value_network.named_parameters(), ref_loss.parameters(), strict=True
    ):
        torch.testing.assert_close(p_fast, p_ref, rtol=1e-5, atol=1e-6, msg=name)
    # the loss module (and the acting network) see the updated weights
    torch.testing.assert_close(
        fast_loss(first.clone())["loss_value"],
        ref_loss(first.clone())["loss_value"],
        rtol=1e-5,
        atol=1e-6,
    )


def test_fast_path_matches_lossmodule_and_adam():
    _fast_vs_reference(k=5)


def test_fast_path_with_a_join_component_matches_lossmodule_and_adam():
    _fast_vs_reference(k=5, join=True)


def test_fast_path_with_three_peaks_matches_lossmodule_and_adam():
    _fast_vs_reference(k=5, peaks=3)


@pytest.mark.parametrize(("bands", "heads"), [(False, "abc"), (True, "abc"), (False, "c")])
def test_peak_share_matches_autograd_of_the_envelope_plus_the_losing_pieces_errors(bands, heads):
    share, k = 0.2, 3
    rep = _filled_replay(300, _gen(21))
    rows = rep.sample((k, 32), _gen(22))
    fast_loss, ref_loss = (
        qq.QuadraticQLoss(_net(7, hidden=16, peaks=3, peak_bands=bands), gamma=0.95) for _ in "ab"
    )
    for loss in (fast_loss, ref_loss):
        _perturb_target(loss, _gen(23))
    fast = qf.FastQuadQUpdater(
        fast_loss, rep, generator=_gen(0), updates_per_call=k, target_update_period=10 * k,
        peak_share=share, peak_share_heads=heads,
    )  # fmt: skip
    net = ref_loss.value_network
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    td_losses = []
    for i in range(k):
        td = rep.to_tensordict(rows[i])
        a, b, c = net(td["observation"])  # [B, 3] each
        q_k = a * (b - td["action"]) ** 2 + c  # [B, 3]
        q, best = q_k.max(-1)
        y = ref_loss.td_target(td)[:, 0]  # [B]
        losing = torch.ones_like(q_k).scatter(-1, best[:, None], 0.0)
        if heads == "c":  # the losing pieces' error moves their levels C only
            q_k = a.detach() * (b.detach() - td["action"]) ** 2 + c
        total = (q - y).pow(2).mean() + share * (losing * (q_k - y[:, None]) ** 2).sum(-1).mean()
        td_losses.append((q - y).pow(2).mean().detach())
        opt.zero_grad()
        total.backward()
        opt.step()
    torch.testing.assert_close(fast.step(rows), torch.stack(td_losses), rtol=1e-5, atol=1e-6)
    for (name, p_fast), p_ref in zip(
        fast_loss.value_network.named_parameters(), net.parameters(), strict=True
    ):
        torch.testing.assert_close(p_fast, p_ref, rtol=1e-5, atol=1e-6, msg=name)


@pytest.mark.parametrize("share", [0.0, 0.1])
def test_a_piece_that_never_wins_learns_only_with_a_peak_share(share):
    net = _net(9, hidden=16, peaks=2)
    with torch.no_grad():
        net.head_bias[5] -= 1e3  # piece 1's C far below: it never wins at any command
    loss = qq.QuadraticQLoss(net, gamma=0.95)
    rep = _filled_replay(200, _gen(24))
    fast = qf.FastQuadQUpdater(
        loss, rep, generator=_gen(0), updates_per_call=5, target_update_period=50,
        peak_share=share,
    )  # fmt: skip
    before = net.head_bias.detach().clone()
    fast.step(rep.sample((5, 32), _gen(25)))
    moved = (net.head_bias.detach() - before).abs()  # rows A_0 A_1 B_0 B_1 C_0 C_1
    assert moved[[0, 2, 4]].min() > 0  # the winning piece learns either way
    assert (moved[[1, 3, 5]].min() > 0) == (share > 0)
    with pytest.raises(ValueError, match=r"peak_share = 0.1 .*\(this network has 1\)"):
        qf.FastQuadQUpdater(qq.QuadraticQLoss(_net()), None, generator=_gen(0), peak_share=0.1)
    with pytest.raises(ValueError, match="peak_share_heads must be one of .* got 'b'"):
        qf.FastQuadQUpdater(qq.QuadraticQLoss(net), None, generator=_gen(0), peak_share_heads="b")


def test_banded_pieces_keep_their_commands_apart():
    banded, spread = _net(3, peaks=3, peak_bands=True), _net(3, peaks=3)
    obs = torch.randn(200, OBS_DIM, generator=_gen(26)) * 3.0
    edges = torch.linspace(LOW, HIGH, 4)  # the three bands' edges, m/s^2
    b = banded(obs)[1]  # [200, 3]
    assert ((b > edges[:-1]) & (b < edges[1:])).all()
    # the bands' middles are where the unbanded pieces start: the same first commands
    torch.testing.assert_close(
        banded.head_bias[3:6], torch.zeros(3), msg="B starts in the middle of its band"
    )
    mid = (edges[:-1] + edges[1:]) / 2
    with torch.no_grad():
        for net in (banded, spread):
            net.head_weight[3:6] = 0.0
    torch.testing.assert_close(banded(obs[:1])[1][0], mid)
    torch.testing.assert_close(spread(obs[:1])[1][0], mid)
    with pytest.raises(ValueError, match="peak_bands splits the command range .* peaks > 1"):
        _net(peak_bands=True)


def test_one_peak_is_the_paper_network():
    paper, one = _net(3), _net(3, peaks=1)
    assert one.n_heads == 3 and paper.state_dict().keys() == one.state_dict().keys()
    for key, value in one.state_dict().items():
        assert torch.equal(value, paper.state_dict()[key]), key
    rows = _filled_replay(200, _gen(5)).sample((5, 32), _gen(6))
    updaters = [
        qf.FastQuadQUpdater(qq.QuadraticQLoss(net), None, generator=_gen(0), updates_per_call=5)
        for net in (paper, one)
    ]
    assert torch.equal(updaters[0].step(rows), updaters[1].step(rows))
    assert torch.equal(updaters[0].flat, updaters[1].flat)


def test_several_peaks_hold_two_good_commands_and_act_on_the_better():
    net = _net(6, peaks=2)
    assert net.n_heads == 6 and net.head_weight.shape == (6, 16)
    obs = torch.randn(7, OBS_DIM, generator=_gen(8))
    a, b, c = net(obs)
    assert a.shape == b.shape == c.shape == (7, 2) and (a < 0).all()
    # the B biases start spread over the range: one piece low, one high
    assert (b[:, 0] < b[:, 1]).all()
    grid = torch.linspace(LOW, HIGH, 701)[:, None]  # [G, 1]
    q = net.q(obs[:, None, :].expand(-1, 701, -1), grid[None])  # [7, G, 1]
    torch.testing.assert_close(grid[q[..., 0].argmax(-1)], net.greedy(obs), atol=0.011, rtol=0)
    torch.testing.assert_close(net.q(obs, net.greedy(obs)), net.max_value(obs))
    torch.testing.assert_close(net.max_value(obs), c.amax(-1, keepdim=True))
    # Q between the two peaks dips below both: two maxima, which one quadratic cannot hold
    with torch.no_grad():
        net.head_bias[4:6] = 0.0  # C_0 = C_1 up to the hidden units' share
        net.head_weight[4:6] = 0.0
        net.head_bias[0:2] = 5.0  # sharp pieces
    q = net.q(obs[:1].expand(701, -1), grid)[:, 0]
    b0, b1 = net(obs[:1])[1][0]
    mid = q[(grid[:, 0] - (b0 + b1) / 2).abs().argmin()]
    assert mid < q[(grid[:, 0] - b0).abs().argmin()] - 1.0
    assert mid < q[(grid[:, 0] - b1).abs().argmin()] - 1.0


def test_several_peaks_are_refused_where_they_do_not_fit():
    with pytest.raises(ValueError, match="peaks must be >= 1"):
        _net(peaks=2, extra_bounds=((-1.0, 1.0),))
    with pytest.raises(ValueError, match="peaks must be >= 1"):
        _net(peaks=0)
    loss = qq.QuadraticQLoss(_net(peaks=2), gamma=0.95)
    fast = qf.FastQuadQUpdater(loss, None, generator=_gen(0), updates_per_call=5)
    with pytest.raises(ValueError, match="imitation takes a network of one peak"):
        fast.imitate(_teacher, 1.0)


def test_a_second_action_component_is_a_separable_quadratic():
    net = _net(3, extra_bounds=((-1.0, 1.0),))
    obs = torch.randn(5, OBS_DIM, generator=_gen(4))
    a, b, c = net(obs)
    assert a.shape == b.shape == (5, 2) and c.shape == (5, 1) and (a < 0).all()
    assert (b[:, 0] > LOW).all() and (b[:, 0] < HIGH).all() and (b[:, 1].abs() < 1.0).all()
    grid = torch.stack(
        torch.meshgrid(torch.linspace(LOW, HIGH, 141), torch.linspace(-1, 1, 81), indexing="ij"),
        -1,
    ).reshape(-1, 2)  # [G, 2]
    q = net.q(obs[:, None, :].expand(-1, grid.shape[0], -1), grid[None])  # [5, G, 1]
    best = grid[q[..., 0].argmax(-1)]
    torch.testing.assert_close(best, net.greedy(obs), atol=0.051, rtol=0.0)
    torch.testing.assert_close(net.q(obs, net.greedy(obs)), net.max_value(obs))
    # the policy-file keys stay the paper's
    assert set(net.state_dict()) == set(_net().state_dict())


@pytest.mark.slow
def test_fast_path_compiled_matches_lossmodule():
    # k = 1 keeps the compile short (a few seconds on 2 cores); training uses k = 10
    _fast_vs_reference(k=1, compile=True)


def test_fast_updater_state_dict_roundtrip():
    loss = qq.QuadraticQLoss(_net())
    rep = _filled_replay(100, _gen(18))
    fast = qf.FastQuadQUpdater(loss, rep, generator=_gen(19), updates_per_call=2)
    fast.step()
    state = fast.state_dict()
    fast.step()
    fast.load_state_dict(state)
    assert fast.num_updates == 2
    torch.testing.assert_close(fast.exp_avg, state["exp_avg"])


def test_transition_replay_ring_and_layout():
    rep = TransitionReplay(5, OBS_DIM)
    td = _batch(7, _gen(20))
    rep.extend_tensordict(td[:3])
    assert len(rep) == 3
    rep.extend_tensordict(td[3:])
    assert len(rep) == 5
    back = rep.to_tensordict(rep.storage)
    # rows 5, 6 overwrote slots 0, 1; slots 2..4 hold 2..4
    order = torch.tensor([5, 6, 2, 3, 4])
    for key in td.keys(True, True):
        torch.testing.assert_close(back[key], td[key][order], msg=str(key))
    idx = rep.sample_indices((3, 4), _gen(21))
    assert idx.shape == (3, 4) and idx.max() < 5
    torch.testing.assert_close(rep.sample_indices((3, 4), _gen(21)), idx)


# --- exploration -----------------------------------------------------------------------------


def test_exploration_schedule_bounds_and_determinism():
    exp = qq.GaussianExploration(sigma_start=1.0, sigma_end=0.1, decay_steps=100)
    assert exp.sigma(0) == pytest.approx(1.0)
    assert exp.sigma(50) == pytest.approx(0.55)
    assert exp.sigma(100) == pytest.approx(0.1) and exp.sigma(10_000) == pytest.approx(0.1)
    greedy = torch.cat([torch.full((500, 1), LOW), torch.full((500, 1), HIGH)])
    wide = qq.GaussianExploration(sigma_start=50.0, sigma_end=50.0)
    a1 = wide(greedy, 0, _gen(22))
    assert torch.all((a1 >= LOW) & (a1 <= HIGH))
    assert (a1 == LOW).any() and (a1 == HIGH).any()
    torch.testing.assert_close(wide(greedy, 0, _gen(22)), a1)
    assert not torch.equal(wide(greedy, 0, _gen(23)), a1)
    mid = torch.zeros(20000, 1)
    noisy = exp(mid, 10_000, _gen(24))
    assert abs(noisy.std().item() - 0.1) < 0.01


def _teacher(obs: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
    """A teacher that overrules the command (to -2 m/s^2) where the first feature is negative."""
    return torch.where(obs[:, :1] < 0.0, torch.full_like(command, -2.0), command)


def test_the_imitation_term_matches_autograd_of_its_loss_and_adam():
    k, weight = 4, 0.7
    g = _gen(21)
    rep = _filled_replay(500, g)
    rows = rep.sample((k, 32), g)
    fast_loss, ref_loss = (qq.QuadraticQLoss(_net(hidden=64), gamma=0.95) for _ in range(2))
    fast = qf.FastQuadQUpdater(
        fast_loss, rep, generator=_gen(22), updates_per_call=k, target_update_period=100 * k
    )
    fast.imitate(_teacher, weight)
    # the teacher labels the call's minibatches once, with the weights before the call
    obs = rows[..., :OBS_DIM]  # [k, B, d]
    before = ref_loss.value_network.greedy(obs).detach()
    taught = _teacher(obs.reshape(-1, OBS_DIM), before.reshape(-1, 1)).view_as(before)
    overruled = ((taught - before).abs() > TEACHER_CHANGED).float()
    assert 0 < overruled.sum() < overruled.numel()
    opt = torch.optim.Adam(ref_loss.parameters(), lr=1e-3)
    td_losses = []
    for i in range(k):
        td_loss = ref_loss(rep.to_tensordict(rows[i]))["loss_value"]
        miss = overruled[i] * (ref_loss.value_network.greedy(obs[i]) - taught[i])
        td_losses.append(td_loss.detach())
        opt.zero_grad()
        (td_loss + weight * (miss * miss).sum(-1).mean()).backward()
        opt.step()
    torch.testing.assert_close(fast.step(rows), torch.stack(td_losses), rtol=1e-5, atol=1e-6)
    for (name, p_fast), p_ref in zip(
        fast_loss.value_network.named_parameters(), ref_loss.parameters(), strict=True
    ):
        torch.testing.assert_close(p_fast, p_ref, rtol=1e-5, atol=1e-6, msg=name)
    # and it moves B(s) towards the teacher where the teacher overruled it
    after = fast_loss.value_network.greedy(obs).detach()
    gap_before = ((before - taught) * overruled).abs().sum()
    assert ((after - taught) * overruled).abs().sum() < gap_before


@pytest.mark.parametrize("tau", [0.25, 0.8])
def test_the_expectile_loss_matches_autograd_of_its_loss_and_adam(tau):
    """Each squared TD error weighs 2 tau where Q(s, a) is below its target and 2 (1 - tau)
    where above (`td_weights`): the hand-written update against autograd and Adam."""
    k = 4
    g = _gen(31)
    rep = _filled_replay(500, g)
    rows = rep.sample((k, 32), g)
    fast_loss, ref_loss = (qq.QuadraticQLoss(_net(hidden=64), gamma=0.95) for _ in range(2))
    fast = qf.FastQuadQUpdater(
        fast_loss, rep, generator=_gen(32), updates_per_call=k, target_update_period=100 * k,
        expectile=tau,
    )  # fmt: skip
    opt = torch.optim.Adam(ref_loss.parameters(), lr=1e-3)
    losses, signs = [], set()
    for i in range(k):
        td = rep.to_tensordict(rows[i])
        a, b, c = ref_loss.value_network(td["observation"])
        pred = (a * (b - td["action"]).pow(2)).sum(-1) + c.squeeze(-1)  # [B]
        with torch.no_grad():
            target = ref_loss.td_target(td).squeeze(-1)  # [B]
        delta = pred - target
        weight = torch.where(delta.detach() > 0, 2.0 * (1.0 - tau), 2.0 * tau)
        signs |= set((delta > 0).tolist())
        loss = (weight * delta * delta).mean()
        losses.append(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert signs == {True, False}  # both weights were used
    torch.testing.assert_close(fast.step(rows), torch.stack(losses), rtol=1e-5, atol=1e-6)
    for (name, p_fast), p_ref in zip(
        fast_loss.value_network.named_parameters(), ref_loss.parameters(), strict=True
    ):
        torch.testing.assert_close(p_fast, p_ref, rtol=1e-5, atol=1e-6, msg=name)


def test_an_imitation_weight_must_be_positive():
    g = _gen(23)
    fast = qf.FastQuadQUpdater(
        qq.QuadraticQLoss(_net(hidden=16), gamma=0.95), _filled_replay(100, g), generator=g
    )
    with pytest.raises(ValueError, match="imitation weight must be > 0, got 0.0"):
        fast.imitate(_teacher, 0.0)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"td_expectile": 0.0}, r"td_expectile must be in \[0.05, 0.95\], got 0.0"),
        ({"td_expectile": 0.3, "algorithm": "td3"}, r"td_expectile = 0.3 .* got 'td3' on"),
        ({"td_expectile": 0.3, "update_path": "torchrl"}, r"got 'quadq' on 'torchrl'"),
        ({"peaks": 0}, r"peaks must be in \[1, 8\], got 0"),
        ({"peaks": 2, "algorithm": "td3"}, r"peaks = 2 .* got 'td3' and 0.0"),
        ({"peaks": 2, "shield": "shield", "shield_imitation": 1.0}, r"got 'quadq' and 1.0"),
        ({"peak_share": 1.5, "peaks": 2}, r"peak_share must be in \[0, 1\], got 1.5"),
        ({"peak_share": 0.1}, r"peak_share = 0.1 .* got peaks = 1 on"),
        ({"peak_share": 0.1, "peaks": 2, "update_path": "torchrl"}, r"peaks = 2 on 'torchrl'"),
        ({"peak_bands": True, "peaks": 2}, r"peak_bands = true .* got peak_share = 0.0 with"),
        ({"peak_share_heads": "ab"}, r"peak_share_heads must be one of \('abc', 'c'\), got 'ab'"),
    ],
)
def test_bad_expectile_and_peaks_settings_are_named(values, message):
    from marlmerge.config.training import TrainConfig

    with pytest.raises(ValueError, match=message):
        TrainConfig(**values)


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("expectile", 0.3, "expectile = 0.3"),
        ("peak_share", 0.1, "peak_share = 0.1"),
        ("lr_schedule", (0.1, 100), "lr_end_fraction = 0.1"),
    ],
)
def test_the_learner_refuses_fast_path_settings_on_the_torchrl_path(key, value, named):
    from marlmerge.learners.quadq_learner import QuadQLearner

    with pytest.raises(ValueError, match=f"{named} is a setting of the fast path's update"):
        QuadQLearner(
            OBS_DIM, 16, LOW, HIGH, gamma=0.95, lr=1e-3, target_update_period=10,
            exploration=qq.GaussianExploration(1.0, 0.1, 100, LOW, HIGH), update_path="torchrl",
            updates_per_call=1, seed=0, sample_generator=_gen(0), peaks=2, **{key: value},
        )  # fmt: skip


def test_learning_rate_decays_linearly_to_its_end_fraction_and_is_constant_by_default():
    rep = _filled_replay(200, _gen(13))

    def updater(**kw):
        return qf.FastQuadQUpdater(
            qq.QuadraticQLoss(_net()), rep, generator=_gen(14), updates_per_call=10,
            target_update_period=100, lr=1e-2, **kw,
        )  # fmt: skip

    constant = updater()
    assert all(constant.lr_at(t) == 1e-2 for t in (1, 50, 10**7))
    decaying = updater(lr_end_fraction=0.1, lr_decay_updates=100)
    assert decaying.lr_at(50) == pytest.approx(1e-2 * (1 - 0.9 * 0.5))
    assert decaying.lr_at(100) == pytest.approx(1e-3) == decaying.lr_at(10**6)
    decaying.num_updates = 40  # the scalars of updates 41-50 use their own rates
    scalars = decaying.adam_scalars()
    expected = [decaying.lr_at(t) / (1 - 0.9**t) for t in range(41, 51)]
    assert torch.allclose(scalars[:, 0], torch.tensor(expected, dtype=scalars.dtype))
    # the first chunk already moves less than the constant rate's
    before = constant.flat.clone()
    decaying.num_updates = 0
    constant.step(rep.sample((10, 32), _gen(5)))
    decaying.step(rep.sample((10, 32), _gen(5)))
    assert not torch.equal(constant.flat, decaying.flat)
    assert not torch.equal(before, decaying.flat)
    for bad in (dict(lr_end_fraction=0.0), dict(lr_end_fraction=1.5), dict(lr_decay_updates=0)):
        with pytest.raises(ValueError, match="lr_end_fraction"):
            updater(**bad)


def _seed_updater(seed, replay=None, **kw):
    """A fast-path updater of seed `seed`'s network: k = 10, target period 100."""
    return qf.FastQuadQUpdater(
        qq.QuadraticQLoss(_net(seed)), replay, generator=_gen(seed if replay is None else 14),
        updates_per_call=10, target_update_period=100, **kw,
    )  # fmt: skip


def test_fused_seeds_need_the_same_learning_rate_schedule():
    from marlmerge.learners.quadq_fused import FusedQuadQUpdates

    updater = _seed_updater
    schedule = dict(lr_end_fraction=0.1, lr_decay_updates=100)
    FusedQuadQUpdates([updater(0, **schedule), updater(1, **schedule)], compile=False)
    with pytest.raises(ValueError, match="the same learner settings"):
        FusedQuadQUpdates([updater(0, **schedule), updater(1)], compile=False)


def _flushing_now() -> bool:
    """Whether subnormal floats are flushed to zero on this thread at the moment."""
    return bool((torch.tensor([1e-39], dtype=torch.float32) * 1.0).item() == 0.0)


def test_flushed_updates_flush_only_inside_the_update():
    """`flush_denormals`: the chunk runs with subnormals flushed, the process computes as
    before around it; without the option nothing is flushed, and a short run keeps its bits
    (no subnormal arises in its first updates)."""
    from marlmerge.learners.quadq_fused import FusedQuadQUpdates

    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush subnormals")
    rep = _filled_replay(200, _gen(13))
    for make in (
        lambda on: _seed_updater(0, rep, flush_denormals=on),
        lambda on: FusedQuadQUpdates([_seed_updater(0, rep, flush_denormals=on)], compile=False),
    ):
        seen: dict[bool, list[bool]] = {}
        outs = {}
        for on in (False, True):
            up = make(on)
            inner = up._fn
            seen[on] = []

            def spy(*args, _inner=inner, _seen=seen[on]):
                _seen.append(_flushing_now())
                return _inner(*args)

            up._fn = spy
            for _ in range(3):
                rows = rep.sample((10, 32), _gen(5))
                up.step(rows if isinstance(up, qf.FastQuadQUpdater) else rows[None])
                assert not _flushing_now()
            outs[on] = up.flat.clone()
        assert seen == {False: [False] * 3, True: [True] * 3}
        assert torch.equal(outs[False], outs[True])


def test_fused_seeds_need_the_same_flush():
    from marlmerge.learners.quadq_fused import FusedQuadQUpdates

    with pytest.raises(ValueError, match="the same learner settings"):
        FusedQuadQUpdates([_seed_updater(0, flush_denormals=True), _seed_updater(1)], compile=False)
