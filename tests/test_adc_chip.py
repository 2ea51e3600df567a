# Ref: issue 6 item 3; AD7380-4 data sheet, serial interface (see sim/adc_chip.py)
"""AdcChip (the AD7380-4's pins as gateware) against AdcPartModel (the Python pin model with the
data sheet checks): the interface reads exactly the same codes, at the same clocks, from both."""

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Module
from amaranth.lib import wiring

from foc_servo.hdl.adc import CHANNELS, AdcInterface
from foc_servo.sim.adc_chip import BITS, JUNK, JUNK_WORD, AdcChip
from foc_servo.sim.adc_part import AdcPartModel
from foc_servo.sim.harness import simulate


class _WithChip(wiring.Component):
    """AdcInterface wired to an AdcChip."""

    def __init__(self, clk_hz):
        self.adc = AdcInterface(clk_hz=clk_hz)
        self.chip = AdcChip()
        super().__init__({})

    def elaborate(self, platform):
        m = Module()
        m.submodules.adc = adc = self.adc
        m.submodules.chip = chip = self.chip
        m.d.comb += [chip.cs_n.eq(adc.cs_n), chip.sclk.eq(adc.sclk), adc.sdo.eq(chip.sdo)]
        return m


def _strobes(adc, n, rng):
    """n strobe clocks, each served (spaced by at least min_period, random extra gaps)."""
    gaps = adc.min_period + rng.integers(0, 40, size=n)
    return (3 + np.concatenate([[0], np.cumsum(gaps[:-1])])).tolist()


def _codes(rng, n):
    codes = rng.integers(-32768, 32768, size=(n, 4))
    codes[0] = (-32768, 32767, 0, -1)
    codes[1] = (1, -2, 0x5555, -0x5556)
    return codes


def _run(dut, adc, strobes, clocks, clk_hz, *, chip_codes=None, model_codes=None):
    """Per-clock record of (valid, payload) and the CS falling edges seen."""
    record, falls = [], []
    strobes = set(strobes)

    async def testbench(ctx):
        cs_prev = 1
        for t in range(clocks):
            ctx.set(adc.sample, t in strobes)
            await ctx.tick()
            p = ctx.get(adc.o.payload)
            record.append((ctx.get(adc.o.valid), tuple(p[n] for n in CHANNELS)))
            cs = ctx.get(adc.cs_n)
            if cs_prev and not cs:
                falls.append(t)
                if chip_codes is not None:
                    # The conversion this fall started gets its codes from the next clock on.
                    word = 0
                    for k, c in enumerate(chip_codes[len(falls) - 1]):
                        word |= (int(c) & 0xFFFF) << (BITS * k)
                    ctx.set(dut.chip.codes, word)
            cs_prev = cs

    processes = []
    if model_codes is not None:
        model = AdcPartModel(cs_n=adc.cs_n, sclk=adc.sclk, sdo=adc.sdo, clk_hz=clk_hz,
                             source=lambda n: model_codes[n])
        processes.append(model.process)
    simulate(dut, [testbench], processes, clock_hz=clk_hz, name="test_adc_chip")
    return record, falls


@pytest.mark.parametrize("clk_hz, seed", [(50e6, 1), (33.333e6, 2)])
def test_adc_chip_returns_what_the_part_model_returns(clk_hz, seed):
    rng = np.random.default_rng(seed)
    n = 6
    codes = _codes(rng, 2 * n + 2)
    ref = AdcInterface(clk_hz=clk_hz)
    strobes = _strobes(ref, n, rng)
    clocks = strobes[-1] + ref.min_period + 4
    rec_model, falls_model = _run(ref, ref, strobes, clocks, clk_hz, model_codes=codes)
    dut = _WithChip(clk_hz)
    rec_chip, falls_chip = _run(dut, dut.adc, strobes, clocks, clk_hz, chip_codes=codes)

    assert falls_chip == falls_model and len(falls_chip) == 2 * n
    valid_model = [(t, r[1]) for t, r in enumerate(rec_model) if r[0]]
    valid_chip = [(t, r[1]) for t, r in enumerate(rec_chip) if r[0]]
    assert valid_chip == valid_model
    # Independent of both: each transaction returns the conversion its first CS fall started.
    assert [v for _, v in valid_chip] == [tuple(codes[2 * k]) for k in range(n)]


def test_adc_chip_pins_cycle_by_cycle():
    # Hand-driven pins. wave[t] is what cs_n / sclk show after clock edge t (as the interface's
    # registers would); the chip answers on SDO one clock later, so seen[t] (SDO after edge t + 1)
    # is its answer to wave[t].
    chip = AdcChip()
    chans = (0x8001, 0x7FFE, 0x1234, 0xFEDC)
    word = sum(c << (BITS * k) for k, c in enumerate(chans))
    wave = [(1, 1)] * 2 + [(0, 1), (0, 0), (0, 1), (0, 0), (0, 1)] + [(1, 1)] * 3
    wave += [(0, 1)] * 2 + [(0, 0), (0, 1)] * 17 + [(1, 1)] * 3
    first_fall, second_fall, read_start = 2, 10, 12
    seen = []

    async def testbench(ctx):
        for t, (cs_n, sclk) in enumerate(wave):
            ctx.set(chip.cs_n, cs_n)
            ctx.set(chip.sclk, sclk)
            if t == first_fall:         # from the clock after the fall: conversion 0's codes
                ctx.set(chip.codes, word)
            if t == second_fall:        # from the clock after the next fall: conversion 1's
                ctx.set(chip.codes, 0)
            await ctx.tick()
            seen.append(ctx.get(chip.sdo))

    simulate(chip, [testbench], clock_hz=50e6, name="test_adc_chip_pins")

    def lines(values, bit):
        return sum(((v >> (BITS - 1 - bit)) & 1) << k for k, v in enumerate(values))

    assert seen[first_fall] == JUNK
    # First frame: no conversion yet, JUNK_WORD on every line.
    assert [seen[3], seen[5]] == [lines([JUNK_WORD] * 4, 0), lines([JUNK_WORD] * 4, 1)]
    assert seen[7] == JUNK                      # CS rise
    assert seen[second_fall] == JUNK
    got = [seen[read_start + 2 * b] for b in range(BITS)]
    assert got == [lines(chans, b) for b in range(BITS)]
    assert seen[read_start + 2 * BITS] == 0b1111            # a 17th bit: ones
    assert seen[read_start + 2 * BITS + 1] == 0b1111        # SCLK rising: no change
    assert seen[read_start + 2 * BITS + 2] == JUNK          # CS rise


def test_adc_chip_converts_to_verilog():
    text = verilog.convert(AdcChip(), name="adc_chip")
    assert "module adc_chip" in text and "codes" in text
