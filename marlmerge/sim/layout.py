"""Where every quantity of the compiled core lives: codes, packed-array rows and parameters.

The core keeps B worlds in a handful of packed NumPy arrays, so that one call of a compiled kernel
takes few arguments (each array argument costs dispatch time), world-major so that everything of
one world lies together in memory while a kernel steps it:

    vf  [B, VF_ROWS, N] float64  per vehicle slot: position, speed, driver parameters, ...
    vi  [B, VI_ROWS, N] int64    per vehicle slot: lane, active, profile, id, collided
    wf  [B, WF_ROWS]    float64  per world: time, the ego's clocks, its gap vehicles, counters
    wi  [B, WI_ROWS]    int64    per world: the ego's outcome, counts, lane-list lengths, ...
    lanes [B, 3, N]     int64    each highway lane's vehicle slots, sorted downstream first,
                                 then the ramp's (`RAMP_LIST`, ramp flow only)
    sched [B, 3, Q, SC_COLS] float64  drawn arrivals (lanes RIGHT, LEFT) and ego departures (2)

and, with imperfect sensing (`[sensing]`), the sensor's state `X = (ring, noise)`:

    ring  [B * R, F]    float64  the ego's last R measured observations per world (rows
                                 b*R .. b*R+R-1, a ring with head `WI_SENSE_HEAD`), R = latency
                                 steps + 1, F the layout's length
    noise [B, QN, NZ_COLS] float64  drawn standard-normal measurement errors, a ring per world
                                 (`WI_NOISE_HEAD`, `WI_NOISE_COUNT`), one row per measurement

Slot 0 of every world is the ramp vehicle (the ego). Rows are named by the constants below; the
Python side reads them through `TrafficState`, never by number.
"""

from __future__ import annotations

import math

import numpy as np

from marlmerge.config import ScenarioConfig, latency_steps
from marlmerge.sim.observation import (
    ACCEL_SCALE_MPS2,
    POSITION_SCALE_M,
    SPEED_SCALE_MPS,
    TIME_SCALE_S,
    ego_features,
)

# NumPy integers rather than Python ints: Numba compiles a separate copy of a function for every
# literal int argument, but types a global NumPy integer as a plain int64.
RAMP, RIGHT, LEFT = np.int64(-1), np.int64(0), np.int64(1)
"""Lane codes. The ego is on `RAMP` until it overlaps the right lane, then in `RIGHT`."""
EGO = np.int64(0)
"""The ego's slot."""
EGO_STREAM = np.int64(2)
"""Row of `sched` that holds the drawn ego departures (rows 0 and 1 are the lanes' arrivals);
with ramp flow (`ramp.flow_vph > 0`) the drawn ramp arrivals instead."""
RAMP_LIST = np.int64(2)
"""Row of `lanes` that holds the ramp's vehicles in ramp flow, downstream first (its length:
`WI_N_RAMP`). The ego never is in it."""

OUTCOME_NONE, OUTCOME_SUCCESS, OUTCOME_COLLISION, OUTCOME_TRUNCATED = 0, 1, 2, 3
OUTCOME_NAMES = {0: "running", 1: "success", 2: "collision", 3: "truncated"}

NEUTRAL, COOPERATIVE, ADVERSARIAL = 0, 1, 2
"""Driver profile codes (`marlmerge.sim.drivers.Profile`)."""

# ---- vf rows: per-slot floats
VF_X, VF_V, VF_A, VF_V0, VF_T, VF_POL, VF_SINCE_LC, VF_AGE, VF_GAP, VF_VLEAD, VF_ACC = range(11)
VF_LAPSE = 11
VF_ROWS = 12
VF_ROWS_V3 = 11
"""`vf` rows of a version-3 core state (before attention lapses)."""
"""x_m (front bumper), v_mps, a_mps2 (realised over the last step), v0_mps (IDM desired speed),
headway_s (IDM T), politeness (MOBIL p), since_lane_change_s, age_s (time on the road);
scratch of the step: gap_m (bumper gap to the own-lane leader, inf if none), v_lead_mps (own
speed if none), acc (the acceleration being applied); lapse (simulator steps left of the
driver's attention lapse after this one, `driver.lapse_rate_per_h`; 0: attentive or on its
last lapsing step)."""

