# Ref: SPEC.md §2.3 (paper Fig. 6): M/T speed, n = ΔM·60·f_TCLK/(P_n·ΔT), D_n = k·ΔM/ΔT
"""Gateware :class:`~foc_servo.hdl.mt_speed.MTSpeed` against its golden model, and the M/T error
table of issue 4.

Two engines, stated in the result:

* **Gateware vs model** (``mismatches``): a seeded random speed profile (constant stretches,
  ramps of steps, reversals, stops longer than the TC span) on a scaled-down instance, the
  encoder strobes from :func:`~foc_servo.sim.models.mt_speed.ideal_encoder_edges`, random update
  spacing down to the minimum; every output (clock, speed, stopped, fresh) compared.
* **Error table** (``mt_err_pct_*``, ``table``, ``mt_min_rpm_1mhz_16bit``): the bit-true
  event-driven golden model (checked against the gateware cycle for cycle in
  ``tests/test_mt_speed.py`` and by the comparison above) at the issue's full-size configurations
  (50 MHz clock, 10 kHz update, 5000-line ideal encoder at constant speed; millions of clocks per
  low speed, out of reach of the Python simulator).
"""

import math

import numpy as np
from amaranth.hdl import Module, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.mt_speed import MTSpeed
from ...hdl.regmap import MT_EDGES_PER_LINE
from ..harness import Progress, simulate
from ..models.mt_speed import MTParams, ideal_encoder_edges, k_for, simulate as model_simulate

__all__ = ["run", "run_gateware", "error_run", "error_table", "min_resolvable_rpm", "table_text",
           "random_profile"]

_FIELDS = ("cycle", "speed", "stopped", "fresh")

# Full-size configurations of the targets.
LINES = 5000
UPDATE_HZ = 10e3
CLK_HZ = 50e6
FULL_SCALE_RPM = 12000          # N_M: 10 000 r/min must be measurable
ERR_OUT_WIDTH = 32              # Q1.31 speed for the error table (see error_table)
CONFIGS = {
    "sysclk": dict(clk_hz=CLK_HZ, tclk_hz=CLK_HZ, tc_width=32),
    "1mhz": dict(clk_hz=CLK_HZ, tclk_hz=1e6, tc_width=16),
}


class _Bench(wiring.Component):
    """Simulation-only wrapper: a stimulus ROM plays the strobes at their clocks into the DUT; a
    RAM captures every output with its clock. The testbench only waits, then reads the RAM.

    ``cycle`` is the clock index; ``received`` the number of outputs captured.
    """

    cycle: Out(40)
    received: Out(32)

    def __init__(self, dut, stim, depth, k):
        self.dut = dut
        self._stim = stim                       # list of (cycle, step, neg, update)
        self._depth = depth
        self._k = k
        self.stim_layout = data.StructLayout({"cycle": 40, "step": 1, "neg": 1, "update": 1})
        self.cap_layout = data.StructLayout({"cycle": 40, "payload": dut.o.payload.shape()})
        words = [c | (st << 40) | (ng << 41) | (up << 42) for c, st, ng, up in stim]
        words.append((1 << 40) - 1)             # sentinel: never reached
        self._words = words
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self.dut
        m.submodules.stim = stim = Memory(shape=unsigned(self.stim_layout.size),
                                          depth=len(self._words), init=self._words)
        m.submodules.cap = self.cap = cap = Memory(shape=unsigned(self.cap_layout.size),
                                                   depth=self._depth, init=[])
        rd = stim.read_port(domain="comb")
        wr = cap.write_port()
        addr = Signal(range(len(self._words)))
        ev = data.View(self.stim_layout, rd.data)
        fire = ev.cycle == self.cycle
        m.d.comb += [
            rd.addr.eq(addr),
            dut.k.eq(self._k),
            dut.edge.step.eq(fire & ev.step),
            dut.edge.neg.eq(fire & ev.neg),
            dut.update.eq(fire & ev.update),
        ]
        with m.If(fire):
            m.d.sync += addr.eq(addr + 1)
        m.d.sync += self.cycle.eq(self.cycle + 1)
        cap_word = data.View(self.cap_layout, wr.data)
        m.d.comb += [
            wr.addr.eq(self.received),
            cap_word.cycle.eq(self.cycle),
            cap_word.payload.eq(dut.o.payload),
            wr.en.eq(dut.o.valid & (self.received < self._depth)),
        ]
        with m.If(dut.o.valid):
            m.d.sync += self.received.eq(self.received + 1)
        return m


