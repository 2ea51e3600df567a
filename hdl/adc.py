# Ref: issue 4 item 7; Analog Devices AD7380-4 data sheet ("Differential Input, Quad, Simultaneous
#      Sampling, 16-Bit SAR ADC"): Specifications → Timing Specifications table and the serial
#      interface timing diagrams (Serial Interface section, 4-wire mode). Cross-checked against the
#      Linux IIO driver drivers/iio/adc/ad7380.c (T_CONVERT_NS = 190, t_csh_ns = 20 for the
#      quad parts, two-step read "toggle CS to convert, then read") and its DT binding
#      adi,ad7380.yaml (SPI mode 3: spi-cpol + spi-cpha, spi-max-frequency ≤ 80 MHz).
"""SPI interface to a simultaneous-sampling SAR ADC (AD7380-4) for i_a, i_b and U_dc.

The AD7380-4 samples its four differential inputs together on the falling edge of CS and converts
them in t_CONVERT; the result is shifted out (MSB first, two's complement, one channel per SDOx
line in 4-wire mode) during the *next* CS-low frame, whose own falling edge starts another
conversion. One transaction therefore has two frames (as the Linux driver does)::

    sample  _|‾|______________________________________________________________
    cs_n    ‾‾‾|_|‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|_________________________________|‾‾‾‾‾‾
                 ^ conversion start = sampling instant (1 clock after the strobe)
    sclk    ‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|_|‾|_|‾ … ‾|_|‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾
                       ≥ max(t_CONVERT, t_CYC) ^ read frame: 16 SCLK cycles
    o.valid __________________________________________________________|‾|____

SPI mode 3: SCLK idles high, the part launches each bit on a falling SCLK edge, the interface
samples SDOx one full SCLK period later, on the system-clock edge that launches the next falling
edge (the last bit one full period after the 16th falling edge). That gives the data a whole SCLK
period (instead of half of one) to cross the board and the part's output delay t_DSDO; the part
holds a bit until after the next falling edge (t_HSDO), which reaches its pin after that clock
edge, so the hold time is met by the output and trace delay.

The read frame's conversion (a dummy) is never read; the next strobe's first falling edge comes at
least t_CYC after it, which the interface enforces (a strobe while busy is dropped and flagged).
"""

import dataclasses
import math
import numbers

from amaranth.hdl import Module, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import check_bool

__all__ = ["AdcPart", "AD7380_4", "PARTS", "AdcInterface", "CHANNELS"]

#: Payload fields, in SDO-line order (SDOA, SDOB, SDOC, SDOD).
CHANNELS = ("ia", "ib", "udc", "aux")


@dataclasses.dataclass(frozen=True)
class AdcPart:
    """Datasheet timing of a simultaneous-sampling SPI SAR ADC read in "convert, then read" frames.

    All times in seconds, minimum values unless stated. The interface waits at least these; the
    pin-level model (:mod:`foc_servo.sim.adc_part`) checks them.

    Attributes
    ----------
    name : str
    bits : int
        Bits per channel and frame (MSB first, two's complement).
    lines : int
        SDO lines read in parallel, one channel each.
    f_sclk_max_hz : float
        Maximum SCLK frequency (``f_SCLK``); its inverse is the minimum SCLK period ``t_SCLK``.
    t_sclkh_s, t_sclkl_s : float
        Minimum SCLK high and low times (``t_SCLKH``, ``t_SCLKL``).
    t_convert_s : float
        Conversion time, maximum (``t_CONVERT``): from a CS falling edge until the result may be
        read, i.e. until the next CS falling edge is allowed.
    t_cyc_s : float
        Minimum time between two conversions (CS falling edges), ``t_CYC`` = 1 / throughput.
    t_csh_s : float
        Minimum CS high time (``t_CSH``).
    t_sclked_s : float
        Minimum time from a CS falling edge to the first SCLK falling edge (``t_SCLKED``).
    """

    name: str
    bits: int
    lines: int
    f_sclk_max_hz: float
    t_sclkh_s: float
    t_sclkl_s: float
    t_convert_s: float
    t_cyc_s: float
    t_csh_s: float
    t_sclked_s: float


#: AD7380-4, 4-wire mode, no oversampling, 16-bit resolution (RES = 0).
#: f_SCLK 80 MHz, t_CONVERT 190 ns (max), t_CSH 20 ns: data sheet timing table, confirmed by the
#: Linux driver and binding quoted at the top of this file; t_CYC 250 ns is the 4 MSPS throughput.
#: t_SCLKH/t_SCLKL (taken as 0.4 × 12.5 ns = 5 ns) and t_SCLKED (10 ns) are conservative values:
#: check them against the current data sheet revision before a board is built.
AD7380_4 = AdcPart(
    name="AD7380-4", bits=16, lines=4,
    f_sclk_max_hz=80e6, t_sclkh_s=5e-9, t_sclkl_s=5e-9,
    t_convert_s=190e-9, t_cyc_s=250e-9, t_csh_s=20e-9, t_sclked_s=10e-9,
)

