"""IDM against its closed forms, in isolation and inside the simulator."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.sim import EGO, LEFT, TrafficCore
from marlmerge.sim.drivers import idm_accel, idm_equilibrium_gap_m


@pytest.mark.parametrize("v", [0.0, 10.0, 25.0, 33.0])
def test_free_road_acceleration_matches_closed_form(v):
    a, v0 = 1.5, 30.0
    got = idm_accel(np.array([v]), np.array([np.inf]), np.array([v]), v0, 1.5, a, 2.0, 2.0)
    assert got[0] == pytest.approx(a * (1 - (v / v0) ** 4), rel=1e-12)


def test_standing_leader_at_jam_distance_brakes():
    # at the jam distance s0 behind a standing car a stopped vehicle must not accelerate
    got = idm_accel(np.array([0.0]), np.array([2.0]), np.array([0.0]), 30.0, 1.5, 1.5, 2.0, 2.0)
    assert got[0] == pytest.approx(0.0, abs=1e-12)


def _two_car_world(v_lead, v0_follow, headway, gap0):
    cfg = ScenarioConfig().replace(
        **{
            "road.highway_upstream_m": 3900.0,
            "road.highway_downstream_m": 3900.0,
            "traffic.flow_vph_per_lane": 0.0,
            "traffic.warmup_s": 0.0,
            "driver.lane_change_threshold_mps2": 1.0e6,  # car following only
        }
    )
    core = TrafficCore(cfg, batch_size=1, seed=0)
    core.clear_traffic()
    lead = core.add_vehicle(0, -3000.0 + gap0 + cfg.vehicle.length_m, v_lead, LEFT, v_lead, headway)
    follow = core.add_vehicle(0, -3000.0, v_lead, LEFT, v0_follow, headway)
    assert (lead, follow) == (1, 2)
    return cfg, core


def test_follower_settles_at_equilibrium_gap():
    v_lead, v0, headway = 20.0, 30.0, 1.5
    cfg, core = _two_car_world(v_lead, v0, headway, gap0=80.0)
    nan = np.full(1, np.nan)
    for _ in range(1500):  # 150 s
        core.step(nan)
    st = core.state
    gap = st.x_m[0, 1] - st.x_m[0, 2] - cfg.vehicle.length_m
    expected = idm_equilibrium_gap_m(v_lead, v0, headway, cfg.driver.min_gap_m)
    assert st.v_mps[0, 1] == pytest.approx(v_lead, abs=1e-9)  # leader cruises at its v0
    assert st.v_mps[0, 2] == pytest.approx(v_lead, abs=1e-3)
    assert gap == pytest.approx(expected, rel=1e-3)
    assert not st.active[0, EGO]
