# amaranth: UnusedElaboratable=no
# Ref: hdl/dsp.py (partial products for pipelined multipliers, saturation by bit tests)
import re

import numpy as np
import pytest
from amaranth.hdl import Const, Module, Signal, signed, unsigned
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from foc_servo.hdl.dsp import (MUL_WIDTH, check_mul_width, chunks, partial_products,
                               partial_sum, registered_products, round_shift_signed,
                               saturate_bits)
from foc_servo.hdl.fixed import round_shift_np, saturate_np
from foc_servo.sim.harness import simulate


@pytest.mark.parametrize("mul_width", [18, 16, 12])
@pytest.mark.parametrize("shape", [signed(16), unsigned(16), signed(18), unsigned(17),
                                   signed(25), unsigned(34), signed(44)])
def test_chunks_fit_the_multiplier(shape, mul_width):
    """Every part is a signed ``mul_width``-bit operand: unsigned parts at most ``mul_width − 1``
    bits (Amaranth adds a sign bit), the signed top part at most ``mul_width``; as few parts as
    that allows."""
    parts = chunks(Signal(shape), mul_width=mul_width)
    for part, _ in parts:
        s = part.shape()
        assert s.width <= (mul_width if s.signed else mul_width - 1)
    assert parts[-1][0].shape().signed == shape.signed
    assert sum(len(p) for p, _ in parts) == shape.width
    assert [shift for _, shift in parts] == [(mul_width - 1) * k for k in range(len(parts))]
    top = mul_width if shape.signed else mul_width - 1
    assert len(parts) == 1 + max(0, -(-(shape.width - top) // (mul_width - 1)))


def test_chunks_default_is_the_ecp5_multiplier():
    assert MUL_WIDTH == 18
    assert [(p.shape(), s) for p, s in chunks(Signal(signed(25)))] == \
        [(unsigned(17), 0), (signed(8), 17)]
    assert [(p.shape(), s) for p, s in chunks(Signal(signed(25)), mul_width=16)] == \
        [(unsigned(15), 0), (signed(10), 15)]
    # A 16-bit signed operand is one SB_MAC16 operand at 16; an unsigned 16-bit one is two.
    assert len(chunks(Signal(signed(16)), mul_width=16)) == 1
    assert len(chunks(Signal(unsigned(16)), mul_width=16)) == 2
    # None: no split (the iCE40's setting: yosys splits whole products better).
    v = Signal(signed(44))
    assert chunks(v, mul_width=None) == [(v, 0)]
    assert len(partial_products(v, Signal(unsigned(30)), mul_width=None)) == 1


@pytest.mark.parametrize("value", [7, 26, 16.0, True, "16"])
def test_mul_width_validation(value):
    with pytest.raises(TypeError, match=rf"^PI mul_width must be None or an integer from 8 to 25 "
                                        rf"\(the signed operand width of the hard multiplier: 18 "
                                        rf"ECP5 / Xilinx; None: products not split, iCE40\), "
                                        rf"not {re.escape(repr(value))}$"):
        check_mul_width("PI", value)
    with pytest.raises(TypeError, match=r"^chunks mul_width must be"):
        chunks(Signal(signed(8)), mul_width=value)
    assert check_mul_width("PI", 8) == 8 and check_mul_width("PI", 25) == 25
    assert check_mul_width("PI", None) is None


class _Product(wiring.Component):
    def __init__(self, sa, sb, mul_width=MUL_WIDTH):
        self._sa, self._sb, self._mw = sa, sb, mul_width
        width = sa.width + sb.width + 1
        super().__init__({"a": In(sa), "b": In(sb), "ok": In(1), "p": Out(signed(width)),
                          "p_comb": Out(signed(width))})

    def elaborate(self, platform):
        m = Module()
        regs = registered_products(m, self.a, self.b, enable=self.ok, name="pp",
                                   mul_width=self._mw)
        m.d.comb += [self.p.eq(partial_sum(regs)),
                     self.p_comb.eq(partial_sum(partial_products(self.a, self.b,
                                                                 mul_width=self._mw)))]
        return m


@pytest.mark.parametrize("mul_width", [18, 16, None])
@pytest.mark.parametrize("sa, sb", [(signed(17), unsigned(27)), (signed(24), unsigned(18)),
                                    (unsigned(16), unsigned(34)), (signed(25), signed(25)),
                                    (signed(18), signed(16))])
def test_partial_products_sum_to_the_product(sa, sb, mul_width):
    """Registered partial products add up to a·b exactly, extremes included, at the ECP5's 18,
    at 16 and unsplit (``None``, the iCE40's): the split changes the netlist, not the result."""
    dut = _Product(sa, sb, mul_width)
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


def test_blocks_take_and_check_mul_width():
    """Every block built on this module takes ``mul_width`` (the ECP5's 18, the iCE40's None)
    and names itself when it is wrong."""
    from foc_servo.hdl.clarke import Clarke
    from foc_servo.hdl.foc import CurrentLoop
    from foc_servo.hdl.pi import PI
    from foc_servo.hdl.servo import Servo, SpeedLoop
    from foc_servo.hdl.svpwm import SVPWM, DCBusCompensation
    from foc_servo.hdl.top import Top
    for cls in (Clarke, PI, SVPWM, DCBusCompensation, CurrentLoop, SpeedLoop, Servo, Top):
        with pytest.raises(TypeError, match=rf"^{cls.__name__} mul_width must be None or an "
                                            r"integer from 8 to 25 .*, not 17\.5$"):
            cls(mul_width=17.5)
    assert PI(mul_width=16).mul_width == 16 and SVPWM().mul_width == 18
    loop = CurrentLoop(mul_width=None)
    assert loop.mul_width is None
    assert {loop._clarke.mul_width, loop._pi_d.mul_width, loop._pi_q.mul_width,
            loop._dcbus.mul_width, loop._svpwm.mul_width} == {None}
