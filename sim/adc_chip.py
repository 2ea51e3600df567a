# Ref: issue 6 item 3 (models of outside chips as Amaranth components, so both engines run them);
#      Analog Devices AD7380-4 data sheet, serial interface (4-wire mode, SPI mode 3, MSB first,
#      two's complement; each CS falling edge starts a conversion and shifts out the previous one)
"""The AD7380-4's pin behaviour as gateware, for simulation wrappers run by any engine.

:class:`AdcChip` behaves on its pins as :class:`~foc_servo.sim.adc_part.AdcPartModel` does (that
model stays the one that checks the data sheet's timing), but it is an Amaranth component, so the
compiled engine (Verilator) runs it as well as Amaranth's simulator. The analog side is the
``codes`` input, which the co-simulation sets once per conversion::

    cs_n    ‾‾‾‾|_____…_____|‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|___________________…
                ^ edge e: conversion n starts  ^ edge e': conversion n+1 starts, n is shifted out
    codes   ====X  codes of conversion n (from clock e + 1 to clock e')  X====

The codes of the conversion that a CS falling edge (at clock edge ``e``) starts are the value
``codes`` holds *after* that edge: whatever the host puts there for clock ``e + 1`` and keeps
until the next falling edge at ``e'``, where the chip takes it (the value sampled by edge
``e'``) into its output shift registers. A co-simulation can therefore stop at a CS falling edge,
compute the analog inputs at that instant and set ``codes`` from the next clock on.

Each SCLK falling edge during a CS-low frame puts the next bit (MSB first) of every channel on
its SDO line one system clock later (as :class:`~foc_servo.sim.adc_part.AdcPartModel`, a
pessimistic ``t_DSDO``); CS edges put :data:`JUNK` on the lines, bits after the 16th are ones,
and the first frame after power-up shifts out :data:`JUNK_WORD` (no conversion yet).
"""

from amaranth.hdl import Const, Module, Mux, Signal
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

__all__ = ["AdcChip", "JUNK", "JUNK_WORD", "BITS", "LINES"]

#: Bits per channel and lines (channels) of the AD7380-4.
BITS = 16
LINES = 4
#: SDO lines (bit 0 = SDOA) after each CS edge, before the first SCLK falling edge.
JUNK = 0b1010
#: What every channel shifts out in the first frame (no conversion has been made yet).
JUNK_WORD = 0xA5C3


class AdcChip(wiring.Component):
    """Pin-level AD7380-4 (4-wire mode) as a component (module docstring).

    Members
    -------
    cs_n, sclk : In(1, init=1)
        Chip select and serial clock from the interface (SPI mode 3: both idle high). Sampled
        once per system clock: the interface drives them from registers.
    sdo : Out(4)
        SDOA … SDOD (bit 0 = SDOA), registered: a change seen on ``cs_n`` / ``sclk`` in clock
        ``t`` (i.e. made by the clock edge that began clock ``t``) shows on ``sdo`` from the next
        edge on.
    codes : In(64)
        The analog side: bits ``16·k … 16·k + 15`` are channel ``k``'s code (A, B, C, D), two's
        complement. The value held from the clock after a CS falling edge until the next CS
        falling edge is that conversion's result (module docstring).
    """

    cs_n: In(1, init=1)
    sclk: In(1, init=1)
    sdo: Out(LINES)
    codes: In(LINES * BITS)

    def elaborate(self, platform):
        m = Module()
        cs_prev = Signal(init=1)
        sclk_prev = Signal(init=1)
        # `codes` as it was before the current clock edge: at the clock after a CS fall (when the
        # fall is seen) this is still the value the previous conversion was given, even if the
        # host changes `codes` for that very clock.
        codes_q = Signal(LINES * BITS)
        converted = Signal()            # a conversion has been started since power-up
        shreg = [Signal(BITS, name=f"sh{k}") for k in range(LINES)]
        m.d.sync += [cs_prev.eq(self.cs_n), sclk_prev.eq(self.sclk), codes_q.eq(self.codes)]

        cs_fall = cs_prev & ~self.cs_n
        cs_rise = ~cs_prev & self.cs_n
        sclk_fall = sclk_prev & ~self.sclk & ~self.cs_n
        loaded = [Mux(converted, codes_q[BITS * k:BITS * (k + 1)], Const(JUNK_WORD, BITS))
                  for k in range(LINES)]

        with m.If(cs_fall):
            m.d.sync += converted.eq(1)
            with m.If(sclk_fall):      # both in one clock: the first bit goes out at once
                for k in range(LINES):
                    m.d.sync += [self.sdo[k].eq(loaded[k][-1]),
                                 shreg[k].eq((loaded[k] << 1) | 1)]
            with m.Else():
                m.d.sync += self.sdo.eq(JUNK)
                for k in range(LINES):
                    m.d.sync += shreg[k].eq(loaded[k])
        with m.Elif(cs_rise):
            m.d.sync += self.sdo.eq(JUNK)
        with m.Elif(sclk_fall):
            for k in range(LINES):
                m.d.sync += [self.sdo[k].eq(shreg[k][-1]), shreg[k].eq((shreg[k] << 1) | 1)]
        return m
