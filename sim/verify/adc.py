# Ref: issue 4 item 7; AD7380-4 data sheet, timing specifications and serial interface
"""Gateware :class:`~foc_servo.hdl.adc.AdcInterface` against the pin-level AD7380-4 model.

A simulation-only wrapper holds the strobe intervals and the expected codes in ROMs, raises
``sample`` at the programmed clocks, and counts outputs, mismatching outputs and overruns in
gateware; :class:`~foc_servo.sim.adc_part.AdcPartModel` drives SDO from the seeded codes and checks
every datasheet timing parameter (a violation raises and ends the run); the testbench only ticks.
"""

import numpy as np
from amaranth.hdl import Module, Signal, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.adc import AdcInterface
from ..adc_part import AdcPartModel
from ..harness import Progress, simulate
from ..models.adc import schedule_np

__all__ = ["run", "stimulus"]


def stimulus(count, *, seed=0, bits=16, lines=4, min_period):
    """Seeded stimulus: strobe intervals and the codes of every conversion.

    Intervals: mostly ``min_period`` … ``min_period + 40`` clocks, one in 16 exactly
    ``min_period``, one in 16 a strobe 1 … ``min_period − 1`` clocks after the previous one (it
    must be dropped). Codes: uniform over the code range, with the corner codes (most negative,
    −1, 0, 1, most positive, alternating bit patterns) on all lines for the first conversions.

    Returns
    -------
    intervals : int64 array
        Clocks from one strobe to the next (the first from clock 0).
    codes : int64 array, shape (2·count + 2, lines)
        Codes of conversion ``n`` (two per served strobe: the read one and the dummy one).
    """
    rng = np.random.default_rng([seed, 7])
    n_strobes = count + count // 8 + 16      # ~1/16 are dropped
    intervals = rng.integers(min_period, min_period + 41, size=n_strobes)
    kind = rng.integers(0, 16, size=n_strobes)
    intervals[kind == 0] = min_period
    early = kind == 1
    intervals[early] = rng.integers(1, min_period, size=int(early.sum()))
    intervals[0] = 3
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    codes = rng.integers(lo, hi + 1, size=(2 * n_strobes + 2, lines))
    alt = int("01" * (bits // 2), 2)            # 0101…01 and its complement 1010…10
    corners = [lo, -1, 0, 1, hi, alt, ~alt]
    for k, c in enumerate(corners):
        codes[2 * k] = c
    return intervals.astype(np.int64), codes.astype(np.int64)


class _AdcBench(wiring.Component):
    """Simulation-only wrapper: interval ROM → ``sample`` strobes → interface; outputs compared
    with the expected-code ROM."""

    received: Out(32)
    mismatches: Out(32)
    overruns: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)

    def __init__(self, dut, intervals, expected):
        self._dut = dut
        self._intervals = intervals
        self._expected = expected
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        width = int(max(self._intervals)).bit_length() + 1
        m.submodules.ivl = ivl = Memory(shape=unsigned(width), depth=len(self._intervals),
                                        init=self._intervals)
        out_bits = dut.o.payload.shape().size
        m.submodules.exp = exp = Memory(shape=unsigned(out_bits),
                                        depth=max(len(self._expected), 1), init=self._expected)
        ird = ivl.read_port(domain="comb")
        erd = exp.read_port(domain="comb")

        index = Signal(range(len(self._intervals) + 1))
        wait = Signal(width, init=int(self._intervals[0]) - 1)
        running = index < len(self._intervals)
        m.d.comb += [ird.addr.eq(index + 1), erd.addr.eq(self.received)]
        with m.If(running):
            with m.If(wait == 0):
                m.d.comb += dut.sample.eq(1)
                m.d.sync += [index.eq(index + 1), wait.eq(ird.data - 1)]
            with m.Else():
                m.d.sync += wait.eq(wait - 1)

        with m.If(dut.overrun):
            m.d.sync += self.overruns.eq(self.overruns + 1)
        with m.If(dut.o.valid):
            m.d.sync += self.received.eq(self.received + 1)
            bad = (self.received >= len(self._expected)) | (dut.o.payload.as_value() != erd.data)
            with m.If(bad):
                m.d.sync += self.mismatches.eq(self.mismatches + 1)
                with m.If(self.mismatches == 0):
                    m.d.sync += self.first_mismatch.eq(self.received)
        return m


def _pack(codes, bits):
    mask = (1 << bits) - 1
    words = []
    for row in codes.tolist():
        w = 0
        for k, c in enumerate(row):
            w |= (c & mask) << (k * bits)
        words.append(w)
    return words


def run(count=100_000, *, seed=0, progress=False, clk_hz=50e6, sclk_hz=25e6, part="AD7380-4",
        marker=False):
    """Simulate :class:`AdcInterface` with the pin-level part model over ``count`` conversions
    (plus dropped strobes) and compare every output with the codes the model converted
    (``marker``: the interface's parameter).

    Returns
    -------
    dict
        ``mismatches`` (wrong or missing outputs, surplus outputs and overrun-count errors),
        ``vectors`` (served conversions), ``clocks``, ``sim_s``, ``clocks_per_s``, ``overruns``
        (dropped strobes, all expected), ``latency_clk``, ``latency_ns``, ``min_period_clk``,
        ``sclk_hz`` (actual), ``first_mismatch`` (index or ``None``).

    Raises
    ------
    foc_servo.sim.adc_part.AdcTimingError
        The interface violated a datasheet timing parameter of the part.
    """
    dut = AdcInterface(clk_hz=clk_hz, sclk_hz=sclk_hz, part=part, marker=marker)
    bits, lines = dut.part.bits, dut.part.lines
    intervals, codes = stimulus(count, seed=seed, bits=bits, lines=lines,
                                min_period=dut.min_period)
    strobes = np.cumsum(intervals) - 1          # clock of each strobe (first at intervals[0]-1)
    served, valid_clk = schedule_np(strobes, min_period=dut.min_period, latency=dut.latency)
    # Keep exactly `count` served strobes.
    last = np.flatnonzero(served)[count - 1]
    intervals = intervals[:last + 1]
    served = served[:last + 1]
    n_served = int(served.sum())
    expected = codes[0:2 * n_served:2]          # conversion 2k is read by transaction k
    clocks = int(strobes[last] + dut.min_period + 2)

    model = AdcPartModel(cs_n=dut.cs_n, sclk=dut.sclk, sdo=dut.sdo, clk_hz=clk_hz,
                         source=lambda n: codes[n], part=part, seed=seed)
    bench = _AdcBench(dut, intervals.tolist(), _pack(expected, bits))
    result = {}
    prog = Progress("adc", clocks, enabled=progress)

    async def testbench(ctx):
        await prog.ticks(ctx, clocks)
        for name in ("received", "mismatches", "overruns", "first_mismatch"):
            result[name] = ctx.get(getattr(bench, name))

    sim_s = simulate(bench, [testbench], [model.process], clock_hz=clk_hz, name="adc")
    prog.close()
    missing = n_served - min(result["received"], n_served)
    dropped_expected = int((~served).sum())
    overrun_err = abs(result["overruns"] - dropped_expected)
    first = result["first_mismatch"]
    return {
        "mismatches": result["mismatches"] + missing + overrun_err,
        "vectors": n_served,
        "clocks": clocks,
        "sim_s": sim_s,
        "clocks_per_s": clocks / sim_s if sim_s > 0 else float("inf"),
        "overruns": result["overruns"],
        "latency_clk": dut.latency,
        "latency_ns": dut.latency_s * 1e9,
        "min_period_clk": dut.min_period,
        "sclk_hz": dut.sclk_actual_hz,
        "first_mismatch": None if first == 0xFFFF_FFFF else int(first),
    }
