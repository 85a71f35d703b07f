"""The draws ahead of arrivals and departures, compiled: NumPy's `Generator` draws, bit for bit.

`Streams` (`marlmerge.sim.streams`) owns each world's seeded generators. Drawing a chunk of
arrivals through NumPy costs about ten calls of a few microseconds each, and the core draws a
chunk per world and stream as its traffic needs it: in steady flow that was about a fifth of a
`rollout` call's wall time. `draw_ahead` makes those draws for every world that needs them in
one compiled call. It reads each generator's own state through the bit generator's C interface
(`BitGenerator.ctypes`: the state's address and the `next_uint64` / `next_double` functions) and
ports NumPy's algorithms: `random` and `uniform` from `next_double`, `exponential` and `normal`
with NumPy's 256-step ziggurats (the tables Numba's own `Generator` support uses). The numbers,
their order and every generator's state afterwards are those of the NumPy calls the streams
made before (`Streams.arrivals`, `ramp_arrivals`, `departures`, which stay as the reference and
for the proposal's tilted draws); `tests/test_draws.py` checks them against NumPy.

The C functions are called through their addresses, passed in at run time (`bitgen_functions`),
so the compiled code holds no address of this process and can be cached on disk. With
`NUMBA_DISABLE_JIT=1` (every kernel as plain Python) they are called through `ctypes`.
"""

from __future__ import annotations

import ctypes

import numpy as np
from llvmlite import ir
from numba import config, types
from numba.extending import intrinsic

# NumPy's ziggurat tables, as Numba's `Generator` support carries them (private to Numba, whose
# version `constraints.txt` pins; `tests/test_draws.py` would catch a change)
from numba.np.random._constants import (
    fe_double,
    fi_double,
    ke_double,
    ki_double,
    we_double,
    wi_double,
    ziggurat_exp_r,
    ziggurat_nor_inv_r,
    ziggurat_nor_r,
)

from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO_STREAM,
    NEUTRAL,
    SC_POL,
    SC_PROFILE,
    SC_T,
    SC_T_HW,
    SC_V,
    SC_V0,
    WF_T,
    WI_COUNT_RIGHT,
    WI_HEAD_RIGHT,
    WI_NEED,
)

CHUNK = 32
"""Vehicles drawn per stream at a time (`Streams` draws the same chunks)."""

# columns of a world's draw parameters, [B, DP_COLS] (`marlmerge.sim.streams.draw_params`)
(
    DP_FLOW_ON,  # 1: the lanes have arrivals (flow > 0)
    DP_MEAN_GAP_S,  # 3600 / flow: the mean of the exponential time gaps, s
    DP_ENTRY_MEAN,  # entry speed: normal(mean, std) clipped to [lo, hi], m/s
    DP_ENTRY_STD,
    DP_ENTRY_LO,
    DP_ENTRY_HI,
    DP_V0_LO,  # desired-speed factor, uniform(lo, hi), times the limit
    DP_V0_HI,
    DP_V_LIMIT,
    DP_HW_LO,  # time headway, s
    DP_HW_HI,
    DP_POL_LO,  # politeness
    DP_POL_HI,
    DP_CDF0,  # the profile mix's normalised cumulative sums
    DP_CDF1,
    DP_CDF2,
    DP_START_LO,  # ramp vehicles' start speed, uniform(lo, hi), m/s
    DP_START_HI,
    DP_RAMP_GAP_S,  # ramp flow: 3600 / ramp flow, s
) = range(19)
DP_COLS = 19


def bitgen_functions() -> np.ndarray:
    """[2] the addresses of PCG64's `next_uint64` and `next_double` (the same C functions for
    every PCG64 generator; each call passes the generator's own state)."""
    c = np.random.PCG64(0).ctypes
    return np.array(
        [ctypes.cast(c.next_uint64, ctypes.c_void_p).value,
         ctypes.cast(c.next_double, ctypes.c_void_p).value],
        dtype=np.uint64,
    )  # fmt: skip


def state_address(g: np.random.Generator) -> int:
    """The address of `g`'s bit generator state, for `draw_ahead` (PCG64 only)."""
    if not isinstance(g.bit_generator, np.random.PCG64):
        raise TypeError(f"compiled draws need PCG64 generators, got {type(g.bit_generator)}")
    return int(g.bit_generator.ctypes.state_address)


def _call_u64_intrinsic(tyctx, fn, state):  # type: ignore[no-untyped-def]
    """uint64 fn(state) for a C function's address `fn` and a bit generator's state address."""
    sig = types.uint64(types.uint64, types.uint64)

    def codegen(cgctx, builder, sig, args):  # type: ignore[no-untyped-def]
        fnty = ir.FunctionType(ir.IntType(64), (ir.IntType(64),))
        return builder.call(builder.inttoptr(args[0], fnty.as_pointer()), (args[1],))

    return sig, codegen