def run_gateware(dut, edge_cycles, edge_neg, update_cycles, *, k, end_cycle, max_outputs=None,
                 name="mt_speed", progress=None):
    """Simulate ``dut`` with these strobes (same arguments as the model's ``simulate``) for
    ``end_cycle`` clocks; returns its outputs as the model does (``cycle``, ``speed``,
    ``stopped``, ``fresh``) and the wall time under ``sim_s``."""
    events = {}
    for c, n in zip(np.asarray(edge_cycles).tolist(), np.asarray(edge_neg).tolist()):
        if c < end_cycle:
            events.setdefault(c, [0, 0, 0])[:2] = [1, int(n)]
    ups = [c for c in np.asarray(update_cycles).tolist() if c < end_cycle]
    for c in ups:
        events.setdefault(c, [0, 0, 0])[2] = 1
    depth = max_outputs if max_outputs is not None else len(ups) + 1
    bench = _Bench(dut, [(c, *events[c]) for c in sorted(events)], max(depth, 1), k)
    got = {}

    async def testbench(ctx):
        # Waiting on time rather than on clock edges is ~20 % faster in pysim. Outputs at or
        # after `end_cycle` (rounding of the clock period) are dropped below.
        chunk = 20_000
        done = 0
        while done < end_cycle:
            n = min(chunk, end_cycle - done)
            await ctx.delay(n / dut.clk_hz)
            done += n
            if progress is not None:
                progress.update(done)
        n = min(ctx.get(bench.received), depth)
        words = [ctx.get(bench.cap.data[i]) for i in range(n)]
        words = [w for w in words if w & ((1 << 40) - 1) < end_cycle]
        pl = [data.Const(dut.o.payload.shape(), w >> 40) for w in words]
        got["cycle"] = [w & ((1 << 40) - 1) for w in words]
        got["speed"] = [p.speed for p in pl]
        got["stopped"] = [p.stopped for p in pl]
        got["fresh"] = [p.fresh for p in pl]
        got["received"] = len(words) + max(ctx.get(bench.received) - n, 0)

    sim_s = simulate(bench, [testbench], clock_hz=dut.clk_hz, name=name)
    out = {f: np.array(got[f], dtype=np.int64) for f in _FIELDS}
    out["received"] = got["received"]
    out["updates"] = len(ups)
    out["sim_s"] = sim_s
    return out


def compare(got, want):
    """Number of outputs that differ (in clock or value), counting surplus or missing ones."""
    n = min(len(got["cycle"]), len(want["cycle"]))
    surplus = abs(got.get("received", len(got["cycle"])) - len(want["cycle"]))
    bad = np.zeros(n, dtype=bool)
    for f in _FIELDS:
        bad |= got[f][:n] != want[f][:n]
    return int(bad.sum()) + surplus


def random_profile(rng, duration_s, *, max_rpm, tc_span_s):
    """Seeded random speed profile: list of ``(duration_s, rpm)`` segments with constant
    stretches, steps, reversals (sign changes, some inside one update period) and stops
    (some longer than the TC span)."""
    segs, t = [], 0.0
    while t < duration_s:
        kind = rng.integers(6)
        if kind == 0:                                   # stop, short or past the TC span
            d = tc_span_s * rng.choice([0.3, 1.5])
            rpm = 0.0
        elif kind == 1:                                 # quick reversal
            d = tc_span_s * rng.uniform(0.005, 0.05)
            rpm = -math.copysign(1, segs[-1][1] if segs else 1) * max_rpm * rng.uniform(0.05, 1)
        else:                                           # constant speed, log-uniform magnitude
            d = tc_span_s * rng.uniform(0.05, 0.6)
            rpm = rng.choice([-1, 1]) * max_rpm * 10 ** rng.uniform(-3, 0)
        segs.append((float(d), float(rpm)))
        t += d
    return segs


def _random_updates(rng, end_cycle, *, mean, minimum):
    """Update strobes with random spacing in [minimum - 5, 2·mean - minimum] (some too early)."""
    gaps = rng.integers(max(minimum - 5, 1), max(2 * mean - minimum, minimum) + 1,
                        size=int(end_cycle / max(minimum, 1)) + 2)
    c = np.cumsum(gaps)
    return c[c < end_cycle]


def compare_run(dut, *, seed, end_cycle, k, lines, max_rpm, update_mean, progress=None):
    """Random profile on ``dut``; returns (mismatches, gateware outputs, model outputs)."""
    rng = np.random.default_rng(seed)
    segs = random_profile(rng, end_cycle / dut.clk_hz, max_rpm=max_rpm, tc_span_s=dut.tc_span_s)
    edges, neg = ideal_encoder_edges(segs, clk_hz=dut.clk_hz, lines=lines,
                                     edge_mode=dut.edge_mode, phase=rng.uniform())
    ups = _random_updates(rng, end_cycle, mean=update_mean, minimum=dut.latency)
    got = run_gateware(dut, edges, neg, ups, k=k, end_cycle=end_cycle, progress=progress)
    want = model_simulate(edges, neg, ups, k=k, params=MTParams.of(dut), end_cycle=end_cycle)
    return compare(got, want), got, want


