"""Top-down RGB frames of one world of a `TrafficCore`, rasterised with NumPy only.

Image axes: columns run along the highway (`x_m`, direction of travel left to right), rows run
across it with the left lane at the top and the ramp at the bottom. The lateral coordinate used
here, `y_m`, is metres to the LEFT of the right lane's centreline (right lane centre 0, left lane
centre `lane_width_m`, ramp centreline `-ramp_offset_m` at the merge-zone start).

Reference point: the core's bumper gap is `x_leader - x - length_m` with one length for every
vehicle, which is consistent with any fixed reference point. We draw `x_m` as the FRONT bumper
(body over `[x - length_m, x]`), matching "success: past the merge point by this distance" and
the ego's start "at the ramp start".

Ramp drawing: inside the merge zone `[-merge_zone_m, 0]` the ramp centreline moves linearly from
`-ramp_offset_m` onto the right lane's centreline, as in the core. Upstream of the merge zone the
core's ramp is only a 1-D path; we draw it approaching at a shallow angle (`RAMP_APPROACH_SLOPE`)
so that it visibly comes from the side. The ego is drawn on that path (at its body's midpoint).

The static road layer is cached per (road, window, scale); a frame copies it and draws vehicles.
"""

from __future__ import annotations

import math
import struct
import zlib
from functools import lru_cache
from pathlib import Path

import numpy as np

from marlmerge.config import RoadConfig
from marlmerge.sim import EGO, TrafficCore
from marlmerge.sim.drivers import Profile

RAMP_APPROACH_SLOPE = 0.06
"""Lateral metres the drawn ramp moves away from the highway per metre upstream of the zone."""
RAMP_STUB_M = 30.0
"""The ramp is drawn from this far upstream of the ramp start."""
WINDOW_MARGIN_M = 30.0
"""Default window: ramp start - margin .. success line + margin."""
LATERAL_MARGIN_M = 2.5
"""Grass above the left lane and below the ramp."""
DASH_M, DASH_PERIOD_M = 3.0, 12.0
"""Dashed lane line: 3 m painted every 12 m (fixed to the road, not to the window)."""

Colour = tuple[int, int, int]
GRASS: Colour = (78, 118, 64)
ASPHALT: Colour = (68, 68, 72)
ZONE_ASPHALT: Colour = (96, 90, 80)
"""The taper of the merge zone (ramp lane outside the right lane)."""
MARKING: Colour = (232, 232, 232)
ZONE_LINE: Colour = (250, 200, 40)
"""Cross lines at the ramp start, merge-zone start and merge point."""
SUCCESS_LIGHT: Colour = (245, 245, 245)
SUCCESS_DARK: Colour = (15, 15, 15)
"""The success line is a chequered flag across both lanes, two squares wide."""
EGO_COLOUR: Colour = (235, 25, 25)
EGO_OUTLINE: Colour = (255, 255, 255)
PROFILE_COLOURS: dict[int, Colour] = {
    int(Profile.NEUTRAL): (125, 145, 180),
    int(Profile.COOPERATIVE): (50, 185, 70),
    int(Profile.ADVERSARIAL): (245, 140, 25),
}
AGENT_MARKER: Colour = (0, 235, 255)
"""Dot on the highway agents (their fill keeps the profile colour)."""
COLLIDED_COLOUR: Colour = (25, 25, 25)
COLLIDED_OUTLINE: Colour = (255, 0, 255)
GAP_FRONT_OUTLINE: Colour = (255, 225, 0)
GAP_BACK_OUTLINE: Colour = (185, 95, 255)
"""Outlines of the ego's gap-front and gap-back vehicles."""


def ego_lateral_m(road: RoadConfig, x_m: np.ndarray | float) -> np.ndarray:
    """Drawn lateral position `y_m` of the ramp centreline (the ego's path) at `x_m`.

    road: `RoadConfig`. Approach upstream of the zone, linear taper inside it, right-lane centre
    (0) downstream of the merge point.
    """
    x = np.asarray(x_m, dtype=np.float64)
    zone, off = road.merge_zone_m, road.ramp_offset_m
    taper = off * np.minimum(x, 0.0) / zone
    approach = -off - RAMP_APPROACH_SLOPE * (-zone - x)
    return np.where(x < -zone, approach, taper)


