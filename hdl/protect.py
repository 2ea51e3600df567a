# Ref: issue 4 item 8 (protection and fault latch); SPEC.md §2.4 (gate drive);
#      issue 6 item 7 (encoder/Hall plausibility fault)
"""Fault detection, trip latch and cause register.

Every cause is evaluated each clock into the registered ``present`` set; ``trip`` is the OR of
that set and the latch, so a fault seen in clock ``t`` raises ``trip`` in clock ``t + 1`` (the
gate stage adds its own register: 2 clocks from a synchronised fault pin to the gates, within the
issue's 3). The latch holds ``trip`` until a ``clear`` strobe comes while no cause is present.

Causes (the field order of :data:`FAULT_LAYOUT`; add a field and its detector to extend it):

==========================  ==================================================================
``external``                ``fault_n`` low (gate driver fault, active low, synchronised)
``overcurrent_a/_b/_c``     ``|i_x| > oc_limit`` on a valid current sample (held until the next)
``overcurrent_comparator``  ``oc_comp`` high (fast analog comparator pin, synchronised)
``overvoltage``             ``udc > ov_limit`` on a valid U_dc sample (held until the next)
``undervoltage``            armed and ``udc < uv_limit`` on a valid U_dc sample (held)
``overspeed``               ``|speed| > os_limit`` on a valid speed sample (held)
``encoder``                 ``encoder_illegal`` (illegal quadrature transition, pulse or level)
``hall``                    ``hall_invalid`` (Hall code 000 or 111, pulse or level)
``encoder_hall``            ``encoder_hall`` (the encoder angle disagrees with the Hall edges:
                            :class:`~.encoder.HallPlausibility`, a pulse per failing edge)
==========================  ==================================================================

Under-voltage arming: at power-up the DC bus is still charging, so an under-voltage check from
reset would trip at once. The check is armed by the first valid U_dc sample above ``uv_limit``
while ``uv_enable`` is high, and disarmed (its cause dropped at once) whenever ``uv_enable`` is
low. To clear an under-voltage trip while the bus is still low (bus switched off), drop
``uv_enable`` first.
"""

from amaranth.hdl import Assert, Cat, Const, Module, Mux, Shape, Signal, Value, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import abs_exceeds, check_bool, check_param, shape_range

__all__ = ["FAULTS", "FAULT_LAYOUT", "Protection", "udc_compares"]

#: Cause names, in bit order of :data:`FAULT_LAYOUT` (bit 0 first).
FAULTS = ("external", "overcurrent_a", "overcurrent_b", "overcurrent_c", "overcurrent_comparator",
          "overvoltage", "undervoltage", "overspeed", "encoder", "hall", "encoder_hall")

#: One flag per cause.
FAULT_LAYOUT = data.StructLayout({name: 1 for name in FAULTS})


def _ordered(x):
    """``x`` as unsigned bits in the same order (offset binary for a signed ``x``)."""
    x = Value.cast(x)
    return Cat(x[:-1], ~x[-1]) if x.shape().signed else x.as_unsigned()


def udc_compares(m, udc, ov_limit, uv_limit, *, arm_chain=False):
    """``(udc > ov_limit, udc < uv_limit, udc > uv_limit)``, the bus-voltage verdicts, on two
    carry chains sharing one inverted ``udc`` (signed or unsigned, all three of one shape), or
    three with ``arm_chain``.

    The codes are compared in offset binary (the sign bit flipped: unsigned chains then order
    signed values). ``ov_limit + ~udc + 1`` carries unless ``udc > ov_limit``;
    ``uv_limit + ~udc = uv_limit − udc − 1 (+ 2**w)`` carries iff ``udc < uv_limit``, and its
    sum is all ones iff ``udc = uv_limit``, so the arming's ``udc > uv_limit`` is neither. The
    three plain comparisons cost three chains and an inverter per limit bit. The ``abs_compare``
    proof shows them equal; :class:`~foc_servo.boards.prove.FaultSpec` states the causes with
    this function (as with :func:`~.fixed.abs_exceeds`). ``m`` takes the shared inverted
    ``udc`` (one signal, so that both chains read the same LUTs).

    ``arm_chain``: the arming's ``udc > uv_limit`` on a third chain of its own, the carry out of
    ``uv_limit + ~udc + 1`` (no carry iff ``udc > uv_limit``), as the over-voltage verdict, in
    place of the second chain's 17-input AND (three LUT levels behind the carry chain): the
    same verdicts, one carry chain more and the AND tree fewer (ECP5 Fmax: the arming was the
    critical path, docs/AREA.md §7.53, §7.58; the iCE40 pays cells for the chain, §7.30).
    """
    w = len(Value.cast(udc))
    udc_n = Signal(w, name="udc_n")
    m.d.comb += udc_n.eq(~_ordered(udc))

    def above(limit):
        """``udc > limit``: ``limit + ~udc + 1`` does not carry."""
        return ~(Cat(Const(1, 1), _ordered(limit)) + Cat(Const(1, 1), udc_n))[w + 1]

    uv_diff = _ordered(uv_limit) + udc_n
    below = uv_diff[w]
    if arm_chain:
        return above(ov_limit), below, above(uv_limit)
    return above(ov_limit), below, ~below & ~uv_diff[:w].all()


