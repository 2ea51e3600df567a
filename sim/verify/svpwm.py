# Ref: SPEC.md §2.4 (paper Fig. 7, SVPWM), §2.5 (DC-bus compensation), §4 (dead time, trip)
"""Gateware of :mod:`foc_servo.hdl.svpwm` and :mod:`foc_servo.hdl.gates` against the golden models.

Three simulations:

1. :class:`SVPWM` alone on ``count`` random commands (inside and outside the hexagon, random
   scales, and corners) from a stimulus ROM, duties compared in gateware with an expected-output
   ROM (the testbench only ticks). The overmodulation angle error is measured on these duties.
2. :class:`DCBusCompensation`: random bus voltages, rated voltages and commands against the model.
3. SVPWM → :class:`PWMTimer` → :class:`Gates` as a system at several clock / PWM frequencies, one
   command or raw duty triple per period written at a random point of the period, random mode
   (symmetric / asymmetric), dead times, enable toggles and trips. A gateware monitor checks the
   dead-time rules on *every* clock and counts the high clocks of each PWM level per period; the
   testbench compares those with the model (shadowing: a write only affects the next period) and
   with the real-valued command (volt-seconds).
"""

import numpy as np
from amaranth.hdl import Module, Mux, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.gates import Gates
from ...hdl.svpwm import SVPWM, DCBusCompensation, PWMTimer, pwm_half_period
from ..harness import Progress, pack_words, simulate
from ..models import svpwm as model

__all__ = ["run", "svpwm_stimulus"]




def svpwm_stimulus(count, *, seed=0, width=16, count_width=16, scale=2500):
    """Seeded commands: ``count`` random ones, then corners.

    Random: a third uniform over the whole input square (mostly outside the hexagon), a third
    inside the hexagon's inscribed circle, a third near the hexagon's boundary (magnitude
    0.8 … 1.2 of the boundary along a random angle). Scales: half ``scale`` (the default symmetric
    full scale, on which the angle error is measured), a quarter ``2·scale``, a quarter uniform.
    Corners: zero, the six vertices and six edge midpoints, the four extreme input corners and
    the axes' extremes, each at scales 1, ``scale`` and the largest.

    Returns
    -------
    dict of int64 arrays
        ``alpha``, ``beta``, ``scale``.
    """
    rng = np.random.default_rng(seed)
    fs = 1 << (width - 1)
    lo, hi = -fs, fs - 1
    s_max = (1 << count_width) - 1
    scale = min(scale, s_max)
    n3 = count // 3
    kinds = [count - 2 * n3, n3, n3]
    alpha, beta = [], []
    alpha.append(rng.integers(lo, hi + 1, kinds[0]))
    beta.append(rng.integers(lo, hi + 1, kinds[0]))
    th = rng.uniform(-np.pi, np.pi, kinds[1])
    r = np.sqrt(rng.uniform(0, 1, kinds[1])) * np.sqrt(3) / 2
    alpha.append(np.rint(r * np.cos(th) * fs))
    beta.append(np.rint(r * np.sin(th) * fs))
    th = rng.uniform(-np.pi, np.pi, kinds[2])
    # Hexagon boundary (vertices at 1.0 on 0°, 60°, ...): r(θ) = (√3/2) / cos(θ mod 60° − 30°).
    rb = np.sqrt(3) / 2 / np.cos(np.mod(th, np.pi / 3) - np.pi / 6)
    r = rb * rng.uniform(0.8, 1.2, kinds[2])
    alpha.append(np.rint(r * np.cos(th) * fs))
    beta.append(np.rint(r * np.sin(th) * fs))
    alpha = np.clip(np.concatenate(alpha), lo, hi).astype(np.int64)
    beta = np.clip(np.concatenate(beta), lo, hi).astype(np.int64)
    pick = rng.random(count)
    scales = np.where(pick < 0.5, scale, np.where(pick < 0.75, min(2 * scale, s_max),
                                                  rng.integers(1, s_max + 1, count)))

    ca, cb = [0], [0]
    for k in range(6):
        for r, off in ((1.0, 0.0), (np.sqrt(3) / 2, np.pi / 6)):
            ca.append(int(np.clip(np.rint(r * np.cos(k * np.pi / 3 + off) * fs), lo, hi)))
            cb.append(int(np.clip(np.rint(r * np.sin(k * np.pi / 3 + off) * fs), lo, hi)))
    for x in (lo, hi):
        for y in (lo, hi):
            ca.append(x)
            cb.append(y)
    for v in (lo, hi, 1, -1):
        ca += [v, 0]
        cb += [0, v]
    ca, cb = np.array(ca), np.array(cb)
    corner_scales = sorted({1, scale, s_max})
    alpha = np.concatenate([alpha] + [ca] * len(corner_scales))
    beta = np.concatenate([beta] + [cb] * len(corner_scales))
    scales = np.concatenate([scales] + [np.full(ca.size, s) for s in corner_scales])
    return {"alpha": alpha, "beta": beta, "scale": scales.astype(np.int64)}


