# Ref: hdl/gates.py (turn-on delayed by max(dead_time, 1) clocks after the turn-off); sim/pmsm.py
#      (freewheeling diodes); issue 6 (dead-time compensation); docs/ARCHITECTURE.md
#      "Dead-time compensation"
"""Dead-time compensation: each phase's compare gets a correction of the volt-seconds the dead
time costs, a trapezoid of that phase's current.

What a dead time costs. :class:`~.gates.Gates` turns the conducting switch off one clock after a
``pwm`` edge and the other one on ``d = max(dead_time, 1)`` clocks later. Meanwhile the leg's
current ``i_x`` flows through a diode: for ``i_x > 0`` (out of the leg into the motor) the low
one, so the rising edge of the terminal is ``d`` clocks late and the falling edge on time: the
leg is high ``d`` clocks less per period than ``pwm``; for ``i_x < 0`` the high diode, ``d``
clocks more. The mean terminal-voltage error is ``−sign(i_x)·d/T·U_dc`` (3.1 V at 1 µs, 10 kHz,
310 V). The correction adds ``sign(i_x)·d`` clocks of high time, as compare counts: ``d`` in
asymmetric mode (high time = compare), ``d/2`` in symmetric mode (high time = 2·compare).

Near a zero crossing the current ripple crosses zero inside the dead time and the loss falls off
smoothly (a bare sign would chatter): the correction is a trapezoid, linear in ``i_x`` up to the
band ``C·2**k`` current LSBs and ``±C`` beyond, computed once per sample from the scaled phase
currents with one 1-bit shifter per phase (no multiplier)::

    k      = band + sym                                  shift (sym = 1 in symmetric mode)
    L      = sym ? (C + 1) >> 1 : C                      limit, compare counts
    u_x    = i_x XOR sign(i_x)                           |i_x|, or |i_x| − 1 for i_x < 0
    m_x    = min(u_x >> k, L)
    comp_x = i_x < 0 ? −m_x : m_x                        signed(clocks_width + 1)
    o_x    = clamp(duty_x + comp_x, 0, 2**count_width − 1)   never wraps

(``C`` = ``clocks``, ``band`` = ``shift``.) It is odd-symmetric about −1/2 LSB (``i`` and
``−1 − i`` get opposite corrections) and 0 for ``−2**k ≤ i_x < 2**k``; the one's-complement
magnitude needs no adder and the clamp compares only ``clocks_width`` bits. In symmetric mode
slope and limit are both halved, so the trapezoid is the same in clocks of high time in both
modes (an odd ``C`` rounds up).

The full scale. A corrected duty may exceed the timer's full scale (``duty_x`` up to it plus
``comp_x``); it is not clamped to it here: :class:`~.svpwm.PWMTimer` treats every compare from
its full scale up as the full scale (always high), in the mode it runs the duties in. So the
levels are those of ``clamp(duty_x + comp_x, 0, full_scale)`` of that mode, without an 18-bit
compare and multiplexer per phase here (iCE40: −80 logic cells). (Until session 11 the block
clamped to the ``scale`` of the mode set when the duties were written; the two differ only if
that mode is not the one the timer runs them in, a mode change racing a duty write, when the
duties were computed for the other scale anyway; docs/AREA.md.)

Timing. ``comp`` is computed from each ``phase`` transfer: the three magnitudes shift together,
then one clamp and, a clock later, one negation, shared, serve phase a, b, c in consecutive
clocks, so ``comp.a`` holds the new value ``3 + band + sym`` clocks after the transfer,
``comp.b`` one clock and ``comp.c`` two clocks later (at most
:attr:`DeadTimeComp.comp_latency`), and holds; a new transfer cancels the phases not yet loaded
(also one whose clamp is done: a ``comp`` loads only in a clock without a transfer); the duties pass from ``i`` to ``o``
combinationally (:attr:`DeadTimeComp.latency` = 0): the timer's shadow register is the pipeline
register, so the block adds no current-loop latency. In the top the phase currents arrive
``Clarke.latency`` clocks after the sample and the duties ``CurrentLoop.latency`` clocks after it,
so each period's duties are corrected with its own sample's currents.
"""


from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import check_bool, check_param

__all__ = ["DeadTimeComp"]