# --- error table (golden model) ---------------------------------------------------------------

def error_run(rpm, *, config="sysclk", phase=0.0, out_width=ERR_OUT_WIDTH, lines=LINES,
              update_hz=UPDATE_HZ, full_scale_rpm=FULL_SCALE_RPM, edge_mode="a_rising"):
    """Worst relative error (%) of the steady outputs at constant ``rpm`` (model engine).

    Steady outputs: every output from the first fresh measurement on (bounded and stopped ones
    included; a stopped output counts 100 %), over max(20 update periods, 4 edge periods).
    """
    cfg = dict(CONFIGS[config])
    clk_hz = cfg["clk_hz"]
    params = MTParams.config(out_width=out_width, **cfg)
    k = k_for(lines, params.tclk_hz(clk_hz), full_scale_rpm, out_width=out_width,
              edge_mode=edge_mode, k_width=params.k_width)
    t_edge = 60.0 / (abs(rpm) * lines * MT_EDGES_PER_LINE[edge_mode])
    t_u = 1.0 / update_hz
    duration = 2 * t_edge + 2 * t_u + max(20 * t_u, 4 * t_edge)
    edges, neg = ideal_encoder_edges([(duration, rpm)], clk_hz=clk_hz, lines=lines,
                                     edge_mode=edge_mode, phase=phase)
    period = round(clk_hz / update_hz)
    ups = np.arange(period, int(duration * clk_hz), period)
    out = model_simulate(edges, neg, ups, k=k, params=params)
    first = np.flatnonzero(out["fresh"])
    if first.size == 0:
        return 100.0
    steady = slice(first[0], None)
    rpm_out = out["speed"][steady] * (full_scale_rpm / 2 ** (out_width - 1))
    return float(np.max(np.abs(rpm_out - rpm)) / abs(rpm) * 100)


def _worst(rpm, config, phases, **kw):
    return max(error_run(s * rpm, config=config, phase=p, **kw) for s in (1, -1) for p in phases)


def error_table(speeds_rpm=None, *, phases=(0.0, 0.37, 0.81), **kw):
    """Rows ``{rpm, err_pct_sysclk, err_pct_1mhz}``: worst over both directions and the encoder
    phases."""
    if speeds_rpm is None:
        speeds_rpm = speed_grid()
    return [{"rpm": float(rpm),
             "err_pct_sysclk": _worst(rpm, "sysclk", phases, **kw),
             "err_pct_1mhz": _worst(rpm, "1mhz", phases, **kw)} for rpm in speeds_rpm]


def speed_grid():
    """0.2 … 10 000 r/min: the decade points and 7 irrational-ratio points per decade between."""
    grid = {0.2, 10.0, 10000.0}
    for e in np.arange(math.log10(0.2), 4.0, 1 / 8):
        grid.add(float(f"{10 ** (e + 0.031):.4g}"))
    return sorted(x for x in grid if 0.2 <= x <= 10000)


def min_resolvable_rpm(*, config="1mhz", tol_rpm=1e-3, err_pct=1.0, phases=(0.0, 0.5)):
    """Lowest constant speed (bisection) whose steady outputs are all measurements (never
    stopped) within ``err_pct``; both directions."""
    ok = lambda rpm: _worst(rpm, config, phases) <= err_pct         # noqa: E731
    lo, hi = 0.01, 1.0
    if not ok(hi):
        return math.inf
    while hi - lo > tol_rpm:
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi


def table_text(result):
    """The error table of :func:`run`'s result as text lines (for ``foc-servo bench io``)."""
    lines = [f"M/T speed error, 5000 lines, 10 kHz update, 50 MHz clock ({result['engine_table']})",
             f"{'r/min':>10} {'f_TCLK=50 MHz/32 bit %':>24} {'f_TCLK=1 MHz/16 bit %':>24}"]
    for row in result["table"]:
        lines.append(f"{row['rpm']:>10.4g} {row['err_pct_sysclk']:>24.5f} "
                     f"{row['err_pct_1mhz']:>24.5f}")
    lines.append(f"lowest resolvable speed, 1 MHz / 16 bit: {result['mt_min_rpm_1mhz_16bit']:.3f} "
                 f"r/min (formula 60·f_TCLK/(lines·(2**16 − 1)) = "
                 f"{result['mt_min_rpm_1mhz_16bit_formula']:.3f})")
    return lines