def _call_double_intrinsic(tyctx, fn, state):  # type: ignore[no-untyped-def]
    """double fn(state), as `_call_u64`."""
    sig = types.float64(types.uint64, types.uint64)

    def codegen(cgctx, builder, sig, args):  # type: ignore[no-untyped-def]
        fnty = ir.FunctionType(ir.DoubleType(), (ir.IntType(64),))
        return builder.call(builder.inttoptr(args[0], fnty.as_pointer()), (args[1],))

    return sig, codegen


if config.DISABLE_JIT:  # the kernels run as Python: the same C functions, called through ctypes
    _U64 = ctypes.CFUNCTYPE(ctypes.c_uint64, ctypes.c_void_p)
    _DOUBLE = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_void_p)

    def _call_u64(fn: int, state: int) -> np.uint64:
        return np.uint64(_U64(int(fn))(int(state)))

    def _call_double(fn: int, state: int) -> float:
        return float(_DOUBLE(int(fn))(int(state)))

else:
    _call_u64 = intrinsic(_call_u64_intrinsic)
    _call_double = intrinsic(_call_double_intrinsic)


@kernel(inline=True)
def next_double(fns: np.ndarray, st: np.uint64) -> float:
    """`Generator.random()`: a double in [0, 1)."""
    return _call_double(fns[1], st)


@kernel(inline=True)
def standard_exponential(fns: np.ndarray, st: np.uint64) -> float:
    """NumPy's `random_standard_exponential` (ziggurat)."""
    while True:
        ri = _call_u64(fns[0], st)
        ri >>= np.uint64(3)
        idx = ri & np.uint64(0xFF)
        ri >>= np.uint64(8)
        x = ri * we_double[idx]
        if ri < ke_double[idx]:
            return x
        if idx == 0:
            return ziggurat_exp_r - np.log1p(-_call_double(fns[1], st))
        if (fe_double[idx - 1] - fe_double[idx]) * _call_double(fns[1], st) + fe_double[
            idx
        ] < np.exp(-x):
            return x


@kernel(inline=True)
def standard_normal(fns: np.ndarray, st: np.uint64) -> float:
    """NumPy's `random_standard_normal` (ziggurat)."""
    while True:
        r = _call_u64(fns[0], st)
        idx = r & np.uint64(0xFF)
        r >>= np.uint64(8)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = rabs * wi_double[idx]
        if r & np.uint64(1):
            x = -x
        if rabs < ki_double[idx]:
            return x
        if idx == 0:
            while True:
                xx = -ziggurat_nor_inv_r * np.log1p(-_call_double(fns[1], st))
                yy = -np.log1p(-_call_double(fns[1], st))
                if yy + yy > xx * xx:
                    if (rabs >> np.uint64(8)) & np.uint64(1):
                        return -(ziggurat_nor_r + xx)
                    return ziggurat_nor_r + xx
        elif (fi_double[idx - 1] - fi_double[idx]) * _call_double(fns[1], st) + fi_double[
            idx
        ] < np.exp(-0.5 * x * x):
            return x


@kernel(inline=True)
def _uniform_col(
    fns: np.ndarray, st: np.uint64, ring: np.ndarray, first: int, col: int, lo: float, hi: float
) -> None:
    """`Generator.uniform(lo, hi, size=CHUNK)` into the ring's rows from `first` on, column
    `col` (ring [Q, SC_COLS]: one world's stream; the rows wrap around)."""
    q, span = ring.shape[0], hi - lo
    for i in range(CHUNK):
        ring[(first + i) % q, col] = lo + span * next_double(fns, st)


@kernel(inline=True)
def _times(
    fns: np.ndarray, st: np.uint64, ring: np.ndarray, first: int, on: bool,
    mean_gap_s: float, t_last_s: float,
) -> None:  # fmt: skip
    """`t_last + cumsum(Generator.exponential(mean_gap, size=CHUNK))` into column SC_T (inf,
    and nothing drawn, when `on` is false)."""
    q, total = ring.shape[0], 0.0
    for i in range(CHUNK):
        if on:
            total += mean_gap_s * standard_exponential(fns, st)
            ring[(first + i) % q, SC_T] = t_last_s + total
        else:
            ring[(first + i) % q, SC_T] = np.inf


@kernel(inline=True)
def _drivers(fns: np.ndarray, st: np.uint64, ring: np.ndarray, first: int, dp: np.ndarray) -> None:
    """`Streams._drivers`: desired speed, time headway, politeness."""
    q = ring.shape[0]
    _uniform_col(fns, st, ring, first, SC_V0, dp[DP_V0_LO], dp[DP_V0_HI])
    for i in range(CHUNK):
        ring[(first + i) % q, SC_V0] *= dp[DP_V_LIMIT]
    _uniform_col(fns, st, ring, first, SC_T_HW, dp[DP_HW_LO], dp[DP_HW_HI])
    _uniform_col(fns, st, ring, first, SC_POL, dp[DP_POL_LO], dp[DP_POL_HI])


