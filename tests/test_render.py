"""Top-down frames (`marlmerge.views.render`): shape, ego placement, clipping, the PNG writer."""

import math
import struct
import zlib

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.sim import EGO, RIGHT, TrafficCore
from marlmerge.views.render import (
    EGO_COLOUR,
    LATERAL_MARGIN_M,
    default_x_range,
    ego_lateral_m,
    render_frame,
    save_png,
)

PX_PER_M = 4.0


@pytest.fixture(scope="module")
def cfg() -> ScenarioConfig:
    return ScenarioConfig().replace(**{"traffic.warmup_s": 2.0})


@pytest.fixture()
def core(cfg: ScenarioConfig) -> TrafficCore:
    return TrafficCore(cfg, batch_size=2, seed=0)


def _ego_mask(img: np.ndarray) -> np.ndarray:
    return (img == np.array(EGO_COLOUR, dtype=np.uint8)).all(axis=2)


def _ego_columns(img: np.ndarray) -> np.ndarray:
    return np.flatnonzero(_ego_mask(img).any(axis=0))


def test_frame_shape_and_dtype(core: TrafficCore, cfg: ScenarioConfig):
    x0, x1 = default_x_range(core)
    assert x0 == pytest.approx(cfg.road.x_ramp_start_m - 30.0)
    assert x1 == pytest.approx(cfg.ego.success_distance_m + 30.0)
    img = render_frame(core, world=1, agent_slots={"highway_0": 1})
    width = math.ceil((x1 - x0) * PX_PER_M)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[1:] == (width, 3)
    assert 60 <= img.shape[0] <= 200  # two lanes, the ramp and margins at 4 px/m
    assert img.flags.writeable  # a fresh copy, not the cached background
    small = render_frame(core, x_range_m=(-120.0, 20.0), px_per_m=2.0)
    assert small.shape[1] == 280


@pytest.mark.parametrize("x_ego", [-250.0, -60.0, 30.0])
def test_ego_drawn_at_its_column(core: TrafficCore, cfg: ScenarioConfig, x_ego: float):
    core.place(0, EGO, x_ego)  # front bumper; the body covers [x - length, x]
    assert core.state.lane[0, EGO] == (RIGHT if x_ego >= cfg.x_overlap_m else -1)
    img = render_frame(core, world=0)
    x0, _ = default_x_range(core)
    cols = _ego_columns(img)
    assert cols.size > 0
    front = (x_ego - x0) * PX_PER_M
    back = (x_ego - cfg.vehicle.length_m - x0) * PX_PER_M
    assert back - 1 <= cols.min() and cols.max() <= front + 1
    assert cols.max() - cols.min() + 1 >= cfg.vehicle.length_m * PX_PER_M - 2
    # lateral: on its path (ramp, taper, right-lane centre); rows count down from the left lane
    rows = np.flatnonzero(_ego_mask(img).any(axis=1))
    y_top = 1.5 * cfg.road.lane_width_m + LATERAL_MARGIN_M
    y_mid = float(ego_lateral_m(cfg.road, x_ego - 0.5 * cfg.vehicle.length_m))
    assert 0.5 * (rows.min() + rows.max() + 1) == pytest.approx((y_top - y_mid) * PX_PER_M, abs=1)
    if x_ego < -cfg.road.merge_zone_m:  # on the ramp, below (right of) the highway's right edge
        assert rows.min() > (y_top + 0.5 * cfg.road.lane_width_m) * PX_PER_M
    if x_ego > 0:
        assert y_mid == 0.0


def test_vehicles_outside_window_are_clipped(core: TrafficCore, cfg: ScenarioConfig):
    st = core.state
    x0, x1 = default_x_range(core)
    slots = np.flatnonzero(st.active[0])[1:5]
    assert slots.size == 4
    for s, x in zip(slots, [-390.0, x0 + 1.0, x1 + 2.0, 195.0], strict=True):  # off, on edges
        core.place(0, int(s), x)
    core.place(0, EGO, x0 + 2.0)  # ego straddles the left edge
    img = render_frame(core, world=0, agent_slots={"highway_0": int(slots[1])})
    cols = _ego_columns(img)
    assert cols.size > 0 and cols.min() == 0
    core.place(0, EGO, x1 + 50.0)  # ego entirely outside
    img = render_frame(core, world=0)
    assert _ego_columns(img).size == 0


def _read_png(data: bytes) -> tuple[int, int, np.ndarray]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        tag, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(tag + body)
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    assert header is not None
    w, h, depth, colour_type = header[:4]
    assert (depth, colour_type) == (8, 2)
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 3 * w)
    return w, h, raw[:, 1:].reshape(h, w, 3)


def test_save_png_round_trip(tmp_path, core: TrafficCore):
    img = render_frame(core, x_range_m=(-60.0, 10.0))
    path = tmp_path / "frame.png"
    save_png(path, img)
    w, h, pixels = _read_png(path.read_bytes())
    assert (h, w) == img.shape[:2]
    np.testing.assert_array_equal(pixels, img)
    with pytest.raises(ValueError):
        save_png(tmp_path / "bad.png", img.astype(np.float32))
