# Ref: SPEC.md §2.4 (paper Fig. 7, SVPWM), §2.5 (DC-bus compensation)
import gc
import math
import re
import warnings

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Fragment, UnusedElaboratable

import foc_servo.sim.verify.svpwm as verify_svpwm
from foc_servo.boards.area import ports
from foc_servo.hdl.svpwm import (SVPWM, DCBusCompensation, PWMTimer, pwm_half_period,
                                 svpwm_constants)
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import svpwm as model

FS = 1 << 15


# --- parameter validation -----------------------------------------------------------------------

@pytest.mark.parametrize("cls, kwargs, exc, message", [
    (SVPWM, {"width": 7}, TypeError, "SVPWM width must be an integer from 8 to 24, not 7"),
    (SVPWM, {"width": 16.0}, TypeError, "SVPWM width must be an integer from 8 to 24, not 16.0"),
    (SVPWM, {"count_width": 3}, TypeError,
     "SVPWM count_width must be an integer from 4 to 24, not 3"),
    (SVPWM, {"radix_bits": 5}, TypeError,
     "SVPWM radix_bits must be an integer from 1 to 4, not 5"),
    (DCBusCompensation, {"width": 25}, TypeError,
     "DCBusCompensation width must be an integer from 8 to 24, not 25"),
    (DCBusCompensation, {"out_width": 18}, ValueError,
     "DCBusCompensation out_width must be width (16) or width + 1, not 18"),
    (DCBusCompensation, {"out_width": "17"}, TypeError,
     "DCBusCompensation out_width must be None or an integer, not '17'"),
    (DCBusCompensation, {"adc_width": True}, TypeError,
     "DCBusCompensation adc_width must be an integer from 4 to 24, not True"),
    (DCBusCompensation, {"gain_limit": 4.0}, ValueError,
     "DCBusCompensation gain_limit must be at least 1.0 and below 4.0, not 4.0"),
    (DCBusCompensation, {"gain_limit": 0.5}, ValueError,
     "DCBusCompensation gain_limit must be at least 1.0 and below 4.0, not 0.5"),
    (DCBusCompensation, {"gain_limit": None}, TypeError,
     "DCBusCompensation gain_limit must be a number, not None"),
    (PWMTimer, {"clk_hz": 0}, TypeError,
     "PWMTimer clk_hz must be a positive number of Hz, not 0"),
    (PWMTimer, {"pwm_hz": "10k"}, TypeError,
     "PWMTimer pwm_hz must be a positive number of Hz, not '10k'"),
    (PWMTimer, {"pwm_hz": 10e6}, ValueError,
     "PWMTimer pwm_hz 1e+07 Hz is too high for clk_hz 5e+07 Hz: the half period must be at "
     "least 4 clocks, not 2"),
    (PWMTimer, {"pwm_hz": 300.0}, ValueError,
     "PWMTimer pwm_hz 300 Hz is too low for clk_hz 5e+07 Hz and count_width 16: the period of "
     "166666 clocks must be below 65536"),
    (PWMTimer, {"count_width": 30}, TypeError,
     "PWMTimer count_width must be an integer from 4 to 24, not 30"),
])
def test_svpwm_parameter_validation(cls, kwargs, exc, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)     # the half-built object
        with pytest.raises(exc, match=f"^{re.escape(message)}$"):
            cls(**kwargs)
        gc.collect()


def test_svpwm_blocks_convert_to_verilog():
    for dut in (SVPWM(), DCBusCompensation(out_width=17), PWMTimer(clk_hz=33.333e6, pwm_hz=100e3)):
        assert "module" in verilog.convert(dut, ports=ports(dut))


# --- the model: min–max injection == textbook sectors and dwell times ---------------------------

def test_svpwm_constants_match_model():
    for width in (8, 12, 16, 20, 24):
        assert svpwm_constants(width) == model.svpwm_constants(width)
        frac, k_frac, k = svpwm_constants(width)
        assert abs(k - 2 ** (8 + k_frac) / math.sqrt(3)) <= 0.5


