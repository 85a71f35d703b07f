"""`marlmerge stress`: the search finds planted failure regions, repeats itself for a seed, and
writes a report whose presets reproduce what it found."""

import json

import numpy as np
import pytest

from marlmerge.config import load_scenario
from marlmerge.evaluation.space import SPACE
from marlmerge.evaluation.stress import Search, StressSettings, snap_roads, stress
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS

PLANTED = [((0, 0.8, 1.0), (5, 0.0, 0.2)), ((3, 0.0, 0.15), (9, 0.85, 1.0))]
"""Two regions of the unit cube, each two conditions on two dimensions."""


class Planted:
    """A toy evaluator: a road fails with probability 0.9 inside a planted region, 0.01 outside."""

    def __init__(self) -> None:
        self.episodes = 0

    def outcomes(self, u: np.ndarray, seeds: np.ndarray) -> np.ndarray:
        self.episodes += len(u)
        inside = np.zeros(len(u), dtype=bool)
        for region in PLANTED:
            inside |= np.all([(lo <= u[:, d]) & (u[:, d] <= hi) for d, lo, hi in region], axis=0)
        draw = np.array([np.random.default_rng(int(s)).uniform() for s in seeds])
        fails = draw < np.where(inside, 0.9, 0.01)
        return np.where(fails, OUTCOME_COLLISION, OUTCOME_SUCCESS)


def _search(seed: int = 0) -> Search:
    s = StressSettings(seed=seed, points=400, episodes_per_point=2, regions=2, rounds=3)
    search = Search(Planted(), s)
    u0, fail0 = search.explore()
    for _ in range(s.regions):
        region = search.focus(u0, fail0)
        assert region is not None
        search.regions.append(region)
    return search


def test_the_search_finds_both_planted_regions_and_their_keys():
    found = _search().regions
    assert sorted(sorted(r.dims) for r in found) == [[0, 5], [3, 9]]
    for r in found:  # the box of each region lies on its planted conditions
        planted = next(p for p in PLANTED if sorted(d for d, _, _ in p) == sorted(r.dims))
        for d, lo, hi in planted:
            assert lo - 0.1 <= r.lo[d] < r.hi[d] <= hi + 0.1
        assert r.search_failure_rate > 0.5


def test_a_seed_repeats_the_search_and_another_seed_searches_anew():
    a, b, c = _search(0), _search(0), _search(1)
    assert all(np.array_equal(x.lo, y.lo) for x, y in zip(a.regions, b.regions, strict=True))
    assert not np.array_equal(a.regions[0].centre, c.regions[0].centre)


def test_roads_snap_to_the_centres_of_their_levels():
    u = np.random.default_rng(0).uniform(size=(50, len(SPACE)))
    snapped = snap_roads(u, 4)
    road = [i for i, d in enumerate(SPACE) if d.key in ("ramp_length_m", "merge_zone_m")]
    assert set(np.unique(snapped[:, road])) <= {0.125, 0.375, 0.625, 0.875}
    others = [i for i in range(len(SPACE)) if i not in road]
    assert np.array_equal(snapped[:, others], u[:, others])


@pytest.mark.parametrize(
    "bad, match",
    [({"box": 0.0}, "box"), ({"points": 0}, "points"), ({"elite_fraction": 0.9}, "elite")],
)
def test_bad_settings_name_the_key(bad, match):
    with pytest.raises(ValueError, match=match):
        StressSettings(**bad)


@pytest.mark.slow
def test_a_small_stress_run_writes_a_report_whose_presets_load(tmp_path):
    s = StressSettings(points=64, episodes_per_point=2, regions=2, rounds=1, verify_episodes=40)
    report = stress("hold", tmp_path, settings=s, clip=False, log=lambda _: None)
    saved = json.loads((tmp_path / "report.json").read_text())
    assert {"policy", "episodes", "failure_rate", "regions", "wall_s"} <= set(saved)
    assert saved["episodes"] == report["episodes"] >= 64 * 2 * 2 + 40
    assert 0 < saved["failure_rate"] < 1  # holding speed fails somewhere, not everywhere
    for row in saved["regions"]:
        cfg = load_scenario(row["preset"])
        assert cfg.sample.active and row["ci95"][0] <= row["failure_rate"] <= row["ci95"][1]
    assert "| rank |" in (tmp_path / "regions.md").read_text()


def test_a_region_preset_draws_inside_the_region_on_a_fixed_road(tmp_path):
    from marlmerge.evaluation.space import write_preset
    from marlmerge.evaluation.stress import Region, region_preset
    from marlmerge.sim.streams import draw_world_scenario

    d = len(SPACE)
    lo, hi = np.zeros(d), np.ones(d)
    lo[0], hi[0], lo[15], hi[15] = 0.8, 0.9, 0.5, 0.75  # flow, and the merge zone's level
    region = Region([0, 15], lo, hi, snap_roads(((lo + hi) / 2)[None], 4)[0], 0.5)
    cfg = load_scenario(write_preset(tmp_path / "r.toml", region_preset(region, "r", "")))
    assert cfg.road.merge_zone_m == pytest.approx(40 + 0.625 * 110)  # its level's centre
    for i in range(20):
        w = draw_world_scenario(cfg, np.random.default_rng(i))
        assert 1800 - 1e-6 <= w.traffic.flow_vph_per_lane <= 2000 + 1e-6
        assert 45 <= w.road.speed_limit_mph <= 80 and w.road.merge_zone_m == cfg.road.merge_zone_m