class _View:
    """Metres -> pixel coordinates (floats; pixel c covers [c, c+1), its centre is c + 0.5)."""

    def __init__(self, road: RoadConfig, x_range_m: tuple[float, float], px_per_m: float):
        self.x0, self.x1 = float(x_range_m[0]), float(x_range_m[1])
        if not self.x1 > self.x0:
            raise ValueError(f"x_range_m must be increasing, got {x_range_m}")
        if not px_per_m > 0:
            raise ValueError(f"px_per_m must be > 0, got {px_per_m}")
        self.ppm = float(px_per_m)
        lw = road.lane_width_m
        self.y_top = 1.5 * lw + LATERAL_MARGIN_M
        # the same height whatever the window shows: down to the most lateral drawn ramp point
        x_low = road.x_ramp_start_m - RAMP_STUB_M
        y_low = min(-0.5 * lw, float(ego_lateral_m(road, x_low)) - 0.5 * road.ramp_width_m)
        self.y_bottom = y_low - LATERAL_MARGIN_M
        self.width = int(math.ceil((self.x1 - self.x0) * self.ppm - 1e-6))
        self.height = int(math.ceil((self.y_top - self.y_bottom) * self.ppm))

    def col(self, x: np.ndarray | float) -> np.ndarray | float:
        return (x - self.x0) * self.ppm

    def row(self, y: np.ndarray | float) -> np.ndarray | float:
        return (self.y_top - y) * self.ppm


def _fill_columns(
    img: np.ndarray, top: np.ndarray, bot: np.ndarray, colour: Colour, c0: int = 0
) -> None:
    """Fill, in columns c0..c0+len(top)-1, the pixels whose centre row lies in [top, bot).

    top, bot: float pixel rows per column (NaN = nothing in that column).
    """
    n = top.shape[0]
    if n == 0:
        return
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(top) & np.isfinite(bot) & (bot > top)
    if not ok.any():
        return
    idx = np.flatnonzero(ok)
    i0, i1 = int(idx[0]), int(idx[-1]) + 1  # only the columns that hold something
    top, bot = top[i0:i1], bot[i0:i1]
    h = img.shape[0]
    r0 = max(int(math.floor(float(np.nanmin(top)))), 0)
    r1 = min(int(math.ceil(float(np.nanmax(bot)))), h)
    if r1 <= r0:
        return
    centres = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5
    with np.errstate(invalid="ignore"):
        mask = (centres >= top[None, :]) & (centres < bot[None, :])
    img[r0:r1, c0 + i0 : c0 + i1][mask] = colour


def _rect(
    img: np.ndarray,
    c_lo: float,
    c_hi: float,
    r_lo: float,
    r_hi: float,
    colour: Colour,
    grow_px: int = 0,
) -> None:
    """Filled axis-aligned rectangle in float pixel coordinates, grown by `grow_px` whole pixels."""
    h, w = img.shape[:2]
    a = max(int(math.ceil(c_lo - 0.5)) - grow_px, 0)
    b = min(int(math.ceil(c_hi - 0.5)) + grow_px, w)
    r = max(int(math.ceil(r_lo - 0.5)) - grow_px, 0)
    s = min(int(math.ceil(r_hi - 0.5)) + grow_px, h)
    if a < b and r < s:
        img[r:s, a:b] = colour


