"""hdl/fixed.py: the gateware helpers agree bit for bit with their numpy twins, and the format
conversions round, wrap and reject as documented."""

import math

import numpy as np
import pytest
from amaranth.hdl import Module, Signal, signed, unsigned

from foc_servo.hdl import fixed
from foc_servo.hdl.fixed import Q, UQ, BinaryAngle, Quantity
from foc_servo.sim.harness import simulate


def _corner_and_random(shape, n, rng):
    lo, hi = fixed.shape_range(shape)
    corners = [lo, lo + 1, -1 if lo < 0 else 0, 0, 1, hi - 1, hi]
    return np.concatenate([corners, rng.integers(lo, hi + 1, n)])


def test_helpers_match_numpy_models():
    a, b = Signal(signed(12)), Signal(signed(10))
    lo, hi = Signal(signed(9)), Signal(signed(9))
    ua = Signal(unsigned(11))
    outs = {
        "mul_round": Signal(signed(8)),
        "round_shift": Signal(signed(20)),
        "sat_add": Signal(signed(9)),
        "sat_sub": Signal(signed(9)),
        "saturate_u": Signal(unsigned(7)),
        "round_shift_u": Signal(unsigned(9)),
        "clamp": Signal(signed(12)),
    }
    m = Module()
    m.d.comb += [
        outs["mul_round"].eq(fixed.mul_round(a, b, 7, signed(8))),
        outs["round_shift"].eq(fixed.round_shift(a * b, 5)),
        outs["sat_add"].eq(fixed.sat_add(a, b, signed(9))),
        outs["sat_sub"].eq(fixed.sat_sub(a, b, signed(9))),
        outs["saturate_u"].eq(fixed.saturate(a, unsigned(7))),
        outs["round_shift_u"].eq(fixed.round_shift(ua, 3)),
        outs["clamp"].eq(fixed.clamp(a, lo, hi)),
    ]
    rng = np.random.default_rng(3)
    n = 4000
    av = _corner_and_random(signed(12), n, rng)
    bv = _corner_and_random(signed(10), n, rng)[:len(av)]
    lov = rng.integers(-256, 256, len(av))
    hiv = rng.integers(-256, 256, len(av))  # lo > hi half of the time: the defined corner
    uav = rng.integers(0, 2048, len(av))
    expected = {
        "mul_round": fixed.mul_round_np(av, bv, 7, signed(8)),
        "round_shift": fixed.round_shift_np(av * bv, 5),
        "sat_add": fixed.saturate_np(av + bv, signed(9)),
        "sat_sub": fixed.saturate_np(av - bv, signed(9)),
        "saturate_u": fixed.saturate_np(av, unsigned(7)),
        "round_shift_u": fixed.round_shift_np(uav, 3),
        "clamp": fixed.clamp_np(av, lov, hiv),
    }
    got = {k: np.zeros(len(av), dtype=np.int64) for k in outs}

    async def testbench(ctx):
        for j in range(len(av)):
            ctx.set(a, int(av[j]))
            ctx.set(b, int(bv[j]))
            ctx.set(lo, int(lov[j]))
            ctx.set(hi, int(hiv[j]))
            ctx.set(ua, int(uav[j]))
            for k, sig in outs.items():
                got[k][j] = ctx.get(sig)

    simulate(m, [testbench], name="fixed_helpers")
    for k in outs:
        np.testing.assert_array_equal(got[k], expected[k], err_msg=k)


def test_saturate_exhaustive_against_numpy():
    """:func:`fixed.saturate` (bit tests, no compares) is :func:`fixed.saturate_np` for every
    value of every signed / unsigned input of 1–7 bits into every signed / unsigned shape of
    1–6 bits: narrower, as wide and wider than the input, each sign combination."""
    shapes = [sh(w) for w in range(1, 7) for sh in (signed, unsigned)]
    cases = [(sh(w), out) for w in range(1, 8) for sh in (signed, unsigned) for out in shapes]
    m = Module()
    ins = [Signal(src, name=f"v{j}") for j, (src, _) in enumerate(cases)]
    outs = [Signal(out, name=f"o{j}") for j, (_, out) in enumerate(cases)]
    m.d.comb += [o.eq(fixed.saturate(v, out)) for v, o, (_, out) in zip(ins, outs, cases)]
    got = {}

    async def testbench(ctx):
        for x in range(1 << 7):
            for v, o, (src, _) in zip(ins, outs, cases):
                lo, hi = fixed.shape_range(src)
                if lo <= x - (1 << 6) * src.signed <= hi:
                    ctx.set(v, x - (1 << 6) * src.signed)
            for j, (v, o) in enumerate(zip(ins, outs)):
                got[j, ctx.get(v)] = ctx.get(o)

    simulate(m, [testbench], name="fixed_saturate")
    for j, (src, out) in enumerate(cases):
        lo, hi = fixed.shape_range(src)
        for x in range(lo, hi + 1):
            assert got[j, x] == fixed.saturate_np(x, out), (src, out, x)