@kernel(inline=True)
def _cap_entry(ring: np.ndarray, first: int) -> None:
    """Nobody enters above its desired speed."""
    q = ring.shape[0]
    for i in range(CHUNK):
        j = (first + i) % q
        ring[j, SC_V] = min(ring[j, SC_V], ring[j, SC_V0])


@kernel(inline=True)
def _arrivals(
    fns: np.ndarray, st: np.uint64, ring: np.ndarray, first: int, dp: np.ndarray, t_last_s: float
) -> None:
    """`Streams.arrivals` into the ring's rows from `first` on."""
    q = ring.shape[0]
    _times(fns, st, ring, first, dp[DP_FLOW_ON] > 0.0, dp[DP_MEAN_GAP_S], t_last_s)
    mean, std = dp[DP_ENTRY_MEAN], dp[DP_ENTRY_STD]
    for i in range(CHUNK):
        v = mean + std * standard_normal(fns, st)
        ring[(first + i) % q, SC_V] = min(max(v, dp[DP_ENTRY_LO]), dp[DP_ENTRY_HI])
    _drivers(fns, st, ring, first, dp)
    for i in range(CHUNK):  # `Generator.choice` over the mix: uniforms searched in its cdf
        u = next_double(fns, st)
        profile = 0.0
        for c in range(DP_CDF0, DP_CDF2 + 1):
            if dp[c] <= u:
                profile += 1.0
        ring[(first + i) % q, SC_PROFILE] = profile
    _cap_entry(ring, first)


@kernel(inline=True)
def _ramp_vehicles(
    fns: np.ndarray, st: np.uint64, ring: np.ndarray, first: int, dp: np.ndarray,
    t_last_s: float, flowing: bool,
) -> None:  # fmt: skip
    """`Streams.ramp_arrivals` (flowing) or `Streams.departures` into the ring's rows."""
    q = ring.shape[0]
    if flowing:
        _times(fns, st, ring, first, True, dp[DP_RAMP_GAP_S], t_last_s)
    else:
        for i in range(CHUNK):
            ring[(first + i) % q, SC_T] = 0.0
    _uniform_col(fns, st, ring, first, SC_V, dp[DP_START_LO], dp[DP_START_HI])
    _drivers(fns, st, ring, first, dp)
    for i in range(CHUNK):
        ring[(first + i) % q, SC_PROFILE] = NEUTRAL
    if flowing:
        _cap_entry(ring, first)


@kernel(inline=True)
def _last_time(wi: np.ndarray, sched: np.ndarray, b: int, stream: int) -> float:
    """`TrafficCore._last_time`: the last drawn arrival's time (-inf when none is left)."""
    count = wi[b, WI_COUNT_RIGHT + stream]
    if count == 0:
        return -np.inf
    return sched[b, stream, (wi[b, WI_HEAD_RIGHT + stream] + count - 1) % sched.shape[2], SC_T]


@kernel
def draw_ahead(
    wf: np.ndarray, wi: np.ndarray, sched: np.ndarray, worlds: np.ndarray, start: int,
    k: int, dt: float, flowing: bool, states: np.ndarray, fns: np.ndarray, dps: np.ndarray,
) -> int:  # fmt: skip
    """`TrafficCore._serve`'s draws for worlds[start:] (before a call of `k` steps): each lane's
    arrivals until two are left and the last lies beyond the call, the ramp's as well with ramp
    flow (`flowing`), else two departures left. states [B, 3] the bit generators' state
    addresses of the lanes' and the ego stream's generators, dps [B, DP_COLS] the worlds' draw
    parameters. Returns -1 when done, or the index into `worlds` of the world whose ring is
    full: grow the rings and call again from there (a world's draws resume where they stopped)."""
    q = sched.shape[2]
    for r in range(start, worlds.shape[0]):
        b = worlds[r]
        horizon = wf[b, WF_T] + (k + 1) * dt
        for stream in range(3):
            ramp = stream == EGO_STREAM
            while wi[b, WI_COUNT_RIGHT + stream] < 2 or (
                (not ramp or flowing) and _last_time(wi, sched, b, stream) <= horizon
            ):
                count = wi[b, WI_COUNT_RIGHT + stream]
                if count + CHUNK + 1 > q:
                    return r
                first = wi[b, WI_HEAD_RIGHT + stream] + count
                t_last = max(_last_time(wi, sched, b, stream), 0.0)
                ring, st = sched[b, stream], states[b, stream]
                if ramp:
                    _ramp_vehicles(fns, st, ring, first, dps[b], t_last, flowing)
                else:
                    _arrivals(fns, st, ring, first, dps[b], t_last)
                wi[b, WI_COUNT_RIGHT + stream] = count + CHUNK
        wi[b, WI_NEED] = 0
    return -1