# ---- vi rows: per-slot ints
VI_LANE, VI_ACTIVE, VI_PROFILE, VI_ID, VI_COLLIDED = range(5)
VI_LEADER, VI_FOLLOWER, VI_FLAGS, VI_RAMP = 5, 6, 7, 8
VI_ROWS = 9
VI_ROWS_V2 = 8
"""`vi` rows of a version-2 core state (before ramp flow)."""
"""lane, active (0/1), profile, vehicle_id (unique per world, never reused), collided (awaiting
removal with the ego's episode); derived each step: leader and follower slots (-1 none), and
event flags (`EV_*` bits): collided or exited during the last call, and flags of the current
simulator step; ramp (ramp flow: 1 from the vehicle's arrival at the ramp start until it passes
the merge point x = 0, else 0)."""
EV_COLLIDED, EV_EXITED = 1, 2
"""... in a collision / off the road's downstream end during the last call."""
EV_HIT, EV_TOW, EV_YIELDING, EV_CHANGE, EV_CONTROLLED = 4, 8, 16, 32, 64
"""... in this simulator step: in a collision, to be towed away, yielding to the ramp vehicle,
changing lanes, driven by an external command."""
EV_CHOOSES, EV_JOIN = 128, 256
"""... a ramp agent choosing its own join (`ego.join = "chosen"`, a join command given), and
that command says join now."""

# ---- wf rows: per-world floats
(
    WF_T,
    WF_EGO_T,
    WF_EGO_STALL,
    WF_EGO_IN_LANE,
    WF_DELAY_SUM,
    WF_DF,
    WF_DB,
    WF_XF,
    WF_XB,
    WF_VF,
    WF_VB,
    WF_EGO_CMD,
    WF_AFTER_V0,
    WF_AFTER_T,
    WF_AFTER_POL,
    WF_RAMP_TRAVEL_SUM,
    WF_RAMP_WAIT_SUM,
    WF_LAPSE_LOGW,
) = range(18)
N_LAPSE_CLASSES = 4
"""Tilted lapse draws by class c (`WF_LAPSE_STEPS + c`, `WF_LAPSE_N + c`, `P_LAPSE_Q + c`): how
soon a lapse beginning now could close the driver's gap to the ego (`marlmerge.sim.lapses`)."""
WF_LAPSE_STEPS = WF_LAPSE_LOGW + 1
WF_LAPSE_N = WF_LAPSE_STEPS + N_LAPSE_CLASSES
WF_ROWS = WF_LAPSE_N + N_LAPSE_CLASSES
WF_ROWS_V4 = WF_LAPSE_STEPS + 2 * 2
"""`wf` rows of a version-4 core state (two lapse classes)."""
WF_ROWS_V3 = 17
"""`wf` rows of a version-3 core state (before attention lapses)."""
WF_ROWS_V2 = 15
"""`wf` rows of a version-2 core state (before ramp flow)."""
"""t_s; ego_time_s (since departure), ego_stall_s, ego_in_lane_s (since it joined the right lane);
entry_delay_s (summed over entered vehicles: entry time minus drawn arrival time); the ego's gap
vehicles after the last step: d_front_m, d_back_m (bumper gaps, sensing range if none), x_front_m,
x_back_m, v_front_mps, v_back_mps; the ego acceleration applied in the last step; the driver
parameters (v0, T, politeness) the current ego drives with once it has merged and stays on the
road as a mainline vehicle; ramp flow: the summed travel times of the ramp vehicles that
passed the merge point (from their drawn arrival at the ramp start to x = 0) and the summed
waits at the ramp's entrance of those that entered; attention lapses of the ego's gap-back
driver while the ego runs in the merge zone (`marlmerge.sim.lapses`): the summed log p/q of
their draws, and per class the steps drawn and the lapses begun."""

