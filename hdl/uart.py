# Ref: docs/PROTOCOL.md §Physical layer (UART 8N1, LSB first)
"""UART receiver and transmitter, 8 data bits, no parity, 1 stop bit, any baud rate up to clk/8.

Both time their bits with a phase accumulator of :data:`PHASE_BITS` bits that adds
``round(baud · 2**PHASE_BITS / clk_hz)`` every clock: the average bit time is exact to
``2**-PHASE_BITS`` relative (3 Mbaud at 50 MHz = 16.67 clocks per bit alternates 16 and 17 clocks),
so neither end accumulates a rate error over a byte.
"""

from amaranth.hdl import Assert, Cat, Const, Module, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

from .fixed import check_bool

__all__ = ["PHASE_BITS", "uart_params", "UartRx", "UartTx"]

#: Width of the baud phase accumulators.
PHASE_BITS = 24


def uart_params(name, clk_hz, baud):
    """Validate a UART's ``clk_hz`` and ``baud`` and return the phase increment.

    Raises
    ------
    TypeError
        If ``clk_hz`` or ``baud`` is not a positive number.
    ValueError
        If ``baud`` is above ``clk_hz / 8`` (fewer than 8 clocks per bit).
    """
    for what, value in (("clk_hz", clk_hz), ("baud", baud)):
        if (not isinstance(value, (int, float)) or isinstance(value, bool)
                or not value > 0 or value != value):
            raise TypeError(f"{name} {what} must be a positive number, not {value!r}")
    if baud * 8 > clk_hz:
        raise ValueError(f"{name} baud must be at most clk_hz / 8 = {clk_hz / 8:g}, not {baud!r}")
    return round(baud * 2 ** PHASE_BITS / clk_hz)


class _UartBase(wiring.Component):
    """Baud-rate parameters shared by :class:`UartTx` and :class:`UartRx` (validated by
    :func:`uart_params`, with the subclass's name in the messages)."""

    def __init__(self, *, clk_hz=50e6, baud=115200):
        self._increment = uart_params(type(self).__name__, clk_hz, baud)
        self._clk_hz, self._baud = clk_hz, baud
        super().__init__()

    clk_hz = property(lambda self: self._clk_hz)
    baud = property(lambda self: self._baud)
    increment = property(lambda self: self._increment)


