# Ref: issue 4 item 8 (protection and fault latch); issue 6 item 7 (encoder/Hall plausibility)
"""Gateware :class:`~foc_servo.hdl.protect.Protection` against its golden model, clock by clock,
and the fault-to-trip latency of every input.

For speed the per-clock inputs and the golden model's per-clock outputs sit in ROMs of a
simulation-only wrapper that drives the block and counts mismatching clocks in gateware; the
testbench only ticks.
"""

import numpy as np
from amaranth.hdl import Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.fixed import shape_range
from ...hdl.protect import FAULT_LAYOUT, FAULTS, LIMITS, Protection
from ..harness import Progress, pack_words, simulate
from ..models.protect import INPUTS, RAM_INPUTS, protect_np

__all__ = ["compare", "run", "stimulus", "measure_latency"]

_OUT_LAYOUT = data.StructLayout({"trip": 1, "present": FAULT_LAYOUT, "first": FAULT_LAYOUT,
                                 "seen": FAULT_LAYOUT, "uv_armed": 1})


def _episodes(rng, n, rate, mean_len):
    """A 0/1 array with episodes starting at ``rate`` per clock, lengths 1 … ~4·mean_len."""
    x = np.zeros(n, dtype=np.int64)
    starts = np.flatnonzero(rng.random(n) < rate)
    lengths = np.minimum(rng.geometric(1 / mean_len, size=starts.size), 4 * mean_len)
    for s, ln in zip(starts.tolist(), lengths.tolist()):
        x[s:s + ln] = 1
    return x


