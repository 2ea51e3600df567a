# amaranth: UnusedElaboratable=no
# Ref: SPEC.md §2.3 (paper Fig. 6): M/T speed, n = ΔM·60·f_TCLK/(P_n·ΔT), D_n = k·ΔM/ΔT
import dataclasses
import math
import re
from fractions import Fraction

import numpy as np
import pytest
from amaranth.back import verilog

import foc_servo.sim.verify.mt_speed as verify
from foc_servo.boards.area import ports
from foc_servo.hdl.mt_speed import MTSpeed
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import divider as divider_model
from foc_servo.sim.models import mt_speed as model
from mt_pins import AB, record_top_mt

FIELDS = ("cycle", "speed", "stopped", "fresh")


def exact_speed(k, dm, dt, out_width):
    """Independent reference of a fresh window's speed: k·ΔM/ΔT as an exact rational, truncated
    toward zero, saturated to ±(2**(out_width − 1) − 1); ΔT = 0 reads full scale with the sign of
    ΔM (whatever k), ΔM = 0 reads 0 (whatever ΔT)."""
    s_max = 2 ** (out_width - 1) - 1
    if dm == 0:
        return 0
    if dt == 0:
        return s_max if dm > 0 else -s_max
    return max(-s_max, min(s_max, math.trunc(Fraction(k * dm, dt))))


def signed_divider_speeds(ops, p):
    """The pre-session-2 data path (``6e4c613``) for a list of (k, ΔM, ΔT): k·ΔM into a *signed*
    Divider(width=k_width + m_width, divisor_width=tc_width + 1), its quotient clamped to
    ±s_max, ΔM = 0 → 0."""
    s_max = 2 ** (p.out_width - 1) - 1
    q, _, _, _ = divider_model.divide(np.array([k * dm for k, dm, _ in ops], dtype=object),
                                      np.array([dt for _, _, dt in ops], dtype=object),
                                      width=p.k_width + p.m_width,
                                      divisor_width=p.tc_width + 1, signed=True)
    return [0 if dm == 0 else max(-s_max, min(s_max, int(x))) for (_, dm, _), x in zip(ops, q)]


def both(dut, edges, neg, ups, *, k, end_cycle):
    """Gateware and model outputs for the same strobes; asserts they are identical, and that
    every fresh output is the exact k·ΔM/ΔT (:func:`exact_speed`) of its operands."""
    got = verify.run_gateware(dut, edges, neg, ups, k=k, end_cycle=end_cycle)
    want = model.simulate(edges, neg, ups, k=k, params=model.MTParams.of(dut),
                          end_cycle=end_cycle)
    assert got["received"] == len(want["cycle"])
    for f in FIELDS:
        np.testing.assert_array_equal(got[f], want[f], err_msg=f)
    fresh = np.flatnonzero(want["fresh"])
    ref = [exact_speed(k, int(want["dm"][i]), int(want["dt"][i]), dut.out_width) for i in fresh]
    np.testing.assert_array_equal(got["speed"][fresh], ref, err_msg="exact k·ΔM/ΔT")
    return want


# --- parameters --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, msg", [
    ({"clk_hz": 0}, TypeError, "MTSpeed clk_hz must be a positive finite number of hertz, not 0"),
    ({"clk_hz": "50e6"}, TypeError, "MTSpeed clk_hz must be a positive finite number of hertz, "
                                    "not '50e6'"),
    ({"tclk_hz": -1.0}, TypeError, "MTSpeed tclk_hz must be a positive finite number of hertz, "
                                   "not -1.0"),
    ({"clk_hz": 1e6, "tclk_hz": 2e6}, ValueError,
     "MTSpeed tclk_hz must be at most clk_hz 1000000.0, not 2000000.0"),
    ({"tc_width": 7}, TypeError, "MTSpeed tc_width must be an integer from 8 to 48, not 7"),
    ({"tc_width": True}, TypeError, "MTSpeed tc_width must be an integer from 8 to 48, not True"),
    ({"out_width": 49}, TypeError, "MTSpeed out_width must be an integer from 8 to 48, not 49"),
    ({"k_width": 1}, TypeError, "MTSpeed k_width must be an integer from 2 to 64, not 1"),
    ({"m_width": 33}, TypeError, "MTSpeed m_width must be an integer from 2 to 32, not 33"),
    ({"chunk_multipliers": 1}, TypeError, "MTSpeed chunk_multipliers must be a bool, not 1"),
    ({"k_steady": 0}, TypeError, "MTSpeed k_steady must be a bool, not 0"),
    ({"k_steady": True}, ValueError, "MTSpeed k_steady needs chunk_multipliers=True"),
    ({"edge_mode": "x2"}, ValueError, "MTSpeed edge_mode must be 'a_rising' or 'x4', not 'x2'"),
])
def test_mt_validation(kwargs, exc, msg):
    with pytest.raises(exc, match=f"^{re.escape(msg)}$"):
        MTSpeed(**kwargs)


@pytest.mark.parametrize("kwargs, msg", [
    ({"edge_mode": "x2"}, "edge_mode must be 'a_rising' or 'x4', not 'x2'"),
    ({"lines": 0}, "lines must be positive, not 0"),
    ({"tclk_hz": 1.0, "out_width": 16}, "k for 5000 lines, f_TCLK 1 Hz, 6000 r/min rounds to 0: raise f_TCLK or "
                       "out_width"),
    ({"tclk_hz": 50e6, "out_width": 16, "k_width": 16}, "k 3276800 for 5000 lines, f_TCLK 5e+07 Hz, 6000 r/min "
                                       "does not fit k_width 16 bits"),
])
def test_mt_validation_k_for(kwargs, msg):
    with pytest.raises(ValueError, match=f"^{re.escape(msg)}$"):
        model.k_for(**{"lines": 5000, "tclk_hz": 1e6, "full_scale_rpm": 6000, **kwargs})


def test_mt_k_for_values():
    # 60·2**15·f_TCLK / (lines·edges_per_line·N_M) for a Q1.15 output
    q15 = {"out_width": 16}
    assert model.k_for(lines=5000, tclk_hz=1e6, full_scale_rpm=6000, **q15) == 65536
    assert model.k_for(lines=5000, tclk_hz=1e6, full_scale_rpm=6000, edge_mode="x4",
                       **q15) == 16384
    assert model.k_for(lines=5000, tclk_hz=50e6, full_scale_rpm=6000, **q15) == 3276800
    assert model.k_for(lines=5000, tclk_hz=1e6, full_scale_rpm=5000, **q15) == 78643  # 78643.2
    # the default Q1.31 output: 2**16 times as large
    assert model.k_for(lines=5000, tclk_hz=1e6, full_scale_rpm=6000) == 65536 << 16