@lru_cache(maxsize=8)
def _background(
    road: RoadConfig, success_m: float, x_range_m: tuple[float, float], px_per_m: float
) -> np.ndarray:
    """The static road layer, [H, W, 3] uint8, read-only (cached)."""
    v = _View(road, x_range_m, px_per_m)
    lw, rw, zone = road.lane_width_m, road.ramp_width_m, road.merge_zone_m
    img = np.empty((v.height, v.width, 3), dtype=np.uint8)
    img[:] = GRASS
    xs = v.x0 + (np.arange(v.width) + 0.5) / v.ppm  # x of every column centre
    nan = np.full(v.width, np.nan)
    t_px = max(1.0, round(0.2 * v.ppm))  # line thickness in pixels

    def band(
        y_lo: np.ndarray | float, y_hi: np.ndarray | float, where: np.ndarray, colour: Colour
    ) -> None:
        """Fill y in [y_lo, y_hi] over the columns where `where`."""
        top = np.where(where, v.row(np.broadcast_to(y_hi, xs.shape)), nan)
        bot = np.where(where, v.row(np.broadcast_to(y_lo, xs.shape)), nan)
        _fill_columns(img, top, bot, colour)

    def line(y: np.ndarray | float, where: np.ndarray, colour: Colour = MARKING) -> None:
        r = np.where(where, v.row(np.broadcast_to(y, xs.shape)), nan)
        _fill_columns(img, r - 0.5 * t_px, r + 0.5 * t_px, colour)

    def cross(x: float, y_lo: float, y_hi: float, colour: Colour, thick: float = 1.0) -> None:
        c = v.col(x)
        _rect(img, c - 0.5 * thick * t_px, c + 0.5 * thick * t_px, v.row(y_hi), v.row(y_lo), colour)

    on_highway = (xs >= road.x_entrance_m) & (xs <= road.x_exit_m)
    on_ramp = (xs >= road.x_ramp_start_m - RAMP_STUB_M) & (xs <= 0.0)
    in_zone = on_ramp & (xs >= -zone)
    y_ramp = ego_lateral_m(road, xs)
    # ramp lane (the taper in a distinct shade), then the highway over it
    band(y_ramp - 0.5 * rw, y_ramp + 0.5 * rw, on_ramp & ~in_zone, ASPHALT)
    band(y_ramp - 0.5 * rw, y_ramp + 0.5 * rw, in_zone, ZONE_ASPHALT)
    band(-0.5 * lw, 1.5 * lw, on_highway, ASPHALT)
    # markings: solid outer edges, dashed lane divider, dashed right edge along the taper
    dashed = np.mod(xs, DASH_PERIOD_M) < DASH_M
    outer = y_ramp - 0.5 * rw
    taper_open = in_zone & (outer < -0.5 * lw)
    line(1.5 * lw, on_highway)
    line(0.5 * lw, on_highway & dashed)
    line(-0.5 * lw, on_highway & ~taper_open)
    line(-0.5 * lw, taper_open & dashed)
    line(outer, on_ramp & (outer < -0.5 * lw))
    line(y_ramp + 0.5 * rw, on_ramp & ~in_zone)
    # cross lines: ramp start, merge-zone start (across the ramp), merge point, success
    y_start = float(ego_lateral_m(road, road.x_ramp_start_m))
    cross(road.x_ramp_start_m, y_start - 0.5 * rw, y_start + 0.5 * rw, ZONE_LINE)
    y_zone = -road.ramp_offset_m
    cross(-zone, y_zone - 0.5 * rw, -0.5 * lw, ZONE_LINE)
    cross(0.0, -0.5 * lw, 0.5 * lw, ZONE_LINE)
    sq = lw / 6.0  # chequer square side, m
    for i in range(12):
        for j in range(2):
            c = v.col(success_m + (j - 1) * sq)
            r = v.row(1.5 * lw - i * sq)
            colour = SUCCESS_DARK if (i + j) % 2 else SUCCESS_LIGHT
            _rect(img, c, c + sq * v.ppm, r, r + sq * v.ppm, colour)
    img.flags.writeable = False
    return img


def default_x_range(core: TrafficCore) -> tuple[float, float]:
    """Ramp start - 30 m .. success line + 30 m (about [-280, 80] m by default)."""
    cfg = core.cfg
    return (cfg.road.x_ramp_start_m - WINDOW_MARGIN_M, cfg.ego.success_distance_m + WINDOW_MARGIN_M)


