# Ref: hdl/dsp.py (partial products for pipelined multipliers, saturation by bit tests)
import numpy as np
import pytest
from amaranth.hdl import Const, Module, Signal, signed, unsigned
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from foc_servo.hdl.dsp import (chunks, partial_products, partial_sum, registered_products,
                               round_shift_signed, saturate_bits)
from foc_servo.hdl.fixed import round_shift_np, saturate_np
from foc_servo.sim.harness import simulate


@pytest.mark.parametrize("shape", [signed(16), unsigned(16), signed(18), unsigned(17),
                                   signed(25), unsigned(34), signed(44)])
def test_chunks_fit_an_18x18_multiplier(shape):
    parts = chunks(Signal(shape))
    for part, _ in parts:
        s = part.shape()
        assert s.width <= (18 if s.signed else 17)
    assert parts[-1][0].shape().signed == shape.signed
    assert sum(len(p) for p, _ in parts) == shape.width


class _Product(wiring.Component):
    def __init__(self, sa, sb):
        self._sa, self._sb = sa, sb
        width = sa.width + sb.width + 1
        super().__init__({"a": In(sa), "b": In(sb), "ok": In(1), "p": Out(signed(width)),
                          "p_comb": Out(signed(width))})

    def elaborate(self, platform):
        m = Module()
        regs = registered_products(m, self.a, self.b, enable=self.ok, name="pp")
        m.d.comb += [self.p.eq(partial_sum(regs)),
                     self.p_comb.eq(partial_sum(partial_products(self.a, self.b)))]
        return m


@pytest.mark.parametrize("sa, sb", [(signed(17), unsigned(27)), (signed(24), unsigned(18)),
                                    (unsigned(16), unsigned(34)), (signed(25), signed(25)),
                                    (signed(18), signed(16))])
def test_partial_products_sum_to_the_product(sa, sb):
    """Registered partial products add up to a·b exactly, extremes included."""
    dut = _Product(sa, sb)
    rng = np.random.default_rng(3)

    def values(s):
        lo, hi = (-(1 << (s.width - 1)), (1 << (s.width - 1)) - 1) if s.signed else \
            (0, (1 << s.width) - 1)
        return [lo, hi, 0, 1, -1 if s.signed else 2] + [int(x) for x in
                                                        rng.integers(lo, hi, 40, endpoint=True)]

    pairs = [(a, b) for a in values(sa)[:5] for b in values(sb)[:5]]
    pairs += list(zip(values(sa)[5:], values(sb)[5:]))
    bad = []

    async def testbench(ctx):
        ctx.set(dut.ok, 1)
        for a, b in pairs:
            ctx.set(dut.a, a)
            ctx.set(dut.b, b)
            if ctx.get(dut.p_comb) != a * b:
                bad.append(("comb", a, b))
            await ctx.tick()
            if ctx.get(dut.p) != a * b:
                bad.append(("reg", a, b))

    simulate(dut, [testbench], name="test_dsp_products")
    assert bad == []


class _Rounder(wiring.Component):
    v: In(signed(12))
    neg: In(1)
    sat: Out(signed(6))
    rnd: Out(signed(12))

    def elaborate(self, platform):
        m = Module()
        m.d.comb += [self.sat.eq(saturate_bits(self.v, signed(6))),
                     self.rnd.eq(round_shift_signed(self.v, 3, self.neg))]
        return m


def test_saturate_bits_and_round_shift_signed_exhaustive():
    """Every 12-bit value: ``saturate_bits`` equals ``saturate``; ``round_shift_signed`` with the
    true sign equals ``round_shift`` (ties away from zero), and 0 rounds to 0 with either
    sign."""
    dut = _Rounder()
    vals = np.arange(-2048, 2048)
    got_sat, got_rnd, zero = [], [], []

    async def testbench(ctx):
        for v in vals.tolist():
            ctx.set(dut.v, v)
            ctx.set(dut.neg, int(v < 0))
            got_sat.append(ctx.get(dut.sat))
            got_rnd.append(ctx.get(dut.rnd))
        ctx.set(dut.v, 0)
        for neg in (0, 1):
            ctx.set(dut.neg, neg)
            zero.append(ctx.get(dut.rnd))

    simulate(dut, [testbench], name="test_dsp_round")
    np.testing.assert_array_equal(got_sat, saturate_np(vals, signed(6)))
    np.testing.assert_array_equal(got_rnd, round_shift_np(vals, 3))
    assert zero == [0, 0]
    # Ties go away from zero: −12 / 8 = −1.5 → −2, 12 / 8 → 2.
    assert got_rnd[2048 - 12] == -2 and got_rnd[2048 + 12] == 2


def test_saturate_bits_rejects_unsigned():
    with pytest.raises(TypeError, match=r"^saturate_bits needs a signed value and shape"):
        saturate_bits(Const(3, unsigned(4)), signed(3))