# ---- wi rows: per-world ints
(
    WI_OUTCOME,
    WI_EGO_COUNT,
    WI_NEXT_ID,
    WI_BG_COLLISIONS,
    WI_STEPS,
    WI_ENTERED,
    WI_EXITED,
    WI_N_RIGHT,
    WI_N_LEFT,
    WI_FRONT,
    WI_BACK,
    WI_N_ACTIVE,
    WI_HEAD_RIGHT,
    WI_HEAD_LEFT,
    WI_HEAD_EGO,
    WI_COUNT_RIGHT,
    WI_COUNT_LEFT,
    WI_COUNT_EGO,
    WI_QUEUE_RIGHT,
    WI_QUEUE_LEFT,
    WI_QUEUE_MAX,
    WI_OVERFLOW,
    WI_VEH_STEPS,
    WI_NEED,
    WI_STEP_OUTCOME,
    WI_EGO_PARTNER,
    WI_EGO_REAR,
    WI_SUBSTEPS,
    WI_EGO_STEPS,
    WI_SENSE_HEAD,
    WI_NOISE_HEAD,
    WI_NOISE_COUNT,
    WI_FILTER_COUNT,
    WI_N_RAMP,
    WI_RAMP_ENTERED,
    WI_RAMP_JOINED,
    WI_RAMP_PASSED,
    WI_RAMP_COLLISIONS,
    WI_RAMP_QUEUE,
    WI_RAMP_QUEUE_MAX,
    WI_RAMP_TOWED,
    WI_LAPSE_KEY,
) = range(42)
WI_ROWS = 42
WI_ROWS_V3 = 41
"""`wi` rows of a version-3 core state (before attention lapses)."""
WI_ROWS_V2 = 33
"""`wi` rows of a version-2 core state (before ramp flow)."""
"""ego_outcome (OUTCOME_*), ego_count, next_id, background_collisions, steps (simulator steps of
this world), entered, exited (vehicles in / out since reset), lane-list lengths (right, left),
the ego's gap-front and gap-back slots (-1 none), active vehicles, ring heads and counts of the
three `sched` streams, entrance queues (right, left) and the longest queue since reset, an
overflow flag (a kernel found no free slot: a bug), vehicle-steps simulated since reset, a
flag set by the last call when the world needs the Python side before the next (`_serve`); and
what the last call did (`WI_CALL`): the outcome reached (0 if none), the ego's collision
partner and whether it was the rear vehicle, simulator steps run, and how many of them the ego
was running at (0 when it was not running at the start of the call); the sensor's ring head, the
head and count of the drawn measurement errors, and the safety filter's interventions in the
current ego's episode (simulator steps whose command it overrode); ramp flow: the ramp list's
length, ramp vehicles that entered the ramp, joined the right lane and passed the merge point,
collisions a ramp vehicle was in (before it passed the merge point; not counted as background
collisions), the ramp's entrance queue and its longest since reset, and ramp vehicles towed away
after a collision before they passed the merge point; the key of the world's attention-lapse
draws since its reset (`marlmerge.sim.lapses.lapse_uniform`)."""
WI_ROWS_V1 = 29
"""`wi` rows of a version-1 core state (before the sensing and safety-filter rows)."""
WI_CALL = slice(WI_STEP_OUTCOME, WI_EGO_STEPS + 1)
assert WI_N_LEFT == WI_N_RIGHT + 1 and WI_HEAD_LEFT == WI_HEAD_RIGHT + 1  # indexed as base + lane
assert WI_COUNT_LEFT == WI_COUNT_RIGHT + 1 and WI_QUEUE_LEFT == WI_QUEUE_RIGHT + 1
assert WI_HEAD_EGO == WI_HEAD_RIGHT + EGO_STREAM and WI_COUNT_EGO == WI_COUNT_RIGHT + EGO_STREAM

