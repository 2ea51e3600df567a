# amaranth: UnusedElaboratable=no
# Ref: issue 4 item 7; AD7380-4 data sheet, timing specifications and serial interface
import dataclasses

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Const, Value

import foc_servo.sim.verify.adc as verify_adc
from foc_servo.hdl.adc import AD7380_4, CHANNELS, AdcInterface
from foc_servo.sim.adc_part import AdcPartModel, AdcTimingError
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.adc import code_from_volts_np, schedule_np, volts_from_code_np

CORNERS = [(-32768, 32767, 0, -1), (1, -2, 0x5555, -0x5556), (32767, -32768, -1, 0)]


def run_interface(dut, strobes, clocks, *, sim_hz=None, codes=None, seed=0):
    """Simulate ``dut`` with the AD7380-4 model; ``sample`` high in the clocks ``strobes``.

    Returns the per-clock record (cs_n, sclk, valid, overrun, payload tuple) and the model."""
    sim_hz = sim_hz or dut.clk_hz
    if codes is None:
        rng = np.random.default_rng(seed)
        codes = rng.integers(-32768, 32768, size=(4 * len(strobes) + 4, 4))
        for k, c in enumerate(CORNERS):
            codes[2 * k] = c
    model = AdcPartModel(cs_n=dut.cs_n, sclk=dut.sclk, sdo=dut.sdo, clk_hz=sim_hz,
                         source=lambda n: codes[n], seed=seed)
    record = []
    strobes = set(strobes)

    async def testbench(ctx):
        for t in range(clocks):
            ctx.set(dut.sample, t in strobes)
            p = ctx.get(dut.o.payload)
            record.append((ctx.get(dut.cs_n), ctx.get(dut.sclk), ctx.get(dut.o.valid),
                           ctx.get(dut.overrun), tuple(p[n] for n in CHANNELS)))
            await ctx.tick()

    simulate(dut, [testbench], [model.process], clock_hz=sim_hz, name="test_adc")
    return record, model, codes


@pytest.mark.parametrize("kwargs, exc, message", [
    ({"clk_hz": "50e6"}, TypeError, r"^AdcInterface clk_hz must be a number in Hz, not '50e6'$"),
    ({"clk_hz": 0.5e6}, ValueError,
     r"^AdcInterface clk_hz must be from 1 MHz to 500 MHz, not 500000\.0$"),
    ({"sclk_hz": 100e6}, ValueError,
     r"^AdcInterface sclk_hz must be above 0 and at most the AD7380-4's f_SCLK of 80 MHz, "
     r"not 100000000\.0$"),
    ({"sclk_hz": 0}, ValueError, r"^AdcInterface sclk_hz must be above 0 and at most"),
    ({"part": "AD7606"}, ValueError,
     r"^AdcInterface part must be one of \['AD7380-4'\], not 'AD7606'$"),
    ({"part": 7380}, TypeError, r"^AdcInterface part must be a part name or an AdcPart, "
                                r"not 7380$"),
    ({"marker": 1}, TypeError, r"^AdcInterface marker must be a bool, not 1$"),
])
def test_adc_parameter_validation(kwargs, exc, message):
    with pytest.raises(exc, match=message):
        AdcInterface(**kwargs)


@pytest.mark.parametrize("clk_hz, latency, h", [(50e6, 47, 1), (33.333e6, 43, 1), (100e6, 91, 2)])
def test_adc_timing_attributes(clk_hz, latency, h):
    dut = AdcInterface(clk_hz=clk_hz)
    assert (dut.latency, dut.half_period) == (latency, h)
    assert dut.sclk_actual_hz <= 25e6
    assert dut.latency_s == pytest.approx(latency / clk_hz)
    assert dut.min_period > dut.latency