def stimulus(count, *, seed=0, current_width=16, udc_shape=signed(16), speed_width=16,
             limits="ports"):
    """Seeded per-clock inputs for ``count`` clocks: random fault sequences.

    Registers change in segments of 200 … 2000 clocks (limits over their whole range, often
    mid-range; under-voltage enabled in 70 % of segments; all causes enabled in 80 %, a random
    mask otherwise). Pin faults come as episodes of 1 … ~12 clocks, about one per 400 clocks
    per pin; current samples in 30 % of clocks (1 % beyond the limit, extremes included), U_dc
    samples in 20 % (drifting in and out of the window), speed samples in 5 %; invalid samples
    carry junk that must be ignored; ``clear`` in 1 clock of 30.

    ``limits="ram"``: the limits as writes of the limit port (:data:`RAM_INPUTS`): a segment's
    four in four consecutive clocks from its start, in a random order, and a random rewrite in
    1 clock of 300; a sample's payload is held for 8 clocks after its ``valid`` (the steps
    compare it then; the Top's payloads are registers), junk after that.

    Returns
    -------
    dict of int64 arrays
        One per name in :data:`foc_servo.sim.models.protect.INPUTS` (``limits="ram"``:
        :data:`~foc_servo.sim.models.protect.RAM_INPUTS`).
    """
    rng = np.random.default_rng([seed, 11])
    n = count
    w, sw = current_width, speed_width
    i_lo, i_hi = shape_range(signed(w))
    u_lo, u_hi = shape_range(udc_shape)
    s_lo, s_hi = shape_range(signed(sw))
    cols = {k: np.zeros(n, dtype=np.int64) for k in INPUTS}

    t = 0
    while t < n:
        ln = int(rng.integers(200, 2001))
        sl = slice(t, min(n, t + ln))
        m = sl.stop - sl.start
        pick = rng.random()
        cols["oc_limit"][sl] = (rng.integers(0, 1 << w) if pick < 0.2 else
                                rng.integers(i_hi // 8, i_hi + 1) if pick < 0.9 else
                                rng.choice([0, i_hi, i_hi + 1, (1 << w) - 1]))
        uv = int(rng.integers(u_lo, u_hi + 1)) if rng.random() < 0.2 else \
            int(rng.integers(u_lo // 4, u_hi // 2))
        ov = int(rng.integers(uv, u_hi + 1))
        cols["uv_limit"][sl], cols["ov_limit"][sl] = uv, ov
        cols["uv_enable"][sl] = rng.random() < 0.7
        cols["os_limit"][sl] = rng.integers(0, 1 << sw) if rng.random() < 0.2 else \
            rng.integers(s_hi // 8, s_hi + 1)
        cols["mask"][sl] = (1 << len(FAULTS)) - 1 if rng.random() < 0.8 else \
            rng.integers(0, 1 << len(FAULTS))

        # Currents: mostly inside the limit, 1 % anywhere (extremes included).
        lim = int(min(cols["oc_limit"][sl.start], i_hi))
        for p in "abc":
            v = rng.integers(-lim, lim + 1, size=m)
            wild = rng.random(m) < 0.01
            v[wild] = rng.choice([i_lo, i_hi, i_lo + 1, 0], size=int(wild.sum())) \
                if rng.random() < 0.3 else rng.integers(i_lo, i_hi + 1, size=int(wild.sum()))
            cols[p][sl] = v
        # U_dc: a random walk across the window, sometimes beyond it.
        span = max(ov - uv, 1)
        walk = np.cumsum(rng.integers(-span // 50 - 1, span // 50 + 2, size=m))
        start = rng.integers(uv - span // 4, ov + span // 4 + 1)
        cols["udc"][sl] = np.clip(start + walk, u_lo, u_hi)
        # Speed: inside the limit, 2 % anywhere.
        slim = int(min(cols["os_limit"][sl.start], s_hi))
        v = rng.integers(-slim, slim + 1, size=m)
        wild = rng.random(m) < 0.02
        v[wild] = rng.integers(s_lo, s_hi + 1, size=int(wild.sum()))
        cols["speed"][sl] = v
        t += ln

    cols["fault_n"] = 1 - _episodes(rng, n, 1 / 400, 3)
    cols["oc_comp"] = _episodes(rng, n, 1 / 400, 3)
    cols["encoder_illegal"] = _episodes(rng, n, 1 / 400, 1)
    cols["hall_invalid"] = _episodes(rng, n, 1 / 400, 3)
    cols["encoder_hall"] = _episodes(rng, n, 1 / 400, 1)
    cols["i_valid"] = (rng.random(n) < 0.3).astype(np.int64)
    cols["udc_valid"] = (rng.random(n) < 0.2).astype(np.int64)
    cols["speed_valid"] = (rng.random(n) < 0.05).astype(np.int64)
    cols["clear"] = (rng.random(n) < 1 / 30).astype(np.int64)
    # Junk in the clocks without a valid sample (limits="ram": from 8 clocks after it).
    for key, valid, (lo, hi) in (("a", "i_valid", (i_lo, i_hi)), ("b", "i_valid", (i_lo, i_hi)),
                                 ("c", "i_valid", (i_lo, i_hi)), ("udc", "udc_valid", (u_lo, u_hi)),
                                 ("speed", "speed_valid", (s_lo, s_hi))):
        junk = cols[valid] == 0
        if limits != "ports":
            last = -100
            for t in range(n):
                if cols[valid][t]:
                    last = t
                elif t - last <= 8:
                    cols[key][t] = cols[key][last]
                    junk[t] = False
        cols[key][junk] = rng.integers(lo, hi + 1, size=int(junk.sum()))
    if limits != "ports":
        cols = _limit_writes(rng, cols)
    return cols


def _limit_writes(rng, cols):
    """``cols`` (:data:`INPUTS`) with the four limit columns replaced by limit-port writes
    (:func:`stimulus`'s ``limits="ram"``)."""
    n = len(cols["fault_n"])
    out = {k: cols[k] for k in RAM_INPUTS if k in cols}
    valid = np.zeros(n, dtype=np.int64)
    index = np.zeros(n, dtype=np.int64)
    data = np.zeros(n, dtype=np.int64)
    starts = [0] + [t for t in range(1, n)
                    if any(cols[k][t] != cols[k][t - 1] for k in LIMITS)]
    for s0 in starts:
        for j, k in enumerate(rng.permutation(len(LIMITS)).tolist()):
            t = s0 + j
            if t < n:
                valid[t], index[t] = 1, k
                data[t] = int(cols[LIMITS[k]][s0]) & 0xFFFF_FFFF
    for t in np.flatnonzero(rng.random(n) < 1 / 300).tolist():
        if not valid[t]:
            k = int(rng.integers(0, len(LIMITS)))
            back = max([s0 for s0 in starts if s0 <= t])
            valid[t], index[t], data[t] = 1, k, int(cols[LIMITS[k]][back]) & 0xFFFF_FFFF
    out["lim_valid"], out["lim_index"], out["lim_data"] = valid, index, data
    return out


def _in_layout(dut):
    """The per-clock input word: the columns of :data:`INPUTS` (``limits="ram"``:
    :data:`RAM_INPUTS`), in their order."""
    w, sw, us = dut.current_width, dut.speed_width, dut.udc_shape
    shapes = {"a": signed(w), "b": signed(w), "c": signed(w), "udc": us, "speed": signed(sw),
              "oc_limit": unsigned(w), "ov_limit": us, "uv_limit": us, "os_limit": unsigned(sw),
              "mask": FAULT_LAYOUT, "lim_index": 2, "lim_data": 32}
    names = INPUTS if dut.limits == "ports" else RAM_INPUTS
    return data.StructLayout({k: shapes.get(k, 1) for k in names})


class _ProtectBench(wiring.Component):
    """Simulation-only wrapper: per-clock input ROM → Protection; outputs compared every clock
    with the expected-output ROM."""

    mismatches: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)

    def __init__(self, dut, in_words, in_layout, exp_words):
        self._dut = dut
        self._in = in_words
        self._in_layout = in_layout
        self._exp = exp_words
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        n = len(self._in)
        m.submodules.stim = stim = Memory(shape=unsigned(self._in_layout.size), depth=n,
                                          init=self._in)
        m.submodules.exp = exp = Memory(shape=unsigned(_OUT_LAYOUT.size), depth=n,
                                        init=self._exp)
        srd = stim.read_port(domain="comb")
        erd = exp.read_port(domain="comb")
        t = Signal(range(n + 1))
        running = t < n
        m.d.comb += [srd.addr.eq(t), erd.addr.eq(t)]
        with m.If(running):
            m.d.sync += t.eq(t + 1)
        s = data.View(self._in_layout, srd.data)
        m.d.comb += [
            dut.fault_n.eq(Mux(running, s.fault_n, 1)),
            dut.oc_comp.eq(running & s.oc_comp),
            dut.i.valid.eq(running & s.i_valid),
            dut.i.payload.a.eq(s.a), dut.i.payload.b.eq(s.b), dut.i.payload.c.eq(s.c),
            dut.udc.valid.eq(running & s.udc_valid),
            dut.udc.payload.eq(s.udc),
            dut.speed.valid.eq(running & s.speed_valid),
            dut.speed.payload.eq(s.speed),
            dut.encoder_illegal.eq(running & s.encoder_illegal),
            dut.hall_invalid.eq(running & s.hall_invalid),
            dut.encoder_hall.eq(running & s.encoder_hall),
            dut.uv_enable.eq(s.uv_enable), dut.mask.eq(s.mask),
            dut.clear.eq(running & s.clear),
        ]
        if dut.limits != "ports":
            m.d.comb += [dut.limit_wr.valid.eq(running & s.lim_valid),
                         dut.limit_wr.index.eq(s.lim_index), dut.limit_wr.data.eq(s.lim_data)]
        else:
            m.d.comb += [dut.oc_limit.eq(s.oc_limit), dut.ov_limit.eq(s.ov_limit),
                         dut.uv_limit.eq(s.uv_limit), dut.os_limit.eq(s.os_limit)]
        got = Signal(_OUT_LAYOUT)
        m.d.comb += [got.trip.eq(dut.trip), got.present.eq(dut.present),
                     got.first.eq(dut.first), got.seen.eq(dut.seen),
                     got.uv_armed.eq(dut.uv_armed)]
        with m.If(running & (got.as_value() != erd.data)):
            m.d.sync += self.mismatches.eq(self.mismatches + 1)
            with m.If(self.mismatches == 0):
                m.d.sync += self.first_mismatch.eq(t)
        return m


def measure_latency(**params):
    """Clocks from each fault input to ``trip``, measured in simulation.

    For each cause, from a cleared latch with every limit set to a mid-range value (and the
    under-voltage check armed), the fault is applied in one clock (a pin, or one valid sample
    beyond its limit) and the clocks are counted until ``trip`` is seen high; then the fault is
    removed and the latch cleared. Returns a dict cause → clocks. (``limits="ram"``: the
    limits written through ``limit_wr`` first; a sample's payload held until the next.)
    """
    dut = Protection(**params)
    result = {}
    # Clocks for a sample's verdicts to settle (the steps of limits="ram").
    settle = 1 if dut.limits == "ports" else 6

    async def testbench(ctx):
        if dut.limits != "ports":
            for k, v in enumerate((1000, 30000, 10000, 1000)):
                ctx.set(dut.limit_wr.valid, 1)
                ctx.set(dut.limit_wr.index, k)
                ctx.set(dut.limit_wr.data, v)
                await ctx.tick()
            ctx.set(dut.limit_wr.valid, 0)
        else:
            ctx.set(dut.oc_limit, 1000)
            ctx.set(dut.ov_limit, 30000)
            ctx.set(dut.uv_limit, 10000)
            ctx.set(dut.os_limit, 1000)
        ctx.set(dut.uv_enable, 1)
        ctx.set(dut.udc.payload, 20000)            # arm the under-voltage check
        ctx.set(dut.udc.valid, 1)
        await ctx.tick()
        ctx.set(dut.udc.valid, 0)
        await ctx.tick().repeat(settle)
        assert ctx.get(dut.uv_armed) and not ctx.get(dut.trip)

        def apply(name, on):
            if name == "external":
                ctx.set(dut.fault_n, 0 if on else 1)
            elif name == "overcurrent_comparator":
                ctx.set(dut.oc_comp, on)
            elif name == "encoder":
                ctx.set(dut.encoder_illegal, on)
            elif name == "hall":
                ctx.set(dut.hall_invalid, on)
            elif name == "encoder_hall":
                ctx.set(dut.encoder_hall, on)
            elif name.startswith("overcurrent_"):
                phase = name[-1]
                ctx.set(dut.i.payload, {p: (-1001 if (on and p == phase) else 0) for p in "abc"})
                ctx.set(dut.i.valid, 1)
            elif name in ("overvoltage", "undervoltage"):
                ctx.set(dut.udc.payload, (30001 if name == "overvoltage" else 9999) if on
                        else 20000)
                ctx.set(dut.udc.valid, 1)
            elif name == "overspeed":
                ctx.set(dut.speed.payload, 1001 if on else 0)
                ctx.set(dut.speed.valid, 1)

        for name in FAULTS:
            apply(name, True)                      # the fault appears in this clock
            clocks = 0
            while True:
                await ctx.tick()
                clocks += 1
                for s in (dut.i.valid, dut.udc.valid, dut.speed.valid):
                    ctx.set(s, 0)                  # one sample only
                if ctx.get(dut.trip) or clocks > 10:
                    break
            result[name] = clocks if ctx.get(dut.trip) else None
            apply(name, False)                     # remove it, then clear
            await ctx.tick()
            for s in (dut.i.valid, dut.udc.valid, dut.speed.valid):
                ctx.set(s, 0)
            await ctx.tick().repeat(settle)
            ctx.set(dut.clear, 1)
            await ctx.tick()
            ctx.set(dut.clear, 0)
            await ctx.tick()
            assert not ctx.get(dut.trip), f"latch did not clear after {name}"

    simulate(dut, [testbench], name="protect_latency")
    return result


def compare(dut, cols, *, progress=False):
    """Drive ``dut`` (a :class:`Protection`) with the per-clock columns ``cols`` (the model's
    :data:`INPUTS`, or :data:`RAM_INPUTS` for ``limits="ram"``) and compare every output in
    every clock with :func:`protect_np`. Returns ``({"mismatches", "first_mismatch"}, the
    model's outputs, simulated seconds)``."""
    count = len(cols["fault_n"])
    exp = protect_np(cols, limits=dut.limits, current_width=dut.current_width,
                     udc_shape=dut.udc_shape, speed_width=dut.speed_width,
                     limit_init=dut.limit_init)
    layout = _in_layout(dut)
    bench = _ProtectBench(dut, pack_words(layout, cols, count), layout,
                          pack_words(_OUT_LAYOUT, exp, count))
    result = {}
    prog = Progress("protect", count, enabled=progress)

    async def testbench(ctx):
        await prog.ticks(ctx, count + 1)
        result["mismatches"] = ctx.get(bench.mismatches)
        result["first_mismatch"] = ctx.get(bench.first_mismatch)

    sim_s = simulate(bench, [testbench], name="protect")
    prog.close()
    first = result["first_mismatch"]
    result["first_mismatch"] = None if first == 0xFFFF_FFFF else int(first)
    return result, exp, sim_s


def run(count=100_000, *, seed=0, progress=False, current_width=16, udc_shape=signed(16),
        speed_width=16, trip_register=True, limits="ports"):
    """Simulate :class:`Protection` for ``count`` clocks of random fault sequences and compare
    every output in every clock with the golden model; measure each input's trip latency.

    Returns
    -------
    dict
        ``mismatches`` (clocks with any output different), ``vectors`` (= ``clocks``),
        ``clocks``, ``sim_s``, ``clocks_per_s``, ``trips`` (latch set events in the run),
        ``clears`` (successful clears), ``first_mismatch``, ``trip_latency_clk`` (cause →
        clocks), ``fault_latency_clk_max`` (their maximum; the gate stage adds 1 more).
    ``trip_register``, ``limits``: :class:`Protection`'s (the ECP5's forms, or ``False`` and
    ``"ram"`` the iCE40's).
    """
    params = dict(current_width=current_width, udc_shape=udc_shape, speed_width=speed_width)
    dut = Protection(**params, trip_register=trip_register, limits=limits)
    cols = stimulus(count, seed=seed, **params, limits=limits)
    result, exp, sim_s = compare(dut, cols, progress=progress)
    latency = measure_latency(**params, trip_register=trip_register, limits=limits)
    trip = exp["trip"]
    first = result["first_mismatch"]
    values = [v for v in latency.values() if v is not None]
    return {
        "mismatches": result["mismatches"],
        "vectors": count,
        "clocks": count,
        "sim_s": sim_s,
        "clocks_per_s": count / sim_s if sim_s > 0 else float("inf"),
        "trips": int(np.sum((trip[1:] == 1) & (trip[:-1] == 0))),
        "clears": int(np.sum((trip[1:] == 0) & (trip[:-1] == 1))),
        "first_mismatch": first,
        "trip_latency_clk": latency,
        "fault_latency_clk_max": (max(values) if len(values) == len(latency) else None),
    }
