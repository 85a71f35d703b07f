"""Every named reward term against its formula, through the kernel's own functions."""

import math

import pytest

from marlmerge.config import InteractionConfig, ScenarioConfig
from marlmerge.sim.reward import (
    INTERACTION_TERMS,
    ego_step_terms,
    highway_step_terms,
    proximity,
    speed_polygon,
)

CFG = ScenarioConfig()
R, INTER = CFG.reward, CFG.interaction
V_LIMIT = CFG.road.speed_limit_mps


def test_proximity_and_speed_polygon_shapes():
    assert proximity(20.0, 10.0) == 0.0
    assert proximity(0.0, 10.0) == 1.0
    assert proximity(5.0, 10.0) == pytest.approx(0.25)
    assert speed_polygon(0.0, V_LIMIT, 0.6, 5.0) == pytest.approx(1.0)
    assert speed_polygon(0.8 * V_LIMIT, V_LIMIT, 0.6, 5.0) == 0.0
    assert speed_polygon(V_LIMIT + 2.5, V_LIMIT, 0.6, 5.0) == pytest.approx(0.5)


def test_each_ego_term_follows_its_formula():
    v, v_back, d_f, d_b = 20.0, 25.0, 10.0, 12.0
    t = ego_step_terms(CFG, -2.0, -50.0, v, d_f, d_b, v_back, collided=True)
    safe_f = R.safe_min_gap_m + R.safe_headway_s * v
    safe_b = R.safe_min_gap_m + R.safe_headway_s * v_back
    assert t["acceleration"] == pytest.approx(-R.w_accel * 2.0)
    assert t["gap_front"] == pytest.approx(-R.w_front * (1 - d_f / safe_f) ** 2)
    assert t["gap_back"] == pytest.approx(-R.w_back * (1 - d_b / safe_b) ** 2)
    assert t["speed"] == 0.0  # 20 m/s lies in the dead band [0.6 v_limit, v_limit]
    assert t["collision"] == -R.collision_penalty
    slow = ego_step_terms(CFG, 0.0, -50.0, 5.0, 100.0, 100.0, 25.0)
    v_low = R.speed_low_fraction * V_LIMIT
    assert slow["speed"] == pytest.approx(-R.w_speed * (v_low - 5.0) / v_low)
    assert slow["gap_front"] == slow["gap_back"] == slow["collision"] == 0.0


def test_ego_distance_terms_are_off_far_upstream():
    far = ego_step_terms(CFG, 0.0, R.distance_active_from_m - 1.0, 20.0, 1.0, 1.0, 25.0)
    near = ego_step_terms(CFG, 0.0, R.distance_active_from_m, 20.0, 1.0, 1.0, 25.0)
    assert far["gap_front"] == far["gap_back"] == 0.0
    assert near["gap_front"] < 0.0 and near["gap_back"] < 0.0


def test_each_highway_driving_term_follows_its_formula():
    v, gap = 20.0, 8.0
    t = highway_step_terms(CFG, a_mps2=-1.5, v_mps=v, gap_m=gap)
    safe = R.safe_min_gap_m + R.safe_headway_s * v
    assert t["acceleration"] == pytest.approx(-R.w_accel * 1.5)
    assert t["gap_front"] == pytest.approx(-R.w_front * (1 - gap / safe) ** 2)
    assert t["speed"] == pytest.approx(-R.w_highway_speed * (V_LIMIT - v) / V_LIMIT)
    fast = highway_step_terms(CFG, v_mps=V_LIMIT + 5.0)
    assert fast["speed"] == pytest.approx(-R.w_highway_speed * 5.0 / R.speed_over_scale_mps)
    assert highway_step_terms(CFG, collided=True)["collision"] == -INTER.own_collision_penalty
    assert all(v == 0.0 for k, v in highway_step_terms(CFG).items() if k != "speed")


def _interaction(**kw):
    return {k: v for k, v in highway_step_terms(CFG, **kw).items() if k in INTERACTION_TERMS}


