# Ref: paper eq. (7)–(9) (speed PI), SPEC.md §2, §2.5, §4 (operating modes); issue 6 targets
#      (reference profile: slew limiter, acceleration feed-forward)
"""Bit-true, clock-by-clock golden models of :class:`~foc_servo.hdl.servo.SpeedLoop` and
:class:`~foc_servo.hdl.servo.Servo` (equations and mode table in ``hdl/servo.py``).

The speed loop's gateware is a sequential datapath that spends ``interval`` clocks on a run;
the model computes the run's equations directly, in the clock the run is accepted, with
:class:`~foc_servo.sim.models.pi.PIModel` and the numpy helpers, and shows the results when the
gateware does (timing from :func:`~foc_servo.hdl.servo.speed_loop_timing`, the one place it is
derived). It checks that the inputs the gateware reads during a run stay as they were when it was
accepted, and the invariants the gateware relies on (the i_q reference stays inside
``[lim_lo, lim_hi]`` with the feed-forward; the interpolation stays between its two taps), and
raises :exc:`AssertionError` if one fails.

Both are stateful and sequential, so they step one clock at a time: :meth:`~ServoModel.clock`
takes the inputs of clock ``t`` and returns the outputs seen in clock ``t`` (registered state plus
the combinational paths from the inputs), then advances the state to clock ``t + 1``. A run
accepted in clock ``t`` shows its ``ref_int`` in ``t + ref_latency`` (13 by default), its i_q
reference in ``t + latency`` (124), and the next run can be accepted in ``t + interval`` (125).
"""

from amaranth.hdl import signed

from ...hdl.fixed import UQ, clamp_np, round_shift_np, saturate_np
from ...hdl.servo import (ANGLE, DELAY_FRAC, IQ_WIDTH, AngleMode, Mode, check_speed_loop,
                          speed_loop_timing)
from .pi import PIModel

__all__ = ["SpeedLoopModel", "ServoModel", "SERVO_INPUTS"]

#: Inputs of :meth:`ServoModel.clock` (the :class:`Servo` members of the same names;
#: ``speed_valid``/``speed`` are ``speed.valid`` / ``speed.payload.speed``).
SERVO_INPUTS = ("loop", "mode", "trip", "ol_src", "ol_theta", "ol_freq", "ud_set", "uq_set",
                "id_set", "iq_set", "theta_meas", "speed_valid", "speed", "speed_ref",
                "speed_kp", "speed_kx", "iq_lim_lo", "iq_lim_hi", "speed_rate_div",
                "speed_slew", "iq_ff", "speed_ref_delay", "speed_int_hold", "ref_change")