# --- run --------------------------------------------------------------------------------------

def run(count=100_000, *, seed=0, progress=False, table=True):
    """Gateware vs model over ``count`` update strobes, plus the error table.

    Python simulation runs ~10 k clocks/s, so the gateware instance for the bulk comparison is
    a narrow one in which every regime and saturation happens within few clocks: 1 MHz clock,
    f_TCLK = clk/2 (prescaler), 8-bit TC (span 512 clocks), 100-line ×4 encoder at 40 … 40 000
    r/min (up to one edge every 3.75 clocks; the 4-bit ΔM saturates at high speed), updates
    every 12 … 33 clocks (latency 17: some arrive too early and are ignored by design),
    out_width 8, k_width 8, m_width 4. The full-width configurations are compared in the tests.

    Returns
    -------
    dict
        ``mismatches``, ``vectors`` (outputs compared), ``updates`` (strobes sent), ``clocks``,
        ``sim_s``, ``clk_per_s``, ``latency_clk``, the counts of ``fresh``/``bound``/``stopped``
        outputs, and with ``table``: ``mt_err_pct_10_10000``, ``mt_err_pct_0p2_10`` (50 MHz
        f_TCLK, 32-bit TC), the same for 1 MHz / 16 bit (``..._1mhz``), ``mt_min_rpm_1mhz_16bit``,
        ``table``, ``engine_table``, ``out_width_table`` and ``full_scale_rpm_table``. The table
        uses a Q1.31 speed output (out_width 32): with the system's Q1.15 one LSB of a
        12 000 r/min full scale is 0.37 r/min, 3.7 % of 10 r/min; ``mt_err_pct_*_q15`` give the
        figures at out_width 16 for comparison.
    """
    dut = MTSpeed(clk_hz=1e6, tclk_hz=0.5e6, tc_width=8, out_width=8, edge_mode="x4",
                  k_width=8, m_width=4)
    lines, full_scale_rpm, max_rpm = 100, 60000, 40000
    k = k_for(lines, dut.tclk_hz, full_scale_rpm, out_width=8, edge_mode="x4",
              k_width=dut.k_width)
    update_mean = 25
    end_cycle = int(count * update_mean) + 200
    prog = Progress("mt_speed gateware vs model", end_cycle, enabled=progress)
    mism, got, want = compare_run(dut, seed=seed, end_cycle=end_cycle, k=k, lines=lines,
                                  max_rpm=max_rpm, update_mean=update_mean, progress=prog)
    prog.close()
    result = {
        "mismatches": mism,
        "vectors": int(len(want["cycle"])),
        "updates": int(got["updates"]),
        "clocks": end_cycle,
        "sim_s": got["sim_s"],
        "clk_per_s": end_cycle / got["sim_s"],
        "latency_clk": dut.latency,
        "fresh": int(want["fresh"].sum()),
        "bound": int(((want["fresh"] == 0) & (want["stopped"] == 0)).sum()),
        "stopped": int(want["stopped"].sum()),
        "engine": "gateware (Amaranth pysim) vs bit-true golden model",
    }
    if table:
        rows = error_table()
        rows16 = error_table(phases=(0.0, 0.37), out_width=16)
        band = lambda key, lo, hi, rows=rows: max(r[key] for r in rows          # noqa: E731
                                                  if lo <= r["rpm"] <= hi)
        result.update({
            "mt_err_pct_10_10000": band("err_pct_sysclk", 10, 10000),
            "mt_err_pct_0p2_10": band("err_pct_sysclk", 0.2, 10),
            "mt_err_pct_10_10000_1mhz": band("err_pct_1mhz", 10, 10000),
            "mt_err_pct_0p2_10_1mhz": band("err_pct_1mhz", 0.2, 10),
            "mt_err_pct_10_10000_q15": band("err_pct_sysclk", 10, 10000, rows16),
            "mt_err_pct_0p2_10_q15": band("err_pct_sysclk", 0.2, 10, rows16),
            "mt_min_rpm_1mhz_16bit": min_resolvable_rpm(),
            "mt_min_rpm_1mhz_16bit_formula": 60 * 1e6 / (LINES * ((1 << 16) - 1)),
            "table": rows,
            "out_width_table": ERR_OUT_WIDTH,
            "full_scale_rpm_table": FULL_SCALE_RPM,
            "engine_table": "golden model (bit-true, checked against gateware in "
                            "tests/test_mt_speed.py)",
        })
    return result
