"""Traffic measurements from vehicle samples, the same for both simulators.

A run of either simulator is recorded as `FlowSamples`: one row per vehicle per simulator step
(time, vehicle id, lane, front-bumper position in metres from the road's start, speed).
`flow_metrics` turns it into the quantities the validation compares: throughput at a detector,
density and space-mean speed over a section, and time headways at the detector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SECTION_M = (100.0, 500.0)
"""Measurement section (road positions): 100 m past the entrance to 100 m before the exit of
the default 600 m road (merge-point axis: -300 m to +100 m)."""
DETECTOR_M = 500.0
"""Detector position for throughput and time headways (merge-point axis: +100 m)."""


@dataclass
class FlowSamples:
    """Vehicle samples of one run, one row per vehicle and simulator step ([M] each)."""

    t_s: np.ndarray
    vehicle: np.ndarray  # int: unique within the run
    lane: np.ndarray  # int: 0 right, 1 left
    pos_m: np.ndarray  # from the road's start
    v_mps: np.ndarray


def detector_crossings(s: FlowSamples, x_det_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(crossing time [C], lane [C]) of every vehicle passing `x_det_m`, linearly interpolated
    between the two samples around the crossing."""
    order = np.lexsort((s.t_s, s.vehicle))
    veh, t, x, lane = s.vehicle[order], s.t_s[order], s.pos_m[order], s.lane[order]
    same = veh[1:] == veh[:-1]
    cross = same & (x[:-1] < x_det_m) & (x[1:] >= x_det_m)
    i = np.flatnonzero(cross)
    frac = (x_det_m - x[i]) / np.maximum(x[i + 1] - x[i], 1e-12)
    return t[i] + frac * (t[i + 1] - t[i]), lane[i + 1]


def time_headways(t_cross: np.ndarray, lane: np.ndarray) -> np.ndarray:
    """Time headways (s) between consecutive vehicles of the same lane at a detector."""
    gaps = []
    for ln in np.unique(lane):
        tt = np.sort(t_cross[lane == ln])
        gaps.append(np.diff(tt))
    return np.concatenate(gaps) if gaps else np.zeros(0)


def flow_metrics(
    s: FlowSamples,
    t_from_s: float,
    n_lanes: int = 2,
    section_m: tuple[float, float] = SECTION_M,
    x_det_m: float = DETECTOR_M,
) -> dict[str, float]:
    """Steady-state measurements of one run from `t_from_s` on: throughput_vphpl (detector
    crossings per hour and lane), density_vpkmpl (vehicles in the section per km and lane),
    space_mean_speed_mps (mean speed of the vehicles in the section), headway_p10_s and
    headway_median_s (time headways at the detector)."""
    keep = s.t_s >= t_from_s
    t = s.t_s[keep]
    times = np.unique(t)
    dt = float(np.median(np.diff(times))) if times.size > 1 else 0.1
    duration_s = times.size * dt
    in_sec = (s.pos_m[keep] >= section_m[0]) & (s.pos_m[keep] < section_m[1])
    length_km = (section_m[1] - section_m[0]) / 1000.0
    t_cross, lane = detector_crossings(s, x_det_m)
    ok = t_cross >= t_from_s
    t_cross, lane = t_cross[ok], lane[ok]
    heads = time_headways(t_cross, lane)
    return {
        "throughput_vphpl": t_cross.size / (duration_s / 3600.0) / n_lanes,
        "density_vpkmpl": in_sec.sum() / times.size / (length_km * n_lanes),
        "space_mean_speed_mps": float(np.mean(s.v_mps[keep][in_sec])) if in_sec.any() else 0.0,
        "headway_p10_s": float(np.percentile(heads, 10)) if heads.size else float("nan"),
        "headway_median_s": float(np.median(heads)) if heads.size else float("nan"),
    }