class DeadTimeComp(wiring.Component):
    """Dead-time compensation of three duties by a trapezoid of the phase currents (module
    docstring).

    Parameters
    ----------
    width : int
        Width ``w`` of the phase currents, Q1.(w−1) of I_FS, 8 … 23 (as the current loop).
    count_width : int
        Width of the duties (compares), 4 … 24.
    clocks_width : int
        Width of ``clocks``, 1 … 16.
    shift_width : int
        Width of ``shift``, 1 … 5.
    clamp : bool
        ``True`` (default): ``o`` is clamped to ``[0, 2**count_width − 1]``. ``False``: ``o`` is
        the sum ``i + comp`` unclamped, ``signed(count_width + 2)``, for
        :class:`~.svpwm.PWMTimer` ``signed_duty=True``, which clamps it in its shadow and active
        registers' LUTs (the iCE40's form, ``Top(timer_clamp)``: the same levels; docs/AREA.md
        §7.72).
    one_count : bool
        ``True``: the shift clocks and the three phases' clamps sequenced by one count (the
        same ``comp`` in the same clocks; the iCE40's and the Spartan-7's form,
        ``Top(dtc_one_count)``: −5 iCE40 cells, −19 LUT6 on the Arty S7; the ECP5 keeps the
        netlist its 100 MHz build was made with, docs/AREA.md §7.79). Default ``False``.

    Members
    -------
    phase : In(stream.Signature(data.StructLayout({"a", "b", "c": signed(w)}), always_ready=True))
        Scaled phase currents (``CurrentLoop.phase``), positive out of the leg into the motor;
        each transfer starts a computation of ``comp`` (restarting one in progress).
    i : In(stream.Signature(data.StructLayout({"a", "b", "c": unsigned(count_width)})))
        Duties in compare counts (``CurrentLoop.o``).
    o : Out(stream.Signature(data.StructLayout({"a", "b", "c": unsigned(count_width)})))
        Corrected duties (for ``PWMTimer.duty``): ``clamp(i + comp, 0, 2**count_width − 1)``
        per phase (the timer clamps to its full scale, module docstring),
        combinational, as are ``o.valid = i.valid`` and ``i.ready = o.ready``. With
        ``clamp=False``: ``i + comp``, ``signed(count_width + 2)`` fields.
    symmetric : In(1)
        1: centre-aligned PWM (high time 2·compare); latched with each ``phase`` transfer.
    clocks : In(unsigned(clocks_width))
        ``C``: the correction at and beyond the band, clocks of high time per period (the
        effective dead time ``max(dead_time, 1)``); 0 turns the compensation off. Latched with
        each ``phase`` transfer.
    shift : In(unsigned(shift_width))
        ``band``: the trapezoid's slope is ``2**-band`` clocks per current LSB (it saturates at
        ``C·2**band`` LSBs). Latched with each ``phase`` transfer.
    comp : Out(data.StructLayout({"a", "b", "c": signed(clocks_width + 1)}))
        The corrections in force, compare counts; 0 at reset.

    Attributes
    ----------
    latency : int
        Clocks from ``i`` to ``o``: 0.
    comp_latency : int
        Most clocks from a ``phase`` transfer (clock ``t``) to all of its ``comp`` (from clock
        ``t + comp_latency``): ``5 + 2**shift_width`` (phase a ``3 + band + sym`` for the
        values latched, b one clock later, c two).

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its range (``clamp`` not a bool).
    """

    latency = 0

    def __init__(self, *, width=16, count_width=16, clocks_width=8, shift_width=4, clamp=True,
                 one_count=False):
        check_bool("DeadTimeComp", "clamp", clamp)
        check_bool("DeadTimeComp", "one_count", one_count)
        for name, value, lo, hi in (("width", width, 8, 23), ("count_width", count_width, 4, 24),
                                    ("clocks_width", clocks_width, 1, 16),
                                    ("shift_width", shift_width, 1, 5)):
            check_param("DeadTimeComp", name, value, lo, hi)
        self._width = width
        self._count_width = count_width
        self._clocks_width = clocks_width
        self._shift_width = shift_width
        self._clamp = clamp
        self._one_count = one_count
        duties = data.StructLayout({p: unsigned(count_width) for p in "abc"})
        sums = data.StructLayout({p: signed(count_width + 2) for p in "abc"})
        super().__init__({
            "phase": In(stream.Signature(data.StructLayout({p: signed(width) for p in "abc"}),
                                         always_ready=True)),
            "i": In(stream.Signature(duties)),
            "o": Out(stream.Signature(duties if clamp else sums)),
            "symmetric": In(1),
            "clocks": In(unsigned(clocks_width)),
            "shift": In(unsigned(shift_width)),
            "comp": Out(data.StructLayout({p: signed(clocks_width + 1) for p in "abc"})),
        })

    width = property(lambda self: self._width)
    count_width = property(lambda self: self._count_width)
    clocks_width = property(lambda self: self._clocks_width)
    shift_width = property(lambda self: self._shift_width)
    clamp = property(lambda self: self._clamp)
    one_count = property(lambda self: self._one_count)

    @property
    def comp_latency(self):
        return 5 + (1 << self._shift_width)

    def elaborate(self, platform):
        m = Module()
        w, cw = self._width, self._clocks_width

        # Sequential trapezoid: load the currents' magnitudes, shift right one bit per clock,
        # then clamp and restore the sign of one phase per clock (a, b, c: `turn`) on one
        # shared clamp and negation.
        if not self._one_count:
            steps = Signal(range((1 << self._shift_width) + 1))
            pending = Signal()
            turn = Signal(range(3))
            # Loaded at every phase.valid before any fire reads it (pending, reset 0): its
            # reset value is never used, so reset_less with init all ones (the iCE40 stores it
            # inverted, which gives the compare u > limit its ~limit without an inverter LUT
            # per bit).
            limit = Signal(unsigned(cw), init=(1 << cw) - 1, reset_less=True)
            fire = Signal()                             # this clock loads comp[turn]
            m.d.comb += fire.eq(~self.phase.valid & (steps == 0) & pending)
            with m.If(self.phase.valid):
                m.d.sync += [
                    steps.eq(self.shift + self.symmetric),
                    pending.eq(1),
                    turn.eq(0),
                    limit.eq(Mux(self.symmetric, (self.clocks + 1) >> 1, self.clocks)),
                ]
            with m.Elif(steps != 0):
                m.d.sync += steps.eq(steps - 1)
            with m.Elif(pending):
                m.d.sync += [turn.eq(turn + 1), pending.eq(turn != 2)]
        else:
            # One count for the whole sequence: `shift + sym` shift clocks then the three
            # phases' clamps, `count` = shift clocks left + 3 while shifting, then 3, 2, 1
            # (phase `turn` = 3 − count = ~count[:2]: a, b, c), 0 idle; no separate step
            # count, turn and pending flag (docs/AREA.md §7.79).
            count = Signal(range((1 << self._shift_width) + 4))
            turn = Signal(range(3))
            limit = Signal(unsigned(cw), init=(1 << cw) - 1, reset_less=True)   # (as above)
            fire = Signal()
            m.d.comb += [turn.eq(~count[:2]),
                         fire.eq(~self.phase.valid & ~count[2:].any() & count[:2].any())]
            with m.If(self.phase.valid):
                m.d.sync += [
                    # shift + sym + 3: the constant 3 or 4 as the operand (Cat(~sym, ~sym, sym))
                    count.eq(self.shift + Cat(~self.symmetric, ~self.symmetric, self.symmetric)),
                    limit.eq(Mux(self.symmetric, (self.clocks + 1) >> 1, self.clocks)),
                ]
            with m.Elif(count != 0):
                m.d.sync += count.eq(count - 1)

        neg, low, high = {}, {}, {}
        for p in "abc":
            # One's-complement magnitude u = i ^ sign (|i| for i ≥ 0, |i| − 1 below): loaded with
            # the XOR, one LUT per bit with the shift; the clamp needs no adder and compares only
            # the low clocks_width bits (and whether any higher one is set).
            i = self.phase.payload[p]
            neg[p] = Signal(name=f"neg_{p}")
            mag = Signal(unsigned(w - 1), name=f"mag_{p}")
            with m.If(self.phase.valid):
                m.d.sync += [neg[p].eq(i[-1]), mag.eq(i[:-1] ^ i[-1].replicate(w - 1))]
            with m.Elif((count[2:].any()) if self._one_count else (steps != 0)):
                m.d.sync += mag.eq(mag >> 1)
            low[p] = mag[:cw]
            high[p] = mag[cw:].any() if w - 1 > cw else Const(0)

        def pick(x):
            return Mux(turn[1], x["c"], Mux(turn[0], x["b"], x["a"]))

        # The turn's phase: m = min(u >> k, L), comp = ±m (s the sign), on one clamp and one
        # negation shared by the three phases. (A stored ~L and ±m as (m XOR s) + s take fewer
        # LUT4s but more iCE40 logic cells after packing: 394–416 against 350 unregistered.)
        u = Signal(unsigned(min(cw, w - 1)))
        s = Signal()
        m.d.comb += [u.eq(pick(low)), s.eq(pick(neg))]
        over = pick(high) | (u > limit)
        # Registered between the clamp and the negation (ECP5: the pick, the compare and the
        # negation in one clock made the block's critical path).
        # Read only when fire_q (reset 0) and loaded every clock: reset value unused, so
        # reset_less with init all ones (iCE40: −mc's ~mc from the flip-flop, no inverter).
        mc = Signal(unsigned(cw), init=(1 << cw) - 1, reset_less=True)
        s_q = Signal()
        fire_q = Signal()
        turn_q = Signal(range(3))
        m.d.sync += [mc.eq(Mux(over, limit, u)), s_q.eq(s), fire_q.eq(fire), turn_q.eq(turn)]
        value = Signal(signed(cw + 1))
        m.d.comb += value.eq(Mux(s_q, -mc, mc))
        for k, p in enumerate("abc"):
            with m.If(fire_q & ~self.phase.valid & (turn_q == k)):
                m.d.sync += self.comp[p].eq(value)

        cw_duty = self._count_width
        for p in "abc":
            # Duties: i + comp in signed(count_width + 2), clamped to [0, 2**count_width − 1]
            # (not to the full scale: the timer's, module docstring). The upper clamp looks at
            # the bits above count_width (a LUT, no carry chain).
            total = Signal(signed(self._count_width + 2), name=f"total_{p}")
            m.d.comb += total.eq(self.i.payload[p] + self.comp[p])
            if not self._clamp:
                m.d.comb += self.o.payload[p].eq(total)     # the timer clamps (``clamp``)
                continue
            m.d.comb += self.o.payload[p].eq(Mux(total[-1], 0,
                                                 Mux(total[cw_duty:].any(), (1 << cw_duty) - 1,
                                                     total[:cw_duty])))
        m.d.comb += [
            self.o.valid.eq(self.i.valid),
            self.i.ready.eq(self.o.ready),
        ]
        return m
