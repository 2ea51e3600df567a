# Ref: paper eq. (7)–(9) (speed PI), SPEC.md §2, §2.5, §4 (operating modes); issue 6 targets
#      (step 0 → 1667 r/min within 1.2·t_min, < 0.5 % overshoot; ramp 0.45 r/min per sample)
"""Speed loop and operating modes: what drives the current loop.

:class:`SpeedLoop` turns the M/T speed (Q1.(speed_width−1) of the full-scale speed N_FS) and the
speed reference into the i_q reference (Q1.15 of I_FS) through a reference profile generator and a
Tustin PI (:class:`~foc_servo.hdl.pi.PI`, paper eq. (7)–(9)) of ``width`` bits; the speed error
needs far more than 16 bits (0.01 % of 1667 r/min is 0.17 r/min; one LSB of Q1.23 at
N_FS = 12 000 r/min is 0.0014 r/min).

**Reference profile.** Per accepted run ``n`` (``S = speed_slew``, ``F = iq_ff``)::

    R[n]  = clamp(speed_ref, sat(R[n−1] − S), sat(R[n−1] + S))     ref_int, Q1.(speed_width−1)
          = R[n−1] + clamp(speed_ref − R[n−1], −S, +S)             (S = 0: R[n] = speed_ref)
    ff[n] = clamp(±F, lim_lo, lim_hi) if speed_ref ≷ R[n], else 0         Q1.15 of I_FS
    ref   = to_pi(R[n])                                          ref_delay = d + f/8 with d = 0
    ref   = a + round_shift(f·(b − a), 3),  a = to_pi(R[n−d]), b = to_pi(R[n−d−1])      (d ≥ 1)
    mv    = S ≠ 0 and (R[n−1] ≠ speed_ref or (d ≥ 1 and ref ≠ to_pi(R[n−1])))   ref moves
    kx    = 0 this run if int_hold and mv                                   (integrator held)
    to_pi(x) = saturate(round_shift(x, speed_width − width), signed(width))    Q1.(width−1)

While ``clear`` is high (not in SPEED mode) ``R`` and its history track the measured speed if
``S ≠ 0`` (a bumpless start from a spinning motor), else ``speed_ref``. ``R[n]`` lies between
``R[n−1]`` and ``speed_ref``, so it never leaves signed(speed_width); the interpolated ``ref``
lies between ``a`` and ``b`` (``|round(f·Δ/8)| ≤ |Δ|`` for ``f ≤ 7``). ``ref_delay`` makes the
PI compare the speed with the reference as the plant can follow it (the delay of the closed
current loop and of the M/T average: about 2.5 runs at 10 kHz for a small current, 3.5 … 5 for a
full-current step, whose rise is voltage-limited),
while ``ff`` acts at once; ``int_hold`` keeps the integrator out of the acceleration, which ``ff``
supplies, until the *delayed* reference has arrived (``mv``: the PI's reference still moves), so
the lag of the plant behind the profile is never integrated. With ``ref_delay = 0`` and
``int_hold = 0`` the PI sees ``R[n]``; with ``S = 0`` and ``F = 0`` too, the loop has no profile
(``mv`` is then never set: no hold).

Timing: a run compares ``speed_ref`` with bounds ``R ± S`` registered in the clock before from
that clock's ``speed_slew``, and for ``d ≥ 1`` takes the interpolation registered in the clock
before from that clock's ``ref_delay``; ``to_pi`` of the bounds, of ``speed_ref`` and of the
speed are computed beside the comparisons, so a run only selects, and the PI's two operands
are registered in the run's clock and taken by the PI in the next (100 MHz on an ECP5: latency
8, interval 7). ``ff``, the hold and the shifted PI limits are registers loaded by the run. In
the top the registers change at the loop boundary, tens of clocks before a run.

**PI and feed-forward**, with the anti-windup working against the room the feed-forward leaves::

    fb   = to_pi(speed)
    O    = PI(ref, fb), limits sat((lim_lo − ff)·2**(width−16)), sat((lim_hi − ff)·2**(width−16))
    i_q  = saturate(round_shift(O + ff·2**(width−16), width − 16), signed(16))          Q1.15

The PI's limits are the current limits shifted by ``−ff`` (saturated to signed(width)): its
integrator clamp and conditional integration act on the PI's share of i_q, so the integrator
never winds up behind the feed-forward, and ``sat`` still means "i_q is at the current limit".
``ff`` is ``+F`` while the profile rises and ``−F`` while it falls, clamped to the current limits
(so it fits signed(16)); then for ``lim_lo ≤ lim_hi``, ``lim_lo − ff ≤ 0 ≤ lim_hi − ff``, a
shifted limit can only saturate towards the inside, and ``O + ff`` never leaves
``[lim_lo, lim_hi]`` (the golden model checks it). Widths: ``lim − ff`` signed(17),
``O + ff·2**(width−16)`` signed(width + 1); the final ``saturate`` never binds (it is there so
that nothing can wrap).

:class:`Servo` holds the operating mode (:class:`Mode`), the open-loop angle generator (a phase
accumulator) and the speed loop, and produces the current loop's inputs (the ``In`` ports of
``hdl/foc.py``: ``enable``, ``ol_enable``, ``ol_ud``, ``ol_uq``, ``theta``, ``iq_ref``,
``id_ref``) plus the PI clear signals and a reference-step strobe for the trace buffer.
"""