# ---- sched columns: one drawn vehicle
SC_T, SC_V, SC_V0, SC_T_HW, SC_POL, SC_PROFILE = range(6)
SC_COLS = 6
"""arrival time (ego stream: unused), speed at the entrance (ego: at the ramp start), IDM v0,
headway T, politeness, profile code (the ego stream's driver joins traffic as NEUTRAL)."""

# ---- noise columns: the measurement errors of one measurement (standard normals)
NZ_FRONT_X, NZ_FRONT_V, NZ_BACK_X, NZ_BACK_V = range(4)
NZ_LEFT_FRONT_X, NZ_LEFT_FRONT_V, NZ_LEFT_BACK_X, NZ_LEFT_BACK_V = range(4, 8)
NZ_COLS = 8
"""Position and speed errors of the gap-front, gap-back, left-lane front and left-lane back
vehicles (the vehicle alongside is the gap-front or gap-back vehicle and shares its errors)."""

# ---- roster rows: the highway agents of a call, int64 [RO_ROWS, B, K]
RO_SLOT, RO_ID, RO_MASK, RO_EXITED = range(4)
RO_ROWS = 4
"""slot (-1 none), vehicle id, mask (still counting: on the road since the roster was drawn), and
whether it left by the downstream end during the last call (set by the kernel)."""

# ---- outputs of a rollout call
TR_X, TR_V, TR_A, TR_DF, TR_VF, TR_DB, TR_VB, TR_AB, TR_HIT = range(9)
TR_COLS = 9
"""Ego trace, one row per simulator step: x_m, v_mps, a_mps2, d_front_m, v_front_mps, d_back_m,
v_back_mps (nan/inf conventions of `marlmerge.evaluation.metrics`: inf gap and nan speed when no
vehicle is sensed), a_back_mps2 (nan if none), collided (0/1)."""

