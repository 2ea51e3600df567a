# Ref: paper eq. (7)–(9) (speed PI), SPEC.md §2, §2.5, §4 (operating modes)
"""Speed loop and operating modes: what drives the current loop.

:class:`SpeedLoop` turns the M/T speed (Q1.(speed_width−1) of the full-scale speed N_FS) and the
speed reference into the i_q reference (Q1.15 of I_FS) through a Tustin PI
(:class:`~foc_servo.hdl.pi.PI`, paper eq. (7)–(9)) of ``width`` bits; the speed error needs far
more than 16 bits (0.01 % of 1667 r/min is 0.17 r/min; one LSB of Q1.23 at N_FS = 12 000 r/min is
0.0014 r/min)::

    fb   = saturate(round_shift(speed,     speed_width − width), signed(width))   Q1.(width−1)
    ref  = saturate(round_shift(speed_ref, speed_width − width), signed(width))
    O    = PI(ref, fb) with limits lim_lo · 2**(width−16), lim_hi · 2**(width−16)
    i_q  = saturate(round_shift(O, width − 16), signed(16))                       Q1.15

``O`` lies within the scaled limits, so ``i_q`` lies within [lim_lo, lim_hi] exactly (the final
``saturate`` never binds; it is there so that nothing can wrap).

:class:`Servo` holds the operating mode (:class:`Mode`), the open-loop angle generator (a phase
accumulator) and the speed loop, and produces the current loop's inputs (the ``In`` ports of
``hdl/foc.py``: ``enable``, ``ol_enable``, ``ol_ud``, ``ol_uq``, ``theta``, ``iq_ref``,
``id_ref``) plus the PI clear signals and a reference-step strobe for the trace buffer.
"""

from amaranth.hdl import Cat, Module, Mux, Signal, signed, unsigned
from amaranth.lib import enum, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import UQ, BinaryAngle, clamp, round_shift, saturate
from .mt_speed import output_layout as mt_output_layout
from .pi import PI, pi_widths

__all__ = ["SpeedLoop", "Servo", "Mode", "AngleSource", "IQ_WIDTH", "ANGLE", "check_speed_loop"]

#: Width of the current references and modulation indices, Q1.15 (docs/ARCHITECTURE.md).
IQ_WIDTH = 16
#: The electrical angle format.
ANGLE = BinaryAngle(16)


def _is_int(value):
    return isinstance(value, int) and not isinstance(value, bool)


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


def check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width):
    """Validate the :class:`SpeedLoop` parameters (shared with the golden model)."""
    if not _is_int(speed_width) or not 16 <= speed_width <= 48:
        raise TypeError(f"SpeedLoop speed_width must be an integer from 16 to 48, "
                        f"not {speed_width!r}")
    if not _is_int(width) or width < IQ_WIDTH:
        raise TypeError(f"SpeedLoop width must be an integer of at least {IQ_WIDTH}, "
                        f"not {width!r}")
    if width > speed_width:
        raise ValueError(f"SpeedLoop width must be at most speed_width {speed_width}, "
                         f"not {width!r}")
    if not _is_int(div_width) or not 1 <= div_width <= 16:
        raise TypeError(f"SpeedLoop div_width must be an integer from 1 to 16, "
                        f"not {div_width!r}")
    pi_widths(width, kp_format, kx_format, int_guard)