def test_svpwm_minmax_equals_sector_dwell_time_formulation():
    rng = np.random.default_rng(11)
    n = 200_000
    alpha = rng.integers(-FS, FS, n)
    beta = rng.integers(-FS, FS, n)
    # Sector boundaries exactly: on the axes and the 30°/60° lines.
    t = rng.integers(-FS // 2, FS // 2, 2000)
    alpha = np.concatenate([alpha, t, 0 * t, t, -t, [0]])
    beta = np.concatenate([beta, 0 * t, t, np.rint(t * math.sqrt(3)).astype(np.int64),
                           np.rint(t * math.sqrt(3)).astype(np.int64), [0]])
    scale = rng.integers(1, 1 << 16, alpha.size)
    mm = model.svpwm(alpha, beta, scale)
    sec = model.svpwm_sector(alpha, beta, scale)
    for k in ("a", "b", "c", "overmod"):
        np.testing.assert_array_equal(mm[k], sec[k])
    assert np.all(sec["t1"] >= 0) and np.all(sec["t2"] >= 0)
    assert set(np.unique(sec["sector"])) == {1, 2, 3, 4, 5, 6}
    # Against the real-valued duties: each within half a count plus the u_β/√3 rounding.
    ideal, over = model.svpwm_ideal(alpha, beta)
    for i, k in enumerate("abc"):
        assert np.max(np.abs(mm[k] - ideal[i] * scale)) <= 0.5 + scale.max() * 2.0 ** -22
    np.testing.assert_array_equal(mm["overmod"] == 1, over)


def test_svpwm_overmodulation_keeps_the_angle():
    # 5 % to 40 % outside the hexagon, at angles where that fits the Q1.15 input range (close to
    # the α axis the hexagon's vertex is at the range's end).
    rng = np.random.default_rng(5)
    th = np.linspace(-math.pi, math.pi, 7201)
    r = np.sqrt(3) / 2 / np.cos(np.mod(th, np.pi / 3) - np.pi / 6) * rng.uniform(1.05, 1.4, th.size)
    ok = (np.abs(r * np.cos(th)) < 1) & (np.abs(r * np.sin(th)) < 1)
    th, r = th[ok], r[ok]
    assert th.size > 3000
    alpha = np.rint(r * np.cos(th) * FS).astype(np.int64)
    beta = np.rint(r * np.sin(th) * FS).astype(np.int64)
    d = model.svpwm(alpha, beta, 2500)
    assert np.all(d["overmod"] == 1)
    ua, ub = model.vector_of_duties(d["a"] / 2500, d["b"] / 2500, d["c"] / 2500)
    err = np.degrees(np.angle(np.exp(1j * (np.arctan2(ub, ua) - np.arctan2(beta, alpha)))))
    assert np.max(np.abs(err)) <= 0.1
    # On the hexagon: the largest line-to-line duty difference is the full scale (±1 count).
    spread = (np.max([d["a"], d["b"], d["c"]], axis=0) - np.min([d["a"], d["b"], d["c"]], axis=0))
    assert np.all(np.abs(spread - 2500) <= 1)


# --- SVPWM gateware -----------------------------------------------------------------------------

def svpwm_outputs(dut, commands, *, ready_delay=0):
    """Run commands one at a time; return ([(a, b, c, overmod)], [latency in clocks])."""
    outs, lats = [], []

    async def testbench(ctx):
        for alpha, beta, scale in commands:
            ctx.set(dut.i.payload, {"alpha": alpha, "beta": beta})
            ctx.set(dut.scale, scale)
            ctx.set(dut.i.valid, 1)
            assert ctx.get(dut.i.ready)
            await ctx.tick()
            ctx.set(dut.i.valid, 0)
            ctx.set(dut.scale, 0)                   # sampled with the command only
            clocks = 1
            while not ctx.get(dut.o.valid):
                assert not ctx.get(dut.i.ready)
                await ctx.tick()
                clocks += 1
            lats.append(clocks)
            for _ in range(ready_delay):            # held until taken
                await ctx.tick()
                assert ctx.get(dut.o.valid)
            p = ctx.get(dut.o.payload)
            outs.append((p.a, p.b, p.c, p.overmod))
            ctx.set(dut.o.ready, 1)
            await ctx.tick()
            ctx.set(dut.o.ready, 0)
            assert not ctx.get(dut.o.valid) and ctx.get(dut.i.ready)

    simulate(dut, [testbench], name="test_svpwm")
    return outs, lats


def test_svpwm_named_corners_and_latency_cycle_by_cycle():
    dut = SVPWM()
    r3 = math.sqrt(3) / 2
    named = {
        "zero": (0, 0, 2500, (1250, 1250, 1250, 0)),
        "zero_odd_scale": (0, 0, 2501, (1251, 1251, 1251, 0)),     # 1250.5 rounds half up
        "vertex_v1": (FS - 1, 0, 2500, None),
        "vertex_v4": (-FS, 0, 2500, (0, 2500, 2500, 0)),
        "edge_midpoint_90deg": (0, round(r3 * FS), 2500, None),
        "corner_min_min": (-FS, -FS, 2500, None),
        "corner_max_max": (FS - 1, FS - 1, 65535, None),
        "scale_one": (1000, -2000, 1, None),
        "max_scale": (12345, -23456, 65535, None),
    }
    cmds = [(a, b, s) for a, b, s, _ in named.values()]
    outs, lats = svpwm_outputs(dut, cmds, ready_delay=2)
    assert lats == [dut.latency] * len(cmds)
    exp = model.svpwm(*(np.array(x) for x in zip(*cmds)))
    for (name, (a, b, s, fixed)), got, k in zip(named.items(), outs, range(len(cmds))):
        assert got == (exp["a"][k], exp["b"][k], exp["c"][k], exp["overmod"][k]), name
        if fixed is not None:
            assert got == fixed, name
    # V1 vertex (just inside): phase A all on, B and C off; the 90° edge: A at half, B on, C off.
    assert outs[2] == (2500, 0, 0, 0)
    assert outs[4][1] >= 2499 and outs[4][2] <= 1
    assert outs[5][3] == 1 and outs[6][3] == 1            # outside the hexagon


def test_svpwm_q2_inputs_against_model_and_physics():
    """``frac = width − 2`` (the DC-bus compensation's Q2 output): 1.0 is ``2**(w−2)``; random
    commands up to |u| = 1.9 match the model, and inside the hexagon the duties make the
    commanded vector (``vector_of_duties``) within a count."""
    width, frac, scale = 17, 15, 2500
    dut = SVPWM(width=width, frac=frac)
    assert dut.in_frac == frac
    rng = np.random.default_rng(11)
    mag = rng.uniform(0, 1.9, 60)
    ang = rng.uniform(-math.pi, math.pi, 60)
    a = np.rint(mag * np.cos(ang) * FS).astype(int)
    b = np.rint(mag * np.sin(ang) * FS).astype(int)
    a[:2], b[:2] = (-(1 << 16), (1 << 16) - 1), (0, (1 << 16) - 1)       # the Q2 extremes
    cmds = [(int(x), int(y), scale) for x, y in zip(a, b)]
    outs, lats = svpwm_outputs(dut, cmds, ready_delay=0)
    assert lats == [dut.latency] * len(cmds)
    exp = model.svpwm(a, b, np.full(len(a), scale), width=width, frac=frac)
    for k, got in enumerate(outs):
        assert got == (exp["a"][k], exp["b"][k], exp["c"][k], exp["overmod"][k]), k
    ua, ub = model.vector_of_duties(*(np.array([o[i] for o in outs]) / scale for i in range(3)))
    inside = exp["overmod"] == 0
    assert inside.sum() > 10 and (~inside).sum() > 10
    err = np.abs((ua + 1j * ub) - (a + 1j * b) / FS)[inside]
    assert err.max() <= 1.5 / scale


def _boundary_commands(width, frac):
    """Commands whose spread (largest line-to-line voltage) is exactly at, or one LSB of the
    internal format above, the hexagon's edge ``2**F`` in each of the three min/max cases
    (``A ≥ |S|``, ``A ≤ −|S|``, ``|A| < |S|``), found with the model's own integers."""
    F, k_frac, k = model.svpwm_constants(width, frac)
    one = 1 << F
    lo, hi = -(1 << (width - 1)), (1 << (width - 1)) - 1
    beta = np.arange(lo, hi + 1)
    s = (beta * k + (1 << (k_frac - 1)) - (beta < 0)) >> k_frac        # S as the model has it
    cmds = []
    # |A| < |S|: spread = 2·|S|; the β nearest to 2·S = 2**F from both sides.
    for target in (one, one + 2):
        j = int(np.argmin(np.abs(2 * s - target)))
        cmds += [(0, int(beta[j])), (0, -int(beta[j])), (1, int(beta[j])), (-1, int(beta[j]))]
    # A ≥ |S| and A ≤ −|S|: spread = |A| + |S| = 2**F exactly where the grid allows it.
    for b in (0, 1, -1, 100, -100, 3000):
        sb = abs(int(s[b - lo]))
        for target in (one, one + 256):
            a = (target - sb) >> 8
            if lo <= a <= hi and (target - sb) % 256 == 0:
                cmds += [(a, b), (-a, b)]
            cmds += [(min(hi, a + 1), b), (max(lo, -a - 1), b)]
    return cmds


@pytest.mark.parametrize("width, frac", [(16, 15), (17, 15)])
def test_svpwm_overmod_flag_exactly_at_the_hexagon_edge(width, frac):
    """On the edge (spread = 2**F) the command is still inside (``overmod`` 0, no division);
    one LSB beyond it is outside: gateware and model agree in all three min/max cases."""
    dut = SVPWM(width=width, frac=frac)
    cmds = _boundary_commands(width, frac)
    outs, _ = svpwm_outputs(dut, [(a, b, 2500) for a, b in cmds])
    a, b = (np.array(x) for x in zip(*cmds))
    exp = model.svpwm(a, b, 2500, width=width, frac=frac)
    got = np.array(outs)
    for i, key in enumerate(("a", "b", "c", "overmod")):
        np.testing.assert_array_equal(got[:, i], exp[key], err_msg=key)
    assert 0 < exp["overmod"].sum() < len(cmds)
    if frac == width - 2:                   # Q2: α = ±1.0 exactly is representable
        edge = model.svpwm(np.array([1 << frac, -(1 << frac)]), np.array([0, 0]), 2500,
                           width=width, frac=frac)
        assert list(edge["overmod"]) == [0, 0]


@pytest.mark.parametrize("radix_bits, count_width, width, frac", [
    (1, 16, 16, 15), (3, 13, 17, 15), (4, 24, 12, 11), (2, 5, 8, 6)])
def test_svpwm_divider_radix_and_widths_against_model(radix_bits, count_width, width, frac):
    """Other divider radices and odd widths (quotient bits not a multiple of the radix's):
    random commands inside and outside the hexagon, random scales, bit for bit; the latency is
    ``7 + ⌈count_width / radix_bits⌉``."""
    dut = SVPWM(width=width, frac=frac, count_width=count_width, radix_bits=radix_bits)
    assert dut.latency == 7 + -(-count_width // radix_bits)
    rng = np.random.default_rng(radix_bits)
    lo, hi = -(1 << (width - 1)), (1 << (width - 1)) - 1
    a = np.concatenate([rng.integers(lo, hi + 1, 40), [lo, hi, 0, hi]])
    b = np.concatenate([rng.integers(lo, hi + 1, 40), [lo, hi, 0, 0]])
    sc = np.concatenate([rng.integers(0, 1 << count_width, 40), [(1 << count_width) - 1] * 4])
    outs, lats = svpwm_outputs(dut, [(int(x), int(y), int(z)) for x, y, z in zip(a, b, sc)])
    assert lats == [dut.latency] * len(a)
    exp = model.svpwm(a, b, sc, width=width, frac=frac)
    got = np.array(outs)
    for i, key in enumerate(("a", "b", "c", "overmod")):
        np.testing.assert_array_equal(got[:, i], exp[key], err_msg=key)
    assert 0 < exp["overmod"].sum() < len(a)


def test_svpwm_random_commands_against_model_via_run():
    r = verify_svpwm._run_svpwm(1500, seed=3, progress=False, width=16, count_width=16,
                                scale=2500)
    assert r["mismatches"] == 0
    assert r["sector_mismatches"] == 0
    assert r["overmod_vectors"] > 300
    assert r["overmod_angle_err_deg"] <= 0.1
    assert r["line_err_counts"] <= 1 + 2500 * 2.0 ** -21


def test_svpwm_bench_detects_a_wrong_duty(monkeypatch):
    real = model.svpwm

    def off_by_one(alpha, beta, scale, **kw):
        out = real(alpha, beta, scale, **kw)
        out["b"] = out["b"].copy()
        out["b"][5] += 1
        return out

    monkeypatch.setattr(verify_svpwm.model, "svpwm", off_by_one)
    r = verify_svpwm._run_svpwm(20, seed=0, progress=False, width=16, count_width=16, scale=2500)
    assert r["mismatches"] == 1 and r["first_mismatch"] == 5


# --- DC-bus compensation ------------------------------------------------------------------------

def test_dcbus_gain_latency_and_latest_measurement_wins():
    dut = DCBusCompensation()
    seen = {}

    async def testbench(ctx):
        assert ctx.get(dut.gain) == 1 << 16                 # 1.0 at reset
        ctx.set(dut.u_rated, 30000)
        ctx.set(dut.u_dc.payload, 20000)
        ctx.set(dut.u_dc.valid, 1)
        await ctx.tick()
        ctx.set(dut.u_dc.valid, 0)
        for k in range(1, dut.gain_latency):
            assert ctx.get(dut.gain) == 1 << 16, k
            await ctx.tick()
            if k == 5:                                      # two more while busy: last one wins
                ctx.set(dut.u_dc.payload, 1234)
                ctx.set(dut.u_dc.valid, 1)
            if k == 6:
                ctx.set(dut.u_dc.payload, 15000)
            if k == 7:
                ctx.set(dut.u_dc.valid, 0)
        seen["first"] = (ctx.get(dut.gain), ctx.get(dut.limited))
        await ctx.tick().repeat(dut.gain_latency + 2)
        seen["second"] = (ctx.get(dut.gain), ctx.get(dut.limited))
        ctx.set(dut.u_dc.payload, 0)                        # division by zero → the limit
        ctx.set(dut.u_dc.valid, 1)
        await ctx.tick()
        ctx.set(dut.u_dc.valid, 0)
        await ctx.tick().repeat(dut.gain_latency)
        seen["zero"] = (ctx.get(dut.gain), ctx.get(dut.limited))

    simulate(dut, [testbench], name="test_dcbus_latency")
    assert seen["first"] == (round(30000 / 20000 * 65536), 0)
    assert seen["second"] == (round(30000 / 15000 * 65536), 0)     # exactly the limit 2.0
    assert seen["zero"] == (dut.gain_limit_raw, 1)
    g, lim = model.dcbus_gain(30000, 1234, gain_limit_raw=dut.gain_limit_raw)
    assert lim == 1 and g == 2 << 16


def test_dcbus_commands_scaled_saturated_pipelined():
    """Back-to-back commands come out ``latency`` (2) clocks later, in order; a result not
    taken is held and stops the pipeline."""
    dut = DCBusCompensation(out_width=17)
    assert dut.latency == 2
    cmds = [(FS - 1, -FS), (1000, -1000), (1, -1), (0, 3)]
    got = []

    async def testbench(ctx):
        ctx.set(dut.u_rated, 4000)
        ctx.set(dut.u_dc.payload, 2500)                 # gain 1.6
        ctx.set(dut.u_dc.valid, 1)
        await ctx.tick()
        ctx.set(dut.u_dc.valid, 0)
        await ctx.tick().repeat(dut.gain_latency)
        ctx.set(dut.o.ready, 1)
        for n in range(len(cmds) + dut.latency - 1):
            if n < len(cmds):
                a, b = cmds[n]
                ctx.set(dut.i.payload, {"alpha": a, "beta": b})
            ctx.set(dut.i.valid, n < len(cmds))
            assert ctx.get(dut.i.ready)
            await ctx.tick()
            assert ctx.get(dut.o.valid) == (n >= dut.latency - 1), n
            if ctx.get(dut.o.valid):
                p = ctx.get(dut.o.payload)
                got.append((p.alpha, p.beta))
        ctx.set(dut.i.valid, 0)
        ctx.set(dut.o.ready, 0)                         # not taken: held, input refused
        await ctx.tick()
        assert ctx.get(dut.o.valid) and not ctx.get(dut.i.ready)
        assert (ctx.get(dut.o.payload.alpha), ctx.get(dut.o.payload.beta)) == got[-1]
        ctx.set(dut.o.ready, 1)
        await ctx.tick()
        assert not ctx.get(dut.o.valid)

    simulate(dut, [testbench], name="test_dcbus_commands")
    gain = round(1.6 * 65536)
    exp = model.dcbus_apply(np.array(cmds), gain, out_width=17)
    assert got == [tuple(x) for x in exp]
    assert got[0][0] > FS and got[0][1] < -FS                    # Q2.15: no saturation
    exp16 = model.dcbus_apply(np.array(cmds), gain, out_width=16)
    assert tuple(exp16[0]) == (FS - 1, -FS)                         # Q1.15 saturates



@pytest.mark.parametrize("mul_width", [18, 12, None])
@pytest.mark.parametrize("out_width", [16, 17])
def test_dcbus_commands_match_the_model(mul_width, out_width):
    """Random commands (and the extremes, and exact rounding ties) at gains below 1, near 2,
    at 2 and above (the gain's top bit, a partial product of its own at mul_width 18) and at
    the limit 3.5: bit for bit ``dcbus_apply``, whatever the products' split."""
    dut = DCBusCompensation(out_width=out_width, gain_limit=3.5, mul_width=mul_width)
    rng = np.random.default_rng(7)
    buses = [(3000, 4000), (4000, 2500), (4000, 2000), (4000, 1500), (30000, 1), (4000, 4001)]
    cmds = np.concatenate([
        rng.integers(-FS, FS, size=(40, 2)),
        [[FS - 1, -FS], [-FS, FS - 1], [0, -1], [1, -1], [0x4000, -0x4000], [-1, 1]],
    ])
    got = {}

    async def testbench(ctx):
        ctx.set(dut.o.ready, 1)
        for u_rated, u_dc in buses:
            ctx.set(dut.u_rated, u_rated)
            ctx.set(dut.u_dc.payload, u_dc)
            ctx.set(dut.u_dc.valid, 1)
            await ctx.tick()
            ctx.set(dut.u_dc.valid, 0)
            await ctx.tick().repeat(dut.gain_latency)
            gain = ctx.get(dut.gain)
            out = []
            for a, b in cmds:
                ctx.set(dut.i.payload, {"alpha": int(a), "beta": int(b)})
                ctx.set(dut.i.valid, 1)
                await ctx.tick()
                ctx.set(dut.i.valid, 0)
                await ctx.tick()
                assert ctx.get(dut.o.valid)
                p = ctx.get(dut.o.payload)
                out.append((p.alpha, p.beta))
            got[u_rated, u_dc] = gain, out

    simulate(dut, [testbench], name="test_dcbus_model")
    for (u_rated, u_dc), (gain, out) in got.items():
        g, _ = model.dcbus_gain(u_rated, u_dc, gain_limit_raw=dut.gain_limit_raw)
        assert gain == g
        np.testing.assert_array_equal(np.array(out), model.dcbus_apply(cmds, gain,
                                                                       out_width=out_width))
    assert {g for g, _ in got.values()} >= {dut.gain_limit_raw, 2 << 16}
    assert any(g > 2 << 16 for g, _ in got.values() if g != dut.gain_limit_raw)

# --- PWM timer ----------------------------------------------------------------------------------

def record_timer(dut, clocks, actions):
    """Record (pwm a, b, c, period_start, sample, position) per clock; ``actions`` maps a clock
    number to a list of (signal, value) set at that clock."""
    rec = []

    async def testbench(ctx):
        for t in range(clocks):
            for sig, val in actions.get(t, ()):
                ctx.set(sig, val)
            p = ctx.get(dut.pwm)
            rec.append((p.a, p.b, p.c, ctx.get(dut.period_start), ctx.get(dut.sample),
                        ctx.get(dut.position)))
            await ctx.tick()

    simulate(dut, [testbench], name="test_pwm_timer")
    return np.array(rec)


def test_pwm_timer_sample_split_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^PWMTimer sample_split must be a bool, not 1$"):
        PWMTimer(sample_split=1)


def test_pwm_timer_one_adder_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^PWMTimer one_adder must be a bool, not 1$"):
        PWMTimer(one_adder=1)


def test_pwm_timer_signed_duty_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^PWMTimer signed_duty must be a bool, not 1$"):
        PWMTimer(signed_duty=1)


def test_pwm_timer_mid_period_duty_writes_wait_for_the_boundary():
    dut = PWMTimer(clk_hz=1e6, pwm_hz=50e3)                # N = 10, period 20 clocks
    n, per = dut.half_period, dut.period
    assert (n, per, dut.pwm_hz_actual) == (10, 20, 50e3)
    duty = dut.duty
    actions = {
        0: [(dut.symmetric, 1), (duty.payload, {"a": 3, "b": 10, "c": 0}), (duty.valid, 1)],
        1: [(duty.valid, 0)],
        # Mid-period writes in period 1 (pos 5 and 13): only the last one counts, from period 2.
        25: [(duty.payload, {"a": 7, "b": 1, "c": 4}), (duty.valid, 1)],
        26: [(duty.valid, 0)],
        33: [(duty.payload, {"a": 5, "b": 2, "c": 25}), (duty.valid, 1)],
        34: [(duty.valid, 0)],
        41: [(dut.symmetric, 0)],                           # mode change: from period 3 on
        # A write on the boundary clock itself (pos 19 of period 2) makes period 3.
        59: [(duty.payload, {"a": 40, "b": 0, "c": 13}), (duty.valid, 1)],
        60: [(duty.valid, 0)],
    }
    rec = record_timer(dut, 4 * per + 1, actions)
    lv = rec[:, :3].astype(bool)
    np.testing.assert_array_equal(rec[:, 5], np.arange(4 * per + 1) % per)
    np.testing.assert_array_equal(np.flatnonzero(rec[:, 3]), [0, 20, 40, 60, 80])
    np.testing.assert_array_equal(np.flatnonzero(rec[:, 4]), [10, 30, 50, 70])
    expect = [((0, 0, 0), False), ((3, 10, 0), True), ((5, 2, 25), True), ((40, 0, 13), False)]
    for k, (comp, sym) in enumerate(expect):
        for ph in range(3):
            np.testing.assert_array_equal(lv[k * per:(k + 1) * per, ph],
                                          model.pwm_levels(comp[ph], n, sym), err_msg=f"{k},{ph}")
    # Symmetric: centred pulse of 2·c clocks; c = 25 > N saturates to always on.
    assert lv[40:60, 2].all() and lv[40:60, 0].sum() == 10
    # Asymmetric: edge-aligned, c = 40 > 2N saturates.
    assert lv[60:80, 0].all() and lv[60:80, 2].sum() == 13 and lv[60:73, 2].all()


@pytest.mark.parametrize("clk_hz, pwm_hz, count_width", [
    (1e6, 50e3, 16),        # N = 10
    (0.8e6, 100e3, 4),      # N = 4, 2N = 8: the level counter as wide as the compares
    (1.1e6, 100e3, 5),      # N = 6 (5.5 rounds up), compares from 2**4 up saturate
    (1e6, 19e3, 8),         # N = 26
])
@pytest.mark.parametrize("signed_duty, one_adder", [(False, True), (True, True), (False, False)])
def test_pwm_timer_random_writes_and_modes_against_model(clk_hz, pwm_hz, count_width,
                                                         signed_duty, one_adder):
    """Levels clock by clock against :func:`model.pwm_levels` of the period's active compares
    and mode, under random duty writes (often on the boundary clock, values at every edge:
    0, 1, N − 1 … N + 1, 2N − 1 … 2N + 1, the counter's and the port's largest) and random
    mode changes; ``period_start`` and ``position`` too. ``signed_duty`` (the iCE40's form, the
    dead-time compensation's sums unclamped): also duties below 0 (acting as 0) and from
    2**count_width up to the port's largest, signed(count_width + 2). ``one_adder=False``: the
    ECP5's triangle counter on two chains."""
    dut = PWMTimer(clk_hz=clk_hz, pwm_hz=pwm_hz, count_width=count_width,
                   signed_duty=signed_duty, one_adder=one_adder)
    n, per = dut.half_period, dut.period
    top = (1 << count_width) - 1
    kw = (2 * n).bit_length()
    lo, hi = (-(2 << count_width), (2 << count_width) - 1) if signed_duty else (0, top)
    edges = sorted({v for v in (0, 1, n - 1, n, n + 1, 2 * n - 1, 2 * n, 2 * n + 1,
                                (1 << kw) - 1, 1 << kw, top, top + 1, -1, -2, -n, -(1 << kw),
                                lo, hi) if lo <= v <= hi})
    rng = np.random.default_rng(count_width + 100 * signed_duty)
    clocks = 30 * per
    actions, valid, duty, sym_in = {}, np.zeros(clocks, int), np.zeros((clocks, 3), int), []
    sym = 0
    for t in range(clocks):
        act = []
        if rng.random() < 0.03:
            sym ^= 1
            act.append((dut.symmetric, sym))
        boundary = t % per == per - 1
        if rng.random() < (0.5 if boundary else 0.08):
            d = [int(rng.choice(edges)) if rng.random() < 0.4 else
                 int(rng.integers(lo, hi + 1)) if signed_duty and rng.random() < 0.2 else
                 int(rng.integers(0, min(top, 2 * n + 1) + 1)) for _ in range(3)]
            valid[t], duty[t] = 1, d
            act += [(dut.duty.payload, dict(zip("abc", d))), (dut.duty.valid, 1)]
        elif t and valid[t - 1]:
            act.append((dut.duty.valid, 0))
        sym_in.append(sym)
        actions[t] = act
    rec = record_timer(dut, clocks, actions)
    # Reference: the shadow takes every write; the period's last clock makes it (or that
    # clock's own write) active together with the mode set in that clock.
    shadow, active, mode = [0, 0, 0], [0, 0, 0], 0
    want = np.zeros((clocks, 3), int)
    for t in range(clocks):
        pos = t % per
        for ph in range(3):
            want[t, ph] = model.pwm_levels(active[ph], n, bool(mode))[pos]
        if valid[t]:
            shadow = [max(int(x), 0) for x in duty[t]]
        if pos == per - 1:
            active, mode = list(shadow), sym_in[t]
    np.testing.assert_array_equal(rec[:, :3], want)
    np.testing.assert_array_equal(rec[:, 5], np.arange(clocks) % per)
    np.testing.assert_array_equal(rec[:, 3], (np.arange(clocks) % per == 0).astype(int))
    assert 0.2 < want.mean() < 0.8 and len(set(map(tuple, want.tolist()))) >= 6


@pytest.mark.parametrize("sample_split", [False, True])
def test_pwm_timer_sample_point_and_full_scale(sample_split):
    dut = PWMTimer(clk_hz=2e6, pwm_hz=100e3, sample_split=sample_split)     # N = 10
    actions = {0: [(dut.sample_custom, 1), (dut.sample_point, 3)],
               25: [(dut.sample_point, 19)], 45: [(dut.sample_point, 20)]}   # 20 ≥ 2N: never
    rec = record_timer(dut, 60, actions)
    np.testing.assert_array_equal(np.flatnonzero(rec[:, 4]), [3, 23, 39])

    seen = []

    async def testbench(ctx):
        for sym in (1, 0):
            ctx.set(dut.symmetric, sym)
            seen.append(ctx.get(dut.full_scale))

    simulate(dut, [testbench], name="test_pwm_full_scale")
    assert seen == [10, 20]


@pytest.mark.parametrize("sample_split", [False, True])
def test_pwm_timer_sample_takes_the_sample_position_one_clock_ahead(sample_split):
    """``sample`` in clock t is ``pos == target`` with the target (``sample_point`` or N) of
    clock t − 1: a change acts from the clock after it. Random changes, often to the position
    of that very clock or the next, and to 0 (after the period's last clock); also positions
    that equal one of the period's when cut to fewer bits (2**5, 2**12 or 2**15 above it, and
    all ones): never a strobe."""
    dut = PWMTimer(clk_hz=2e6, pwm_hz=100e3, sample_split=sample_split)    # N = 10, period 20
    n, per = dut.half_period, dut.period
    rng = np.random.default_rng(5)
    clocks = 400
    custom = (rng.random(clocks) < 0.8).astype(int)
    point = np.zeros(clocks, dtype=int)
    for t in range(clocks):
        point[t] = (point[t - 1] if t and rng.random() < 0.7 else
                    int(rng.choice([t % per, (t + 1) % per, 0, 1, per - 1, per, 25,
                                    (1 << 5) + (t + 1) % per, (1 << 12) + (t + 1) % per,
                                    (1 << 15) + (t + 1) % per, (1 << 16) - 1])))
    actions = {t: [(dut.sample_custom, int(custom[t])), (dut.sample_point, int(point[t]))]
               for t in range(clocks)}
    rec = record_timer(dut, clocks, actions)
    pos = rec[:, 5]
    np.testing.assert_array_equal(pos, np.arange(clocks) % per)
    target = np.where(custom == 1, point, n)
    want = np.concatenate([[0], pos[1:] == target[:-1]]).astype(int)
    np.testing.assert_array_equal(rec[:, 4], want)
    # The changes hit a sample the combinational compare would have taken in the same clock.
    assert ((pos == target) != want.astype(bool)).sum() > 10 and want.sum() > 20


def test_pwm_timer_100khz_and_33mhz_periods():
    for clk, pwm, n in ((50e6, 100e3, 250), (33.333e6, 100e3, 167), (33.333e6, 10e3, 1667),
                        (50e6, 10e3, 2500)):
        dut = PWMTimer(clk_hz=clk, pwm_hz=pwm)
        Fragment.get(dut, None)                             # elaborates
        assert dut.half_period == n == pwm_half_period(clk, pwm)
        assert abs(dut.pwm_hz_actual - pwm) / pwm < 0.5 / n
    # One period at 33.333 MHz / 100 kHz, symmetric: pulse centred, 2·c clocks.
    dut = PWMTimer(clk_hz=33.333e6, pwm_hz=100e3)
    per = dut.period
    actions = {0: [(dut.symmetric, 1), (dut.duty.payload, {"a": 100, "b": 1, "c": 166}),
                   (dut.duty.valid, 1)],
               1: [(dut.duty.valid, 0)]}
    rec = record_timer(dut, 2 * per, actions)
    for ph, c in enumerate((100, 1, 166)):
        np.testing.assert_array_equal(rec[per:, ph].astype(bool),
                                      model.pwm_levels(c, dut.half_period, True))


# --- the whole chain, default run ---------------------------------------------------------------

def test_svpwm_timer_gates_system_default_run():
    r = verify_svpwm.run(1000, seed=1, system_periods=150, dcbus_cases=20)
    assert r["mismatches"] == 0
    for key in ("svpwm_mismatches", "svpwm_sector_mismatches", "timer_mismatches",
                "deadtime_violations", "runt_pulses", "stop_violations", "dcbus_mismatches"):
        assert r[key] == 0, key
    assert r["overmod_angle_err_deg"] <= 0.1
    assert r["volt_seconds_err_counts"] <= 1 + 2.0 ** -10
    assert 1 <= r["trip_latency_clk"] <= 1
    assert set(r["system"]) == {"50MHz_500kHz", "50MHz_100kHz", "33.333MHz_100kHz",
                                "33.333MHz_1000kHz", "50MHz_10kHz"}


@pytest.mark.slow
def test_svpwm_100k_commands_and_long_pwm_run():
    r = verify_svpwm.run(100_000, seed=0)
    assert r["mismatches"] == 0
    assert r["svpwm_vectors"] > 100_000
    assert r["overmod_angle_err_deg"] <= 0.1
    assert r["volt_seconds_err_counts"] <= 1 + 2.0 ** -10
    assert r["trip_latency_clk"] == 1