# ---- parameters: one float64 vector built from the config
_PARAMS = (
    "dt_s",
    "lane_change_every_steps",
    "x_entrance_m",
    "x_exit_m",
    "x_ramp_start_m",
    "x_overlap_m",
    "v_limit_mps",
    "success_distance_m",
    "length_m",
    "max_brake_mps2",
    "max_accel_mps2",
    "idm_a",
    "idm_b",
    "idm_s0",
    "idm_delta",
    "lc_threshold",
    "keep_right_bias",
    "safe_brake",
    "lc_cooldown_s",
    "interaction_range_m",
    "yield_max_brake",
    "yield_lc_bonus",
    "adv_v0_mps",
    "adv_headway_s",
    "adv_accel",
    "ego_headway_s",
    "ego_lo",
    "ego_hi",
    "sensing_range_m",
    "max_episode_s",
    "stall_speed_mps",
    "stall_time_s",
    "w_accel",
    "w_front",
    "w_back",
    "w_speed",
    "safe_headway_s",
    "safe_min_gap_m",
    "speed_low_fraction",
    "speed_over_scale_mps",
    "distance_active_from_m",
    "collision_penalty",
    "w_highway_speed",
    "i_sign",
    "i_w_ego_collision",
    "i_w_hard_brake_per_s",
    "i_w_stall",
    "i_w_unsafe_gap_per_s",
    "i_own_collision_penalty",
    "i_hard_brake_mps2",
    "i_cut_in_grace_s",
    "hw_lo",
    "hw_hi",
    "speed_scale_mps",
    "position_scale_m",
    "time_scale_s",
    "obs_extended",
    "time_cap_s",
    "lane_width_m",
    "ramp_offset_m",
    "merge_zone_m",
    "width_m",
    "sense_on",
    "sense_ring",
    "noise_on",
    "position_noise_std_m",
    "speed_noise_std_mps",
    "occlusion",
    "safety_filter",
    "safety_min_headway_s",
    "safety_min_gap_m",
    "w_back_headway",
    "back_headway_s",
    "w_back_ttc",
    "back_ttc_s",
    "obs_accel",
    "accel_scale_mps2",
    "w_jerk",
    "ramp_flow",
    "ramp_join_when_safe",
    "x_zone_start_m",
    "ego_join_chosen",
    "obs_on_ramp_col",
    "entrance_best",
    "ramp_zipper",
    "lc_sees_ramp",
    "lapse_p",
    "lapse_q",
    "lapse_q_1",
    "lapse_q_2",
    "lapse_q_3",
    "lapse_steps",
    "lapse_split",
    "lapse_r",
    "lapse_r_1",
    "lapse_r_2",
    "lapse_r_3",
    "lapse_force",
    "obs_join",
)
(
    P_DT,
    P_LC_EVERY,
    P_X_ENTRANCE,
    P_X_EXIT,
    P_X_RAMP_START,
    P_X_OVERLAP,
    P_V_LIMIT,
    P_SUCCESS,
    P_LEN,
    P_MAX_BRAKE,
    P_MAX_ACCEL,
    P_A,
    P_B,
    P_S0,
    P_DELTA,
    P_LC_THRESHOLD,
    P_KEEP_RIGHT,
    P_SAFE_BRAKE,
    P_LC_COOLDOWN,
    P_INTERACTION_RANGE,
    P_YIELD_MAX_BRAKE,
    P_YIELD_LC_BONUS,
    P_ADV_V0,
    P_ADV_T,
    P_ADV_A,
    P_EGO_T,
    P_EGO_LO,
    P_EGO_HI,
    P_SENSING,
    P_MAX_EPISODE,
    P_STALL_SPEED,
    P_STALL_TIME,
    P_W_ACCEL,
    P_W_FRONT,
    P_W_BACK,
    P_W_SPEED,
    P_SAFE_HEADWAY,
    P_SAFE_MIN_GAP,
    P_SPEED_LOW,
    P_SPEED_OVER,
    P_DIST_ACTIVE,
    P_COLLISION_PENALTY,
    P_W_HW_SPEED,
    P_I_SIGN,
    P_I_W_COLLISION,
    P_I_W_HARD_BRAKE,
    P_I_W_STALL,
    P_I_W_UNSAFE,
    P_I_OWN_COLLISION,
    P_I_HARD_BRAKE,
    P_I_GRACE,
    P_HW_LO,
    P_HW_HI,
    P_SPEED_SCALE,
    P_POSITION_SCALE,
    P_TIME_SCALE,
    P_OBS_EXTENDED,
    P_TIME_CAP,
    P_LANE_WIDTH,
    P_RAMP_OFFSET,
    P_MERGE_ZONE,
    P_WIDTH,
    P_SENSE_ON,
    P_SENSE_RING,
    P_NOISE_ON,
    P_POS_NOISE,
    P_SPEED_NOISE,
    P_OCCLUSION,
    P_FILTER,
    P_FILTER_HEADWAY,
    P_FILTER_GAP,
    P_W_BACK_HW,
    P_BACK_HW,
    P_W_BACK_TTC,
    P_BACK_TTC,
    P_OBS_ACCEL,
    P_ACCEL_SCALE,
    P_W_JERK,
    P_RAMP_FLOW,
    P_RAMP_WHEN_SAFE,
    P_X_ZONE_START,
    P_JOIN_CHOSEN,
    P_OBS_ON_RAMP,
    P_ENTRANCE_BEST,
    P_RAMP_ZIPPER,
    P_LC_SEES_RAMP,
    P_LAPSE_P,
    P_LAPSE_Q,
    P_LAPSE_Q_1,
    P_LAPSE_Q_2,
    P_LAPSE_Q_3,
    P_LAPSE_STEPS,
    P_LAPSE_SPLIT,
    P_LAPSE_R,
    P_LAPSE_R_1,
    P_LAPSE_R_2,
    P_LAPSE_R_3,
    P_LAPSE_FORCE,
    P_OBS_JOIN,
) = range(len(_PARAMS))
N_PARAMS = len(_PARAMS)