def test_mt_tclk_ratio_exact_and_rounded():
    dut = MTSpeed(clk_hz=50e6, tclk_hz=1e6)
    assert (dut.tclk_ratio, dut.tclk_hz) == (50, 1e6)
    assert dut.tc_span_s == 2 ** 32 / 1e6
    dut = MTSpeed(clk_hz=33.333e6, tclk_hz=1e6, tc_width=16)       # rounded: documented
    assert dut.tclk_ratio == 33 and dut.tclk_hz == 33.333e6 / 33
    dut = MTSpeed(edge_mode="x4")
    assert (dut.tclk_ratio, dut.edges_per_line, dut.k_width) == (1, 4, 48)
    assert dut.latency == dut.out_width + 3 + dut.k_chunks == 38 == model.MTParams.of(dut).latency


def test_mt_verilog_converts():
    # The constant o.ready of the always-ready output is left out (amaranth-lang/amaranth#1574).
    dut = MTSpeed(clk_hz=33.333e6, tclk_hz=1e6, tc_width=16)
    text = verilog.convert(dut, name="mt_speed", ports=ports(dut))
    assert "module mt_speed" in text and "o__payload" in text


# --- cycle by cycle ----------------------------------------------------------------------------

def test_mt_latency_cycle_by_cycle():
    """o.valid exactly `latency` clocks after an accepted update; an update while busy is
    ignored (its window stays open); the payload is k·ΔM/ΔT of the edges' TC values."""
    dut = MTSpeed(clk_hz=1e6, tc_width=10, out_width=16, k_width=16, m_width=8)
    lat = dut.latency
    k = 1000
    u1 = 60
    u_early = u1 + lat - 1              # busy in that clock: ignored
    u2 = u1 + lat                       # accepted
    edges = {10: 0, 30: 0, 50: 0, 70: 1}     # cycle: neg
    ups = {u1, u_early, u2}
    trace = []

    async def testbench(ctx):
        ctx.set(dut.k, k)
        for c in range(u2 + lat + 3):
            ctx.set(dut.edge, {"step": int(c in edges), "neg": edges.get(c, 0)})
            ctx.set(dut.update, int(c in ups))
            valid = ctx.get(dut.o.valid)
            p = ctx.get(dut.o.payload)
            trace.append((valid, p.speed, p.stopped, p.fresh))
            await ctx.tick()

    simulate(dut, [testbench], clock_hz=dut.clk_hz, name="mt_latency")
    valid_at = [c for c, t in enumerate(trace) if t[0]]
    assert valid_at == [u1 + lat, u2 + lat]
    # Window 1: reference edge at TC 10, edges at 30 and 50: ΔM = 2, ΔT = 40.
    assert trace[u1 + lat][1:] == (k * 2 // 40, 0, 1)
    # Window 2 (update u2; u_early was ignored): edge at 70 backward: ΔM = -1, ΔT = 20.
    assert trace[u2 + lat][1:] == (-(k // 20), 0, 1)
    # Payload held between strobes.
    assert all(t[1:] == trace[u1 + lat][1:] for t in trace[u1 + lat:u2 + lat])
    want = model.simulate(sorted(edges), [edges[c] for c in sorted(edges)], sorted(ups), k=k,
                          params=model.MTParams.of(dut))
    assert want["cycle"].tolist() == valid_at


# --- gateware against model --------------------------------------------------------------------

@pytest.mark.parametrize("edge_mode", ["a_rising", "x4"])
def test_mt_matches_model_high_speed(edge_mode):
    """Full-size instance (50 MHz, f_TCLK = 50 MHz, 32-bit TC), 5000-line encoder at
    1 000 … 10 000 r/min both ways, 100 kHz updates; steady outputs within the M/T bound."""
    dut = MTSpeed(edge_mode=edge_mode)
    fs_rpm = 12000
    k = model.k_for(5000, dut.tclk_hz, fs_rpm, edge_mode=edge_mode, k_width=dut.k_width)
    segs = [(80e-6, 10000.0), (60e-6, -6000.0), (80e-6, -1234.5)]
    end = int(sum(d for d, _ in segs) * dut.clk_hz)
    edges, neg = model.ideal_encoder_edges(segs, clk_hz=dut.clk_hz, lines=5000,
                                           edge_mode=edge_mode, phase=0.3)
    ups = np.arange(500, end, 500)
    out = both(dut, edges, neg, ups, k=k, end_cycle=end)
    assert out["fresh"].sum() >= 15
    # Outputs whose window lies inside one segment: error ≤ 1 LSB + ΔT quantisation.
    bounds = np.cumsum([0] + [d * dut.clk_hz for d, _ in segs])
    for (d, rpm), t0, t1 in zip(segs, bounds, bounds[1:]):
        start = out["t_end"] - out["dt"]                    # window's first edge (ratio 1)
        sel = (out["fresh"] == 1) & (start > t0 + 1) & (out["t_end"] < t1)
        assert sel.any()
        lsb_rpm = fs_rpm / 2 ** (dut.out_width - 1)
        rpm_out = out["speed"][sel] * lsb_rpm
        tol = lsb_rpm + abs(rpm) / (out["dt"][sel] - 1)
        assert np.all(np.abs(rpm_out - rpm) <= tol)


def test_mt_matches_model_low_speed_scaled_clock():
    """Low speeds with the clock scaled down 50× (1 MHz clock = f_TCLK, 10 kHz updates,
    5000 lines, 12-bit TC: span 4.1 ms): windows open over several updates (bounded outputs),
    edge intervals beyond the span (stopped), restart."""
    dut = MTSpeed(clk_hz=1e6, tc_width=12)
    fs_rpm = 100
    k = model.k_for(5000, dut.tclk_hz, fs_rpm, k_width=dut.k_width)
    segs = [(2e-3, 30.0), (3e-3, 15.0), (9e-3, 2.0), (2.5e-3, -40.0), (1.5e-3, 0.0), (2e-3, -25.0)]
    end = int(sum(d for d, _ in segs) * dut.clk_hz)
    edges, neg = model.ideal_encoder_edges(segs, clk_hz=dut.clk_hz, lines=5000, phase=0.5)
    ups = np.arange(100, end, 100)
    out = both(dut, edges, neg, ups, k=k, end_cycle=end)
    bound = (out["fresh"] == 0) & (out["stopped"] == 0)
    assert out["fresh"].sum() >= 8 and bound.sum() >= 50 and out["stopped"].sum() >= 20
    assert np.any(out["speed"] < 0) and np.any(out["speed"] > 0)


def test_mt_reversal():
    """ΔM counts net edges: a window with a reversal reads the mean speed over it, a net-zero
    window exactly 0; the direction gives the sign."""
    dut = MTSpeed(clk_hz=1e6, tc_width=12, k_width=16, m_width=8)
    k = 6000
    ev = [(100, 0), (200, 0), (300, 0), (400, 0),       # window 1 (ref 100): +3 in 300
          (500, 0), (600, 1), (700, 1),                 # window 2: +1 -1 -1 in 300
          (800, 0),                                     # window 3: +1 in 100
          (900, 0), (950, 1)]                           # window 4: +1 -1 in 150
    ups = [450, 750, 850, 1000, 1100]
    edges, neg = zip(*ev)
    out = both(dut, edges, neg, ups, k=k, end_cycle=1200)
    assert out["speed"].tolist() == [k * 3 // 300, -(k // 300), k // 100, 0, 0]
    assert out["fresh"].tolist() == [1, 1, 1, 1, 0]
    assert out["dm"].tolist()[:4] == [3, -1, 1, 0]


@pytest.mark.parametrize("out_width", [16, 32])     # quotient 15 bits = out_width − 1; 23 < 31
@pytest.mark.parametrize("k", [1000, 0])
def test_mt_zero_dt_saturates_with_the_sign_of_dm(out_width, k):
    """Two edges in one TC tick (ΔT = 0): full scale with the sign of ΔM, whatever k (the
    unsigned divider's saturation, or its division by zero, then the sign fix)."""
    dut = MTSpeed(clk_hz=1e6, tclk_hz=1e5, tc_width=10, out_width=out_width, k_width=16,
                  m_width=8)
    s_max = 2 ** (out_width - 1) - 1
    ev = [(100, 0), (103, 0),            # tick 10, tick 10: ΔM = +1, ΔT = 0
          (200, 1), (202, 1),            # tick 20: ΔM = −2, ΔT = 10
          (207, 1)]                      # tick 20: ΔM = −1, ΔT = 0
    edges, neg = zip(*ev)
    out = both(dut, edges, neg, [105, 205, 300], k=k, end_cycle=400)
    assert out["speed"].tolist() == [s_max, -(k * 2 // 10), -s_max]
    assert out["dt"].tolist() == [0, 10, 0] and out["fresh"].tolist() == [1, 1, 1]


def _division_operands(rng, p, n_random):
    """Corner and random (k, ΔM, ΔT) within the ranges the gateware can produce: k < 2**k_width,
    |ΔM| <= 2**(m_width − 1) (ΔM saturates at −2**(m_width − 1) … 2**(m_width − 1) − 1),
    0 <= ΔT < 2**tc_width; plus quotients at the saturation boundary and exact divisions."""
    k_max, m_lo, m_hi, t_max = 2 ** p.k_width - 1, -2 ** (p.m_width - 1), 2 ** (p.m_width - 1) - 1, \
        2 ** p.tc_width - 1
    s_max = 2 ** (p.out_width - 1) - 1
    ks = {0, 1, 2, 3, k_max, k_max - 1, k_max // 2, min(k_max, 2 ** 16 - 1), min(k_max, 2 ** 16)}
    dms = {m_lo, m_lo + 1, -2, -1, 0, 1, 2, m_hi - 1, m_hi}
    dts = {0, 1, 2, 3, t_max, t_max - 1, t_max // 2 + 1}
    ops = [(k, dm, dt) for k in ks for dm in dms for dt in dts]
    for _ in range(n_random):
        k = int(rng.integers(0, k_max + 1)) >> int(rng.integers(0, p.k_width))
        dm = int(rng.integers(m_lo, m_hi + 1)) >> int(rng.integers(0, p.m_width))
        dt = int(rng.integers(0, t_max + 1)) >> int(rng.integers(0, p.tc_width))
        ops.append((k, dm, dt))
        if dm != 0 and dt != 0:
            # |k·ΔM| / ΔT around s_max (saturation boundary) and exact multiples (remainder 0).
            for target in (s_max * dt - 1, s_max * dt, s_max * dt + dt - 1, s_max * dt + dt,
                           (s_max // 3) * dt, 7 * dt):
                for kk in (target // abs(dm), target // abs(dm) + 1):
                    if 0 <= kk <= k_max:
                        ops.append((kk, dm, dt))
    return ops


@pytest.mark.parametrize("config", [
    {},                                                 # the top's: Q1.31, k 48, ΔM 16, TC 32
    {"out_width": 16, "k_width": 24, "m_width": 8, "tc_width": 12},
    {"out_width": 32, "k_width": 8, "m_width": 4, "tc_width": 8},   # quotient 11 < 31 bits
])
def test_mt_unsigned_division_is_the_signed_truncating_division(config):
    """The M/T data path divides k·|ΔM| by ΔT unsigned (``out_width − 1`` or fewer quotient
    bits) and applies the sign of ΔM after. Over corner and random operands it equals (a) the
    exact rational k·ΔM/ΔT truncated toward zero and saturated symmetrically, and (b) the signed
    Divider path it replaced (truncation toward zero, C99), bit for bit, except the one documented
    degenerate case k = 0, ΔT = 0, ΔM < 0 (signed: 0/0 saturates positive; now: −full scale, the
    sign of ΔM like every other ΔT = 0) and, in narrow instances (k_width + m_width < out_width;
    not the top's), ΔT = 0 at all, which the signed divider saturated to its dividend's range
    (±(2**(k_width + m_width − 1) − 1)) instead of full scale."""
    p = model.MTParams.config(**config)
    ops = _division_operands(np.random.default_rng(5), p, 3000)
    assert len(ops) > 4000
    s_max = 2 ** (p.out_width - 1) - 1
    seen = {"sat": 0, "neg_inexact": 0, "div0": 0}
    for (k, dm, dt), old in zip(ops, signed_divider_speeds(ops, p)):
        want = exact_speed(k, dm, dt, p.out_width)
        assert model.fresh_speed(k, dm, dt, out_width=p.out_width) == want, (k, dm, dt)
        if dt == 0 and dm != 0:
            # Division by zero: the signed divider saturated to the limit of its dividend's
            # width with the sign of k·ΔM (0 counts as positive), then the clamp to ±s_max.
            n = p.k_width + p.m_width - 1
            assert old == (min(s_max, 2 ** n - 1) if k * dm >= 0 else max(-s_max, -2 ** n))
            assert want == (s_max if dm > 0 else -s_max)
            differs = old != want
            assert differs == ((k == 0 and dm < 0) or n < p.out_width - 1), (k, dm)
        else:
            assert old == want, (k, dm, dt)
        seen["sat"] += abs(want) == s_max and dt != 0
        seen["neg_inexact"] += dm < 0 and dt != 0 and (k * dm) % dt != 0 and abs(want) < s_max
        seen["div0"] += dt == 0 and dm != 0
    if p.k_width + p.m_width - 1 <= p.out_width - 1:    # |k·ΔM| / ΔT cannot reach s_max
        del seen["sat"]
    assert min(seen.values()) > 20, seen
    # Truncation toward zero, not floor: −7/2 reads −3.
    assert model.fresh_speed(7, -1, 2, out_width=16) == -3 == exact_speed(7, -1, 2, 16)


@pytest.mark.parametrize("chunk_multipliers", [False, True])
@pytest.mark.parametrize("out_width", [12, 32])     # quotient 11 bits = out_width − 1; 23 < 31
@pytest.mark.parametrize("k", [0, 1, 2 ** 20 - 1, 12345])
def test_mt_division_corners_through_the_gateware(out_width, k, chunk_multipliers):
    """Windows built edge by edge on a small instance (4-bit ΔM, 8-bit TC, 32 clocks per TC
    tick) reach the corners: ΔM saturated at −8 and +7, net-zero windows, ΔT = 0 (edges in the
    reference's tick), 1, 2 and near the span, full-scale k; gateware == model == exact (one
    multiplier behind the chunk select, or one per chunk)."""
    dut = MTSpeed(clk_hz=3.2e6, tclk_hz=1e5, tc_width=8, out_width=out_width, k_width=20,
                  m_width=4, chunk_multipliers=chunk_multipliers)
    r, lat = dut.tclk_ratio, dut.latency
    assert r == 32
    windows = [(1, 1), (-1, 1), (10, 0), (-1, 2), (-12, 0), (3, 250), (0, 0), (0, 3), (-8, 1),
               (7, 2), (-3, 0), (2, 5), (-12, 250), (1, 0)]     # (edges, signed; ΔT ticks)
    edges, neg, ups = [], [], []
    c_ref = 4 * r                                       # reference edge: tick 4, offset 0
    edges.append(c_ref)
    neg.append(False)
    c_up = c_ref + 1
    ups.append(c_up)                                    # STOPPED (no measurement yet)
    want_ops = []
    for n, dt in windows:
        t_ref = c_ref // r
        seq = [n < 0] * abs(n) if n else [False, True]
        if dt == 0:                                     # all in the reference's tick
            first = max(c_ref, c_up) + 1
            assert first + len(seq) <= (t_ref + 1) * r
        else:
            first = (t_ref + dt) * r
            assert first > c_up
        cs = list(range(first, first + len(seq)))
        edges += cs
        neg += seq
        c_ref = cs[-1]
        c_up = max(c_ref + 1, c_up + lat)
        ups.append(c_up)
        m = sum(-1 if x else 1 for x in seq)
        want_ops.append((max(-8, min(7, m)) if abs(n) <= 12 else None, dt))
    out = both(dut, edges, neg, ups, k=k, end_cycle=c_up + lat + 2)
    fresh = out["fresh"] == 1
    assert fresh.sum() == len(windows)
    assert out["dt"][fresh].tolist() == [dt for _, dt in want_ops]
    dms = out["dm"][fresh].tolist()
    assert dms[2] == 7 and dms[4] == -8 and dms[6] == 0 and -8 in dms and 7 in dms
    s_max = 2 ** (out_width - 1) - 1
    speeds = out["speed"][fresh].tolist()
    assert speeds[2] == s_max and speeds[4] == -s_max and speeds[6] == 0    # ΔT = 0, 0/0


def test_mt_reversal_random_profile_x4():
    """Random profile with reversals, stops and steps on a ×4, prescaled (f_TCLK = clk/3)
    instance; gateware == model."""
    dut = MTSpeed(clk_hz=1.5e6, tclk_hz=0.5e6, tc_width=9, out_width=12, edge_mode="x4",
                  k_width=16, m_width=6)
    rng = np.random.default_rng(7)
    k = model.k_for(100, dut.tclk_hz, 8000, out_width=12, edge_mode="x4", k_width=16)
    end = 12_000
    segs = verify.random_profile(rng, end / dut.clk_hz, max_rpm=8000, tc_span_s=dut.tc_span_s)
    edges, neg = model.ideal_encoder_edges(segs, clk_hz=dut.clk_hz, lines=100, edge_mode="x4")
    assert neg.any() and not neg.all()
    ups = np.cumsum(rng.integers(dut.latency - 3, 3 * dut.latency, size=end // dut.latency))
    both(dut, edges, neg, ups[ups < end], k=k, end_cycle=end)


def test_mt_stopped_reports_zero_and_flag():
    """After the last edge: bounded outputs decaying as k/elapsed (never above the last
    measurement, never stale); from the first update after the TC span: 0 with `stopped`; after
    a restart: stopped until a full window is measured."""
    dut = MTSpeed(clk_hz=1e6, tc_width=10, k_width=20, m_width=8)      # span 1024 clocks
    k = 100_000
    run_edges = list(range(100, 1100, 100))                # 10 edges, last at 1000
    restart = [3000, 3100, 3200]
    edges = run_edges + restart
    ups = list(range(50, 4000, 50))
    out = both(dut, edges, [0] * len(edges), ups, k=k, end_cycle=4200)
    upd, spd, stp, frs = out["update"], out["speed"], out["stopped"], out["fresh"]
    # Before the second edge: no measurement yet.
    assert np.all(stp[upd < 200] == 1) and np.all(spd[upd < 200] == 0)
    last_fresh = k * 1 // 100
    assert spd[(upd > 200) & (upd <= 1000)].tolist() == \
        [last_fresh] * int(((upd > 200) & (upd <= 1000)).sum())
    after = (upd > 1000) & (upd < 1000 + 1024)
    elapsed = upd[after] - 1000
    np.testing.assert_array_equal(spd[after], np.minimum(last_fresh, k // elapsed))
    assert np.all(np.diff(spd[after]) <= 0) and spd[after][-1] < last_fresh
    assert np.all((stp[after] == 0) & (frs[after] == 0))
    gone = (upd >= 1000 + 1024) & (upd < 3100)         # the edge at 3000 is only a reference
    assert gone.sum() > 10 and np.all((stp[gone] == 1) & (spd[gone] == 0))
    back = (upd >= 3100) & (upd <= 3300)
    assert np.all((stp[back] == 0) & (spd[back] == k // 100)) and frs[back][0] == 1


def test_mt_random_vs_model():
    res = verify.run(700, seed=3, table=False)
    assert res["mismatches"] == 0
    assert res["vectors"] > 550 and res["updates"] > res["vectors"]     # some updates too early
    assert min(res["fresh"], res["bound"], res["stopped"]) > 40


@pytest.mark.slow
def test_mt_100k_vs_model():
    res = verify.run(100_000, seed=1, table=False)
    assert res["mismatches"] == 0 and res["vectors"] > 90_000


# --- the targets (golden model engine) ------------------------------------------------

def test_mt_ideal_encoder_edges():
    """Constant speed: evenly spaced strobes at the right rate; a back-and-forth inside one
    clock interval makes no strobe; reversals flip `neg`."""
    c, n = model.ideal_encoder_edges([(1e-3, 600.0)], clk_hz=1e6, lines=100, phase=0.5)
    assert len(c) == 1 and c[0] == 500 and not n.any()     # 600 r/min, 100 lines: 1 per ms
    c, n = model.ideal_encoder_edges([(10e-3, 600.0), (10e-3, -600.0)], clk_hz=1e6,
                                     lines=100, edge_mode="x4", phase=0.0)
    assert len(c) == 80 and n.sum() == 40 and np.all(np.diff(c) > 0)
    with pytest.raises(ValueError, match="^two encoder edges in one clock"):
        model.ideal_encoder_edges([(1e-5, 1e6)], clk_hz=1e6, lines=5000)


def test_mt_error_table_targets():
    """5000 lines, 10 kHz update, 50 MHz clock, constant speed, both directions: ≤ 0.05 % over
    10 … 10 000 r/min and ≤ 1 % over 0.2 … 10 r/min with f_TCLK = 50 MHz; lowest resolvable
    speed with the paper's 1 MHz / 16-bit TC ≈ 0.18 r/min (paper: 0.2)."""
    grid = verify.speed_grid()
    assert grid[0] == 0.2 and grid[-1] == 10000 and len(grid) > 40
    rows = verify.error_table(grid[::5] + [10.0, 10000.0], phases=(0.0, 0.61))
    hi = max(r["err_pct_sysclk"] for r in rows if r["rpm"] >= 10)
    lo = max(r["err_pct_sysclk"] for r in rows if r["rpm"] <= 10)
    assert hi <= 0.05 and lo <= 1.0
    assert max(r["err_pct_1mhz"] for r in rows if r["rpm"] <= 10) <= 1.0
    rpm_min = verify.min_resolvable_rpm(tol_rpm=4e-3, phases=(0.3,))
    assert 60e6 / (5000 * 2 ** 16) <= rpm_min <= 0.2
    assert verify.error_run(0.9 * 60e6 / (5000 * 2 ** 16), config="1mhz") == 100.0   # stopped


# --- through the top's wiring (the encoder front end's strobes into MTSpeed) ------------------

def _top_pin_schedule(rng):
    """Quadrature state changes (clock, position) of a walk: still, forward, a pause longer than
    two PWM periods (bounded outputs), backward, fast forward."""
    plan = [(100, 0, 0)] + [(int(rng.integers(25, 46)), 1, 0) for _ in range(40)]
    plan += [(600, 0, 0)] + [(int(rng.integers(25, 46)), -1, 0) for _ in range(30)]
    plan += [(int(rng.integers(8, 16)), 1, 0) for _ in range(24)]
    clock, pos, changes = 0, 0, []
    for dwell, step, _ in plan:
        clock += dwell
        if step:
            pos += step
            changes.append((clock, pos))
    return changes, clock + 400


@pytest.mark.parametrize("mt_edges", ["x4", "a_rising"])
def test_mt_through_top_wiring_matches_model(mt_edges):
    """The Top's encoder pins → EncoderFrontEnd → MTSpeed: the edge strobes are exactly the
    counted pin changes (x4: every quadrature state change; a_rising: A rising in time) a fixed
    latency later, with the direction; the top's ``mt_k`` reset is the model's ``k_for`` for
    that edge mode; every M/T output (speed, stopped, fresh, clock) equals the golden model's for
    those strobes and the top's update strobes."""
    from foc_servo.hdl.encoder import EncoderFrontEnd
    from foc_servo.hdl.regmap import MT_EDGES_PER_LINE
    from foc_servo.hdl.top import Top

    top = Top(pwm_hz=250e3, mt_edges=mt_edges)
    mt = top._mt
    assert top.mt_edges == mt.edge_mode == mt_edges
    assert mt.edges_per_line == MT_EDGES_PER_LINE[mt_edges]
    k = top.regmap["mt_k"].reset
    assert k == model.k_for(5000, mt.tclk_hz, top.scales.n_fs_rpm, edge_mode=mt_edges,
                            k_width=mt.k_width)
    changes, end = _top_pin_schedule(np.random.default_rng(11))
    at = dict(changes)
    r = record_top_mt(top, at, end, hall=0b101, name=f"mt_top_{mt_edges}")
    # The counted edges, from the pin schedule alone.
    delay = EncoderFrontEnd.latency + top.regmap["enc_filter"].reset - 1
    want_c, want_neg, prev = [], [], 0
    for c, pos in changes:
        a_rise = AB[pos % 4][0] == 1 and AB[prev % 4][0] == 0
        if mt_edges == "x4" or a_rise:
            want_c.append(c + delay)
            want_neg.append(int(pos < prev))
        prev = pos
    got_c = np.flatnonzero(r["step"])
    np.testing.assert_array_equal(got_c, want_c)
    np.testing.assert_array_equal(r["neg"][got_c], want_neg)
    assert len(want_c) == (94 if mt_edges == "x4" else 24) and 0 < sum(want_neg) < len(want_c)
    ups = np.flatnonzero(r["update"])
    want = model.simulate(want_c, np.array(want_neg, dtype=bool), ups, k=k,
                          params=model.MTParams.of(mt), end_cycle=end)
    got_v = np.flatnonzero(r["valid"])
    np.testing.assert_array_equal(got_v, want["cycle"])
    for f in ("speed", "stopped", "fresh"):
        np.testing.assert_array_equal(r[f][got_v], want[f], err_msg=f)
    assert want["fresh"].sum() >= 10 and (want["speed"] < 0).any() and (want["speed"] > 0).any()
    # The forward run: ≈ 60·f_clk/(35 clocks · 4 edges · 5000 lines) = 4286 r/min (x4 sees it
    # from each quadrature state change).
    fs = top.scales.n_fs_rpm / 2 ** 31
    fwd = (want["fresh"] == 1) & (want["update"] > want_c[2]) & (want["update"] < 40 * 25)
    assert fwd.any()
    assert np.all(np.abs(want["speed"][fwd] * fs - 4286) < 0.3 * 4286)


def test_mt_x4_quadrature_phase_error_at_low_speed():
    """Physics of ×4 counting with an encoder whose B is φ = +10° (electrical, of the 360° line
    period) late: the state changes sit at 0°, 100°, 180°, 280° of each line, so the edge
    intervals are 100° and 80° instead of 90°. At a speed so low that each window spans one
    edge, M/T reads 90/100 and 90/80 of the true speed in turn (−10 %, +12.5 %); over a whole
    line (4 edges) the error cancels. (The plant's encoder has no phase-error parameter; the
    edges are built here.)"""
    lines, clk_hz, rpm, fs_rpm, phi_deg = 100, 1e6, 6.0, 60.0, 10.0
    k = model.k_for(lines, clk_hz, fs_rpm, edge_mode="x4")
    line_s = 60.0 / (rpm * lines)
    frac = np.array([0.0, 90.0 + phi_deg, 180.0, 270.0 + phi_deg]) / 360.0
    t = (np.arange(6)[:, None] + frac[None, :]).ravel() * line_s + 1e-3
    edges = np.ceil(t * clk_hz).astype(np.int64)
    ups = np.arange(500, edges[-1] + 2000, 1000)
    out = model.simulate(edges, np.zeros(len(edges), dtype=bool), ups, k=k,
                         params=model.MTParams.config(clk_hz=clk_hz))
    fresh = out["fresh"] == 1
    ratio = out["speed"][fresh] * fs_rpm / 2 ** 31 / rpm
    assert fresh.sum() == len(edges) - 1 and np.all(out["dm"][fresh] == 1)
    # Interval after an A edge (0° → 100°, 180° → 280°): 100°; after a B edge: 80°.
    want = np.where(np.arange(1, len(edges)) % 2 == 1, 90 / (90 + phi_deg), 90 / (90 - phi_deg))
    np.testing.assert_allclose(ratio, want, atol=1e-3)
    # Over every whole line the mean of the time intervals is exact.
    dt = np.diff(edges)
    whole = dt[:len(dt) // 4 * 4].reshape(-1, 4).sum(axis=1)
    np.testing.assert_allclose(whole / clk_hz, line_s, rtol=1e-4)


def test_mt_window_count_saturates_both_ways():
    """ΔM saturates to signed(m_width) in either direction and steps back from the limit; the
    sign clears on crossing zero (the gateware keeps ΔM as magnitude and sign: its limits are
    2**(m_width − 1) − 1 forward and 2**(m_width − 1) backward; a window back at 0 reads 0)."""
    dut = MTSpeed(clk_hz=1e6, tc_width=12, out_width=16, k_width=16, m_width=3)
    k = 3000
    fwd = [(100, 0)] + [(110 + 10 * i, 0) for i in range(6)]            # +6 → +3
    fwd_back = [(300 + 10 * i, 0) for i in range(6)] + [(370, 1), (380, 1)]   # +3, −2 → +1
    bwd = [(500 + 10 * i, 1) for i in range(7)]                        # −7 → −4
    bwd_back = [(700 + 10 * i, 1) for i in range(6)] + [(770, 0)]      # −4, +1 → −3
    cross = [(900, 0), (910, 1), (920, 1), (930, 1), (940, 0)]         # +1 −1 −1 −1 +1 → −1
    back0 = [(1100, 1), (1110, 0)]                                     # −1 +1 → 0
    edges, neg = zip(*(fwd + fwd_back + bwd + bwd_back + cross + back0))
    out = both(dut, edges, neg, [200, 400, 600, 800, 1000, 1200], k=k, end_cycle=1300)
    assert out["dm"].tolist() == [3, 1, -4, -3, -1, 0]
    assert out["fresh"].tolist() == [1, 1, 1, 1, 1, 1]
    assert out["speed"][-1] == 0


@pytest.mark.parametrize("gap", [1, 2, 3])
def test_mt_expiry_right_after_a_close(gap):
    """A window closed a clock or two before its last edge expires in turn: two edges `gap`
    clocks apart, no update for a whole TC span, so the first expires (its window closes on the
    second, which becomes the reference) and the second expires `gap` clocks later; updates
    around both expiries. The registered expiry compare (`at_span`) must follow the new
    reference from the closing clock on."""
    dut = MTSpeed(clk_hz=1e6, tc_width=8, out_width=16, k_width=16, m_width=8)
    span = 2 ** dut.tc_width
    for up in range(20 + span - 3, 20 + span + gap + 3):
        edges, neg = [20, 20 + gap], [0, 0]
        out = both(dut, edges, neg, [up, up + 200], k=1000, end_cycle=up + 300)
        assert out["stopped"][-1] == 1


@pytest.mark.parametrize("ratio", [1, 3])
def test_mt_expiry_clock_with_a_prescaled_tc(ratio):
    """The reference expires in the clock of the tick that makes its age a whole span (not in
    the clocks between ticks with the age at 2**w − 1): a fresh window (reference edge at 23)
    and then no edge, an update in every clock around the expiry; before it the update reads
    the bounded speed, from it on stopped — gateware == model, with TC at the clock and at a
    third of it."""
    dut = MTSpeed(clk_hz=3e6, tclk_hz=3e6 / ratio, tc_width=8, out_width=16, k_width=16,
                  m_width=8)
    assert dut.tclk_ratio == ratio
    span = 2 ** dut.tc_width * ratio
    modes = set()
    for up in range(23 + span - 3 * ratio, 23 + span + 2 * ratio):
        out = both(dut, [20, 23], [0, 0], [30, up], k=1000, end_cycle=up + 100)
        assert out["fresh"].tolist() == [1, 0]
        modes.add(int(out["stopped"][-1]))
    assert modes == {0, 1}


def test_mt_expiry_during_the_computation_invalidates_it():
    """A fresh window whose new reference (its last edge) expires while the division runs: the
    expiry clears the 'measurement valid' flag and the result does not set it again (it is set
    at the fresh snapshot), so a single new edge afterwards reads stopped until a whole new
    window is measured, as documented (before session 9 it read the stale measurement bounded
    by k/elapsed)."""
    dut = MTSpeed(clk_hz=1e6, tc_width=8, out_width=16, k_width=16, m_width=8)
    span, lat, k = 2 ** dut.tc_width, dut.latency, 1000
    # Reference at 10, last edge at 11; the update at 262 closes the window (ΔM = 1, ΔT = 1)
    # on the edge at 11, which expires in clock 11 + span − 1 = 266, inside the computation.
    u = 11 + span - 5
    assert u < 10 + span and u + lat > 11 + span
    # A new reference edge at 320, then an update at 400 (stopped: no measurement since the
    # expiry), an edge at 450 and the update at 500 (fresh: ΔM = 1, ΔT = 130).
    edges, neg = [10, 11, 320, 450], [0, 0, 0, 0]
    ups = [u, 400, 500]
    out = both(dut, edges, neg, ups, k=k, end_cycle=600)
    assert out["update"].tolist() == ups
    assert out["fresh"].tolist() == [1, 0, 1]
    assert out["speed"].tolist() == [k, 0, k // 130]
    assert out["stopped"].tolist() == [0, 1, 0]


@pytest.mark.parametrize("config, k_values", [
    ({}, [0, 2 ** 48 - 1, 3 * 2 ** 40 + 12345, 2 ** 31 * 7, 2 ** 31 * 150, 98_765_432_100,
          2 ** 25 + 1]),
    ({"out_width": 16, "k_width": 24, "m_width": 8, "tc_width": 12},
     [1, 2 ** 24 - 1, 2 ** 15 * 9, 2 ** 15 * 200, 777_777]),
])
@pytest.mark.parametrize("chunk_multipliers", [False, True])
def test_mt_division_random_windows_through_the_gateware(config, k_values, chunk_multipliers):
    """Short random windows (1 … 40 edges both ways, 0 … 3000 clocks) on the top's instance
    (48-bit k, 63-bit product, 32 quotient steps) and a narrow one whose product (31 bits)
    exceeds the division register (28 bits): fresh quotients small, large, exact and saturated;
    gateware == model == exact k·ΔM/ΔT, clock for clock (one multiplier behind the chunk
    select, or one per chunk)."""
    dut = MTSpeed(clk_hz=50e6, chunk_multipliers=chunk_multipliers, **config)
    rng = np.random.default_rng(9)
    lat = dut.latency
    for k in k_values:
        edges, neg, ups = [], [], []
        c = 5
        for _ in range(25):
            n = int(rng.integers(1, 41))
            gap = int(rng.choice([0, 1, 2, 7, 100, 3000])) // max(n, 1) + 1
            direction = bool(rng.integers(0, 2))
            for _ in range(n):
                c += gap
                edges.append(c)
                neg.append(direction if rng.random() < 0.85 else not direction)
            c += 1
            ups.append(c)
            c += lat
        out = both(dut, edges, neg, ups, k=k, end_cycle=c + lat + 2)
        assert out["fresh"].sum() >= 20


_LOCKSTEP_KW = dict(clk_hz=50e6, tc_width=10, out_width=32, m_width=6)


def _lockstep(forms, k_width):
    """A module holding the two M/T ``forms`` side by side and their shared inputs
    ``(k, step, neg, update)``."""
    from amaranth.hdl import Module, Signal
    m = Module()
    k = Signal(k_width)
    step, neg, update = Signal(), Signal(), Signal()
    for i, dut in enumerate(forms):
        m.submodules[f"dut{i}"] = dut
        m.d.comb += [dut.k.eq(k), dut.edge.step.eq(step), dut.edge.neg.eq(neg),
                     dut.update.eq(update)]
    return m, (k, step, neg, update)


def _same_outputs(ctx, forms, c, seen):
    """Both forms' outputs equal in clock ``c``; the kinds of results counted in ``seen``."""
    got = [(ctx.get(d.o.valid), ctx.get(d.o.payload.as_value())) for d in forms]
    assert got[0] == got[1], c
    if got[0][0]:
        p = ctx.get(forms[0].o.payload)
        seen["fresh"] += p.fresh
        seen["bound"] += not p.fresh and not p.stopped
        seen["unsaturated"] += p.fresh and 0 < abs(p.speed) < 2 ** 31 - 1


@pytest.mark.parametrize("k_width", [16, 20, 48])
def test_mt_chunk_multipliers_sample_k_as_the_chunk_select(k_width):
    """``chunk_multipliers=True`` against the default form, clock for clock, with ``k`` changing
    in every clock (random, so that each chunk's sampling clock u + c matters), random edges
    both ways and updates early, late and while busy: the same outputs in the same clocks."""
    forms = [MTSpeed(**_LOCKSTEP_KW, k_width=k_width),
             MTSpeed(chunk_multipliers=True, **_LOCKSTEP_KW, k_width=k_width)]
    assert forms[1].chunk_multipliers and not forms[0].chunk_multipliers
    m, (k, step, neg, update) = _lockstep(forms, k_width)
    rng = np.random.default_rng(17)
    lat = forms[0].latency
    seen = {"fresh": 0, "bound": 0, "unsaturated": 0}

    async def testbench(ctx):
        for c in range(60 * lat):
            # log-uniform: most results below saturation, so that every chunk counts
            ctx.set(k, int(rng.integers(0, 2 ** int(rng.integers(4, k_width + 1)),
                                        dtype=np.uint64)))
            ctx.set(step, int(rng.random() < (0.3 if (c // 400) % 2 else 0.02)))
            ctx.set(neg, int(rng.random() < 0.2))
            ctx.set(update, int(rng.random() < 1.5 / lat))
            _same_outputs(ctx, forms, c, seen)
            await ctx.tick()

    simulate(m, [testbench], clock_hz=50e6, name="mt_chunk_multipliers")
    assert seen["fresh"] > 10 and seen["bound"] > 2 and seen["unsaturated"] > 5, seen


@pytest.mark.parametrize("k_width", [16, 48])
def test_mt_k_steady_against_the_default_form(k_width):
    """``k_steady=True`` against the default form, clock for clock, with ``k`` changing only in
    the clock before each update (updates ``latency + 2`` … apart: so steady through every
    computation, as the Top's committed ``mt_k``), random edges both ways: the same outputs in
    the same clocks. A ``k`` change during a computation is what the form does not follow."""
    forms = [MTSpeed(**_LOCKSTEP_KW, k_width=k_width),
             MTSpeed(chunk_multipliers=True, k_steady=True, **_LOCKSTEP_KW, k_width=k_width)]
    assert forms[1].k_steady and not forms[0].k_steady
    m, (k, step, neg, update) = _lockstep(forms, k_width)
    rng = np.random.default_rng(23)
    lat = forms[0].latency
    seen = {"fresh": 0, "bound": 0, "unsaturated": 0}

    async def testbench(ctx):
        next_up = 5
        for c in range(60 * lat):
            if c == next_up - 1:
                ctx.set(k, int(rng.integers(0, 2 ** int(rng.integers(4, k_width + 1)),
                                            dtype=np.uint64)))
            ctx.set(update, int(c == next_up))
            if c == next_up:
                next_up += lat + 2 + int(rng.integers(0, 40))
            ctx.set(step, int(rng.random() < (0.3 if (c // 400) % 2 else 0.02)))
            ctx.set(neg, int(rng.random() < 0.2))
            _same_outputs(ctx, forms, c, seen)
            await ctx.tick()

    simulate(m, [testbench], clock_hz=50e6, name="mt_k_steady")
    assert seen["fresh"] > 10 and seen["bound"] > 2 and seen["unsaturated"] > 5, seen


# --- arith="engine": the window logic here, the arithmetic on the loop engine ------------------

def _engine_pair(k, **kwargs):
    """``MTSpeed(arith="engine", **kwargs)`` with its run on an ``EngineCurrentLoop(mt=True)``
    (``k`` in the engine's configuration RAM as the register file's two export words), as one
    component with MTSpeed's ``edge``, ``update``, ``k`` (unused: k is the RAM's) and ``o``,
    and the model's parameters (the latency: the request a clock after the update, the run's
    ``mt_latency`` after it, when the engine is idle)."""
    from amaranth.lib import stream, wiring
    from amaranth.lib.wiring import In, Out

    from foc_servo.hdl.engine_mt import mt_k_words
    from foc_servo.hdl.foc_engine import CONFIG, EngineCurrentLoop
    from foc_servo.hdl.mt_speed import EDGE_LAYOUT, output_layout

    mt = MTSpeed(arith="engine", **kwargs)
    words = mt_k_words(k)
    cl = EngineCurrentLoop(config="ram", mt=True,
                           config_init=[0] * len(CONFIG) + [words["mtk0"] % (1 << 32),
                                                            words["mtk1"]])

    class Pair(wiring.Component):
        def __init__(self):
            super().__init__({"edge": In(EDGE_LAYOUT), "update": In(1), "k": In(48),
                              "o": Out(stream.Signature(output_layout(32), always_ready=True))})
            self.clk_hz, self.out_width, self.mt, self.cl = mt.clk_hz, 32, mt, cl

        def elaborate(self, platform):
            from amaranth.hdl import Module
            m = Module()
            m.submodules.mt, m.submodules.cl = mt, cl
            m.d.comb += [mt.edge.eq(self.edge), mt.update.eq(self.update)]
            wiring.connect(m, mt.run, cl.mt_run)
            wiring.connect(m, cl.mt_res, mt.res)
            wiring.connect(m, mt.o, wiring.flipped(self.o))
            return m

    @dataclasses.dataclass(frozen=True)
    class Params(model.MTParams):
        run_latency: int = 0

        @property
        def latency(self):
            return self.run_latency

    params = Params(mt.tclk_ratio, mt.tc_width, 32, 48, 16, run_latency=1 + cl.mt_latency)
    return Pair(), params


def _both_engine(k, edges, neg, ups, *, end_cycle, **kwargs):
    dut, params = _engine_pair(k, **kwargs)
    got = verify.run_gateware(dut, edges, neg, ups, k=k, end_cycle=end_cycle, name="mt_engine")
    want = model.simulate(edges, neg, ups, k=k, params=params, end_cycle=end_cycle)
    assert got["received"] == len(want["cycle"])
    for f in FIELDS:
        np.testing.assert_array_equal(got[f], want[f], err_msg=f)
    return want


def test_mt_engine_form_validation():
    for kwargs, msg in (({"tc_width": 28}, "tc_width at most 27"),
                        ({"out_width": 16}, "needs out_width 32"),
                        ({"k_width": 40}, "needs k_width 48"),
                        ({"m_width": 8}, "needs m_width 16"),
                        ({"chunk_multipliers": True}, "has no multiplier"),
                        ({"arith": "dsp"}, "arith")):
        with pytest.raises((ValueError, TypeError), match=msg):
            MTSpeed(**{"arith": "engine", "tc_width": 27, **kwargs})
    dut = MTSpeed(arith="engine", tc_width=27)
    assert dut.latency is None and "k" not in dut.signature.members
    assert MTSpeed().arith == "gateware"


@pytest.mark.parametrize("k", [3 * 2 ** 40 + 12345, 2 ** 48 - 1, (1 << 31) + 98_765, 1])
def test_mt_engine_form_matches_the_model(k):
    """The window logic with its run on the engine's program (``EngineCurrentLoop(mt=True)``,
    the piece reading ``k`` as two configuration words) against ``MTSpeedModel`` with the
    run's latency: every output (fresh, bounded, stopped: the TC span 1 024 clocks), its clock
    and flags; random windows both ways (ΔM 1 … 40, saturated quotients), stops beyond the span
    and restarts."""
    rng = np.random.default_rng(k % 1000)
    edges, neg, ups = [], [], []
    c, u = 5, 2
    for _ in range(30):
        n = int(rng.integers(1, 41))
        gap = int(rng.choice([0, 1, 2, 7, 30, 200])) // max(n, 1) + 1
        direction = bool(rng.integers(0, 2))
        for _ in range(n):
            c += gap
            edges.append(c)
            neg.append(direction if rng.random() < 0.85 else not direction)
        if rng.random() < 0.2:
            c += int(rng.integers(900, 2500))              # a stop (or near one)
        c += int(rng.integers(1, 150))
    while u < c + 1500:
        ups.append(u)
        u += int(rng.integers(113, 400))
    out = _both_engine(k, edges, neg, ups, end_cycle=u + 200, clk_hz=50e6, tc_width=10)
    kinds = set(zip(out["stopped"].tolist(), out["fresh"].tolist()))
    assert kinds == {(1, 0), (0, 1), (0, 0)}, kinds