def test_interaction_terms_are_zero_when_the_agent_did_not_contribute():
    assert not any(_interaction(ego_truncated=True).values())  # not a gap vehicle
    assert not any(_interaction(ego_a_mps2=-4.5, is_back=True).values())  # hard brake, not front
    assert not any(_interaction(is_front=True, is_back=False).values())  # no failure at all
    assert not any(_interaction(collided=True).values())  # a collision with someone else


def test_each_interaction_term_credits_the_contributing_agent():
    dt = CFG.sim.dt_s
    t = _interaction(hit_ego=True, collided=True, ego_rear=True)  # the ego ran into it
    assert t["ego_collision"] == INTER.w_ego_collision
    t = _interaction(ego_a_mps2=-INTER.hard_brake_mps2, is_front=True)
    assert t["ego_hard_brake"] == pytest.approx(INTER.w_ego_hard_brake_per_s * dt)
    milder = _interaction(ego_a_mps2=-INTER.hard_brake_mps2 + 0.1, is_front=True)
    assert milder["ego_hard_brake"] == 0
    assert _interaction(ego_truncated=True, is_back=True)["ego_stall"] == INTER.w_ego_stall
    t = _interaction(is_front=True, is_back=True, close_front=0.5, close_back=0.25)
    assert t["ego_unsafe_gap"] == pytest.approx(INTER.w_ego_unsafe_gap_per_s * dt * 0.75)
    coop = CFG.replace(**{"interaction.sign": -1.0})
    flipped = highway_step_terms(coop, hit_ego=True, collided=True, ego_rear=True)
    assert flipped["ego_collision"] == -INTER.w_ego_collision


def test_blame_in_a_collision_with_the_ego():
    # the agent rear-ends an ego that joined the lane 5 s ago: its own fault, no credit
    t = highway_step_terms(CFG, hit_ego=True, collided=True, ego_rear=False, ego_in_lane_s=5.0)
    assert t["ego_collision"] == 0.0 and t["collision"] == -INTER.own_collision_penalty
    # the ego cut in 0.3 s before: the ego is to blame, the agent is credited and not charged
    grace = InteractionConfig().cut_in_grace_s
    t = highway_step_terms(
        CFG, hit_ego=True, collided=True, ego_rear=False, ego_in_lane_s=0.3 * grace
    )
    assert t["ego_collision"] == INTER.w_ego_collision and t["collision"] == 0.0
    assert math.isclose(
        highway_step_terms(CFG, hit_ego=True, collided=True, ego_rear=True)["collision"], 0.0
    )


FOLLOWER = CFG.replace(**{"reward.w_back_headway": 2.0, "reward.w_back_ttc": 3.0})


def test_follower_terms_are_off_by_default():
    t = ego_step_terms(CFG, 0.0, -20.0, 15.0, 50.0, 3.0, 28.0)  # a fast follower 3 m behind
    assert t["back_headway"] == t["back_ttc"] == 0.0
    assert tuple(t)[-3:] == ("back_headway", "back_ttc", "jerk")


def test_follower_terms_follow_their_formulas():
    v, v_back, d_b = 15.0, 25.0, 5.0  # headway 0.2 s, time-to-collision 0.5 s
    t = ego_step_terms(FOLLOWER, 0.0, -20.0, v, 50.0, d_b, v_back)
    w = FOLLOWER.reward
    g_hw = (1 - d_b / (w.back_headway_s * v_back)) ** 2
    g_ttc = (1 - d_b / (w.back_ttc_s * (v_back - v))) ** 2
    assert t["back_headway"] == pytest.approx(-w.w_back_headway * g_hw) and g_hw > 0
    assert t["back_ttc"] == pytest.approx(-w.w_back_ttc * g_ttc) and g_ttc > 0