def lapse_step_probability(cfg: ScenarioConfig) -> float:
    """The chance that an attentive mainline driver begins an attention lapse in one simulator
    step: 1 - exp(-rate dt), rate = `driver.lapse_rate_per_h` / 3600 per second."""
    return -math.expm1(-cfg.driver.lapse_rate_per_h / 3600.0 * cfg.sim.dt_s)


def pack_params(cfg: ScenarioConfig) -> np.ndarray:
    """The config's numbers in the order of `P`, as the kernels read them (with the scales of
    the observation tables, `marlmerge.sim.observation`)."""
    r, d, e, w, i, s = cfg.road, cfg.driver, cfg.ego, cfg.reward, cfg.interaction, cfg.sim
    v_limit = r.speed_limit_mps
    values = {
        "dt_s": s.dt_s,
        "lane_change_every_steps": float(d.lane_change_every_steps),
        "x_entrance_m": r.x_entrance_m,
        "x_exit_m": r.x_exit_m,
        "x_ramp_start_m": r.x_ramp_start_m,
        "x_overlap_m": cfg.x_overlap_m,
        "v_limit_mps": v_limit,
        "success_distance_m": e.success_distance_m,
        "length_m": cfg.vehicle.length_m,
        "max_brake_mps2": cfg.vehicle.max_brake_mps2,
        "max_accel_mps2": cfg.vehicle.max_accel_mps2,
        "idm_a": d.accel_mps2,
        "idm_b": d.comfort_brake_mps2,
        "idm_s0": d.min_gap_m,
        "idm_delta": d.delta,
        "lc_threshold": d.lane_change_threshold_mps2,
        "keep_right_bias": d.keep_right_bias_mps2,
        "safe_brake": d.safe_brake_mps2,
        "lc_cooldown_s": d.lane_change_cooldown_s,
        "interaction_range_m": d.interaction_range_m,
        "yield_max_brake": d.yield_max_brake_mps2,
        "yield_lc_bonus": d.yield_lane_change_bonus_mps2,
        "adv_v0_mps": d.adversarial_speed_factor * v_limit,
        "adv_headway_s": d.adversarial_time_headway_s,
        "adv_accel": d.adversarial_accel_mps2,
        "ego_headway_s": float(np.mean(d.time_headway_s)),
        "ego_lo": e.accel_bounds_mps2[0],
        "ego_hi": e.accel_bounds_mps2[1],
        "sensing_range_m": e.sensing_range_m,
        "max_episode_s": e.max_episode_s,
        "stall_speed_mps": e.stall_speed_mps,
        "stall_time_s": e.stall_time_s,
        "w_accel": w.w_accel,
        "w_front": w.w_front,
        "w_back": w.w_back,
        "w_speed": w.w_speed,
        "safe_headway_s": w.safe_headway_s,
        "safe_min_gap_m": w.safe_min_gap_m,
        "speed_low_fraction": w.speed_low_fraction,
        "speed_over_scale_mps": w.speed_over_scale_mps,
        "distance_active_from_m": w.distance_active_from_m,
        "collision_penalty": w.collision_penalty,
        "w_highway_speed": w.w_highway_speed,
        "i_sign": i.sign,
        "i_w_ego_collision": i.w_ego_collision,
        "i_w_hard_brake_per_s": i.w_ego_hard_brake_per_s,
        "i_w_stall": i.w_ego_stall,
        "i_w_unsafe_gap_per_s": i.w_ego_unsafe_gap_per_s,
        "i_own_collision_penalty": i.own_collision_penalty,
        "i_hard_brake_mps2": i.hard_brake_mps2,
        "i_cut_in_grace_s": i.cut_in_grace_s,
        "hw_lo": s.highway_agent_accel_bounds_mps2[0],
        "hw_hi": s.highway_agent_accel_bounds_mps2[1],
        "speed_scale_mps": SPEED_SCALE_MPS,
        "position_scale_m": POSITION_SCALE_M,
        "time_scale_s": TIME_SCALE_S,
        "accel_scale_mps2": ACCEL_SCALE_MPS2,
        **_option_params(cfg),
    }
    if set(values) != set(_PARAMS):  # pragma: no cover - a developer error, caught by any test
        raise AssertionError(f"pack_params out of date: {set(values) ^ set(_PARAMS)}")
    return np.array([float(values[name]) for name in _PARAMS])


