"""Driver profiles change what happens to a ramp vehicle, in the direction their names promise."""

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim import OUTCOME_NONE, OUTCOME_SUCCESS, TrafficCore


def _success_rate(mix, seed=11, episodes=120, batch=40):
    cfg = ScenarioConfig().replace(
        **{
            "driver.mix_cooperative": mix[0],
            "driver.mix_neutral": mix[1],
            "driver.mix_adversarial": mix[2],
        }
    )
    core = TrafficCore(cfg, batch_size=batch, seed=seed)
    hold = np.zeros(batch)  # the ramp vehicle simply holds its speed
    outcomes = []
    while len(outcomes) < episodes:
        ev = core.step(hold)
        done = ev.ego_outcome != OUTCOME_NONE
        outcomes += ev.ego_outcome[done].tolist()
        core.next_ego(done)
    return np.mean(np.array(outcomes[:episodes]) == OUTCOME_SUCCESS)


def test_hold_speed_merges_more_often_among_cooperative_than_adversarial_drivers():
    coop = _success_rate((1.0, 0.0, 0.0))
    adv = _success_rate((0.0, 0.0, 1.0))
    neutral = _success_rate((0.0, 1.0, 0.0))
    assert coop > neutral > adv
    assert coop - adv > 0.1
