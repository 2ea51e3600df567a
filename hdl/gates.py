# Ref: SPEC.md §4 (complementary gate outputs, programmable dead time, global enable, PWM off at
# reset, gates off on any fault); issue 4 item 6
"""Complementary gate drive with dead time, enable and trip.

Each phase is a three-state machine on its two registered outputs: high on, low on, or both off.
The *wanted* state is high (``pwm & enable & ~trip``), low (``~pwm & enable & ~trip``) or off. A
change of it turns the conducting switch off at the next clock; a switch turns on only after both
have been off, and the wanted state has stayed the same, for ``max(dead_time, 1)`` clocks (every
change restarts that count). Hence every turn-on follows at least the dead time with both off, and
only a ``pwm`` level that has lasted at least the dead time ever turns a switch on: a pulse
shorter than the dead time is dropped cleanly (the opposite switch turns off, nothing turns on, and
it turns back on a dead time after the pulse) — no runt pulse, also when enabling mid-pulse.
"""

from amaranth.hdl import Assert, Cat, Const, Module, Mux, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.wiring import In, Out

from .fixed import check_bool

__all__ = ["Gates", "PHASES_LAYOUT", "dead_n", "dead_n_const"]

#: One bit per phase.
PHASES_LAYOUT = data.StructLayout({"a": 1, "b": 1, "c": 1})


def dead_n(dead_time):
    """``Gates(dead_n=True)``'s operand from the dead time (a ``Value``):
    ``~(max(dead_time, 1) − 1)`` in ``len(dead_time)`` bits, the inverted right side of the
    turn-on compare (``off + 1 ≥ max(dead_time, 1)``)."""
    return ~Mux(dead_time == 0, 0, dead_time - 1)


def dead_n_const(dead_time, dead_width=8):
    """:func:`dead_n` of an ``int`` dead time, ``dead_width`` bits (the register file's reset
    value of the operand, the golden models)."""
    return ~(max(dead_time, 1) - 1) & ((1 << dead_width) - 1)