from amaranth.hdl import Cat, Module, Mux, Signal, signed, unsigned
from amaranth.lib import enum, stream, wiring
from amaranth.lib.wiring import In, Out

from .dsp import MUL_WIDTH, check_mul_width, saturate_bits
from .fixed import is_int, UQ, BinaryAngle, clamp, round_shift, saturate, shape_range
from .mt_speed import output_layout as mt_output_layout
from .pi import PI, pi_widths

__all__ = ["SpeedLoop", "Servo", "Mode", "AngleSource", "IQ_WIDTH", "ANGLE", "DELAY_FRAC",
           "check_speed_loop"]

#: Width of the current references and modulation indices, Q1.15 (docs/ARCHITECTURE.md).
IQ_WIDTH = 16
#: The electrical angle format.
ANGLE = BinaryAngle(16)
#: Fraction bits of ``ref_delay`` (steps of 1/8 speed-loop run).
DELAY_FRAC = 3


class Mode(enum.Enum, shape=2):
    """Operating mode (the ``mode`` register)."""
    DISABLED = 0    # gates off, current and speed PIs cleared
    OPEN_LOOP = 1   # u_d, u_q from registers at a fixed, rotating or measured angle
    CURRENT = 2     # i_d, i_q references from registers (torque control)
    SPEED = 3       # i_q reference from the speed PI, i_d reference from its register


class AngleSource(enum.Enum, shape=2):
    """Angle used in :attr:`Mode.OPEN_LOOP` (the ``ol_src`` register). The unused code 3 acts as
    ``FIXED``."""
    FIXED = 0       # ol_theta
    ROTATING = 1    # phase accumulator: starts at ol_theta, advances ol_freq per loop strobe
    MEASURED = 2    # the measured θ_e (encoder / Hall check with a voltage vector)


def check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                     delay_width=5):
    """Validate the :class:`SpeedLoop` parameters (shared with the golden model)."""
    if not is_int(speed_width) or not 16 <= speed_width <= 48:
        raise TypeError(f"SpeedLoop speed_width must be an integer from 16 to 48, "
                        f"not {speed_width!r}")
    if not is_int(width) or width < IQ_WIDTH:
        raise TypeError(f"SpeedLoop width must be an integer of at least {IQ_WIDTH}, "
                        f"not {width!r}")
    if width > speed_width:
        raise ValueError(f"SpeedLoop width must be at most speed_width {speed_width}, "
                         f"not {width!r}")
    if not is_int(div_width) or not 1 <= div_width <= 16:
        raise TypeError(f"SpeedLoop div_width must be an integer from 1 to 16, "
                        f"not {div_width!r}")
    if not is_int(delay_width) or not DELAY_FRAC + 1 <= delay_width <= DELAY_FRAC + 4:
        raise TypeError(f"SpeedLoop delay_width must be an integer from {DELAY_FRAC + 1} to "
                        f"{DELAY_FRAC + 4}, not {delay_width!r}")
    pi_widths(width, kp_format, kx_format, int_guard)