class SpeedLoopModel:
    """Clock-by-clock model of :class:`~foc_servo.hdl.servo.SpeedLoop` (same parameters and
    validation; timing from :func:`~foc_servo.hdl.servo.speed_loop_timing`).

    A run is computed whole in the clock it is accepted, from that clock's inputs; its
    results show when the gateware's do: ``ref_int`` ``ref_latency`` clocks later, the i_q
    reference ``latency`` clocks later; the next run can be accepted ``interval`` clocks later.
    The inputs the gateware reads during a run (``speed_ref``, ``speed_slew``,
    ``iq_ff``, ``ref_delay``, ``int_hold``, ``kp``, ``kx``, ``lim_lo``, ``lim_hi``) must keep
    their accept-clock values until the run ends (``interval − 1`` clocks after acceptance, or a
    ``clear``): the model raises :exc:`AssertionError` naming the input that changed. With
    ``engine_timing`` (the engine reads the ``speed`` port itself) ``speed`` must likewise keep
    its accept-clock value until the engine reads it (:attr:`speed_held`).

    Attributes
    ----------
    o_valid, o_payload, sat : int
        The registered outputs in the current clock.
    ref_int : int
        The profile's reference ``R`` (the ``ref_int`` output) in the current clock.
    ff, hold : int
        Feed-forward and integrator hold of the last run (0 after ``clear``).
    plan : int
        The reference ``R`` the last run set (``ref_int`` shows it ``ref_latency`` clocks after
        the run).
    pi : PIModel
        The speed PI (``pi.last`` describes the last run).
    runs, dropped : int
        Accepted runs, and runs dropped because a run was in flight.
    latency, interval, ref_latency : int
        The gateware's timing.
    """

    #: Inputs that must be stable during a run (argument names of :meth:`clock`).
    STABLE = ("speed_ref", "speed_slew", "iq_ff", "ref_delay", "int_hold", "kp", "kx",
              "lim_lo", "lim_hi")

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, delay_width=5, engine_timing=None):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                         delay_width)
        timing = speed_loop_timing(speed_width, width, kp_format, kx_format, int_guard,
                                   delay_width)
        self.latency, self.interval = timing["latency"], timing["interval"]
        self.ref_latency = timing["ref_latency"]
        # The speed loop on the loop engine (EngineCurrentLoop(speed=True)): per profile path
        # (speed_run_timing), counted from the run's start, which waits for the engine.
        self.engine_timing = engine_timing
        self.waiting = None                 # engine: the accepted run not yet started
        self.started = None                 # engine: (path, clocks waited) of a start now
        self.read_due = -1                  # engine: the clock the started run reads speed
        self.speed_width, self.width = speed_width, width
        self.pi = PIModel(width=width, kp_format=kp_format, kx_format=kx_format,
                          int_guard=int_guard)
        self._shift_in = speed_width - width
        self._shift_out = width - IQ_WIDTH
        self.max_delay = (1 << (delay_width - DELAY_FRAC)) - 1
        self.t = 0
        self.count = 0
        self.pending = None                 # (due clock, PI out, PI sat, lim_lo, lim_hi, ff)
        self.pending_ref = None             # (due clock, R)
        self.run_end = 0                    # first clock a new run can be accepted
        self.run_inputs = None              # the stable inputs of the run in flight
        self.o_valid = self.o_payload = self.sat = 0
        self.ref_int = 0
        self.hist = [0] * self.max_delay    # to_pi(R) 1 … max_delay runs before the last
        self.ff = self.hold = 0
        self.plan = 0
        self.runs = self.dropped = 0

    @property
    def busy(self):
        """A run is in flight (no run can be accepted) in the current clock."""
        return self.t < self.run_end or self.waiting is not None

    @property
    def speed_held(self):
        """``engine_timing``: the speed of the last accepted run is yet to be read by the
        engine in the current clock (waiting, or started and before its timing's
        ``speed_read``: the engine reads the ``speed`` port itself, which must hold)."""
        return self.run_inputs is not None and (self.waiting is not None
                                                or self.t <= self.read_due)

    def _to_pi(self, value):
        return saturate_np(round_shift_np(value, self._shift_in), signed(self.width))

    def _interp(self, d_int, d_frac):
        """The delayed reference of a run with the current history (``d_int ≥ 1``)."""
        taps = [self._to_pi(self.ref_int)] + self.hist
        a, b = taps[d_int - 1], taps[d_int]
        v = a + round_shift_np(d_frac * (b - a), DELAY_FRAC)
        if not min(a, b) <= v <= max(a, b):
            raise AssertionError(f"SpeedLoop interpolation {v} outside [{a}, {b}]")
        return v

    def clock(self, valid, speed, speed_ref, kp, kx, lim_lo, lim_hi, rate_div, clear,
              speed_slew=0, iq_ff=0, ref_delay=0, int_hold=0, start=0):
        """Inputs of the current clock → ``(o_valid, o_payload, sat, ref_int)`` seen in it;
        advance one clock.

        With ``engine_timing``, an accepted run waits until a clock with ``start`` (the
        engine takes it: the caller models the engine's arbitration; it may be the accepting
        clock) and its results follow that clock by the path's ``ref_latency`` and
        ``latency``; the next run can be accepted from its ``o.valid`` on. ``clear`` drops a
        waiting run."""
        out = (self.o_valid, self.o_payload, self.sat, self.ref_int)
        self.started = None
        s = self._shift_out
        d_int, d_frac = ref_delay >> DELAY_FRAC, ref_delay & ((1 << DELAY_FRAC) - 1)
        now = dict(speed=speed, speed_ref=speed_ref, speed_slew=speed_slew, iq_ff=iq_ff,
                   ref_delay=ref_delay, int_hold=int_hold, kp=kp, kx=kx, lim_lo=lim_lo,
                   lim_hi=lim_hi)
        self.o_valid = 0
        if clear:
            self.pending = self.pending_ref = self.run_inputs = self.waiting = None
            self.run_end, self.read_due = 0, -1
            self.pi.clear()
            self.count = 0
            self.o_payload = self.sat = 0
            self.ff = self.hold = 0
            track = speed_ref if speed_slew == 0 else speed
            self.ref_int = track
            self.hist = [self._to_pi(track)] * self.max_delay
        else:
            if self.busy and self.run_inputs is not None:
                changed = [k for k in self.STABLE if now[k] != self.run_inputs[k]]
                if changed:
                    raise AssertionError(f"SpeedLoop input {changed[0]} changed during a run "
                                         f"(clock {self.t}: {self.run_inputs[changed[0]]} → "
                                         f"{now[changed[0]]})")
            if self.speed_held and speed != self.run_inputs["speed"]:
                raise AssertionError(f"SpeedLoop speed changed before the engine read it "
                                     f"(clock {self.t}: {self.run_inputs['speed']} → {speed})")
            if self.pending is not None and self.pending[0] == self.t:
                _, pi_out, pi_sat, lo, hi, ff = self.pending
                self.pending = None
                self.o_valid = 1
                self.o_payload = saturate_np(round_shift_np(pi_out + (ff << s), s),
                                             signed(IQ_WIDTH))
                self.sat = pi_sat
                if lo <= hi and not lo <= self.o_payload <= hi:
                    raise AssertionError(f"SpeedLoop i_q {self.o_payload} outside the limits "
                                         f"[{lo}, {hi}]")
            if self.pending_ref is not None and self.pending_ref[0] == self.t:
                self.ref_int = self.pending_ref[1]
                self.pending_ref = None
            if valid:
                if self.count == 0:
                    if self.busy:
                        self.dropped += 1
                    else:
                        self._run(now, d_int, d_frac)
                self.count = 0 if self.count >= rate_div else self.count + 1
            if start and self.waiting is not None:
                self._start()
        self.t += 1
        return out

    def _start(self):
        """The engine starts the waiting run in this clock (``engine_timing``)."""
        path, pi_out, pi_sat, lo, hi, ff, plan, accepted = self.waiting
        self.waiting = None
        self.started = (path, self.t - accepted)
        tm = self.engine_timing[path]
        self.pending = (self.t + tm["latency"] - 1, pi_out, pi_sat, lo, hi, ff)
        self.pending_ref = (self.t + tm["ref_latency"] - 1, plan)
        self.run_end = self.t + tm["latency"]
        self.read_due = self.t + tm.get("speed_read", -1 - self.t)

    def _run(self, inp, d_int, d_frac):
        """Compute an accepted run (clock ``self.t``) and schedule its results."""
        s = self._shift_out
        r, slew, sref = self.ref_int, inp["speed_slew"], inp["speed_ref"]
        lim_lo, lim_hi, iq_ff = inp["lim_lo"], inp["lim_hi"], inp["iq_ff"]
        up = slew != 0 and sref > r + slew
        dn = slew != 0 and sref < r - slew
        plan = r + slew if up else r - slew if dn else sref
        ff = clamp_np(iq_ff if up else -iq_ff, lim_lo, lim_hi) if up or dn else 0
        tp = self._to_pi(r)
        ref = self._to_pi(plan) if d_int == 0 else self._interp(d_int, d_frac)
        # The PI's reference moves (a profile only): R has not reached speed_ref, or the
        # delayed reference has not reached R, before this run.
        moving = slew != 0 and (r != sref or (d_int != 0 and ref != tp))
        hold = int(bool(inp["int_hold"]) and moving)
        # The PI runs with the limits shifted by this run's feed-forward.
        lo_s, hi_s = (saturate_np((lim - ff) << s, signed(self.width))
                      for lim in (lim_lo, lim_hi))
        pi_out, pi_sat = self.pi.step(ref, self._to_pi(inp["speed"]), inp["kp"],
                                      0 if hold else inp["kx"], lo_s, hi_s)
        if self.engine_timing is not None:
            self.waiting = ("up" if up else "dn" if dn else "none", pi_out, pi_sat, lim_lo,
                            lim_hi, ff, plan, self.t)
        else:
            self.pending = (self.t + self.latency - 1, pi_out, pi_sat, lim_lo, lim_hi, ff)
            self.pending_ref = (self.t + self.ref_latency - 1, plan)
            self.run_end = self.t + self.interval
        self.run_inputs = dict(inp)
        self.runs += 1
        self.plan = plan
        self.hist = [tp] + self.hist[:-1]
        self.ff, self.hold = ff, hold