@pytest.mark.parametrize("marker", [False, True])
@pytest.mark.parametrize("clk_hz", [50e6, 33.333e6])
def test_adc_codes_round_trip_and_latency_cycle_by_cycle(clk_hz, marker):
    dut = AdcInterface(clk_hz=clk_hz, marker=marker)
    period = dut.min_period
    strobes = [2, 2 + period, 2 + 2 * period + 7]
    rec, model, codes = run_interface(dut, strobes, strobes[-1] + period + 2)
    cs = [r[0] for r in rec]
    valid_at = [t for t, r in enumerate(rec) if r[2]]
    # The CS falling edge (the sampling instant) comes sample_delay clocks after each strobe.
    falls = [t for t in range(1, len(cs)) if cs[t - 1] and not cs[t]]
    assert falls[0::2] == [s + dut.sample_delay for s in strobes]
    assert valid_at == [s + dut.latency for s in strobes]
    # Each output is the conversion started by its strobe's first CS pulse, exactly.
    for k, t in enumerate(valid_at):
        assert rec[t][4] == tuple(codes[2 * k]), k
        assert rec[t + 1][4] == rec[t][4]           # payload holds between valids
    assert model.reads == [(-1, 0), (0, 16), (1, 0), (2, 16), (3, 0), (4, 16)]
    assert not any(r[3] for r in rec)
    # SCLK idles high and toggles only while CS is low.
    assert all(r[1] for r in rec if r[0])


@pytest.mark.parametrize("marker", [False, True])
@pytest.mark.parametrize("held", [None, ("udc",), (), ("ia", "aux")])
def test_adc_held_channels_and_hold_window(held, marker):
    # Back-to-back strobes (min_period apart): a held channel keeps its code until the next
    # valid; another (its shift register) for exactly `hold` clocks from its valid (with the
    # marker the first channel's; the others' 2·h clocks longer, as without it).
    dut = AdcInterface(clk_hz=33.333e6, held=held, marker=marker)
    assert dut.held == (CHANNELS if held is None else held)
    p = dut.min_period
    strobes = [1, 1 + p, 1 + 2 * p]
    # Codes whose first shifted-in bit changes them (not the corners 0 / −1 / −2**15 …).
    codes = np.array([[0x1234, -0x4321, 0x0F0F, -0x7070]] * 16) + np.arange(16)[:, None]
    rec, model, codes = run_interface(dut, strobes, 1 + 3 * p + 2, codes=codes)
    valid_at = [t for t, r in enumerate(rec) if r[2]]
    assert valid_at == [s + dut.latency for s in strobes]
    for k, t in enumerate(valid_at[:2]):
        for c, name in enumerate(CHANNELS):
            seq = [rec[u][4][c] for u in range(t, valid_at[k + 1])]
            assert seq[0] == codes[2 * k][c]
            if name in dut.held:
                assert set(seq) == {seq[0]}, name
            else:
                hold = dut.hold + (2 * dut.half_period if marker and c else 0)
                assert seq[:hold] == [seq[0]] * hold, name
                # Then the next frame's bits (or the marker) come in.
                assert seq[hold] != seq[0], name
    assert dut.hold == p - 2 * dut.half_period * (AD7380_4.bits - (0 if marker else 1))


def test_adc_held_validation():
    with pytest.raises(TypeError, match=r"^AdcInterface held must be None or a tuple of "
                                        r"distinct channel names, not \['udc'\]$"):
        AdcInterface(held=["udc"])
    with pytest.raises(TypeError, match=r"^AdcInterface held must be None or a tuple"):
        AdcInterface(held=("udc", "udc"))
    with pytest.raises(ValueError, match=r"^AdcInterface held must name channels of "
                                         r"\('ia', 'ib', 'udc', 'aux'\), not \('vbus',\)$"):
        AdcInterface(held=("vbus",))


def test_adc_sclk_cycles_and_half_period_at_100mhz():
    dut = AdcInterface(clk_hz=100e6)
    rec, model, codes = run_interface(dut, [1], dut.min_period + 2)
    sclk = [r[1] for r in rec]
    falls = [t for t in range(1, len(sclk)) if sclk[t - 1] and not sclk[t]]
    assert len(falls) == 16 and set(np.diff(falls).tolist()) == {2 * dut.half_period}
    assert rec[1 + dut.latency][4] == tuple(codes[0])