def render_frame(
    core: TrafficCore,
    world: int = 0,
    agent_slots: dict[str, int] | None = None,
    x_range_m: tuple[float, float] | None = None,
    px_per_m: float = 4.0,
) -> np.ndarray:
    """Top-down RGB frame of world `world`: [H, W, 3] uint8.

    W = ceil((x_range_m[1] - x_range_m[0]) * px_per_m) (1440 by default); H covers the two lanes,
    the ramp and margins (about 105 px by default). `agent_slots` maps highway agent names to slots;
    those vehicles carry a cyan dot. Ego red; mainline vehicles filled by profile (cooperative
    green, neutral blue-grey, adversarial orange); the ego's gap-front vehicle outlined yellow,
    its gap-back vehicle violet; collided vehicles dark with a magenta outline. Vehicles outside
    the window are clipped. `render_scene` adds the heads-up line and the legend.
    """
    cfg = core.cfg
    road = cfg.road
    x_range = tuple(map(float, x_range_m)) if x_range_m is not None else default_x_range(core)
    ppm = float(px_per_m)
    img = _background(road, float(cfg.ego.success_distance_m), x_range, ppm).copy()
    v = _View(road, x_range, ppm)
    w = img.shape[1]
    st = core.state
    length = cfg.vehicle.length_m
    half_w = 0.5 * cfg.vehicle.width_m
    lw = road.lane_width_m

    active = st.active[world]
    x = st.x_m[world]
    c_hi = v.col(x)
    c_lo = v.col(x - length)
    visible = active & (c_hi > 0.0) & (c_lo < w)
    visible[EGO] = False
    agents = set((agent_slots or {}).values())
    gaps = core.ego_gaps()
    roles = {int(gaps.front[world]): GAP_FRONT_OUTLINE, int(gaps.back[world]): GAP_BACK_OUTLINE}
    rows_c = v.row(np.clip(st.lane[world], 0, 1) * lw)  # lane-centre rows of mainline vehicles
    hw_px = half_w * ppm
    for s in np.flatnonzero(visible).tolist():
        a, b, rc = float(c_lo[s]), float(c_hi[s]), float(rows_c[s])
        fill = PROFILE_COLOURS.get(int(st.profile[world, s]), PROFILE_COLOURS[0])
        outline = roles.get(s)
        if st.collided[world, s]:
            fill, outline = COLLIDED_COLOUR, COLLIDED_OUTLINE
        if outline is not None:
            _rect(img, a, b, rc - hw_px, rc + hw_px, outline, grow_px=max(1, round(ppm / 4)))
        _rect(img, a, b, rc - hw_px, rc + hw_px, fill)
        if s in agents:
            cm, dot = 0.5 * (a + b), max(1.5, 0.4 * ppm)
            _rect(img, cm - dot, cm + dot, rc - dot, rc + dot, AGENT_MARKER)

    if active[EGO] and c_hi[EGO] > 0.0 and c_lo[EGO] < w:
        # on its drawn path, at the lateral position of the body's midpoint
        rc = float(v.row(ego_lateral_m(road, x[EGO] - 0.5 * length)))
        a, b = float(c_lo[EGO]), float(c_hi[EGO])
        fill, outline = (
            (COLLIDED_COLOUR, COLLIDED_OUTLINE)
            if st.collided[world, EGO]
            else (EGO_COLOUR, EGO_OUTLINE)
        )
        _rect(img, a, b, rc - hw_px, rc + hw_px, outline, grow_px=1)
        _rect(img, a, b, rc - hw_px, rc + hw_px, fill)
    return img


VIEWS = ("merge", "follow")
"""`merge`: the ramp start to past the success line at 4 px/m; `follow`: 120 m around the ego at
8 px/m."""
FOLLOW_BEHIND_M, FOLLOW_AHEAD_M, FOLLOW_PX_PER_M = 60.0, 60.0, 8.0
HUD_BG: Colour = (20, 22, 28)
HUD_TEXT: Colour = (235, 235, 235)
LEGEND = (
    ("ego", EGO_COLOUR, None),
    ("gap-front", PROFILE_COLOURS[0], GAP_FRONT_OUTLINE),
    ("gap-back", PROFILE_COLOURS[0], GAP_BACK_OUTLINE),
    ("cooperative", PROFILE_COLOURS[int(Profile.COOPERATIVE)], None),
    ("neutral", PROFILE_COLOURS[int(Profile.NEUTRAL)], None),
    ("adversarial", PROFILE_COLOURS[int(Profile.ADVERSARIAL)], None),
    ("highway agent", PROFILE_COLOURS[0], AGENT_MARKER),
    ("collided", COLLIDED_COLOUR, COLLIDED_OUTLINE),
)


def view_range(core: TrafficCore, world: int, view: str) -> tuple[tuple[float, float], float]:
    """(x range in m, px per m) of a named view."""
    if view == "merge":
        return default_x_range(core), 4.0
    if view == "follow":
        x = float(core.state.x_m[world, EGO])
        return (x - FOLLOW_BEHIND_M, x + FOLLOW_AHEAD_M), FOLLOW_PX_PER_M
    raise ValueError(f"view must be one of {VIEWS}, got {view!r}")


def hud_text(core: TrafficCore, world: int = 0) -> str:
    """The heads-up line: time, the ego's speed and acceleration, its gaps, the outcome."""
    from marlmerge.sim import OUTCOME_NAMES

    st, g = core.state, core.ego_gaps()
    front = f"{g.d_front_m[world]:5.1f} m" if g.front[world] >= 0 else "  none"
    back = f"{g.d_back_m[world]:5.1f} m" if g.back[world] >= 0 else "  none"
    return (
        f"t {st.ego_time_s[world]:5.1f} s   ego {st.v_mps[world, EGO]:4.1f} m/s "
        f"{st.a_mps2[world, EGO]:+5.2f} m/s2   gap front {front}  back {back}   "
        f"x {st.x_m[world, EGO]:+6.1f} m   {OUTCOME_NAMES[int(st.ego_outcome[world])]}"
    )