class SpeedLoop(wiring.Component):
    """Reference profile and speed PI: M/T speed and speed reference → i_q reference (module
    docstring: equations).

    Runs on every ``rate_div + 1``-th valid speed sample (the first one after ``clear`` runs); a
    run that finds the PI still busy (samples less than :attr:`interval` clocks apart) is dropped
    and leaves the profile alone. The M/T block delivers one sample per PWM period, thousands of
    clocks apart.

    Parameters
    ----------
    speed_width : int
        Width of the speed, speed reference and slew, Q1.(speed_width−1) of N_FS (MTSpeed
        ``out_width``, 32 by default), 16 … 48.
    width : int
        Width of the speed PI (error, integrator scale, output), ``16 … speed_width``.
    kp_format, kx_format, int_guard
        Of the speed PI (:class:`~foc_servo.hdl.pi.PI`). ``kp`` is the gain in per-unit
        (I_FS per N_FS), ``kx = K_i·T_s/2`` with ``T_s`` the speed-loop period. The defaults,
        ``UQ(24, 12)`` (0 … 4096), ``UQ(24, 24)`` (0 … 1 in steps of 6·10⁻⁸) and 16 guard bits,
        keep a small ``kx`` integrating errors far below 0.01 % of full scale.
    div_width : int
        Width of ``rate_div``, 1 … 16.
    delay_width : int
        Width of ``ref_delay``, UQ(delay_width, 3): ``4 … 7`` (largest delay 1.875 … 15.875
        runs; the default 5 gives 0 … 3.875 and stores 3 past references).
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx; ``None`` iCE40: products not split), for the speed PI's partial
        products; never changes a result.

    Members
    -------
    i : In(stream.Signature(MTSpeed output layout, always_ready=True))
        The M/T speed (``wiring.connect`` it to :attr:`MTSpeed.o`); only ``speed`` is used
        (a stopped motor reads 0; the payload is held between strobes).
    speed_ref : In(signed(speed_width))
        Speed reference, Q1.(speed_width−1) of N_FS, read in the clock a run is accepted (and
        every clock while ``clear`` with ``speed_slew = 0``). A host or DSP closing a position
        loop writes it (or, in current mode, the i_q reference).
    speed_slew : In(unsigned(speed_width))
        Largest change of ``ref_int`` per run, UQ1.(speed_width−1) of N_FS; 0: off (``ref_int``
        steps to ``speed_ref``). A run uses the value of the clock before it.
    iq_ff : In(signed(16))
        Acceleration feed-forward ``J·α/K_t``, Q1.15 of I_FS, added with the direction of the
        profile while ``ref_int`` has not reached ``speed_ref`` (read in the run's clock).
    ref_delay : In(unsigned(delay_width))
        UQ(delay_width, 3): the PI's reference is ``ref_int`` this many runs ago, interpolated
        linearly between runs; integer part 0: ``ref_int`` itself (the fraction is ignored).
        A run uses the value of the clock before it (for ``d ≥ 1``).
    int_hold : In(1)
        Hold the PI's integrator (its ``kx`` is 0) in runs whose reference still moves
        (``ref_int`` has not reached ``speed_ref``, or the delayed reference has not reached
        ``ref_int``): the feed-forward supplies the acceleration.
    kp : In(kp_format.shape)
    kx : In(kx_format.shape)
    lim_lo, lim_hi : In(signed(16))
        i_q limits (the current limit), Q1.15 of I_FS. Gains, limits, ``ref_delay`` and
        ``int_hold`` must be stable while a run is in flight (the register file changes them
        only at loop boundaries).
    rate_div : In(unsigned(div_width))
        The loop runs on every ``rate_div + 1``-th speed sample.
    clear : In(1)
        While high: PI cleared (integrator 0), run in flight abandoned, output 0, feed-forward
        0, decimation counter restarted, ``ref_int`` and its history track ``i.payload.speed``
        (``speed_slew ≠ 0``) or ``speed_ref``.
    o : Out(stream.Signature(signed(16), always_ready=True))
        i_q reference, Q1.15 of I_FS, rounded half away from zero, within [lim_lo, lim_hi];
        ``valid`` strobes :attr:`latency` clocks after an accepted run, payload held (0 after
        reset and ``clear``).
    sat : Out(1)
        The last output was clamped to a limit (updates with ``o.valid``).
    ref_int : Out(signed(speed_width))
        The profile's reference ``R``, Q1.(speed_width−1) of N_FS (updates the clock after a
        run; 0 after reset).

    Attributes
    ----------
    latency : int
        Clocks from a valid speed sample that runs the loop to ``o.valid``: PI latency + 2 = 8
        (the run's operands are registered before the PI takes them, for 100 MHz on the ECP5).
    interval : int
        Minimum clocks between runs: the PI's + 1 = 7.
    max_delay : int
        Largest integer part of ``ref_delay``: ``2**(delay_width − 3) − 1``.
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, delay_width=5, mul_width=MUL_WIDTH):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                         delay_width)
        self._mul_width = check_mul_width("SpeedLoop", mul_width)
        self._speed_width = speed_width
        self._width = width
        self._kp_format = kp_format
        self._kx_format = kx_format
        self._int_guard = int_guard
        self._div_width = div_width
        self._delay_width = delay_width
        super().__init__({
            "i": In(stream.Signature(mt_output_layout(speed_width), always_ready=True)),
            "speed_ref": In(signed(speed_width)),
            "speed_slew": In(unsigned(speed_width)),
            "iq_ff": In(signed(IQ_WIDTH)),
            "ref_delay": In(unsigned(delay_width)),
            "int_hold": In(1),
            "kp": In(kp_format.shape),
            "kx": In(kx_format.shape),
            "lim_lo": In(signed(IQ_WIDTH)),
            "lim_hi": In(signed(IQ_WIDTH)),
            "rate_div": In(unsigned(div_width)),
            "clear": In(1),
            "o": Out(stream.Signature(signed(IQ_WIDTH), always_ready=True)),
            "sat": Out(1),
            "ref_int": Out(signed(speed_width)),
        })

    speed_width = property(lambda self: self._speed_width)
    width = property(lambda self: self._width)
    kp_format = property(lambda self: self._kp_format)
    kx_format = property(lambda self: self._kx_format)
    int_guard = property(lambda self: self._int_guard)
    div_width = property(lambda self: self._div_width)
    delay_width = property(lambda self: self._delay_width)
    mul_width = property(lambda self: self._mul_width)
    max_delay = property(lambda self: (1 << (self._delay_width - DELAY_FRAC)) - 1)
    latency = property(lambda self: 6 + 2)
    interval = property(lambda self: 6 + 1)

    def elaborate(self, platform):
        m = Module()
        sw, w = self._speed_width, self._width
        shift_in = sw - w
        shift_out = w - IQ_WIDTH
        m.submodules.pi = pi = PI(width=w, kp_format=self._kp_format,
                                  kx_format=self._kx_format, int_guard=self._int_guard,
                                  mul_width=self._mul_width)
        if pi.latency + 2 != self.latency:
            raise RuntimeError(f"PI latency {pi.latency} changed; update SpeedLoop.latency")

        def to_pi(value):
            # saturate by bit tests (no comparator behind the rounding adder).
            return saturate_bits(round_shift(value, shift_in).as_signed(), signed(w))

        count = Signal(unsigned(self._div_width))
        run = Signal()
        m.d.comb += run.eq(self.i.valid & (count == 0) & ~self.clear)
        with m.If(self.clear):
            m.d.sync += count.eq(0)
        with m.Elif(self.i.valid):
            m.d.sync += count.eq(Mux(count >= self.rate_div, 0, count + 1))
        # A run accepted in clock t hands its registered operands to the PI in t + 1 (``start``),
        # which is busy from t + 2: no second run may be accepted in t + 1.
        start = Signal()
        accept = Signal()
        m.d.comb += accept.eq(run & pi.i.ready & ~start)
        m.d.sync += start.eq(accept)

        # Profile. The bounds R ± S (signed(sw + 2), unsaturated) are registers, so a run only
        # compares ``speed_ref`` with them and selects (no adder before the PI's rounding).
        # They are loaded every clock from the tracked value while clear, else from R:
        # stale only in the clock after a run, when the PI is busy and no run can be accepted.
        # S = 0 opens them beyond any speed_ref. A bound is selected only when speed_ref lies
        # beyond it, so it lies between R and speed_ref: the truncation of ``plan`` to
        # signed(sw) is exact.
        b_lo, b_hi = shape_range(signed(sw + 2))
        ref_int = Signal(signed(sw))
        # to_pi of each candidate (bounds, speed_ref, speed) side by side with the comparisons:
        # a run then selects among them (no rounding adder behind the bound comparison).
        tp_ref = Signal(signed(w))
        tp_speed = Signal(signed(w))
        tp_lo = Signal(signed(w))
        tp_hi = Signal(signed(w))
        tp_plan = Signal(signed(w))
        lo_b = Signal(signed(sw + 2), init=b_lo)
        hi_b = Signal(signed(sw + 2), init=b_hi)
        up = Signal()
        dn = Signal()
        plan = Signal(signed(sw))
        track = Signal(signed(sw))
        ref_next = Signal(signed(sw))
        ref_next_pi = Signal(signed(w))
        ref_pi = Signal(signed(w))                      # to_pi(ref_int)
        m.d.comb += [
            up.eq(self.speed_ref > hi_b),
            dn.eq(self.speed_ref < lo_b),
            plan.eq(Mux(up, hi_b, Mux(dn, lo_b, self.speed_ref))),
            track.eq(Mux(self.speed_slew == 0, self.speed_ref, self.i.payload.speed)),
            self.ref_int.eq(ref_int),
            tp_ref.eq(to_pi(self.speed_ref)),
            tp_speed.eq(to_pi(self.i.payload.speed)),
            # A bound is selected only when it lies within signed(sw): to_pi of the wider
            # value is then to_pi(plan).
            tp_lo.eq(to_pi(lo_b)),
            tp_hi.eq(to_pi(hi_b)),
            tp_plan.eq(Mux(up, tp_hi, Mux(dn, tp_lo, tp_ref))),
        ]
        with m.If(self.clear):
            m.d.comb += [ref_next.eq(track),
                         ref_next_pi.eq(Mux(self.speed_slew == 0, tp_ref, tp_speed))]
        with m.Elif(accept):
            m.d.comb += [ref_next.eq(plan), ref_next_pi.eq(tp_plan)]
        with m.Else():
            m.d.comb += [ref_next.eq(ref_int), ref_next_pi.eq(ref_pi)]
        m.d.sync += [ref_int.eq(ref_next), ref_pi.eq(ref_next_pi)]
        base = Mux(self.clear, track, ref_int)
        with m.If(self.speed_slew == 0):
            m.d.sync += [lo_b.eq(b_lo), hi_b.eq(b_hi)]
        with m.Else():
            m.d.sync += [lo_b.eq(base - self.speed_slew), hi_b.eq(base + self.speed_slew)]

        # Delayed reference: hist[k] = to_pi(R) k runs before the last; the interpolation for
        # the next run is registered in ``ref_pre`` (its inputs change only at runs and clear).
        # The tap differences b − a are registered first (``tap_diff``, zeroed while clear):
        # after a run they are one clock late, so ``ref_pre`` is right from the third clock
        # after a run on, long before the PI can take the next one.
        d_int = self.ref_delay[DELAY_FRAC:]
        d_frac = self.ref_delay[:DELAY_FRAC]
        hist = [Signal(signed(w), name=f"hist{k}") for k in range(1, self.max_delay + 1)]
        taps = [ref_pi] + hist
        tap_diff = [Signal(signed(w + 1), name=f"tap_diff{k}")
                    for k in range(1, self.max_delay + 1)]
        a = Signal(signed(w))
        diff = Signal(signed(w + 1))
        with m.Switch(d_int):
            for k in range(1, self.max_delay + 1):
                with m.Case(k):
                    m.d.comb += [a.eq(taps[k - 1]), diff.eq(tap_diff[k - 1])]
        ref_pre = Signal(signed(w))
        # a + round_shift(f·(b − a), 3) = (8a + f·(b − a) + 4 − [f·(b − a) < 0]) >> 3 (8a has no
        # low bits), f·(b − a) by shift-and-add (f has DELAY_FRAC bits: no multiplier). It lies
        # between a and b: the truncation to signed(w) is exact.
        prod = sum(Mux(d_frac[k], diff << k, 0) for k in range(DELAY_FRAC))
        neg = diff[-1] & d_frac.any()
        interp = ((a << DELAY_FRAC) + prod + ((1 << (DELAY_FRAC - 1)) - neg)) >> DELAY_FRAC
        with m.If(self.clear):
            m.d.sync += [h.eq(ref_next_pi) for h in hist]
            m.d.sync += [d.eq(0) for d in tap_diff]
            m.d.sync += ref_pre.eq(ref_next_pi)
        with m.Else():
            with m.If(accept):
                m.d.sync += [dst.eq(src) for dst, src in zip(hist, taps)]
            m.d.sync += [d.eq(taps[k + 1] - taps[k]) for k, d in enumerate(tap_diff)]
            m.d.sync += ref_pre.eq(interp)

        # The PI's reference this run, and whether it still moves (a profile only): R has not
        # reached speed_ref before this run, or the delayed reference has not reached R
        # (registers and inputs only: no comparison after the profile's multiplexer). Both
        # operands are registered in the run's clock; the PI takes them in the next (``start``).
        pi_ref = Signal(signed(w))
        pi_fb = Signal(signed(w))
        moving = Signal()
        m.d.comb += moving.eq((self.speed_slew != 0)
                              & ((ref_int != self.speed_ref)
                                 | ((d_int != 0) & (ref_pre != ref_pi))))
        with m.If(accept):
            m.d.sync += [pi_ref.eq(Mux(d_int == 0, tp_plan, ref_pre)), pi_fb.eq(tp_speed)]

        # Feed-forward and integrator hold of the run in flight (held until the next run).
        # The feed-forward is clamped to the current limits, so lim − ff never leaves the PI's
        # range in the direction that would let O + ff pass a limit.
        ff = Signal(signed(IQ_WIDTH))
        hold = Signal()
        with m.If(self.clear):
            m.d.sync += [ff.eq(0), hold.eq(0)]
        with m.Elif(accept):
            # Both clamped candidates are ready before ``up``/``dn`` select one.
            m.d.sync += [ff.eq(Mux(up, clamp(self.iq_ff, self.lim_lo, self.lim_hi),
                                   Mux(dn, clamp(-self.iq_ff, self.lim_lo, self.lim_hi), 0))),
                         hold.eq(self.int_hold & moving)]

        # PI limits shifted by −ff (registered: the PI reads them from its third clock on).
        pi_lo = Signal(signed(w))
        pi_hi = Signal(signed(w))
        m.d.sync += [
            pi_lo.eq(saturate((self.lim_lo - ff) << shift_out, signed(w))),
            pi_hi.eq(saturate((self.lim_hi - ff) << shift_out, signed(w))),
        ]

        m.d.comb += [
            pi.i.valid.eq(start),
            pi.i.payload.ref.eq(pi_ref),
            pi.i.payload.fb.eq(pi_fb),
            pi.kp.eq(self.kp),
            pi.kx.eq(Mux(hold, 0, self.kx)),
            pi.lim_lo.eq(pi_lo),
            pi.lim_hi.eq(pi_hi),
            pi.clear.eq(self.clear),
        ]

        # i_q = saturate(round_shift(O + ff·2**s, s), signed(16)), s = shift_out, in one adder:
        # with O = H0·2**s + lo (0 ≤ lo < 2**s) the sum is H·2**s + lo, H = H0 + ff, negative
        # iff H is, and the rounding adds [lo ≥ 2**(s−1) + neg] to H. H and H + 1 are formed side
        # by side and saturated by bit tests; H's sign and lo choose.
        h0 = pi.o.payload[shift_out:].as_signed()
        h = Signal(signed(w - shift_out + 2))
        h1 = Signal(signed(w - shift_out + 2))
        m.d.comb += [h.eq(h0 + ff), h1.eq(h0 + ff + 1)]
        if shift_out:
            lo = pi.o.payload[:shift_out]
            half = lo[shift_out - 1]
            inc = Mux(h[-1], half & lo[:shift_out - 1].any(), half)
        else:
            inc = 0
        iq = Mux(inc, saturate_bits(h1, signed(IQ_WIDTH)), saturate_bits(h, signed(IQ_WIDTH)))
        m.d.sync += self.o.valid.eq(pi.o.valid & ~self.clear)
        with m.If(self.clear):
            m.d.sync += [self.o.payload.eq(0), self.sat.eq(0)]
        with m.Elif(pi.o.valid):
            m.d.sync += [
                self.o.payload.eq(iq),
                self.sat.eq(pi.sat),
            ]
        return m


class Servo(wiring.Component):
    """Operating modes, open-loop angle generator and speed loop (module docstring).

    **Mode changes take effect at a loop boundary**: the ``mode`` register is copied into the
    active mode on each ``loop`` strobe. A ``trip`` forces DISABLED behaviour at once (outputs
    are combinational in ``trip``) and sets the active mode to DISABLED; the ``mode`` register
    keeps its value, and once ``trip`` is low again (faults cleared) the next ``loop`` strobe
    brings the mode back.

    Effective mode (DISABLED while ``trip`` is high) → outputs:

    ===========  ======  =========  ===============  ==========  =========  ==============
    mode         enable  ol_enable  theta            iq_ref      id_ref     clears
    ===========  ======  =========  ===============  ==========  =========  ==============
    DISABLED     0       0          theta_meas       0           0          current, speed
    OPEN_LOOP    1       1          by ``ol_src``    0           0          current, speed
    CURRENT      1       0          theta_meas       clamp(iq)   id_set     speed
    SPEED        1       0          theta_meas       speed PI    id_set     —
    ===========  ======  =========  ===============  ==========  =========  ==============

    ``ol_ud``, ``ol_uq`` are ``ud_set``, ``uq_set`` in OPEN_LOOP, else 0. ``clamp(iq)`` is
    ``iq_set`` clamped to [``iq_lim_lo``, ``iq_lim_hi``], the limits of the speed PI output too.

    **Bumpless transfer.** The speed PI is cleared (integrator 0) whenever the effective mode is
    not SPEED; on entering SPEED the i_q reference is 0 until the first speed-PI result, which
    starts from a zero integrator. So the switch is bumpless towards zero torque, not towards the
    previous current-mode ``iq_set`` (that would need an integrator preset on the PI). With a
    reference profile (``speed_slew ≠ 0``) the profile starts from the measured speed and moves
    to ``speed_ref`` at the slew rate, so entering SPEED with a spinning motor is smooth; without
    one, set ``speed_ref`` to the measured speed before switching.

    **Position loop.** A host or DSP closes a position loop (paper Fig. 1) by writing
    ``speed_ref`` (SPEED mode) or ``iq_set`` (CURRENT mode) over the link each of its periods:
    nothing here is specific to it.

    **Open-loop angle.** A ``phase_width``-bit phase accumulator (BinaryAngle(phase_width)):
    while the effective mode is not OPEN_LOOP with ``ol_src = ROTATING`` it is loaded with
    ``ol_theta · 2**(phase_width−16)`` every clock; in that mode it advances by ``ol_freq``
    (wrapping, as angles do) on every ``loop`` strobe, so θ is constant during one current-loop
    computation. Electrical frequency ``f = ol_freq · f_loop / 2**phase_width`` (negative =
    reverse); ``theta`` is the accumulator's top 16 bits (truncated).

    **Reference step.** ``ref_step`` strobes in a ``loop`` clock when any of ``mode``,
    ``speed_ref``, ``id_set``, ``iq_set``, ``ud_set``, ``uq_set`` differs from its value at the
    previous ``loop`` strobe (the trace buffer's ``trigger``).

    Parameters
    ----------
    speed_width, width, kp_format, kx_format, int_guard, div_width, delay_width, mul_width
        Of the :class:`SpeedLoop`.
    phase_width : int
        Width of the open-loop phase accumulator, 16 … 48.

    Members
    -------
    loop : In(1)
        Loop-boundary strobe (the PWM ``period_start``).
    mode : In(Mode)
    trip : In(1)
        Protection trip (level).
    ol_src : In(AngleSource)
    ol_theta : In(16)
        Fixed (or start) open-loop angle, BinaryAngle(16).
    ol_freq : In(signed(phase_width))
        Open-loop angle increment per ``loop`` strobe, BinaryAngle(phase_width).
    ud_set, uq_set : In(signed(16))
        Open-loop modulation indices, Q1.15 of (2/3)·U_dc.
    id_set, iq_set : In(signed(16))
        Current references, Q1.15 of I_FS (``id_set`` also in SPEED mode).
    theta_meas : In(16)
        Measured electrical angle, BinaryAngle(16).
    speed : In(stream.Signature(MTSpeed output layout, always_ready=True))
    speed_ref : In(signed(speed_width))
    speed_kp, speed_kx, iq_lim_lo, iq_lim_hi, speed_rate_div
        The :class:`SpeedLoop`'s ``kp``, ``kx``, ``lim_lo``, ``lim_hi``, ``rate_div``.
    speed_slew, iq_ff, speed_ref_delay, speed_int_hold
        The :class:`SpeedLoop`'s ``speed_slew`` (UQ1.(speed_width−1) of N_FS per run),
        ``iq_ff`` (Q1.15 of I_FS), ``ref_delay`` (UQ(delay_width, 3) runs), ``int_hold``: the
        reference profile; all 0 = none.
    enable : Out(1)
        Gate enable and current-loop enable.
    ol_enable : Out(1)
    ol_ud, ol_uq : Out(signed(16))
    theta : Out(16)
        The angle the current loop uses, BinaryAngle(16).
    iq_ref, id_ref : Out(signed(16))
        Current references, Q1.15 of I_FS.
    current_clear, speed_clear : Out(1)
        Clear for the current PIs and (already applied inside) the speed PI.
    active : Out(Mode)
        The effective mode (DISABLED while tripped), for the status register.
    ref_step : Out(1)
        Reference-step strobe.
    speed_sat : Out(1)
        The speed PI output is at the current limit.
    speed_valid : Out(1)
        Strobe: a new speed-PI result (the speed loop's ``o.valid``).
    speed_ref_int : Out(signed(speed_width))
        The profile's reference (the speed loop's ``ref_int``), Q1.(speed_width−1) of N_FS.

    Attributes
    ----------
    speed_loop_latency : int
        :attr:`SpeedLoop.latency`.
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, delay_width=5, phase_width=32, mul_width=MUL_WIDTH):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                         delay_width)
        mul_width = check_mul_width("Servo", mul_width)
        if not is_int(phase_width) or not 16 <= phase_width <= 48:
            raise TypeError(f"Servo phase_width must be an integer from 16 to 48, "
                            f"not {phase_width!r}")
        self._loop_params = dict(speed_width=speed_width, width=width, kp_format=kp_format,
                                 kx_format=kx_format, int_guard=int_guard, div_width=div_width,
                                 delay_width=delay_width, mul_width=mul_width)
        self._phase_width = phase_width
        a = ANGLE.shape
        q = signed(IQ_WIDTH)
        super().__init__({
            "loop": In(1),
            "mode": In(Mode),
            "trip": In(1),
            "ol_src": In(AngleSource),
            "ol_theta": In(a),
            "ol_freq": In(signed(phase_width)),
            "ud_set": In(q),
            "uq_set": In(q),
            "id_set": In(q),
            "iq_set": In(q),
            "theta_meas": In(a),
            "speed": In(stream.Signature(mt_output_layout(speed_width), always_ready=True)),
            "speed_ref": In(signed(speed_width)),
            "speed_kp": In(kp_format.shape),
            "speed_kx": In(kx_format.shape),
            "iq_lim_lo": In(q),
            "iq_lim_hi": In(q),
            "speed_rate_div": In(unsigned(div_width)),
            "speed_slew": In(unsigned(speed_width)),
            "iq_ff": In(q),
            "speed_ref_delay": In(unsigned(delay_width)),
            "speed_int_hold": In(1),
            "enable": Out(1),
            "ol_enable": Out(1),
            "ol_ud": Out(q),
            "ol_uq": Out(q),
            "theta": Out(a),
            "iq_ref": Out(q),
            "id_ref": Out(q),
            "current_clear": Out(1),
            "speed_clear": Out(1),
            "active": Out(Mode),
            "ref_step": Out(1),
            "speed_sat": Out(1),
            "speed_valid": Out(1),
            "speed_ref_int": Out(signed(speed_width)),
        })

    loop_params = property(lambda self: dict(self._loop_params))
    phase_width = property(lambda self: self._phase_width)
    speed_loop_latency = property(lambda self: 6 + 2)

    def elaborate(self, platform):
        m = Module()
        pw = self._phase_width
        m.submodules.speed_loop = sl = SpeedLoop(**self._loop_params)
        wiring.connect(m, speed=wiring.flipped(self.speed), speed_loop=sl.i)

        # Active mode: copied at loop boundaries, forced to DISABLED by a trip.
        active = Signal(Mode)
        with m.If(self.trip):
            m.d.sync += active.eq(Mode.DISABLED)
        with m.Elif(self.loop):
            m.d.sync += active.eq(self.mode)
        eff = Signal(Mode)
        with m.If(self.trip):
            m.d.comb += eff.eq(Mode.DISABLED)
        with m.Else():
            m.d.comb += eff.eq(active)
        m.d.comb += self.active.eq(eff)

        is_ol = eff == Mode.OPEN_LOOP
        is_cur = eff == Mode.CURRENT
        is_speed = eff == Mode.SPEED

        # Speed loop.
        m.d.comb += [
            sl.speed_ref.eq(self.speed_ref),
            sl.kp.eq(self.speed_kp),
            sl.kx.eq(self.speed_kx),
            sl.lim_lo.eq(self.iq_lim_lo),
            sl.lim_hi.eq(self.iq_lim_hi),
            sl.rate_div.eq(self.speed_rate_div),
            sl.speed_slew.eq(self.speed_slew),
            sl.iq_ff.eq(self.iq_ff),
            sl.ref_delay.eq(self.speed_ref_delay),
            sl.int_hold.eq(self.speed_int_hold),
            sl.clear.eq(~is_speed),
            self.speed_clear.eq(~is_speed),
            self.speed_sat.eq(sl.sat),
            self.speed_valid.eq(sl.o.valid),
            self.speed_ref_int.eq(sl.ref_int),
        ]

        # Open-loop phase accumulator.
        acc = Signal(unsigned(pw))
        rotating = is_ol & (self.ol_src == AngleSource.ROTATING)
        with m.If(~rotating):
            m.d.sync += acc.eq(self.ol_theta << (pw - ANGLE.width))
        with m.Elif(self.loop):
            m.d.sync += acc.eq(acc + self.ol_freq)                  # binary angle: wraps

        # Outputs.
        m.d.comb += [
            self.enable.eq(eff != Mode.DISABLED),
            self.ol_enable.eq(is_ol),
            self.current_clear.eq(~(is_cur | is_speed)),
            self.theta.eq(self.theta_meas),
        ]
        with m.If(is_ol):
            m.d.comb += [self.ol_ud.eq(self.ud_set), self.ol_uq.eq(self.uq_set)]
            with m.Switch(self.ol_src):
                with m.Case(AngleSource.ROTATING):
                    m.d.comb += self.theta.eq(acc[pw - ANGLE.width:])
                with m.Case(AngleSource.MEASURED):
                    m.d.comb += self.theta.eq(self.theta_meas)
                with m.Default():
                    m.d.comb += self.theta.eq(self.ol_theta)
        with m.If(is_cur):
            m.d.comb += [
                self.iq_ref.eq(clamp(self.iq_set, self.iq_lim_lo, self.iq_lim_hi)),
                self.id_ref.eq(self.id_set),
            ]
        with m.If(is_speed):
            m.d.comb += [self.iq_ref.eq(sl.o.payload), self.id_ref.eq(self.id_set)]

        # Reference-step detection at loop boundaries.
        refs = Cat(self.mode, self.speed_ref, self.id_set, self.iq_set, self.ud_set, self.uq_set)
        last = Signal(len(refs))
        with m.If(self.loop):
            m.d.sync += last.eq(refs)
        m.d.comb += self.ref_step.eq(self.loop & (refs != last))
        return m