def test_adc_overrun_drops_strobe_and_min_period_is_exact():
    dut = AdcInterface()
    p = dut.min_period
    strobes = [1, 1 + p - 1, 1 + p, 1 + p + 5]      # 2nd and 4th come while busy
    rec, model, codes = run_interface(dut, strobes, 1 + 2 * p + 2)
    overrun_at = [t for t, r in enumerate(rec) if r[3]]
    assert overrun_at == [strobes[1] + 1, strobes[3] + 1]
    valid_at = [t for t, r in enumerate(rec) if r[2]]
    assert valid_at == [1 + dut.latency, 1 + p + dut.latency]
    assert [rec[t][4] for t in valid_at] == [tuple(codes[0]), tuple(codes[2])]
    served, vclk = schedule_np(strobes, min_period=p, latency=dut.latency)
    assert served.tolist() == [True, False, True, False] and vclk.tolist() == valid_at


@pytest.mark.parametrize("interface, sim_hz, param", [
    # Told the part converts in 50 ns: the read frame starts during the conversion.
    ({"part": dataclasses.replace(AD7380_4, t_convert_s=50e-9, t_cyc_s=50e-9)}, 50e6,
     "t_CONVERT"),
    # Told 50 MHz but clocked at 100 MHz: every wait is half as long (reading during conversion).
    ({"clk_hz": 50e6}, 100e6, "t_CONVERT"),
    # Conversion time respected, throughput not: falling edges 200 ns apart.
    ({"part": dataclasses.replace(AD7380_4, t_cyc_s=150e-9)}, 50e6, "t_CYC"),
    # SCLK too fast: 100 MHz.
    ({"clk_hz": 200e6, "sclk_hz": 100e6,
      "part": dataclasses.replace(AD7380_4, f_sclk_max_hz=100e6)}, 200e6, "t_SCLK"),
    # CS high for 10 ns between transactions.
    ({"clk_hz": 200e6, "part": dataclasses.replace(AD7380_4, t_csh_s=5e-9)}, 200e6, "t_CSH"),
    # First SCLK falling edge 5 ns after CS.
    ({"clk_hz": 200e6, "part": dataclasses.replace(AD7380_4, t_sclked_s=0.0)}, 200e6,
     "t_SCLKED"),
])
def test_adc_model_detects_each_violation(interface, sim_hz, param):
    dut = AdcInterface(**interface)
    p = dut.min_period
    with pytest.raises(AdcTimingError, match=rf"^AD7380-4 {param} violated: .* requires at least"):
        run_interface(dut, [1, 1 + p, 1 + 2 * p], 1 + 3 * p + 2, sim_hz=sim_hz)


@pytest.mark.parametrize("high, low, param", [(1, 4, "t_SCLKH"), (4, 1, "t_SCLKL")])
def test_adc_model_detects_short_sclk_phases(high, low, param):
    # A hand-driven master at 400 MHz (2.5 ns clocks): one SCLK phase below 5 ns.
    from amaranth.hdl import Module, Signal
    from amaranth.lib import wiring
    from amaranth.lib.wiring import In, Out

    class Pins(wiring.Component):
        cs_n: Out(1, init=1)
        sclk: Out(1, init=1)
        sdo: In(4)

        def elaborate(self, platform):
            m = Module()
            m.d.sync += Signal().eq(1)               # a sync domain for the clock
            return m

    pins = Pins()
    model = AdcPartModel(cs_n=pins.cs_n, sclk=pins.sclk, sdo=pins.sdo, clk_hz=400e6,
                         source=lambda n: (0, 0, 0, 0))

    async def testbench(ctx):
        # Plain ticks (not .repeat()): the model's exception leaves this coroutine suspended.
        wave = [(0, 1)] * 8 + ([(0, 0)] * low + [(0, 1)] * high) * 4
        for cs_n, sclk in wave:
            ctx.set(pins.cs_n, cs_n)
            ctx.set(pins.sclk, sclk)
            await ctx.tick()

    with pytest.raises(AdcTimingError, match=rf"^AD7380-4 {param} violated"):
        simulate(pins, [testbench], [model.process], clock_hz=400e6)