def on_ramp_column(cfg: ScenarioConfig) -> int:
    """The ego observation's column of `on_ramp` (`ego.join = "chosen"`: the last one of
    `ego_features`); 0: none."""
    return len(ego_features(cfg)) - 1 if cfg.ego.chooses_join else 0


def _option_params(cfg: ScenarioConfig) -> dict[str, float]:
    """The opt-in options: the extended observations, sensing, the safety filter, the follower's
    and the jerk reward terms, attention lapses (flags as 0/1)."""
    e, sensing, w = cfg.ego, cfg.sensing, cfg.reward
    p_lapse = lapse_step_probability(cfg)
    return {
        "obs_extended": float(e.observation != "paper"),
        "time_cap_s": e.time_to_merge_cap_s,
        "lane_width_m": cfg.road.lane_width_m,
        "ramp_offset_m": cfg.road.ramp_offset_m,
        "merge_zone_m": cfg.road.merge_zone_m,
        "width_m": cfg.vehicle.width_m,
        "sense_on": float(sensing.active),
        "sense_ring": float(latency_steps(cfg) + 1),
        "noise_on": float(sensing.noisy),
        "position_noise_std_m": sensing.position_noise_std_m,
        "speed_noise_std_mps": sensing.speed_noise_std_mps,
        "occlusion": float(sensing.occlusion),
        "safety_filter": float(e.safety_filter),
        "safety_min_headway_s": e.safety_min_headway_s,
        "safety_min_gap_m": e.safety_min_gap_m,
        "w_back_headway": w.w_back_headway,
        "back_headway_s": w.back_headway_s,
        "w_back_ttc": w.w_back_ttc,
        "back_ttc_s": w.back_ttc_s,
        "obs_accel": float(e.observation in ("extended_accel", "extended_join")),
        "w_jerk": w.w_jerk,
        "ramp_flow": float(cfg.ramp.flowing),
        "ramp_join_when_safe": float(cfg.ramp.join == "when_safe"),
        "x_zone_start_m": cfg.road.x_zone_start_m,
        "ego_join_chosen": float(e.chooses_join),
        "obs_on_ramp_col": float(on_ramp_column(cfg)),
        "entrance_best": float(cfg.traffic.entrance_lane == "best"),
        "ramp_zipper": float(cfg.ramp.cooperation == "zipper"),
        "lc_sees_ramp": float(cfg.driver.lane_change_sees_ramp),
        "lapse_p": p_lapse,
        "lapse_q": p_lapse,  # the proposal's per class (`marlmerge.sim.lapses`): natural here
        "lapse_q_1": p_lapse,
        "lapse_q_2": p_lapse,
        "lapse_q_3": p_lapse,
        "lapse_steps": float(max(round(cfg.driver.lapse_s / cfg.sim.dt_s), 1)),
        # lapse splitting (`marlmerge.sim.lapses`): off here; the core sets it per world
        "lapse_split": 0.0,
        "lapse_r": 1.0,
        "lapse_r_1": 1.0,
        "lapse_r_2": 1.0,
        "lapse_r_3": 1.0,
        "lapse_force": -1.0,
        "obs_join": float(e.observation == "extended_join"),
    }