@pytest.mark.parametrize(
    ("v", "d_back", "v_back", "x"),
    [
        (15.0, 40.0, 25.0, -20.0),  # headway 1.6 s, time-to-collision 4 s: safe
        (30.0, 5.0, 25.0, -20.0),  # 0.2 s behind but slower: headway only
        (15.0, 5.0, 25.0, -200.0),  # far upstream: off
        (15.0, 150.0, 29.06, -20.0),  # no gap-back vehicle: the virtual one at the range edge
    ],
)
def test_follower_terms_are_zero_when_safe(v, d_back, v_back, x):
    t = ego_step_terms(FOLLOWER, 0.0, x, v, 50.0, d_back, v_back)
    assert t["back_ttc"] == 0.0
    if d_back > 20.0 or x < -150.0:
        assert t["back_headway"] == 0.0


def test_follower_terms_in_a_hand_built_scene():
    import numpy as np
    from scenes import scene

    over = {"reward.w_back_headway": 1.0, "reward.w_back_ttc": 1.0}
    unsafe = scene((5.0, 15.0), right=[(-3.0, 27.0)], overrides=over).rollout(np.zeros(1), k=1)
    safe = scene((5.0, 15.0), right=[(-60.0, 15.0)], overrides=over).rollout(np.zeros(1), k=1)
    back_hw, back_ttc = 5, 6
    assert unsafe.ego_terms[0, back_hw] < 0.0 and unsafe.ego_terms[0, back_ttc] < 0.0
    assert safe.ego_terms[0, back_hw] == 0.0 and safe.ego_terms[0, back_ttc] == 0.0


def test_jerk_term_follows_its_formula_and_is_off_by_default():
    assert ego_step_terms(CFG, 1.0, -50.0, 20.0, 80.0, 80.0, 20.0, False, 3.0)["jerk"] == 0.0
    cfg = CFG.replace(**{"reward.w_jerk": 0.25})
    got = ego_step_terms(cfg, 1.0, -50.0, 20.0, 80.0, 80.0, 20.0, False, -3.0)
    assert got["jerk"] == -0.25 * 9.0


def test_jerk_term_charges_each_change_of_the_applied_acceleration_once():
    import numpy as np
    from scenes import scene

    core = scene((-140.0, 20.0), overrides={"reward.w_jerk": 0.5})
    jerk = [float(core.rollout(np.array([a])).ego_terms[0, 7]) for a in (1.0, 1.0, -1.0, 0.5)]
    # the first step of the episode has nothing to change from; a held command costs nothing
    assert jerk == [0.0, 0.0, -0.5 * 2.0**2, -0.5 * 1.5**2]


def test_the_total_reward_is_bit_for_bit_the_sum_of_the_papers_terms():
    import numpy as np

    from marlmerge.sim.reward import total_reward

    rng = np.random.default_rng(0)
    terms = -rng.exponential(size=(1000, 7)) * rng.integers(0, 2, size=(1000, 7))
    with_zero_terms = np.concatenate([terms, np.zeros((1000, 1))], axis=1)
    assert np.array_equal(total_reward(with_zero_terms), terms.sum(axis=1))
    assert total_reward(with_zero_terms).tobytes() == terms.sum(axis=1).tobytes()


def test_the_total_reward_adds_its_terms_left_to_right_from_plus_zero():
    """`total_reward` is one accumulate, not a loop of 8 array additions: the same bits as the
    loop, signed zeros included (a total is never -0.0), for a batch and for one world."""
    import numpy as np

    from marlmerge.sim.reward import total_reward

    def loop(terms):
        total = 0.0 + terms[..., 0]
        for i in range(1, terms.shape[-1]):
            total = total + terms[..., i]
        return total

    rng = np.random.default_rng(1)
    terms = rng.normal(size=(500, 8)) * rng.choice([1e-9, 1.0, 1e7], size=(500, 8))
    zeros = rng.random((500, 8)) < 0.4
    terms[zeros] = rng.choice([0.0, -0.0], size=int(zeros.sum()))
    terms[:5] = -0.0  # all terms negative zeros
    assert total_reward(terms).tobytes() == loop(terms).tobytes()
    assert not np.signbit(total_reward(terms[:5])).any()
    for row in terms[:50]:
        assert np.asarray(total_reward(row)).tobytes() == np.asarray(loop(row)).tobytes()