class ServoModel:
    """Clock-by-clock model of :class:`~foc_servo.hdl.servo.Servo` (same parameters and
    validation).

    Attributes
    ----------
    active : int
        The registered active mode (before the ``trip`` override).
    acc : int
        Phase accumulator, BinaryAngle(phase_width).
    step_pending : int
        The reference-step flag (set by ``ref_change``, cleared by ``loop``).
    speed_loop : SpeedLoopModel

    ``speed_engine_timing``: the speed loop on the loop engine (``Servo(speed_loop="engine")``
    with ``EngineCurrentLoop(speed=True)``; its :attr:`speed_timing`): a run starts in a clock
    whose input ``speed_start`` is 1 (default 1: the engine free, as at M/T's strobe in the
    top), see :meth:`SpeedLoopModel.clock`.
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, delay_width=5, phase_width=32,
                 speed_engine_timing=None):
        self.speed_loop = SpeedLoopModel(speed_width=speed_width, width=width,
                                         kp_format=kp_format, kx_format=kx_format,
                                         int_guard=int_guard, div_width=div_width,
                                         delay_width=delay_width,
                                         engine_timing=speed_engine_timing)
        if (not isinstance(phase_width, int) or isinstance(phase_width, bool)
                or not 16 <= phase_width <= 48):
            raise TypeError(f"Servo phase_width must be an integer from 16 to 48, "
                            f"not {phase_width!r}")
        self.phase_width = phase_width
        self.active = Mode.DISABLED.value
        self.acc = 0
        self.step_pending = 0

    def clock(self, inp):
        """``inp``: dict of :data:`SERVO_INPUTS` (raw integers) for the current clock → dict of
        the outputs seen in it (raw integers, members of :class:`Servo`); advance one clock."""
        pw, aw = self.phase_width, ANGLE.width
        eff = Mode.DISABLED.value if inp["trip"] else self.active
        is_ol, is_cur, is_speed = (eff == Mode.OPEN_LOOP.value, eff == Mode.CURRENT.value,
                                   eff == Mode.SPEED.value)
        sl_valid, sl_out, sl_sat, sl_ref = self.speed_loop.clock(
            inp["speed_valid"], inp["speed"], inp["speed_ref"], inp["speed_kp"],
            inp["speed_kx"], inp["iq_lim_lo"], inp["iq_lim_hi"], inp["speed_rate_div"],
            not is_speed, inp["speed_slew"], inp["iq_ff"], inp["speed_ref_delay"],
            inp["speed_int_hold"], start=inp.get("speed_start", 1))

        theta = inp["theta_meas"]
        if is_ol:
            if inp["ol_src"] == AngleMode.ROTATING.value:
                theta = self.acc >> (pw - aw)
            elif inp["ol_src"] != AngleMode.MEASURED.value:
                theta = inp["ol_theta"]
        iq_ref = id_ref = 0
        if is_cur:
            iq_ref = clamp_np(inp["iq_set"], inp["iq_lim_lo"], inp["iq_lim_hi"])
            id_ref = inp["id_set"]
        elif is_speed:
            iq_ref, id_ref = sl_out, inp["id_set"]
        out = {
            "enable": int(eff != Mode.DISABLED.value),
            "ol_enable": int(is_ol),
            "ol_ud": inp["ud_set"] if is_ol else 0,
            "ol_uq": inp["uq_set"] if is_ol else 0,
            "theta": theta,
            "iq_ref": iq_ref,
            "id_ref": id_ref,
            "current_clear": int(not (is_cur or is_speed)),
            "speed_clear": int(not is_speed),
            "active": eff,
            "ref_step": int(bool(inp["loop"]) and self.step_pending),
            "speed_sat": sl_sat,
            "speed_valid": sl_valid,
            "speed_ref_int": sl_ref,
        }

        # Next state.
        if not (is_ol and inp["ol_src"] == AngleMode.ROTATING.value):
            self.acc = inp["ol_theta"] << (pw - aw)
        elif inp["loop"]:
            self.acc = (self.acc + inp["ol_freq"]) % (1 << pw)
        if inp["trip"]:
            self.active = Mode.DISABLED.value
        elif inp["loop"]:
            self.active = inp["mode"]
        self.step_pending = int(bool(inp["ref_change"])
                                or (self.step_pending and not inp["loop"]))
        return out