class UartTx(_UartBase):
    """UART transmitter (8N1, LSB first, line idle high).

    Parameters
    ----------
    clk_hz : float
        Clock frequency, Hz.
    baud : float
        Bit rate, bit/s; at most ``clk_hz / 8``.
    compact : bool
        ``True``: no bit count and no ``busy`` flip-flop; the shift register holds the data
        bits, the stop bit and a marker bit (all ones above the data), shifted out with zeros
        behind them, so the byte is busy while the register is not zero and in its last bit
        time while only the marker is left (the iCE40's form, with the host link's
        ``compact``: fewer logic cells, docs/AREA.md §7.86; the ECP5 keeps the registered
        last-bit flag on its 100 MHz path). The same ``tx``, ``busy`` and ``i.ready``. Default
        ``False``.

    Members
    -------
    i : In(stream.Signature(8))
        Bytes to send. ``i.ready`` is high while the transmitter is idle and in the last clock of
        a stop bit, so back-to-back bytes leave with exactly one stop bit between them.
    tx : Out(1, init=1)
        Serial output (registered).
    busy : Out(1)
        A byte is being sent.

    Attributes
    ----------
    increment : int
        Phase increment per clock; the true baud rate is ``increment · clk_hz / 2**PHASE_BITS``.
    latency : int
        1: with a transfer on ``i`` in clock ``t`` the start bit is on ``tx`` from clock ``t + 1``.

    Raises
    ------
    TypeError, ValueError
        See :func:`uart_params`; ``compact`` not a bool (``TypeError``).
    """

    i: In(stream.Signature(8))
    tx: Out(1, init=1)
    busy: Out(1)

    latency = 1

    def __init__(self, *, clk_hz=50e6, baud=115200, compact=False):
        self._compact = check_bool("UartTx", "compact", compact)
        super().__init__(clk_hz=clk_hz, baud=baud)

    compact = property(lambda self: self._compact)

    def elaborate(self, platform):
        if self._compact:
            return self._elaborate_compact()
        m = Module()
        # The phase is loaded when a byte starts from idle and advances only while busy (its
        # carry is used only then), and it has no reset: its flip-flops' synchronous
        # set/reset pins then take the load, no multiplexer in front (iCE40: 22 LUT4 fewer).
        phase = Signal(PHASE_BITS + 1, reset_less=True)     # top bit: carry = a bit time passed
        shreg = Signal(9)                       # data bits then the stop bit, shifted out LSB first
        left = Signal(range(11))                # bits still to send after the current one
        # ``left == 0`` as a flip-flop loaded with ``left`` (ECP5: the compare sat between
        # ``left`` and ``i.ready``, on the host link's path to its frame buffer's read address,
        # docs/AREA.md, "Session 11"); equal to the compare whenever it is used (busy).
        left_zero = Signal(init=1)

        carry = phase[-1]
        with m.If(self.i.valid & ~self.busy):
            m.d.sync += phase.eq(self._increment)               # a full bit from now
        with m.Elif(self.busy):
            m.d.sync += phase.eq(phase[:-1] + self._increment)
        last = self.busy & carry & left_zero
        m.d.comb += self.i.ready.eq(~self.busy | last)
        m.d.comb += Assert(~self.busy | (left_zero == (left == 0)), "UartTx: left_zero")

        with m.If(self.busy & carry):
            m.d.sync += [
                self.tx.eq(shreg[0]),
                shreg.eq(shreg >> 1),
                left.eq(left - 1),
                left_zero.eq(left == 1),
            ]
            with m.If(left_zero):
                m.d.sync += [self.busy.eq(0), self.tx.eq(1)]
        with m.If(self.i.valid & self.i.ready):
            m.d.sync += [
                self.tx.eq(0),                                  # start bit
                shreg.eq(Cat(self.i.payload, Const(1, 1))),
                left.eq(9),
                left_zero.eq(0),
                self.busy.eq(1),
            ]
        return m

    def _elaborate_compact(self):
        m = Module()
        phase = Signal(PHASE_BITS + 1, reset_less=True)     # as in the other form
        # Data bits, the stop bit and a marker bit, shifted out LSB first with zeros in behind:
        # after k of the byte's bit times it holds its bits k … 9, so it is zero from the end
        # of the stop bit (k = 10) and exactly the marker in the stop bit (k = 9).
        shreg = Signal(10)
        above = Signal()                        # a bit above bit 0 is set
        m.d.comb += [above.eq(shreg[1:].any()), self.busy.eq(shreg[0] | above)]
        last_bit = shreg[0] & ~above            # only the marker left: the stop bit's time

        carry = phase[-1]
        with m.If(self.i.valid & ~self.busy):
            m.d.sync += phase.eq(self._increment)               # a full bit from now
        with m.Elif(self.busy):
            m.d.sync += phase.eq(phase[:-1] + self._increment)
        last = carry & last_bit
        m.d.comb += self.i.ready.eq(~self.busy | last)

        with m.If(self.busy & carry):
            m.d.sync += [self.tx.eq(shreg[0]), shreg.eq(shreg >> 1)]     # (the marker: 1)
        with m.If(self.i.valid & self.i.ready):
            m.d.sync += [
                self.tx.eq(0),                                  # start bit
                shreg.eq(Cat(self.i.payload, Const(0b11, 2))),
            ]
        return m