@lru_cache(maxsize=4)
def _font(size: int):  # noqa: ANN202 - a PIL font
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def render_scene(
    core: TrafficCore,
    world: int = 0,
    agent_slots: dict[str, int] | None = None,
    view: str = "merge",
    caption: str = "",
) -> np.ndarray:
    """A frame people can read: the heads-up line (`hud_text`, and `caption`) above the road
    (`render_frame` in the `view`), the legend below. [H, W, 3] uint8."""
    from PIL import Image, ImageDraw

    x_range, ppm = view_range(core, world, view)
    road = render_frame(core, world, agent_slots, x_range, ppm)
    w = road.shape[1]
    font = _font(14)
    hud_h, legend_h = 26, 24
    img = Image.new("RGB", (w, hud_h + road.shape[0] + legend_h), HUD_BG)
    img.paste(Image.fromarray(road), (0, hud_h))
    draw = ImageDraw.Draw(img)
    text = hud_text(core, world) + (f"   {caption}" if caption else "")
    draw.text((8, 5), text, fill=HUD_TEXT, font=font)
    x, y = 8, hud_h + road.shape[0] + 5
    for label, fill, outline in LEGEND:
        if outline is not None and label != "highway agent":
            draw.rectangle((x - 2, y - 2, x + 24, y + 13), fill=outline)
        draw.rectangle((x, y, x + 22, y + 11), fill=fill)
        if label == "highway agent":
            draw.rectangle((x + 8, y + 3, x + 14, y + 8), fill=outline)
        draw.text((x + 28, y - 2), label, fill=HUD_TEXT, font=font)
        x += 34 + int(draw.textlength(label, font=font)) + 14
        if x > w - 60:
            break
    return np.asarray(img, dtype=np.uint8).copy()


class Window:
    """A window that shows frames at a fixed rate (pygame, the `[video]` extra)."""

    def __init__(self, title: str, fps: float):
        try:
            import pygame
        except ImportError:
            raise ImportError(
                'render_mode="human" needs pygame: pip install -c constraints.txt ".[video]"'
            ) from None
        self._pg = pygame
        pygame.init()
        pygame.display.set_caption(title)
        self._screen = None
        self._clock = pygame.time.Clock()
        self.fps = fps

    def show(self, frame: np.ndarray) -> None:
        pg = self._pg
        h, w = frame.shape[:2]
        if self._screen is None or self._screen.get_size() != (w, h):
            self._screen = pg.display.set_mode((w, h))
        pg.event.pump()
        self._screen.blit(
            pg.surfarray.make_surface(np.ascontiguousarray(frame.swapaxes(0, 1))), (0, 0)
        )
        pg.display.flip()
        self._clock.tick(self.fps)

    def close(self) -> None:
        self._pg.display.quit()
        self._pg.quit()


def write_video(path: str | Path, frames: list[np.ndarray], fps: float) -> Path:
    """Frames [H, W, 3] uint8 to `.mp4` (H.264, imageio-ffmpeg) or `.gif` (imageio)."""
    path = Path(path)
    if path.suffix.lower() not in (".mp4", ".gif"):
        raise ValueError(f"video path must end in .mp4 or .gif, got {str(path)!r}")
    if not frames:
        raise ValueError("no frames to write")
    try:
        import imageio.v2 as imageio
    except ImportError:
        raise ImportError(
            'videos need imageio: pip install -c constraints.txt ".[video]"'
        ) from None
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        imageio.mimsave(path, frames, duration=1000.0 / fps, loop=0)
        return path
    h, w = frames[0].shape[:2]
    ph, pw = -h % 16, -w % 16  # H.264 wants sizes in multiples of 16: pad with the HUD colour
    with imageio.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=16) as out:
        for f in frames:
            if ph or pw:
                f = np.pad(f, ((0, ph), (0, pw), (0, 0)), constant_values=0)
            out.append_data(f)
    return path


def save_png(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB uint8 image [H, W, 3] as an 8-bit PNG (zlib + struct, no dependencies)."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be uint8 [H, W, 3], got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    raw = np.empty((h, 1 + 3 * w), dtype=np.uint8)
    raw[:, 0] = 0  # filter type 0 (None) on every scanline
    raw[:, 1:] = img.reshape(h, 3 * w)

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8-bit truecolour, no interlace
    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )
    Path(path).write_bytes(png)
