"""Scripted traffic on its own: safe, physical, and carrying the configured flow."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.sim import TrafficCore


@pytest.mark.parametrize("mix", ["default", "cooperative", "adversarial"])
def test_scripted_traffic_runs_10000_steps_without_collision(mix):
    cfg = ScenarioConfig()
    if mix != "default":
        shares = {"cooperative": (1.0, 0.0, 0.0), "adversarial": (0.0, 0.0, 1.0)}[mix]
        cfg = cfg.replace(
            **{
                "driver.mix_cooperative": shares[0],
                "driver.mix_neutral": shares[1],
                "driver.mix_adversarial": shares[2],
            }
        )
    core = TrafficCore(cfg, batch_size=4, seed=3)
    core.remove_ego()
    st = core.state
    conserved = st.n_active - st.entered + st.exited  # [B] the road filled at reset
    nan = np.full(4, np.nan)
    exits = 0
    min_v = np.inf
    for _ in range(10_000):
        ev = core.step(nan)
        exits += int(ev.exited.sum())
        assert not ev.collided.any()
        min_v = min(min_v, float(core.state.v_mps[core.state.active].min()))
    assert st.background_collisions.sum() == 0
    assert min_v >= 0.0
    # nothing is lost: on the road = filled at reset + entered - exited; below capacity nobody
    # waits long at the entrance (only Poisson clumps queue)
    assert np.array_equal(st.n_active - st.entered + st.exited, conserved)
    assert st.max_queue.max() <= 8
    assert (st.entry_delay_s / st.entered).max() < 3.0
    # throughput over 1000 s and 2 lanes matches the configured arrival flow within 10 %
    expected = 4 * 2 * cfg.traffic.flow_vph_per_lane * 1000.0 / 3600.0
    assert exits == pytest.approx(expected, rel=0.10)


def test_ramp_vehicle_and_traffic_with_idm_ego_never_reverses():
    core = TrafficCore(ScenarioConfig(), batch_size=8, seed=5)
    for _ in range(2000):
        ev = core.step(np.full(8, -4.5))  # full braking: the ego stops, never reverses
        assert (core.state.v_mps[core.state.active] >= 0.0).all()
        core.next_ego(ev.ego_outcome != 0)