class SpeedLoop(wiring.Component):
    """Speed PI: M/T speed and speed reference → i_q reference (module docstring: equations).

    Runs on every ``rate_div + 1``-th valid speed sample (the first one after ``clear`` runs); a
    run that finds the PI still busy (samples less than :attr:`interval` clocks apart) is dropped.
    The M/T block delivers one sample per PWM period, thousands of clocks apart.

    Parameters
    ----------
    speed_width : int
        Width of the speed and speed reference, Q1.(speed_width−1) of N_FS (MTSpeed
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

    Members
    -------
    i : In(stream.Signature(MTSpeed output layout, always_ready=True))
        The M/T speed (``wiring.connect`` it to :attr:`MTSpeed.o`); only ``speed`` is used
        (a stopped motor reads 0).
    speed_ref : In(signed(speed_width))
        Speed reference, Q1.(speed_width−1) of N_FS, read in the clock a run is accepted. A host
        or DSP closing a position loop writes it (or, in current mode, the i_q reference).
    kp : In(kp_format.shape)
    kx : In(kx_format.shape)
    lim_lo, lim_hi : In(signed(16))
        i_q limits (the current limit), Q1.15 of I_FS. Gains and limits must be stable while a
        run is in flight (the register file changes them only at loop boundaries).
    rate_div : In(unsigned(div_width))
        The loop runs on every ``rate_div + 1``-th speed sample.
    clear : In(1)
        While high: PI cleared (integrator 0), run in flight abandoned, output 0, decimation
        counter restarted.
    o : Out(stream.Signature(signed(16), always_ready=True))
        i_q reference, Q1.15 of I_FS, rounded half away from zero, within [lim_lo, lim_hi];
        ``valid`` strobes :attr:`latency` clocks after an accepted run, payload held (0 after
        reset and ``clear``).
    sat : Out(1)
        The last output was clamped to a limit (updates with ``o.valid``).

    Attributes
    ----------
    latency : int
        Clocks from a valid speed sample that runs the loop to ``o.valid``: PI latency + 1 = 7.
    interval : int
        Minimum clocks between runs (the PI's).
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width)
        self._speed_width = speed_width
        self._width = width
        self._kp_format = kp_format
        self._kx_format = kx_format
        self._int_guard = int_guard
        self._div_width = div_width
        super().__init__({
            "i": In(stream.Signature(mt_output_layout(speed_width), always_ready=True)),
            "speed_ref": In(signed(speed_width)),
            "kp": In(kp_format.shape),
            "kx": In(kx_format.shape),
            "lim_lo": In(signed(IQ_WIDTH)),
            "lim_hi": In(signed(IQ_WIDTH)),
            "rate_div": In(unsigned(div_width)),
            "clear": In(1),
            "o": Out(stream.Signature(signed(IQ_WIDTH), always_ready=True)),
            "sat": Out(1),
        })

    speed_width = property(lambda self: self._speed_width)
    width = property(lambda self: self._width)
    kp_format = property(lambda self: self._kp_format)
    kx_format = property(lambda self: self._kx_format)
    int_guard = property(lambda self: self._int_guard)
    div_width = property(lambda self: self._div_width)
    latency = property(lambda self: 6 + 1)
    interval = property(lambda self: 6)

    def elaborate(self, platform):
        m = Module()
        w = self._width
        shift_in = self._speed_width - w
        shift_out = w - IQ_WIDTH
        m.submodules.pi = pi = PI(width=w, kp_format=self._kp_format,
                                  kx_format=self._kx_format, int_guard=self._int_guard)
        if pi.latency + 1 != self.latency:
            raise RuntimeError(f"PI latency {pi.latency} changed; update SpeedLoop.latency")

        count = Signal(unsigned(self._div_width))
        run = Signal()
        m.d.comb += run.eq(self.i.valid & (count == 0) & ~self.clear)
        with m.If(self.clear):
            m.d.sync += count.eq(0)
        with m.Elif(self.i.valid):
            m.d.sync += count.eq(Mux(count >= self.rate_div, 0, count + 1))

        m.d.comb += [
            pi.i.valid.eq(run),
            pi.i.payload.ref.eq(saturate(round_shift(self.speed_ref, shift_in), signed(w))),
            pi.i.payload.fb.eq(saturate(round_shift(self.i.payload.speed, shift_in), signed(w))),
            pi.kp.eq(self.kp),
            pi.kx.eq(self.kx),
            pi.lim_lo.eq(self.lim_lo << shift_out),
            pi.lim_hi.eq(self.lim_hi << shift_out),
            pi.clear.eq(self.clear),
        ]

        m.d.sync += self.o.valid.eq(pi.o.valid & ~self.clear)
        with m.If(self.clear):
            m.d.sync += [self.o.payload.eq(0), self.sat.eq(0)]
        with m.Elif(pi.o.valid):
            m.d.sync += [
                self.o.payload.eq(saturate(round_shift(pi.o.payload, shift_out),
                                           signed(IQ_WIDTH))),
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
    previous current-mode ``iq_set`` (that would need an integrator preset on the PI): set
    ``speed_ref`` to the measured speed before switching for a smooth hand-over.

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
    speed_width, width, kp_format, kx_format, int_guard, div_width
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

    Attributes
    ----------
    speed_loop_latency : int
        :attr:`SpeedLoop.latency`.
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, phase_width=32):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width)
        if not _is_int(phase_width) or not 16 <= phase_width <= 48:
            raise TypeError(f"Servo phase_width must be an integer from 16 to 48, "
                            f"not {phase_width!r}")
        self._loop_params = dict(speed_width=speed_width, width=width, kp_format=kp_format,
                                 kx_format=kx_format, int_guard=int_guard, div_width=div_width)
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
        })

    loop_params = property(lambda self: dict(self._loop_params))
    phase_width = property(lambda self: self._phase_width)
    speed_loop_latency = property(lambda self: 6 + 1)

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
            sl.clear.eq(~is_speed),
            self.speed_clear.eq(~is_speed),
            self.speed_sat.eq(sl.sat),
            self.speed_valid.eq(sl.o.valid),
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