def test_adc_transfer_function_model():
    vref = 3.3
    lsb = 2 * vref / 65536
    v = np.array([0.0, lsb * 0.49, lsb * 0.5, -lsb * 0.5, 2 * vref, -2 * vref, 1000.5 * lsb])
    np.testing.assert_array_equal(code_from_volts_np(v, vref=vref),
                                  [0, 0, 1, 0, 32767, -32768, 1001])
    codes = np.array([-32768, -1, 0, 1, 32767])
    np.testing.assert_array_equal(code_from_volts_np(volts_from_code_np(codes)), codes)


def test_adc_random_vs_model_50mhz():
    result = verify_adc.run(300, seed=5)
    assert result["mismatches"] == 0, result
    assert result["vectors"] == 300 and result["overruns"] > 5


@pytest.mark.parametrize("marker", [False, True])
def test_adc_random_vs_model_33mhz(marker):
    result = verify_adc.run(150, seed=6, clk_hz=33.333e6, marker=marker)
    assert result["mismatches"] == 0, result


@pytest.mark.parametrize("held", [(), None])
@pytest.mark.parametrize("clk_hz, sclk_hz", [(33.333e6, 25e6), (100e6, 25e6), (50e6, 5e6)])
def test_adc_marker_lockstep_with_the_counter(clk_hz, sclk_hz, held):
    """``marker=True`` against the counter form, every clock, on the same strobes (served,
    dropped, back to back) and codes: the same pins, ``valid``, ``overrun``, ``busy`` and
    payload but, not held, the first channel's between its load with the marker (2·h·bits
    clocks before a frame's ``o.valid``) and that ``o.valid``, where the marker form's register
    holds the bits sampled so far below a marker bit (zeros above it)."""
    h = AdcInterface(clk_hz=clk_hz, sclk_hz=sclk_hz).half_period
    recs = {}
    for marker in (False, True):
        dut = AdcInterface(clk_hz=clk_hz, sclk_hz=sclk_hz, marker=marker, held=held)
        p = dut.min_period
        strobes = [1, 1 + p, 1 + 2 * p - 1, 1 + 2 * p + 3, 2 + 3 * p + 11, 2 + 4 * p + 11]
        recs[marker] = run_interface(dut, strobes, 4 + 5 * p + 11, seed=3)[0]
    old, new = recs[False], recs[True]
    valid_at = [t for t, r in enumerate(old) if r[2]]
    assert len(valid_at) == 5
    window = {t for v in valid_at for t in range(v - 2 * h * AD7380_4.bits, v)}
    for t, (a, b) in enumerate(zip(old, new)):
        assert a[:4] == b[:4], t
        assert a[4][1:] == b[4][1:], t
        if t not in window or held is None:
            assert a[4][0] == b[4][0], t
        else:
            # The marker at bit k with the k bits sampled so far below it.
            k = (t - (valid_at[0] if t < valid_at[0] else
                      min(v for v in valid_at if v > t)) + 2 * h * AD7380_4.bits) // (2 * h)
            got = b[4][0] & 0xFFFF
            assert got >> k == 1, t
            assert got & ((1 << k) - 1) == (a[4][0] & 0xFFFF) & ((1 << k) - 1), t


def test_adc_converts_to_verilog():
    dut = AdcInterface()
    # amaranth 0.5.10's convert() cannot take a Component whose interface holds constants (the
    # always-ready `o.ready`, amaranth-lang/amaranth#1574): list the ports without them.
    ports = [Value.cast(v) for _, _, v in dut.signature.flatten(dut)]
    ports = [p for p in ports if not isinstance(p, Const)]
    text = verilog.convert(dut, name="adc_interface", ports=ports)
    assert "module adc_interface" in text and "cs_n" in text


@pytest.mark.slow
def test_adc_10k_conversions_vs_model():
    result = verify_adc.run(10_000)
    assert result["mismatches"] == 0, result