class Protection(wiring.Component):
    """Fault detection and latched trip with a first-cause and all-causes register.

    Parameters
    ----------
    current_width : int
        Width ``w`` of the scaled phase currents (signed, Q1.(w−1) as the Clarke block outputs
        them), 4 … 32.
    udc_shape : Shape
        Shape of the U_dc code from the ADC (``signed(16)`` for the AD7380-4), 2 … 32 bits.
    speed_width : int
        Width of the signed speed (Q1.(w−1) of N_M), 4 … 32.
    uv_arm_chain : bool
        The under-voltage arming's ``udc > uv_limit`` on a carry chain of its own
        (:func:`udc_compares`' ``arm_chain``; the same verdicts: the ECP5's form, where the
        shared chain's AND tree was the critical path); ``False``: two chains (fewer iCE40
        cells).
    trip_register : bool
        ``present``'s OR in a flip-flop of its own beside ``present``, loaded from the same
        terms (the same value in every clock): ``trip`` and the gates behind it start at one
        flip-flop (the ECP5's form, for its Fmax, docs/AREA.md §7.34; default ``True``);
        ``False``: the OR of ``present``'s flip-flops (the iCE40's: each of them then packs
        with the LUT of its term, which no longer also feeds the OR, docs/AREA.md §7.70).
        The same outputs either way.

    Members
    -------
    fault_n : In(1, init=1)
        External fault from the gate driver, active low, already synchronised.
    oc_comp : In(1)
        Fast over-current comparator, active high, already synchronised.
    i : In(stream.Signature(data.StructLayout({"a", "b", "c": signed(w)}), always_ready=True))
        Scaled phase currents (the Clarke block's ``a``, ``b``, ``c``).
    udc : In(stream.Signature(udc_shape, always_ready=True))
        DC-bus voltage code.
    speed : In(stream.Signature(signed(speed_width), always_ready=True))
        Measured speed.
    encoder_illegal, hall_invalid, encoder_hall : In(1)
        Flags from the encoder / Hall front end (1-clock pulses or levels): illegal quadrature
        transition, invalid Hall code, encoder/Hall plausibility failure.
    oc_limit : In(unsigned(w), init=2**w − 1)
        Over-current threshold on ``|i_x|`` (same scale as ``i``); the reset value never trips.
    ov_limit, uv_limit : In(udc_shape, init=max / min code)
        Over- and under-voltage thresholds (the reset values never trip).
    uv_enable : In(1)
        Enables (arms, see the module docstring) the under-voltage check.
    os_limit : In(unsigned(speed_width), init=2**speed_width − 1)
        Over-speed threshold on ``|speed|``; the reset value never trips.
    mask : In(FAULT_LAYOUT, init=all ones)
        Causes to act on; a cleared bit ignores that cause entirely.
    clear : In(1)
        Release strobe: clears the latch, ``first`` and ``seen`` when no cause is present, else
        does nothing.
    trip : Out(1)
        Level, high from the clock after a fault until a successful ``clear``; forces the gates
        off.
    present : Out(FAULT_LAYOUT)
        Causes present now (registered; sampled causes hold their last sample's verdict).
    first : Out(FAULT_LAYOUT)
        The cause(s) present in the clock the latch tripped (several if simultaneous); like
        ``seen`` it is registered, so it shows them from the clock after ``trip`` rose.
    seen : Out(FAULT_LAYOUT)
        Every cause present at any time since the last successful ``clear``.
    uv_armed : Out(1)
        The under-voltage check is armed.

    Attributes
    ----------
    latency : int
        Clocks from a fault input (or a valid sample beyond its limit) to ``trip``: 1.

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its range.
    """

    latency = 1

    def __init__(self, *, current_width=16, udc_shape=signed(16), speed_width=16,
                 uv_arm_chain=False, trip_register=True):
        for name, value in (("current_width", current_width), ("speed_width", speed_width)):
            check_param("Protection", name, value, 4, 32)
        self._uv_arm_chain = check_bool("Protection", "uv_arm_chain", uv_arm_chain)
        self._trip_register = check_bool("Protection", "trip_register", trip_register)
        if not isinstance(udc_shape, Shape) or not 2 <= udc_shape.width <= 32:
            raise TypeError(f"Protection udc_shape must be a Shape of 2 to 32 bits such as "
                            f"signed(16), not {udc_shape!r}")
        self._current_width = current_width
        self._udc_shape = udc_shape
        self._speed_width = speed_width
        u_lo, u_hi = shape_range(udc_shape)
        super().__init__({
            "fault_n": In(1, init=1),
            "oc_comp": In(1),
            "i": In(stream.Signature(
                data.StructLayout({p: signed(current_width) for p in "abc"}), always_ready=True)),
            "udc": In(stream.Signature(udc_shape, always_ready=True)),
            "speed": In(stream.Signature(signed(speed_width), always_ready=True)),
            "encoder_illegal": In(1),
            "hall_invalid": In(1),
            "encoder_hall": In(1),
            "oc_limit": In(unsigned(current_width), init=(1 << current_width) - 1),
            "ov_limit": In(udc_shape, init=u_hi),
            "uv_limit": In(udc_shape, init=u_lo),
            "uv_enable": In(1),
            "os_limit": In(unsigned(speed_width), init=(1 << speed_width) - 1),
            "mask": In(FAULT_LAYOUT, init={name: 1 for name in FAULTS}),
            "clear": In(1),
            "trip": Out(1),
            "present": Out(FAULT_LAYOUT),
            "first": Out(FAULT_LAYOUT),
            "seen": Out(FAULT_LAYOUT),
            "uv_armed": Out(1),
        })

    current_width = property(lambda self: self._current_width)
    udc_shape = property(lambda self: self._udc_shape)
    speed_width = property(lambda self: self._speed_width)
    uv_arm_chain = property(lambda self: self._uv_arm_chain)
    trip_register = property(lambda self: self._trip_register)

    def elaborate(self, platform):
        m = Module()

        # Sampled causes: the verdict of the current sample, else the held one.
        def sampled(name, valid, verdict):
            held = Signal(name=f"held_{name}")
            now = Signal(name=f"now_{name}")
            m.d.comb += now.eq(Mux(valid, verdict, held))
            m.d.sync += held.eq(now)
            return now

        i = self.i.payload
        udc_over, udc_below, udc_above = udc_compares(m, self.udc.payload, self.ov_limit,
                                                      self.uv_limit,
                                                      arm_chain=self._uv_arm_chain)
        armed = Signal()
        with m.If(~self.uv_enable):
            m.d.sync += armed.eq(0)
        with m.Elif(self.udc.valid & udc_above):
            m.d.sync += armed.eq(1)
        m.d.comb += self.uv_armed.eq(armed)

        cause = {
            "external": ~self.fault_n,
            "overcurrent_a": sampled("oc_a", self.i.valid, abs_exceeds(i.a, self.oc_limit)),
            "overcurrent_b": sampled("oc_b", self.i.valid, abs_exceeds(i.b, self.oc_limit)),
            "overcurrent_c": sampled("oc_c", self.i.valid, abs_exceeds(i.c, self.oc_limit)),
            "overcurrent_comparator": self.oc_comp,
            "overvoltage": sampled("ov", self.udc.valid, udc_over),
            "undervoltage": self.uv_enable & armed & sampled("uv", self.udc.valid, udc_below),
            "overspeed": sampled("os", self.speed.valid,
                                 abs_exceeds(self.speed.payload, self.os_limit)),
            "encoder": self.encoder_illegal,
            "hall": self.hall_invalid,
            "encoder_hall": self.encoder_hall,
        }
        assert tuple(cause) == FAULTS

        present = Signal(FAULT_LAYOUT)
        for name in FAULTS:
            m.d.sync += present[name].eq(cause[name] & self.mask[name])
        any_present = Signal()
        if self._trip_register:
            # ``present``'s OR, registered beside it from the same terms (the same value in
            # every clock): the trip and the gates behind it see one flip-flop, not an 11-input
            # OR of flip-flops across the die (ECP5 Fmax, docs/AREA.md §7.34).
            m.d.sync += any_present.eq(
                Cat(cause[name] & self.mask[name] for name in FAULTS).any())
            m.d.comb += Assert(any_present == present.as_value().any(),
                               "protect: the registered OR equals present's OR")
        else:
            m.d.comb += any_present.eq(present.as_value().any())

        latched = Signal()
        first = Signal(FAULT_LAYOUT)
        seen = Signal(FAULT_LAYOUT)
        with m.If(self.clear & ~any_present):
            m.d.sync += [latched.eq(0), first.eq(0), seen.eq(0)]
        with m.Elif(any_present):
            m.d.sync += [latched.eq(1), seen.eq(seen.as_value() | present.as_value())]
            with m.If(~latched):
                m.d.sync += first.eq(present)

        m.d.comb += [
            self.trip.eq(latched | any_present),
            self.present.eq(present),
            self.first.eq(first),
            self.seen.eq(seen),
        ]
        return m