class UartRx(_UartBase):
    """UART receiver (8N1, LSB first) with a 2-flop synchroniser and 3-sample majority.

    The synchronised line passes a majority-of-3 filter (glitches of one clock vanish). A falling
    edge starts the bit timer at half a bit; each bit is sampled where the timer carries, i.e. in
    the middle of the bit. A start bit found high in its middle is a glitch and is ignored. The
    byte is delivered in the middle of the stop bit, and the receiver looks for the next start
    edge from there (a sender up to ~5 % fast is followed). A stop bit found low is a framing
    error: the byte is discarded, ``error`` pulses and the receiver waits for the line to be high
    before it looks for a start bit again (a break does not produce a flood of bytes).

    Tolerance: the sample of the stop bit lies ``9.5`` bit times after the start edge, within
    ±1 clock (edge detection and phase quantisation, centred); the sender's own bit-time
    quantisation adds half a clock. With ``c = clk_hz / baud`` clocks per bit the sender's rate
    may differ by about ``±(0.5 - 1.5/c) / 9.5``: ±4.3 % at 3 Mbaud and 50 MHz (c = 16.7),
    ±3.8 % at 3 Mbaud and 33.333 MHz (c = 11.1), ±3.3 % at c = 8, ±5.2 % at 115 200 baud.
    ``tests/test_uart.py`` checks ±3 % at each of these.

    Parameters
    ----------
    clk_hz : float
        Clock frequency, Hz.
    baud : float
        Bit rate, bit/s; at most ``clk_hz / 8``.
    compact : bool
        ``True``: no BREAK state: after a framing error the receiver returns to IDLE at
        once, which starts a byte only at a falling edge of the line, i.e. not before the line
        has been high, as BREAK waits for (the iCE40's form, with the host link's
        ``compact``, docs/AREA.md §7.86). The same outputs. Default ``False``.

    Members
    -------
    rx : In(1, init=1)
        Serial input (asynchronous; synchronised inside).
    o : Out(stream.Signature(8))
        Received bytes. The receiver cannot stall: ``o.valid`` holds the byte until ``o.ready``
        or until the middle of the next start bit, where the next byte takes its place in the
        shift register (``o.payload`` *is* the shift register: no copy of it); a byte withdrawn
        so is lost, and the next byte that completes pulses ``overrun``. The payload never
        changes while ``o.valid`` is high.
    error : Out(1)
        One-clock pulse: framing error (stop bit low); the byte is dropped.
    overrun : Out(1)
        One-clock pulse with the ``o.valid`` of a byte completed after an earlier byte was lost
        because ``o`` was not taken in time (before the later byte's start bit).

    Attributes
    ----------
    latency_bits : float
        9.5: a byte is delivered 9.5 bit times (plus 4 clocks: synchroniser, filter, register)
        after the falling edge of its start bit.

    Raises
    ------
    TypeError, ValueError
        See :func:`uart_params`; ``compact`` not a bool (``TypeError``).
    """

    rx: In(1, init=1)
    o: Out(stream.Signature(8))
    error: Out(1)
    overrun: Out(1)

    latency_bits = 9.5

    def __init__(self, *, clk_hz=50e6, baud=115200, compact=False):
        self._compact = check_bool("UartRx", "compact", compact)
        super().__init__(clk_hz=clk_hz, baud=baud)

    compact = property(lambda self: self._compact)

    def elaborate(self, platform):
        m = Module()
        synced = Signal(init=1)
        m.submodules.sync = FFSynchronizer(self.rx, synced, init=1)
        taps = Signal(3, init=0b111)
        line = Signal(init=1)                   # majority of the last three synchronised samples
        m.d.sync += [
            taps.eq(Cat(synced, taps[:2])),
            line.eq((taps[0] & taps[1]) | (taps[1] & taps[2]) | (taps[0] & taps[2])),
        ]
        line_prev = Signal(init=1)
        m.d.sync += line_prev.eq(line)

        # No reset: IDLE loads the phase before any state uses it, and the set/reset pins of its
        # flip-flops take that load (iCE40: 23 LUT4 fewer than with the domain's reset on them).
        phase = Signal(PHASE_BITS + 1, reset_less=True)
        carry = phase[-1]
        # The data bits shift in at the top behind a marker bit loaded at the start bit: the
        # marker at bit 1 is the last data bit's clock (the bits below the marker are 0), at
        # bit 0 the byte is complete in bits 1 … 8. No bit counter; the payload is these bits.
        shreg = Signal(9)
        lost = Signal()                         # a held byte was withdrawn for this one
        m.d.comb += self.o.payload.eq(shreg[1:])

        m.d.sync += [self.error.eq(0), self.overrun.eq(0)]
        with m.If(self.o.ready):
            m.d.sync += self.o.valid.eq(0)

        with m.FSM():
            with m.State("IDLE"):
                with m.If(line_prev & ~line):
                    # Half a bit to the middle, less the clock by which the edge and the
                    # sampling are late on average: samples land within ±1 clock of mid-bit.
                    m.d.sync += phase.eq((1 << (PHASE_BITS - 1)) + self._increment)
                    m.next = "START"
            with m.State("START"):
                m.d.sync += phase.eq(phase[:-1] + self._increment)
                with m.If(carry):
                    m.next = "IDLE"
                    with m.If(~line):
                        m.d.sync += shreg.eq(1 << 8)
                        with m.If(self.o.valid & ~self.o.ready):    # the held byte goes
                            m.d.sync += [self.o.valid.eq(0), lost.eq(1)]
                        m.next = "DATA"
            with m.State("DATA"):
                m.d.sync += phase.eq(phase[:-1] + self._increment)
                with m.If(carry):
                    m.d.sync += shreg.eq(Cat(shreg[1:], line))
                    with m.If(shreg[1]):                # the marker reaches bit 0
                        m.next = "STOP"
            with m.State("STOP"):
                m.d.sync += phase.eq(phase[:-1] + self._increment)
                with m.If(carry):
                    with m.If(line):
                        m.d.sync += [self.o.valid.eq(1), self.overrun.eq(lost), lost.eq(0)]
                        m.next = "IDLE"
                    with m.Else():
                        m.d.sync += self.error.eq(1)
                        # (compact: IDLE at once; it starts only at a falling edge, so not
                        # before the line has been high: the same as BREAK's wait)
                        m.next = "IDLE" if self._compact else "BREAK"
            with m.State("BREAK"):
                with m.If(line):
                    m.next = "IDLE"
        return m