def test_round_shift_is_half_away_from_zero():
    v = np.array([-7, -6, -5, -3, -2, -1, 0, 1, 2, 3, 5, 6, 7])
    np.testing.assert_array_equal(fixed.round_shift_np(v, 1),
                                  [-4, -3, -3, -2, -1, -1, 0, 1, 1, 2, 3, 3, 4])
    # odd symmetry: f(-v) == -f(v)
    w = np.arange(-1000, 1001)
    np.testing.assert_array_equal(fixed.round_shift_np(-w, 4), -fixed.round_shift_np(w, 4))


def test_saturate_never_wraps_at_extremes():
    assert fixed.saturate_np(2**20, signed(16)) == 32767
    assert fixed.saturate_np(-2**20, signed(16)) == -32768
    assert fixed.saturate_np(-1, unsigned(8)) == 0
    assert fixed.mul_round_np(-32768, -32768, 15, signed(16)) == 32767


def test_qformat_conversions():
    q15 = Q(16, 15)
    assert (q15.min, q15.max_raw, q15.lsb) == (-1.0, 32767, 2**-15)
    np.testing.assert_array_equal(q15.to_raw([0.5, -1.0, -0.5 * 2**-15, 0.5 * 2**-15]),
                                  [16384, -32768, -1, 1])
    assert q15.from_raw(-16384) == -0.5
    assert UQ(16, 8).max == 255.99609375
    assert q15.to_raw(3.0, saturate=True) == 32767
    with pytest.raises(ValueError, match=r"^kp 1\.0 is outside the range \[-1\.0, 0\.99996"):
        q15.to_raw(1.0, name="kp")
    with pytest.raises(ValueError, match=r"^value must be finite"):
        q15.to_raw(float("nan"))


def test_qformat_validation():
    with pytest.raises(TypeError, match=r"^QFormat width must be an integer, not 16\.0$"):
        Q(16.0, 15)
    with pytest.raises(ValueError, match=r"^QFormat width must be at least 1 and at most 64, not 0$"):
        Q(0, 0)


def test_binary_angle_wraps():
    ang = BinaryAngle(16)
    assert ang.to_raw(-math.pi / 2) == 49152
    assert ang.to_raw(2 * math.pi) == 0
    assert ang.to_raw(math.pi) == 32768
    assert ang.to_rad(32768) == -math.pi
    assert ang.to_rad(32768, signed=False) == math.pi
    np.testing.assert_allclose(ang.to_rad(ang.to_raw(np.linspace(-3, 3, 50))),
                               np.linspace(-3, 3, 50), atol=ang.lsb_rad / 2)


def test_quantity_names_value_range_and_unit():
    i_q = Quantity("i_q", Q(16, 15), 20.0, "A")
    assert i_q.to_raw(10.0) == 16384
    assert i_q.from_raw(-32768) == -20.0
    with pytest.raises(ValueError, match=r"^i_q 25 A is outside the range \[-20, 19\.9994\] A$"):
        i_q.to_raw(25.0)
    with pytest.raises(ValueError, match=r"^Quantity full_scale must be a positive number"):
        Quantity("x", Q(16, 15), 0, "V")


@pytest.mark.parametrize("width", [1, 3, 5])
def test_at_least_exhaustive_against_python(width):
    """:func:`fixed.at_least` (AND/OR of the bits, no comparator) is ``v ≥ k`` for every
    ``v`` and every constant from below 0 to beyond the range."""
    v = Signal(unsigned(width))
    ks = list(range(-1, (1 << width) + 2))
    m = Module()
    outs = {k: Signal(name=f"ge_{k + 1}") for k in ks}
    m.d.comb += [outs[k].eq(fixed.at_least(v, k)) for k in ks]
    got = {}

    async def testbench(ctx):
        for x in range(1 << width):
            ctx.set(v, x)
            for k in ks:
                got[x, k] = ctx.get(outs[k])

    simulate(m, [testbench], name="fixed_at_least")
    assert got == {(x, k): int(x >= k) for x in range(1 << width) for k in ks}


def test_at_least_rejects_signed_and_non_integer():
    with pytest.raises(TypeError, match=r"^at_least needs an unsigned value, not signed\(4\)$"):
        fixed.at_least(Signal(signed(4)), 3)
    with pytest.raises(TypeError, match=r"^at_least needs an integer constant, not 2\.5$"):
        fixed.at_least(Signal(4), 2.5)