class Gates(wiring.Component):
    """Three complementary gate pairs from three PWM levels.

    Parameters
    ----------
    dead_width : int
        Width of ``dead_time``, 1 … 16 bits.
    dead_n : bool
        ``True``: the member ``dead_n`` = :func:`dead_n` of the dead time, the turn-on compare's
        operand, instead of ``dead_time`` (the register file's flip-flops hold it on the iCE40,
        ``Top(gates_dead_n)``: no decrement and zero test here; the same outputs). Default
        ``False``.
    wrap : bool
        ``True``: the off counts modulo ``2**dead_width`` instead of saturating (never read
        past ``2**dead_width − 2``, docs/AREA.md §7.79; the iCE40's and the Spartan-7's form,
        ``Top(gates_wrap)``; the ECP5 keeps the saturating counts, §7.80). The same outputs.
        Default ``False``.
    prev_pwm : bool
        ``True``: "the wanted state unchanged" from the previous clock's ``pwm`` level (a
        flip-flop a phase) and ``run`` (one for the three phases) instead of the previous
        wanted states (two flip-flops a phase, each loaded from a LUT that also feeds the
        compare: the iCE40's form, ``Top(gates_prev_pwm)``, docs/AREA.md §7.86). The same
        outputs. Default ``False``.

    Members
    -------
    pwm : In(data.StructLayout({"a", "b", "c": 1}))
        Wanted level per phase (1: high-side switch on).
    dead_time : In(unsigned(dead_width))
        Dead time in clocks, read every clock; 0 acts as 1. (``dead_n``: ``dead_n``, that
        operand of it.)
    enable : In(1)
        Global gate enable; low forces all gates off.
    trip : In(1)
        From protection (level, latched there); high forces all gates off.
    high, low : Out(data.StructLayout({"a", "b", "c": 1}))
        Registered gate outputs, all 0 at reset.

    Invariants (``Assert`` in the design, checked in every simulation): never ``high`` and ``low``
    of one phase together; no gate on the clock after ``trip`` or ``~enable``.

    Attributes
    ----------
    trip_latency : int
        Clocks from ``trip`` (or ``~enable``) high to all gates low: 1.
    latency : int
        Clocks from a ``pwm`` edge to the conducting switch turning off: 1. The other switch turns
        on ``max(dead_time, 1)`` clocks after that (``1 + max(dead_time, 1)`` after the edge).

    dead_input : str
        The dead time's member: ``"dead_n"`` or ``"dead_time"``.

    Raises
    ------
    TypeError
        ``dead_width`` of the wrong type or outside its range; ``dead_n``, ``wrap`` or
        ``prev_pwm`` not a bool.
    """

    trip_latency = 1
    latency = 1

    def __init__(self, *, dead_width=8, dead_n=False, wrap=False, prev_pwm=False):
        if (not isinstance(dead_width, int) or isinstance(dead_width, bool)
                or not 1 <= dead_width <= 16):
            raise TypeError(f"Gates dead_width must be an integer from 1 to 16, not {dead_width!r}")
        check_bool("Gates", "dead_n", dead_n)
        check_bool("Gates", "wrap", wrap)
        check_bool("Gates", "prev_pwm", prev_pwm)
        self._prev_pwm = prev_pwm
        self._dead_width = dead_width
        self._dead_n = dead_n
        self._wrap = wrap
        super().__init__({
            "pwm": In(PHASES_LAYOUT),
            ("dead_n" if dead_n else "dead_time"): In(unsigned(dead_width)),
            "enable": In(1),
            "trip": In(1),
            "high": Out(PHASES_LAYOUT),
            "low": Out(PHASES_LAYOUT),
        })

    dead_width = property(lambda self: self._dead_width)
    dead_input = property(lambda self: "dead_n" if self._dead_n else "dead_time")
    wrap = property(lambda self: self._wrap)
    prev_pwm = property(lambda self: self._prev_pwm)

    def elaborate(self, platform):
        m = Module()
        dw = self._dead_width
        run = self.enable & ~self.trip
        # `off + 1 ≥ max(dead_time, 1)` as `off ≥ dead_time − (dead_time ≠ 0)`: the right side
        # once for the three phases, inverted (d_n), so each phase's compare is one carry chain
        # `off + d_n + 1` with no adder or inverter in front.
        # (``dead_n``: the port is that operand, from the register file's flip-flops.)
        d_n = Signal(unsigned(dw))
        m.d.comb += d_n.eq(self.dead_n if self._dead_n else dead_n(self.dead_time))
        stopped = Signal()                      # trip or ~enable on the previous clock
        m.d.sync += stopped.eq(~run)

        if self._prev_pwm:
            was_run = Signal()                  # run on the previous clock (0 at reset)
            m.d.sync += was_run.eq(run)
        for p in "abc":
            high, low = self.high[p], self.low[p]
            # Clocks before this one with both switches off and the wanted state unchanged:
            # saturating at 2**dw − 1, or with `wrap` modulo 2**dw. It needs no saturation:
            # with the wanted state steady and both off the count starts at 0 (a change of the
            # wanted state, or of `run`, which changes it, resets it) and the wanted switch
            # turns on once `off + 1 ≥ max(dead_time, 1)`, so it never passes 2**dw − 2 while
            # `run`; without `run` it is not read (and the clock `run` rises is not steady).
            # (iCE40: no `off == 2**dw − 1` test in front of each counter, docs/AREA.md §7.79.)
            off = Signal(unsigned(dw), name=f"off_{p}")
            want_h = run & self.pwm[p]
            want_l = run & ~self.pwm[p]
            if self._prev_pwm:
                # The wanted state is (0, 0) without `run`, else (pwm, ~pwm): unchanged iff
                # `run` was low too, or `run` was high and `pwm` is unchanged.
                prev_pwm = Signal(name=f"pwm_prev_{p}")
                m.d.sync += prev_pwm.eq(self.pwm[p])
                steady = Mux(run, was_run & (self.pwm[p] == prev_pwm), ~was_run)
            else:
                prev_h = Signal(name=f"want_h_{p}")
                prev_l = Signal(name=f"want_l_{p}")
                m.d.sync += [prev_h.eq(want_h), prev_l.eq(want_l)]
                steady = (want_h == prev_h) & (want_l == prev_l)
            both_off = ~high & ~low
            with m.If(both_off & steady):
                m.d.sync += off.eq(off + 1 if self._wrap else
                                   Mux(off == (1 << dw) - 1, off, off + 1))
            with m.Else():
                m.d.sync += off.eq(0)

            with m.If(~run):
                m.d.sync += [high.eq(0), low.eq(0)]
            with m.Elif(high):
                m.d.sync += high.eq(want_h)
            with m.Elif(low):
                m.d.sync += low.eq(want_l)
            long_enough = (Cat(Const(1, 1), off) + Cat(Const(1, 1), d_n))[dw + 1]
            with m.Elif(steady & long_enough):
                m.d.sync += [high.eq(want_h), low.eq(want_l)]

            m.d.comb += [
                Assert(~(high & low), f"gates: phase {p} high and low on together"),
                Assert(~stopped | both_off, f"gates: phase {p} on after trip or disable"),
            ]
        return m