class _SVPWMBench(wiring.Component):
    """Stimulus ROM → SVPWM → comparison with the expected-duty ROM, counted in gateware."""

    received: Out(32)
    mismatches: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)

    def __init__(self, dut, stim, stim_layout, exp):
        self._dut, self._stim, self._layout, self._exp = dut, stim, stim_layout, exp
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        out_layout = dut.o.payload.shape()
        n = len(self._stim)
        m.submodules.stim = stim = Memory(shape=unsigned(self._layout.size), depth=n,
                                          init=self._stim)
        m.submodules.exp = exp = Memory(shape=unsigned(out_layout.size), depth=n, init=self._exp)
        srd = stim.read_port(domain="comb")
        erd = exp.read_port(domain="comb")
        n_in = Signal(range(n + 1))
        word = data.View(self._layout, srd.data)
        m.d.comb += [
            srd.addr.eq(n_in),
            erd.addr.eq(self.received),
            dut.i.valid.eq(n_in < n),
            dut.i.payload.alpha.eq(word.alpha),
            dut.i.payload.beta.eq(word.beta),
            dut.scale.eq(word.scale),
            dut.o.ready.eq(1),
        ]
        with m.If(dut.i.valid & dut.i.ready):
            m.d.sync += n_in.eq(n_in + 1)
        with m.If(dut.o.valid):
            m.d.sync += self.received.eq(self.received + 1)
            with m.If(dut.o.payload.as_value() != erd.data):
                m.d.sync += self.mismatches.eq(self.mismatches + 1)
                with m.If(self.mismatches == 0):
                    m.d.sync += self.first_mismatch.eq(self.received)
        return m


def _run_svpwm(count, *, seed, progress, width, count_width, scale):
    vec = svpwm_stimulus(count, seed=seed, width=width, count_width=count_width, scale=scale)
    n = vec["alpha"].size
    exp = model.svpwm(vec["alpha"], vec["beta"], vec["scale"], width=width)
    dut = SVPWM(width=width, count_width=count_width)
    stim_layout = data.StructLayout({"alpha": width, "beta": width, "scale": count_width})
    bench = _SVPWMBench(dut, pack_words(stim_layout, vec, n), stim_layout,
                        pack_words(dut.o.payload.shape(), exp, n))
    clocks = n * (dut.latency + 1) + 2
    prog = Progress("svpwm duties", clocks, enabled=progress)
    result = {}

    async def testbench(ctx):
        # ctx.delay() lets the simulator run the clock without waking the testbench every clock;
        # the half-period offset makes the sampling point unambiguous.
        done = 0
        await ctx.delay(0.5 / 50e6)
        while done < clocks:
            k = min(5000, clocks - done)
            await ctx.delay(k / 50e6)
            done += k
            prog.update(done)
        for key in ("received", "mismatches", "first_mismatch"):
            result[key] = ctx.get(getattr(bench, key))

    sim_s = simulate(bench, [testbench], name="svpwm_duties")
    prog.close()

    # Overmodulation angle error and line-to-line error against the real-valued command, on the
    # duties just verified (they are the gateware's when mismatches == 0).
    sel = vec["scale"] == scale
    da, db, dc = (exp[k][sel] / scale for k in "abc")
    ua, ub = model.vector_of_duties(da, db, dc)
    a, b = vec["alpha"][sel], vec["beta"][sel]
    om = (exp["overmod"][sel] == 1) & ((a != 0) | (b != 0))
    err = np.angle(np.exp(1j * (np.arctan2(ub, ua) - np.arctan2(b, a))))
    ideal, _ = model.svpwm_ideal(a, b, width=width)
    line_err = 0.0
    for i, j in ((0, 1), (1, 2), (0, 2)):
        got = exp["abc"[i]][sel] - exp["abc"[j]][sel]
        line_err = max(line_err, float(np.max(np.abs(got - (ideal[i] - ideal[j]) * scale))))
    sector = model.svpwm_sector(vec["alpha"], vec["beta"], vec["scale"], width=width)
    sector_mm = int(sum(np.count_nonzero(sector[k] != exp[k]) for k in ("a", "b", "c", "overmod")))
    missing = n - min(result["received"], n)
    first = result["first_mismatch"]
    return {
        "mismatches": result["mismatches"] + missing,
        "vectors": n,
        "overmod_vectors": int(exp["overmod"].sum()),
        "clocks": clocks,
        "sim_s": sim_s,
        "overmod_angle_err_deg": float(np.degrees(np.max(np.abs(err[om])))) if om.any() else 0.0,
        "line_err_counts": line_err,
        "sector_mismatches": sector_mm,
        "first_mismatch": None if first == 0xFFFF_FFFF else int(first),
        "latency": dut.latency,
    }