#: Parts by name.
PARTS = {AD7380_4.name: AD7380_4}


def _clocks(t_s, clk_hz):
    """Smallest whole number of clocks lasting at least ``t_s`` (a 1e-6 clock tolerance absorbs
    float rounding such as 190e-9 · 50e6 = 9.500000000000002)."""
    return max(0, math.ceil(t_s * clk_hz - 1e-6))


class AdcInterface(wiring.Component):
    """Drives an AD7380-4 (or a part with the same frame structure) and streams its four codes.

    Parameters
    ----------
    clk_hz : float
        System clock frequency, 1 MHz … 500 MHz.
    sclk_hz : float
        Highest SCLK frequency wanted; the interface uses ``clk_hz / (2·h)`` with the smallest
        whole ``h`` (system clocks per SCLK half period) that does not exceed it. At most the
        part's ``f_SCLK``. Default 25 MHz (``h = 1`` at 50 MHz, 16.7 MHz at 33.333 MHz).
    part : str or AdcPart
        ``"AD7380-4"`` (see :data:`PARTS`) or a timing record.
    held : tuple of str or None
        The channels (of :data:`CHANNELS`, the part's ``lines`` first) whose code is copied
        into an output register with the frame's last bit, so that ``payload`` holds it
        between valids (``None``, the default: all of them). The others' ``payload`` is the shift register
        itself, valid from ``o.valid`` for :attr:`hold` clocks (no copy: on the iCE40 a
        register loaded from a register costs a logic cell per bit); a consumer that needs it
        longer latches it at ``o.valid``, as the current loops do (:class:`~.top.Top` holds
        only ``udc``, for its status register and the scope).
    marker : bool
        ``True``: no bit counter; the first channel's shift register (``ia``) is loaded with 1
        in the clock before the read frame's first SCLK falling edge (its code then zeros with
        a marker bit at bit 0), and the frame's last bit is the one sampled while the marker
        is at the top bit (the iCE40's form, ``Top(adc_marker)``: the counter, its increment
        and compare cost logic cells; docs/AREA.md §7.86). The same pins, ``o.valid`` and
        codes; only the first channel's shift register differs, from a read frame's first
        SCLK falling edge until its ``o.valid``, and :attr:`hold` is ``2·h`` clocks shorter.
        Default ``False``.

    Members
    -------
    sample : In(1)
        Conversion start strobe (1 clock) from the PWM timing master. The analog inputs are
        sampled ``sample_delay`` clocks later (the CS falling edge). A strobe while ``busy`` is
        dropped and pulses ``overrun``.
    cs_n, sclk : Out(1)
        Chip select (active low) and serial clock pins; both idle high (SPI mode 3).
    sdo : In(lines)
        SDOA … SDOD (bit 0 = SDOA), straight from the pins: the shift registers are the input
        flip-flops (they may be packed into the I/O cells). Do not add a register or
        synchroniser in front: the sampling point described in the module docstring assumes
        none.
    o : Out(stream.Signature(data.StructLayout({"ia", "ib", "udc", "aux": signed(bits)}),
        always_ready=True))
        The codes of the conversion started by the strobe, raw two's complement ADC codes (SDOA →
        ``ia``, SDOB → ``ib``, SDOC → ``udc``, SDOD → ``aux``). All are valid in the
        ``o.valid`` clock; a ``held`` channel's code holds between valids, another's for
        :attr:`hold` clocks (from the ``o.valid`` clock) at least.
    busy : Out(1)
        A transaction (or the recovery time after it) is in progress.
    overrun : Out(1)
        One-clock pulse: a ``sample`` strobe came while busy and was ignored.

    Attributes
    ----------
    latency : int
        Clocks from the ``sample`` strobe to ``o.valid`` (strobe in clock 0 → valid in clock
        ``latency``); ``latency_s`` the same in seconds.
    sample_delay : int
        Clocks from the strobe to the CS falling edge (the sampling instant): 1.
    min_period : int
        Smallest number of clocks between two strobes that are both served.
    hold : int
        Clocks (the ``o.valid`` clock included) that a channel not ``held`` keeps its code at
        least: ``min_period − 2·h·(bits − 1)``, the next read frame shifting its first bit in
        ``2·h·(bits − 1)`` clocks before its own ``o.valid`` (``marker``: ``min_period −
        2·h·bits``, the first channel's loaded with the marker ``2·h·bits`` clocks before it).
    held : tuple of str
        The parameter.
    marker : bool
        The parameter.
    half_period : int
        ``h``, system clocks per SCLK half period; ``sclk_actual_hz = clk_hz / (2·h)``.

    Raises
    ------
    TypeError
        A parameter of the wrong type (``marker`` not a bool).
    ValueError
        A frequency out of range, or an SCLK faster than the part allows.
    """

    sample_delay = 1

    def __init__(self, *, clk_hz=50e6, sclk_hz=25e6, part="AD7380-4", held=None,
                 marker=False):
        if isinstance(part, str):
            if part not in PARTS:
                raise ValueError(f"AdcInterface part must be one of {sorted(PARTS)}, "
                                 f"not {part!r}")
            part = PARTS[part]
        if not isinstance(part, AdcPart):
            raise TypeError(f"AdcInterface part must be a part name or an AdcPart, not {part!r}")
        for name, value in (("clk_hz", clk_hz), ("sclk_hz", sclk_hz)):
            if not isinstance(value, numbers.Real) or isinstance(value, bool):
                raise TypeError(f"AdcInterface {name} must be a number in Hz, not {value!r}")
        if not 1e6 <= clk_hz <= 500e6:
            raise ValueError(f"AdcInterface clk_hz must be from 1 MHz to 500 MHz, "
                             f"not {clk_hz!r}")
        if not 0 < sclk_hz <= part.f_sclk_max_hz:
            raise ValueError(f"AdcInterface sclk_hz must be above 0 and at most the "
                             f"{part.name}'s f_SCLK of {part.f_sclk_max_hz / 1e6:g} MHz, "
                             f"not {sclk_hz!r}")
        names = CHANNELS[:part.lines]
        if held is None:
            held = names
        if (not isinstance(held, tuple) or not all(isinstance(n, str) for n in held)
                or len(set(held)) != len(held)):
            raise TypeError(f"AdcInterface held must be None or a tuple of distinct channel "
                            f"names, not {held!r}")
        if not set(held) <= set(names):
            raise ValueError(f"AdcInterface held must name channels of {names!r}, "
                             f"not {held!r}")
        check_bool("AdcInterface", "marker", marker)
        h = max(1, math.ceil(clk_hz / (2 * sclk_hz) - 1e-9))
        # Half periods must also meet t_SCLKH / t_SCLKL (a slow part, or a very slow clock).
        h = max(h, _clocks(part.t_sclkh_s, clk_hz), _clocks(part.t_sclkl_s, clk_hz))

        self._clk_hz = float(clk_hz)
        self._part = part
        self._h = h
        self._held = tuple(n for n in names if n in held)     # in channel order
        self._marker = marker
        n_csh = max(1, _clocks(part.t_csh_s, clk_hz))
        n_conv = max(_clocks(part.t_convert_s, clk_hz), _clocks(part.t_cyc_s, clk_hz))
        # Convert pulse: CS low for t_CSH clocks too (no separate minimum low time is used).
        self._n_csl = n_csh
        # Second falling edge: >= t_CONVERT and t_CYC after the first, CS high >= t_CSH.
        self._n_fall2 = max(n_conv, self._n_csl + n_csh)
        self._n_sclked = max(1, _clocks(part.t_sclked_s, clk_hz))
        shift = 2 * h * part.bits
        # Clocks from the second falling edge to the end of the read frame (CS rising edge).
        self._n_frame = self._n_sclked + shift
        # After CS rises: CS high >= t_CSH and the next falling edge >= t_CYC/t_CONVERT after
        # the read frame's falling edge.
        self._n_recover = max(n_csh, n_conv - self._n_frame)
        self._latency = 1 + self._n_fall2 + self._n_frame
        # Strobe in clock 0 → o.valid and CS high in clock `latency`; back in IDLE (a strobe is
        # served again) n_recover clocks later.
        self._min_period = self._latency + self._n_recover

        layout = data.StructLayout({name: signed(part.bits) for name in CHANNELS[:part.lines]})
        super().__init__({
            "sample": In(1),
            "cs_n": Out(1, init=1),
            "sclk": Out(1, init=1),
            "sdo": In(part.lines),
            "o": Out(stream.Signature(layout, always_ready=True)),
            "busy": Out(1),
            "overrun": Out(1),
        })

    clk_hz = property(lambda self: self._clk_hz)
    part = property(lambda self: self._part)
    half_period = property(lambda self: self._h)
    sclk_actual_hz = property(lambda self: self._clk_hz / (2 * self._h))
    latency = property(lambda self: self._latency)
    latency_s = property(lambda self: self._latency / self._clk_hz)
    min_period = property(lambda self: self._min_period)
    held = property(lambda self: self._held)
    marker = property(lambda self: self._marker)
    hold = property(lambda self: self._min_period
                    - 2 * self._h * (self._part.bits - (0 if self._marker else 1)))

    def elaborate(self, platform):
        m = Module()
        part = self._part
        h = self._h
        bits = part.bits
        names = CHANNELS[:part.lines]

        # The timer counts down from the longest value it is loaded with (one register bit less
        # than the longest interval needs where that is the conversion time less the CS pulse).
        longest = max(self._n_csl - 1, self._n_fall2 - self._n_csl - 1, self._n_sclked - 1,
                      h - 1, self._n_recover - 1)
        timer = Signal(range(longest + 1))
        shreg = [Signal(bits, name=f"sh_{n}") for n in names]
        if self._marker:
            # The first channel's register carries a marker bit, loaded at bit 0 with the
            # frame's first falling edge (the bits above it 0): it is at the top bit while the
            # frame's last bit is sampled, and that shift moves it out (no bit counter).
            last_bit = shreg[0][bits - 1]
        else:
            nbit = Signal(range(bits + 1))     # SDO bits sampled so far in this frame
            last_bit = nbit == bits - 1
        cs_n = Signal(init=1)
        sclk = Signal(init=1)
        valid = Signal()
        m.d.comb += [self.cs_n.eq(cs_n), self.sclk.eq(sclk), self.o.valid.eq(valid)]
        # A channel not held: its payload is its shift register, which holds the code after
        # the frame's last bit until the next frame's first bit (``hold``).
        m.d.comb += [self.o.payload[n].eq(sh) for n, sh in zip(names, shreg)
                     if n not in self._held]
        m.d.sync += [valid.eq(0), self.overrun.eq(0)]

        done = timer == 0
        with m.If(~done):
            m.d.sync += timer.eq(timer - 1)

        with m.FSM(init="IDLE") as fsm:
            with m.State("IDLE"):
                with m.If(self.sample):
                    m.d.sync += [cs_n.eq(0), timer.eq(self._n_csl - 1)]
                    m.next = "CONVERT_PULSE"

            with m.State("CONVERT_PULSE"):
                # CS low: the part samples its inputs and starts converting.
                with m.If(done):
                    m.d.sync += [cs_n.eq(1), timer.eq(self._n_fall2 - self._n_csl - 1)]
                    m.next = "CONVERT_WAIT"

            with m.State("CONVERT_WAIT"):
                with m.If(done):
                    m.d.sync += [cs_n.eq(0), timer.eq(self._n_sclked - 1)]
                    m.next = "LEAD"

            with m.State("LEAD"):
                with m.If(done):
                    m.d.sync += [sclk.eq(0), timer.eq(h - 1)]
                    m.d.sync += shreg[0].eq(1) if self._marker else nbit.eq(0)
                    m.next = "SHIFT"

            with m.State("SHIFT"):
                with m.If(done):
                    m.d.sync += timer.eq(h - 1)
                    with m.If(~sclk):
                        m.d.sync += sclk.eq(1)
                    with m.Else():
                        # One full SCLK period after the launching falling edge: sample SDOx.
                        if not self._marker:
                            m.d.sync += nbit.eq(nbit + 1)
                        for k, sh in enumerate(shreg):
                            m.d.sync += sh.eq((sh << 1) | self.sdo[k])
                        with m.If(last_bit):
                            m.d.sync += [cs_n.eq(1), valid.eq(1),
                                         timer.eq(self._n_recover - 1)]
                            for k, (n, sh) in enumerate(zip(names, shreg)):
                                if n in self._held:
                                    m.d.sync += self.o.payload[n].eq((sh << 1) | self.sdo[k])
                            m.next = "RECOVER"
                        with m.Else():
                            m.d.sync += sclk.eq(0)

            with m.State("RECOVER"):
                # CS high time and t_CYC after the read frame's (dummy) conversion start. The
                # timer was loaded with n_recover − 1, so IDLE is reached n_recover − 1 clocks
                # after CS rose and a strobe there makes CS fall n_recover clocks after.
                with m.If(done):
                    m.next = "IDLE"
        m.d.comb += self.busy.eq(~fsm.ongoing("IDLE"))
        with m.If(self.sample & ~fsm.ongoing("IDLE")):
            m.d.sync += self.overrun.eq(1)
        return m
