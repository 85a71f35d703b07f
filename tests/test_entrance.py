"""The entrance: safe admissions, a counted queue, and not a single drawn vehicle lost."""

from pathlib import Path

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.sim import TrafficCore
from marlmerge.sim.drivers import desired_gap_m, entry_speed, idm
from marlmerge.validation.scenarios import drawn_arrivals

ENVS = sorted((Path(__file__).resolve().parent.parent / "envs").glob("*.toml"))
D = ScenarioConfig().driver


def test_entry_speed_waits_until_the_desired_gap_is_there():
    v, v_lead, t = 25.0, 20.0, 1.4
    s_star = desired_gap_m(v, v_lead, t, D.accel_mps2, D.comfort_brake_mps2, D.min_gap_m)
    args = (D.accel_mps2, D.comfort_brake_mps2, D.min_gap_m)
    assert entry_speed(v, s_star + 0.01, v_lead, t, *args) == v
    assert entry_speed(v, s_star - 0.01, v_lead, t, *args) == -1.0
    assert entry_speed(v, -1.0, v_lead, t, *args) == -1.0
    # at the desired gap IDM brakes at most a (v/v0)^4, gentler than b
    a = idm(v, s_star, v_lead, 30.0, t, D.accel_mps2, D.comfort_brake_mps2, D.min_gap_m, 4.0)
    assert -D.comfort_brake_mps2 < a == pytest.approx(-D.accel_mps2 * (v / 30.0) ** 4)


@pytest.mark.parametrize("flow", [1200.0, 2400.0])
def test_entering_vehicles_never_brake_harder_than_b(flow):
    # lane changes off: what an entering vehicle does is the entrance's doing alone
    cfg = ScenarioConfig().replace(
        **{"traffic.flow_vph_per_lane": flow, "driver.lane_change_threshold_mps2": 1.0e6}
    )
    core = TrafficCore(cfg, batch_size=4, seed=11)
    core.remove_ego()
    st = core.state
    worst, young_seen = 0.0, 0
    for _ in range(3000):
        core.step(np.full(4, np.nan))
        young = st.active & (st.age_s <= 5.0)
        young_seen += int(young.sum())
        worst = min(worst, float(st.a_mps2[young].min(initial=0.0)))
    assert young_seen > 10_000
    assert worst >= -cfg.driver.comfort_brake_mps2 - 1e-9
    if flow > 2000.0:  # above the entrance's capacity a queue builds and is reported
        stats = core.entrance_stats()
        assert stats["queue"].min() > 20 and stats["mean_delay_s"].min() > 5.0


@pytest.mark.parametrize("preset", ENVS, ids=lambda p: p.stem)
def test_no_drawn_arrival_is_ever_lost(preset):
    cfg = load_scenario(preset).replace(**{"traffic.flow_vph_per_lane": 2200.0})
    seeds = [5, 6]
    core = TrafficCore(cfg, batch_size=2, seed=seeds)
    core.remove_ego()
    st = core.state
    n_steps = 2000
    for _ in range(n_steps):
        core.step(np.full(2, np.nan))
    now = n_steps * cfg.sim.dt_s + cfg.traffic.warmup_s
    assert np.allclose(st.t_s, now)
    for w, seed in enumerate(seeds):
        due = sum(int((a[:, 0] <= now + 1e-9).sum()) for a in drawn_arrivals(cfg, seed, now + 5))
        assert due == st.entered[w] + st.queue[w].sum()  # entered or still waiting
    on_road_filled = st.n_active - st.entered + st.exited + 2 * st.background_collisions
    assert (on_road_filled >= 0).all()


def test_slots_grow_with_the_traffic():
    cfg = ScenarioConfig().replace(**{"traffic.flow_vph_per_lane": 100.0})
    core = TrafficCore(cfg, batch_size=1, seed=0)
    small = core.n_slots
    for i in range(60):  # a standing queue in the left lane, far beyond 100 veh/h/lane
        core.add_vehicle(0, -390.0 + 8.0 * i, 0.0, 1)
    assert core.n_slots > small and core.state.n_active[0] >= 61
    out = core.rollout(np.zeros(1), k=50)
    assert out.substeps[0] >= 1