def _run_dcbus(cases, *, seed, width, adc_width, gain_limit, out_width):
    rng = np.random.default_rng([seed, 2])
    dut = DCBusCompensation(width=width, out_width=out_width, adc_width=adc_width,
                            gain_limit=gain_limit)
    a_max = (1 << adc_width) - 1
    fs = 1 << (width - 1)
    per_case = 6
    u_rated = rng.integers(a_max // 4, a_max + 1, cases)
    u_dc = np.clip(np.rint(u_rated * rng.uniform(0.3, 1.5, cases)), 0, a_max).astype(np.int64)
    u_dc[:4] = [0, 1, a_max, u_rated[3]]
    cmd = rng.integers(-fs, fs, (cases, per_case, 2))
    cmd[:, 0] = [-fs, -fs]
    cmd[:, 1] = [fs - 1, fs - 1]
    gain, limited = model.dcbus_gain(u_rated, u_dc, gain_limit_raw=dut.gain_limit_raw)
    exp = model.dcbus_apply(cmd, gain[:, None, None], out_width=dut.out_width)
    got = np.zeros_like(exp)
    got_gain = np.zeros(cases, dtype=np.int64)
    got_lim = np.zeros(cases, dtype=np.int64)

    async def testbench(ctx):
        ctx.set(dut.o.ready, 1)
        for k in range(cases):
            ctx.set(dut.u_rated, int(u_rated[k]))
            ctx.set(dut.u_dc.payload, int(u_dc[k]))
            ctx.set(dut.u_dc.valid, 1)
            await ctx.tick()
            ctx.set(dut.u_dc.valid, 0)
            await ctx.tick().repeat(dut.gain_latency)
            got_gain[k] = ctx.get(dut.gain)
            got_lim[k] = ctx.get(dut.limited)
            # Back to back: result j comes out `latency` clocks after command j goes in.
            out = 0
            for j in range(per_case + dut.latency):
                ctx.set(dut.i.valid, j < per_case)
                if j < per_case:
                    ctx.set(dut.i.payload, {"alpha": int(cmd[k, j, 0]),
                                            "beta": int(cmd[k, j, 1])})
                await ctx.tick()
                if ctx.get(dut.o.valid):
                    p = ctx.get(dut.o.payload)
                    got[k, out] = [p.alpha, p.beta]
                    out += 1
            ctx.set(dut.i.valid, 0)
            if out != per_case or j + 1 - per_case != dut.latency:
                got[k] = exp[k] + 1          # a lost or late result counts as a mismatch

    sim_s = simulate(dut, [testbench], name="dcbus")
    mism = (int(np.count_nonzero(np.any(got != exp, axis=-1)))
            + int(np.count_nonzero(got_gain != gain)) + int(np.count_nonzero(got_lim != limited)))
    return {"mismatches": mism, "vectors": cases * per_case + cases,
            "clocks": cases * (dut.gain_latency + per_case + dut.latency + 1), "sim_s": sim_s,
            "gain_latency": dut.gain_latency}


class PWMSystemBench(wiring.Component):
    """Simulation-only system: per-period stimulus ROM → SVPWM → PWMTimer → Gates, with a monitor.

    ROM entry ``k`` is used during period ``k``: ``symmetric`` is driven from it for the whole
    period (so it is the mode of period ``k + 1``), and at position ``wpos`` either the raw duties
    are written to the timer or the command is started on the SVPWM (scale = the timer's full
    scale); the result reaches the timer's shadow registers before the boundary.

    Monitor (every clock, per phase): ``overlap`` (high and low together), ``short_dead`` (a
    turn-on after fewer than ``max(dead_time, 1)`` clocks with both off, dead time as on the
    previous clock), ``runts`` (a turn-on following a pwm level that lasted less than that),
    ``stop_violations`` (a gate on the clock after ``trip`` or ``~enable``), ``trip_latency_max``
    (clocks from a rising ``trip`` until all gates are off). ``hi_a/b/c`` hold the number of clocks
    each pwm level was high in the last complete period.
    """

    overlap: Out(32)
    short_dead: Out(32)
    runts: Out(32)
    stop_violations: Out(32)
    trip_latency_max: Out(8)
    hi_a: Out(24)
    hi_b: Out(24)
    hi_c: Out(24)

    def __init__(self, *, clk_hz, pwm_hz, width=16, count_width=16, dead_width=8):
        self.timer = PWMTimer(clk_hz=clk_hz, pwm_hz=pwm_hz, count_width=count_width)
        self.svpwm = SVPWM(width=width, count_width=count_width)
        self.gates = Gates(dead_width=dead_width)
        cw = count_width
        self.entry_layout = data.StructLayout({
            "raw": 1, "sym": 1, "alpha": width, "beta": width,
            "a": cw, "b": cw, "c": cw, "wpos": cw})
        self._words = None
        super().__init__()

    def set_entries(self, entries):
        """Load the per-period stimulus (dict of arrays, see :func:`pwm_entries`)."""
        self._words = pack_words(self.entry_layout, entries, len(entries["raw"]))

    def elaborate(self, platform):
        m = Module()
        m.submodules.timer = timer = self.timer
        m.submodules.svpwm = sv = self.svpwm
        m.submodules.gates = gates = self.gates
        n_entries = len(self._words)
        m.submodules.rom = rom = Memory(shape=unsigned(self.entry_layout.size), depth=n_entries,
                                        init=self._words)
        rd = rom.read_port(domain="comb")
        idx = Signal(range(n_entries + 1))
        e = data.View(self.entry_layout, rd.data)
        with m.If((timer.position == timer.period - 1) & (idx < n_entries - 1)):
            m.d.sync += idx.eq(idx + 1)
        write = timer.position == e.wpos
        m.d.comb += [
            rd.addr.eq(idx),
            timer.symmetric.eq(e.sym),
            sv.i.valid.eq(write & ~e.raw),
            sv.i.payload.alpha.eq(e.alpha),
            sv.i.payload.beta.eq(e.beta),
            sv.scale.eq(timer.full_scale),
            sv.o.ready.eq(1),
            timer.duty.valid.eq(sv.o.valid | (write & e.raw)),
            gates.pwm.eq(timer.pwm),
        ]
        for p in "abc":
            m.d.comb += timer.duty.payload[p].eq(Mux(sv.o.valid, sv.o.payload[p], e[p]))

        # Per-period high clocks of the pwm levels.
        for p in "abc":
            acc = Signal(24, name=f"acc_{p}")
            with m.If(timer.position == timer.period - 1):
                m.d.sync += [getattr(self, f"hi_{p}").eq(acc + timer.pwm[p]), acc.eq(0)]
            with m.Else():
                m.d.sync += acc.eq(acc + timer.pwm[p])

        # Dead-time rule monitor.
        dead_prev = Signal.like(gates.dead_time)
        run_prev = Signal()
        m.d.sync += [dead_prev.eq(gates.dead_time), run_prev.eq(gates.enable & ~gates.trip)]
        dead_req = Mux(dead_prev == 0, 1, dead_prev)
        counts = {"overlap": [], "short_dead": [], "runts": [], "stop": []}
        any_on = 0
        for p in "abc":
            h, lo, level = gates.high[p], gates.low[p], timer.pwm[p]
            h_d, lo_d, level_d = (Signal(name=f"{x}_d_{p}") for x in ("h", "l", "pwm"))
            off_run = Signal(16, name=f"off_run_{p}")
            level_run = Signal(16, name=f"level_run_{p}")
            m.d.sync += [h_d.eq(h), lo_d.eq(lo), level_d.eq(level)]
            # Clocks both off / pwm at its level, up to and including the previous clock.
            m.d.sync += [
                off_run.eq(Mux(~h & ~lo, Mux(off_run == 0xFFFF, off_run, off_run + 1), 0)),
                level_run.eq(Mux(level == level_d, Mux(level_run == 0xFFFF, level_run,
                                                        level_run + 1), 1)),
            ]
            on_h = h & ~h_d
            on_l = lo & ~lo_d
            counts["overlap"].append(h & lo)
            counts["short_dead"].append((on_h | on_l) & (off_run < dead_req))
            counts["runts"].append((on_h & (~level_d | (level_run < dead_req)))
                                   | (on_l & (level_d | (level_run < dead_req))))
            counts["stop"].append(~run_prev & (h | lo))
            any_on = any_on | h | lo
        for name, reg in (("overlap", self.overlap), ("short_dead", self.short_dead),
                          ("runts", self.runts), ("stop", self.stop_violations)):
            total = sum(x.as_unsigned() for x in counts[name])
            m.d.sync += reg.eq(reg + total)

        trip_d = Signal()
        since = Signal(8)
        timing = Signal()
        m.d.sync += trip_d.eq(gates.trip)
        with m.If(gates.trip & ~trip_d):
            m.d.sync += [timing.eq(1), since.eq(1)]
        with m.Elif(timing):
            with m.If(~any_on):
                m.d.sync += timing.eq(0)
                with m.If(since > self.trip_latency_max):
                    m.d.sync += self.trip_latency_max.eq(since)
            with m.Else():
                m.d.sync += since.eq(since + 1)
        return m


def pwm_entries(periods, *, rng, half_period, latency, width=16, count_width=16, dead_max=20):
    """Random per-period stimulus for :class:`PWMSystemBench`: a third raw duty triples (many
    near 0, near full scale and shorter than ``dead_max``), the rest SVPWM commands inside and
    outside the hexagon; random mode per period; write position random in the period, early
    enough for the SVPWM result to reach the boundary."""
    n = half_period
    fs = 1 << (width - 1)
    raw = (rng.random(periods) < 1 / 3).astype(np.int64)
    sym = (rng.random(periods) < 0.5).astype(np.int64)
    full = np.where(sym == 1, n, 2 * n)
    duties = []
    for _ in range(3):
        kind = rng.integers(0, 4, periods)
        short = rng.integers(0, dead_max + 1, periods)
        d = np.select([kind == 0, kind == 1, kind == 2],
                      [short, full - short, rng.integers(0, full + 1)],
                      rng.integers(0, (1 << count_width), periods))   # also above full scale
        duties.append(np.clip(d, 0, (1 << count_width) - 1))
    r = rng.uniform(0, 1.3, periods)
    th = rng.uniform(-np.pi, np.pi, periods)
    alpha = np.clip(np.rint(r * np.cos(th) * fs), -fs, fs - 1).astype(np.int64)
    beta = np.clip(np.rint(r * np.sin(th) * fs), -fs, fs - 1).astype(np.int64)
    wpos = rng.integers(0, 2 * n - latency - 2, periods)
    return {"raw": raw, "sym": sym, "alpha": alpha, "beta": beta,
            "a": duties[0], "b": duties[1], "c": duties[2], "wpos": wpos}


def _run_system(periods, *, seed, clk_hz, pwm_hz, width, count_width, dead_max, events=True):
    rng = np.random.default_rng([seed, 3, int(clk_hz), int(pwm_hz)])
    n = pwm_half_period(clk_hz, pwm_hz)
    bench = PWMSystemBench(clk_hz=clk_hz, pwm_hz=pwm_hz, width=width, count_width=count_width)
    ent = pwm_entries(periods, rng=rng, half_period=n, latency=bench.svpwm.latency, width=width,
                      count_width=count_width, dead_max=dead_max)
    bench.set_entries(ent)
    gates = bench.gates
    period = 2 * n
    hi = np.zeros((periods, 3), dtype=np.int64)
    res = {}

    clk_s = 1 / clk_hz

    async def testbench(ctx):
        # Time advances by ctx.delay() (the testbench is not woken every clock), sampling and
        # driving half a clock after each edge.
        await ctx.delay(clk_s / 2)
        ctx.set(gates.enable, 1)
        ctx.set(gates.dead_time, int(rng.integers(0, dead_max + 1)))
        for k in range(periods):
            t = 0
            if events:
                # Random gate events inside the period: dead-time change, enable toggle, trip.
                evs = []
                if rng.random() < 0.3:
                    evs.append((int(rng.integers(period)), gates.dead_time,
                                int(rng.integers(0, dead_max + 1))))
                if rng.random() < 0.1:
                    evs.append((int(rng.integers(period)), gates.enable, int(rng.random() < 0.6)))
                if rng.random() < 0.05:
                    a = int(rng.integers(period))
                    evs += [(a, gates.trip, 1), (a + int(rng.integers(1, 8)), gates.trip, 0)]
                for at, sig, val in sorted(evs, key=lambda x: x[0]):
                    at = min(at, period - 1)
                    if at > t:
                        await ctx.delay((at - t) * clk_s)
                        t = at
                    ctx.set(sig, val)
                if k % 16 == 15:
                    ctx.set(gates.enable, 1)
            await ctx.delay((period - t) * clk_s)
            hi[k] = [ctx.get(bench.hi_a), ctx.get(bench.hi_b), ctx.get(bench.hi_c)]
        for key in ("overlap", "short_dead", "runts", "stop_violations", "trip_latency_max"):
            res[key] = ctx.get(getattr(bench, key))

    sim_s = simulate(bench, [testbench], clock_hz=clk_hz, name=f"pwm_system_{int(pwm_hz)}")

    # Expected: period k + 1 runs entry k's duties in entry k's mode (period 0: reset, all 0).
    sym = ent["sym"][:-1] == 1
    full = np.where(sym, n, 2 * n)
    cmd = model.svpwm(ent["alpha"][:-1], ent["beta"][:-1], full, width=width)
    raw = ent["raw"][:-1] == 1
    comp = np.stack([np.where(raw, ent[p][:-1], cmd[p]) for p in "abc"], axis=1)
    exp_hi = model.pwm_high_clocks(comp, n, sym[:, None])
    got_hi = hi[1:]
    timer_mm = int(np.count_nonzero(np.any(got_hi != exp_hi, axis=1))) + int(np.any(hi[0] != 0))
    # Volt-seconds of the SVPWM periods against the real-valued command, in counts.
    ideal, _ = model.svpwm_ideal(ent["alpha"][:-1], ent["beta"][:-1], width=width)
    counts = got_hi / np.where(sym, 2, 1)[:, None]
    vs_err = 0.0
    svp = ~raw
    for i, j in ((0, 1), (1, 2), (0, 2)):
        e = np.abs((counts[:, i] - counts[:, j]) - (ideal[i] - ideal[j]) * full)[svp]
        vs_err = max(vs_err, float(e.max()) if e.size else 0.0)
    violations = res["overlap"] + res["short_dead"]
    return {
        "clocks": periods * period, "sim_s": sim_s, "periods": periods, "half_period": n,
        "timer_mismatches": timer_mm, "volt_seconds_err_counts": vs_err,
        "deadtime_violations": violations, "runt_pulses": res["runts"],
        "stop_violations": res["stop_violations"], "trip_latency_clk": res["trip_latency_max"],
    }


#: System simulations: (clk_hz, pwm_hz, periods per 1000 of ``system_periods``).
SYSTEM_CONFIGS = ((50e6, 500e3, 400), (50e6, 100e3, 60), (33.333e6, 100e3, 60),
                  (33.333e6, 1e6, 400), (50e6, 10e3, 4))


def run(count=100_000, *, seed=0, progress=False, width=16, count_width=16, system_periods=1000,
        dcbus_cases=300, dead_max=20):
    """Simulate the SVPWM, DC-bus compensation, PWM timer and gates against the models.

    Parameters
    ----------
    count : int
        Random SVPWM commands (corner cases on top).
    system_periods : int
        Scales the number of PWM periods of the system simulations (1000: 924 periods, 124 000
        clocks, at five clock / PWM frequency pairs: 500 kHz and 100 kHz at 50 MHz, 100 kHz and
        1 MHz at 33.333 MHz, 10 kHz at 50 MHz).
    dcbus_cases : int
        Bus-voltage cases for the DC-bus compensation (6 commands each).

    Returns
    -------
    dict
        ``mismatches`` (all mismatches and rule breaks together), ``vectors``, ``clocks``,
        ``sim_s``, ``clocks_per_s``; ``svpwm_mismatches``, ``svpwm_vectors``,
        ``svpwm_sector_mismatches`` (model: min–max vs textbook sectors), ``overmod_angle_err_deg``
        and ``svpwm_line_err_counts`` (line-to-line duty differences vs the real-valued
        command, counts), both on the commands at the full scale 2500 (10 kHz at 50 MHz),
        ``volt_seconds_err_counts`` (measured PWM waveforms), ``timer_mismatches``,
        ``deadtime_violations``, ``runt_pulses``, ``stop_violations``, ``trip_latency_clk``,
        ``dcbus_mismatches``, ``svpwm_latency``, ``dcbus_gain_latency``, and ``system`` (per
        configuration figures).
    """
    sv = _run_svpwm(count, seed=seed, progress=progress, width=width, count_width=count_width,
                    scale=min(pwm_half_period(50e6, 10e3), (1 << count_width) - 1))
    dc = _run_dcbus(dcbus_cases, seed=seed, width=width, adc_width=16, gain_limit=2.0,
                    out_width=width)
    systems = {}
    prog = Progress("pwm/gates systems", len(SYSTEM_CONFIGS), enabled=progress)
    for i, (clk, pwm, per) in enumerate(SYSTEM_CONFIGS):
        periods = max(4, per * system_periods // 1000)
        systems[f"{clk / 1e6:g}MHz_{pwm / 1e3:g}kHz"] = _run_system(
            periods, seed=seed, clk_hz=clk, pwm_hz=pwm, width=width, count_width=count_width,
            dead_max=dead_max)
        prog.update(i + 1)
    prog.close()
    sysv = list(systems.values())
    out = {
        "svpwm_mismatches": sv["mismatches"],
        "svpwm_vectors": sv["vectors"],
        "svpwm_overmod_vectors": sv["overmod_vectors"],
        "svpwm_sector_mismatches": sv["sector_mismatches"],
        "overmod_angle_err_deg": sv["overmod_angle_err_deg"],
        "svpwm_line_err_counts": sv["line_err_counts"],
        "svpwm_latency": sv["latency"],
        "svpwm_first_mismatch": sv["first_mismatch"],
        "volt_seconds_err_counts": max(s["volt_seconds_err_counts"] for s in sysv),
        "timer_mismatches": sum(s["timer_mismatches"] for s in sysv),
        "deadtime_violations": sum(s["deadtime_violations"] for s in sysv),
        "runt_pulses": sum(s["runt_pulses"] for s in sysv),
        "stop_violations": sum(s["stop_violations"] for s in sysv),
        "trip_latency_clk": max(s["trip_latency_clk"] for s in sysv),
        "dcbus_mismatches": dc["mismatches"],
        "dcbus_gain_latency": dc["gain_latency"],
        "pwm_periods": sum(s["periods"] for s in sysv),
    }
    out["mismatches"] = (out["svpwm_mismatches"] + out["svpwm_sector_mismatches"]
                         + out["timer_mismatches"] + out["deadtime_violations"]
                         + out["runt_pulses"] + out["stop_violations"] + out["dcbus_mismatches"])
    out["vectors"] = sv["vectors"] + dc["vectors"] + out["pwm_periods"]
    out["clocks"] = sv["clocks"] + dc["clocks"] + sum(s["clocks"] for s in sysv)
    out["sim_s"] = sv["sim_s"] + dc["sim_s"] + sum(s["sim_s"] for s in sysv)
    out["clocks_per_s"] = out["clocks"] / out["sim_s"] if out["sim_s"] > 0 else 0.0
    out["svpwm_clocks_per_s"] = sv["clocks"] / sv["sim_s"] if sv["sim_s"] > 0 else 0.0
    out["system"] = systems
    return out
