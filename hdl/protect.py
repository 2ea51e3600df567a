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

With ``limits="ram"`` (the iCE40's form, docs/AREA.md §7.77) the four limits live in a small
RAM and one comparator takes the sampled causes' compares one per clock (the class's
"Sequential compare"): a sampled cause is then seen 1 … 3 clocks later than above (more if
several streams' samples or limit writes meet: :attr:`Protection.step_latency`); the pin
causes keep their timing.
"""

from amaranth.hdl import Assert, Cat, Const, Module, Mux, Shape, Signal, Value, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from .bus import WordWriteSignature
from .fixed import abs_exceeds, check_bool, check_choice, check_param, shape_range

__all__ = ["FAULTS", "FAULT_LAYOUT", "LIMITS", "LIMIT_FORMS", "STEPS", "Protection",
           "step_compare", "step_operand", "step_verdict", "store_limit", "udc_compares"]

#: Cause names, in bit order of :data:`FAULT_LAYOUT` (bit 0 first).
FAULTS = ("external", "overcurrent_a", "overcurrent_b", "overcurrent_c", "overcurrent_comparator",
          "overvoltage", "undervoltage", "overspeed", "encoder", "hall", "encoder_hall")

#: One flag per cause.
FAULT_LAYOUT = data.StructLayout({name: 1 for name in FAULTS})

#: Values of ``Protection(limits=...)``.
LIMIT_FORMS = ("ports", "ram", "ram16")

#: ``limits="ram"``: the limits' words of the limit RAM, in ``limit_wr.index`` order.
LIMITS = ("oc_limit", "ov_limit", "uv_limit", "os_limit")

#: ``limits="ram"``: the sequential compare's steps, in priority order: ``(name, sample,
#: limit)`` (the held verdict it sets, the stream whose sample requests it, the limit word it
#: reads). ``uv`` is ``udc < uv_limit`` (the under-voltage verdict), ``arm`` ``udc > uv_limit``
#: (the arming).
STEPS = (("oc_a", "i", "oc_limit"), ("oc_b", "i", "oc_limit"), ("oc_c", "i", "oc_limit"),
         ("ov", "udc", "ov_limit"), ("uv", "udc", "uv_limit"), ("arm", "udc", "uv_limit"),
         ("os", "speed", "os_limit"))


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


def store_limit(index, word, width, udc_signed):
    """The limit RAM's word (``width`` bits) for ``limit_wr`` word ``word`` at ``index``
    (:data:`LIMITS`): its low ``width`` bits, the top one inverted for a U_dc limit of a signed
    U_dc (offset binary, as :func:`udc_compares` orders the codes)."""
    flip = udc_signed and LIMITS[index] in ("ov_limit", "uv_limit")
    return (word & ((1 << width) - 1)) ^ (flip << (width - 1))


def step_compare(go, i, udc, speed, limit, *, split=None):
    """:func:`step_verdict` of :func:`step_operand`: the comparator of one step as one
    function (the proofs state it so)."""
    x, cin = step_operand(go, i, udc, speed, limit, split=split)
    return step_verdict(x, cin, limit, go["uv"])


def step_verdict(x, cin, limit, uv):
    """The verdict of a step from its operand ``x``, ``cin`` (:func:`step_operand`) and
    ``limit``: the carry out of ``limit + x + cin``, inverted unless ``uv`` (the under-voltage
    step's)."""
    n = len(Value.cast(limit))
    carry = (Cat(cin, limit) + Cat(Const(1, 1), x))[n + 1]
    return carry ^ ~uv


def step_operand(go, i, udc, speed, limit, *, split=None):
    """``Protection(limits="ram")``'s one comparator: ``(X, cin)`` of the step that ``go``
    selects (a dict of one bit per name of :data:`STEPS`, at most one high) on the currents
    ``i`` (a, b, c), ``udc`` and ``speed`` against ``limit``, the limit RAM's word (``n`` bits,
    as :meth:`Protection.stored_limit` stores it).

    One carry chain, the carry out of ``L + X + cin`` on ``n`` bits: for ``|v| > limit`` (the
    currents, the speed) :func:`~.fixed.abs_exceeds`' ``~(v XOR sign)`` with ones above ``v``'s
    magnitude bits and ``cin = ~sign`` (verdict: no carry); for U_dc the inverted offset-binary
    code (``udc`` extended to ``n`` bits, a signed one with its top bit flipped, as the RAM holds
    the U_dc limits) with ``cin = 1`` for ``udc > limit`` (over-voltage, arming; verdict: no
    carry) and ``cin = 0`` for ``udc < limit`` (under-voltage: carry), :func:`udc_compares`'
    forms. The ``abs_compare`` proof shows every step equal to the plain compare.

    ``split`` (``limits="ram16"``): the currents' and U_dc's compares on the low ``split`` bits
    only (U_dc's offset binary at bit ``split − 1``); above them ``X = ~limit`` (the carry
    passes through) but for the speed's, which takes all ``n`` bits."""
    limit = Value.cast(limit)
    udc = Value.cast(udc)
    speed = Value.cast(speed)
    n = len(limit)
    top = n if split is None else split         # the currents' and U_dc's compare width
    cw, sw, uw = len(Value.cast(i.a)), len(speed), len(udc)
    g_i = go["oc_a"] | go["oc_b"] | go["oc_c"]
    g_u = go["ov"] | go["uv"] | go["arm"]
    g_s = go["os"]
    phase = Mux(go["oc_a"], i.a, Mux(go["oc_b"], i.b, i.c))
    s_i, s_s = phase[-1], speed[-1]

    def bits(v, sign, width):
        return [~(v[j] ^ sign) if j < width - 1 else Const(1, 1) for j in range(n)]
    x_i = bits(phase, s_i, cw)
    x_s = bits(speed, s_s, sw)
    if udc.shape().signed:
        x_u = [~udc[j] if j < uw - 1 else ~udc[-1] for j in range(top - 1)] + [udc[-1]]
    else:
        x_u = [~udc[j] if j < uw else Const(1, 1) for j in range(top)]
    xs = [Mux(g_i, x_i[j], Mux(g_u, x_u[j], x_s[j])) if j < top
          else Mux(g_s, x_s[j], ~limit[j]) for j in range(n)]
    x = Cat(xs)
    cin = Mux(g_i, ~s_i, Mux(g_s, ~s_s, ~go["uv"]))
    return x, cin


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
    limits : str
        Where the four limits live and how the sampled causes are compared (:data:`LIMIT_FORMS`):
        ``"ports"`` (default) the ``oc_limit`` … ``os_limit`` ports, a comparator per cause, each
        sample compared in its ``valid`` clock; ``"ram"`` (the iCE40's form, docs/AREA.md §7.77)
        a small RAM written through ``limit_wr`` and **one** comparator that steps through the
        requested compares one per clock (the class's "Sequential compare" below): a sampled
        cause is then seen a few clocks later, the pin causes as before; ``"ram16"`` the same
        with a RAM as wide as the currents and U_dc (one iCE40 block RAM, not two) and the
        over-speed limit's upper bits in flip-flops (:attr:`ram_width`).
    limit_init : sequence of 4 int or None
        ``limits="ram"`` / ``"ram16"``: the limit RAM's initial words (:data:`LIMITS` order, in
        the format ``limit_wr`` carries); ``None``: the ports' reset values (never trip).

    Sequential compare (``limits="ram"``)
    -------------------------------------
    A valid sample requests its compares (:data:`STEPS`: ``i`` the three over-currents,
    ``udc`` over-voltage, under-voltage and the arming, ``speed`` over-speed); every clock
    without a ``limit_wr`` write the first requested step in :data:`STEPS` order (this clock's
    requests included) is taken: its limit word is read from the RAM and its operand taken from
    the payload in that clock (both registered), and in the next the one comparator compares
    them and its verdict acts as the parallel form's verdict in a ``valid`` clock. So a step's
    verdict reaches ``present`` two clocks after it is taken, i.e. ``1 + (steps taken before it) + (write clocks waited)`` clocks
    later than the parallel form's (the first over-current 1, the third 3; all seven requested
    at once: the over-speed 7 clocks later); a step compares the payload of the clock it is
    taken in, so the payload must hold until then (the Top's are registers that hold for a PWM
    period; a second sample of a stream before its steps are taken is compared in their place,
    the first one's verdict never seen; samples of a stream less than 7 clocks apart can keep
    the later steps waiting); a limit written in clock ``w`` is used by the steps taken from
    ``w + 1`` on. The under-voltage and arming steps read the under-voltage limit in their own
    clocks.

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
    limit_wr : In(WordWriteSignature(4))
        Only with ``limits="ram"`` / ``"ram16"`` (in place of the four limit ports): a write
        of limit word ``index`` (:data:`LIMITS`) with ``data``, the limit as a 32-bit word, a
        signed one sign-extended (the register file's read format); the RAM holds it from the
        next clock.
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
        Clocks from a fault input (or, with ``limits="ports"``, a valid sample beyond its limit)
        to ``trip``: 1.
    step_latency : dict
        ``limits="ram"``: per sampled cause, the clocks from its valid sample alone (no other
        step requested, no limit write) to ``trip``: ``latency`` + 1 + the steps before it in
        :data:`STEPS` requested by the same sample; ``limits="ports"``: ``latency`` for each.

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its range.
    """

    latency = 1

    def __init__(self, *, current_width=16, udc_shape=signed(16), speed_width=16,
                 uv_arm_chain=False, trip_register=True, limits="ports", limit_init=None):
        for name, value in (("current_width", current_width), ("speed_width", speed_width)):
            check_param("Protection", name, value, 4, 32)
        self._uv_arm_chain = check_bool("Protection", "uv_arm_chain", uv_arm_chain)
        self._trip_register = check_bool("Protection", "trip_register", trip_register)
        self._limits = check_choice("Protection", "limits", limits, LIMIT_FORMS)
        if not isinstance(udc_shape, Shape) or not 2 <= udc_shape.width <= 32:
            raise TypeError(f"Protection udc_shape must be a Shape of 2 to 32 bits such as "
                            f"signed(16), not {udc_shape!r}")
        self._current_width = current_width
        self._udc_shape = udc_shape
        self._speed_width = speed_width
        u_lo, u_hi = shape_range(udc_shape)
        resets = ((1 << current_width) - 1, u_hi & 0xFFFF_FFFF, u_lo & 0xFFFF_FFFF,
                  (1 << speed_width) - 1)
        if limit_init is None:
            limit_init = resets
        elif limits == "ports":
            raise ValueError(f"Protection limit_init applies only to limits='ram' or 'ram16', "
                             f"not limits={limits!r}")
        elif (not isinstance(limit_init, (tuple, list)) or len(limit_init) != len(LIMITS)
              or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 1 << 32
                         for v in limit_init)):
            raise TypeError(f"Protection limit_init must be 4 integers from 0 to 2**32 - 1 "
                            f"(the words of {', '.join(LIMITS)}), not {limit_init!r}")
        self._limit_init = tuple(limit_init)
        if limits != "ports":
            lim_members = {"limit_wr": In(WordWriteSignature(len(LIMITS)))}
        else:
            lim_members = {
                "oc_limit": In(unsigned(current_width), init=(1 << current_width) - 1),
                "ov_limit": In(udc_shape, init=u_hi),
                "uv_limit": In(udc_shape, init=u_lo),
                "os_limit": In(unsigned(speed_width), init=(1 << speed_width) - 1),
            }
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
            **{k: v for k, v in lim_members.items() if k in ("oc_limit", "ov_limit",
                                                               "uv_limit", "limit_wr")},
            "uv_enable": In(1),
            **{k: v for k, v in lim_members.items() if k == "os_limit"},
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
    limits = property(lambda self: self._limits)
    limit_init = property(lambda self: self._limit_init)

    @property
    def step_latency(self):
        """Per sampled cause: clocks from its valid sample alone to ``trip`` (class docstring)."""
        causes = {"oc_a": "overcurrent_a", "oc_b": "overcurrent_b", "oc_c": "overcurrent_c",
                  "ov": "overvoltage", "uv": "undervoltage", "os": "overspeed"}
        if self._limits == "ports":
            return {c: self.latency for c in causes.values()}
        out = {}
        for k, (name, src, _) in enumerate(STEPS):
            if name in causes:
                before = sum(1 for s in STEPS[:k] if s[1] == src)
                out[causes[name]] = self.latency + 1 + before
        return out

    def elaborate(self, platform):
        m = Module()

        # Sampled causes: the verdict of the current sample (its compare clock), else the
        # held one.
        def sampled(name, valid, verdict):
            held = Signal(name=f"held_{name}")
            now = Signal(name=f"now_{name}")
            m.d.comb += now.eq(Mux(valid, verdict, held))
            m.d.sync += held.eq(now)
            return now

        i = self.i.payload
        if self._limits != "ports":
            go, verdict = self._sequential(m)
            test = {name: (go[k], verdict) for k, (name, _, _) in enumerate(STEPS)}
            udc_arm = go[[s[0] for s in STEPS].index("arm")] & verdict
        else:
            udc_over, udc_below, udc_above = udc_compares(m, self.udc.payload, self.ov_limit,
                                                          self.uv_limit,
                                                          arm_chain=self._uv_arm_chain)
            test = {"oc_a": (self.i.valid, abs_exceeds(i.a, self.oc_limit)),
                    "oc_b": (self.i.valid, abs_exceeds(i.b, self.oc_limit)),
                    "oc_c": (self.i.valid, abs_exceeds(i.c, self.oc_limit)),
                    "ov": (self.udc.valid, udc_over), "uv": (self.udc.valid, udc_below),
                    "os": (self.speed.valid, abs_exceeds(self.speed.payload, self.os_limit))}
            udc_arm = self.udc.valid & udc_above
        armed = Signal()
        with m.If(~self.uv_enable):
            m.d.sync += armed.eq(0)
        with m.Elif(udc_arm):
            m.d.sync += armed.eq(1)
        m.d.comb += self.uv_armed.eq(armed)

        cause = {
            "external": ~self.fault_n,
            "overcurrent_a": sampled("oc_a", *test["oc_a"]),
            "overcurrent_b": sampled("oc_b", *test["oc_b"]),
            "overcurrent_c": sampled("oc_c", *test["oc_c"]),
            "overcurrent_comparator": self.oc_comp,
            "overvoltage": sampled("ov", *test["ov"]),
            "undervoltage": self.uv_enable & armed & sampled("uv", *test["uv"]),
            "overspeed": sampled("os", *test["os"]),
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

    def _chain_width(self):
        """``limits="ram"``: the one comparator's width: the widest compare's."""
        return max(self._current_width, self._udc_shape.width, self._speed_width)

    @property
    def ram_width(self):
        """``limits="ram"`` / ``"ram16"``: the limit RAM's width (the comparator's, or with
        ``"ram16"`` the currents' and U_dc's: the over-speed limit's bits above it are
        flip-flops); ``None`` with ``"ports"``."""
        if self._limits == "ports":
            return None
        n = self._chain_width()
        if self._limits == "ram":
            return n
        return min(n, max(self._current_width, self._udc_shape.width))

    def stored_limit(self, index, word):
        """``limits="ram"`` / ``"ram16"``: the limit the comparator sees for ``limit_wr`` word
        ``word`` at ``index``: its low :meth:`_chain_width` bits (``"ram16"``: the low
        :attr:`ram_width` bits but the over-speed limit's), the top one inverted for a U_dc
        limit of a signed ``udc_shape`` (offset binary, as :func:`udc_compares` orders the
        codes)."""
        width = self._chain_width() if LIMITS[index] == "os_limit" else self.ram_width
        return store_limit(index, word, width, self._udc_shape.signed)

    def _sequential(self, m):
        """``limits="ram"``: the limit RAM, the step sequencer and the one comparator (class
        docstring, "Sequential compare"). Returns ``(go, verdict)``: ``go`` one bit per step
        of :data:`STEPS`, high in its compare clock, and that compare's verdict
        (:func:`step_compare`)."""
        n = self._chain_width()
        w_ram = self.ram_width
        u_signed = self._udc_shape.signed
        wr = self.limit_wr
        mask = (1 << w_ram) - 1
        mem = Memory(shape=w_ram, depth=len(LIMITS),
                     init=[self.stored_limit(k, w) & mask
                           for k, w in enumerate(self._limit_init)],
                     attrs={"ram_style": "block", "no_rw_check": 1})
        m.submodules.limits = mem
        wp = mem.write_port()
        # The read port asynchronous with a register behind it, which yosys merges into the
        # block RAM's synchronous port (an Amaranth synchronous port would ask for the old
        # word in a write clock, which yosys emulates with flip-flops and multiplexers): no
        # step is taken in a write clock (the sequencer waits), so its word is never used
        # (``no_rw_check``).
        rp = mem.read_port(domain="comb")
        rd_data = Signal(w_ram, name="limit_rd", reset_less=True)
        m.d.sync += rd_data.eq(rp.data)
        flip = Const(0, 1)
        if u_signed:
            flip = (wr.index == LIMITS.index("ov_limit")) | (wr.index == LIMITS.index("uv_limit"))
        m.d.comb += [wp.en.eq(wr.valid), wp.addr.eq(wr.index),
                     wp.data.eq(Cat(wr.data[:w_ram - 1], wr.data[w_ram - 1] ^ flip))]
        limit, split = rd_data, None
        if w_ram < n:
            # "ram16": the over-speed limit's bits above the RAM's in flip-flops, loaded with
            # its write (read by the over-speed step only; the other steps pass the carry
            # through them).
            os_k = LIMITS.index("os_limit")
            os_hi = Signal(n - w_ram, name="limit_os_hi", init=self._limit_init[os_k] >> w_ram)
            with m.If(wr.valid & (wr.index == os_k)):
                m.d.sync += os_hi.eq(wr.data[w_ram:n])
            limit, split = Cat(rd_data, os_hi), w_ram

        # The sequencer: requests, the first one taken in each clock without a write.
        names = [s[0] for s in STEPS]
        valid = {"i": self.i.valid, "udc": self.udc.valid, "speed": self.speed.valid}
        req = Cat(valid[src] for _, src, _ in STEPS)
        pend = Signal(len(STEPS), name="step_pend")
        want = Signal(len(STEPS), name="step_want")
        pick = Signal(len(STEPS), name="step_pick")
        go = Signal(len(STEPS), name="step_go")
        m.d.comb += want.eq(pend | req)
        for k in range(len(STEPS)):
            first = want[k] if k == 0 else want[k] & ~want[:k].any()
            m.d.comb += pick[k].eq(first & ~wr.valid)
        m.d.sync += [pend.eq(want & ~pick), go.eq(pick)]
        word = [LIMITS.index(lim) for _, _, lim in STEPS]
        m.d.comb += rp.addr.eq(Cat(Cat(pick[k] for k in range(len(STEPS)) if word[k] >> b & 1)
                                   .any() for b in range(len(rp.addr))))

        # The step's operand formed from the payloads in the clock it is taken (``pick``) and
        # registered beside the RAM's word (iCE40 Fmax: the operand multiplexer in front of
        # the 33-bit chain missed 33.333 MHz), compared in the next clock (``go``).
        x, cin = step_operand({name: pick[k] for k, name in enumerate(names)}, self.i.payload,
                              self.udc.payload, self.speed.payload, limit, split=split)
        x_q = Signal(len(x), name="cmp_x", reset_less=True)
        cin_q = Signal(name="cmp_cin", reset_less=True)
        m.d.sync += [x_q.eq(x), cin_q.eq(cin)]
        verdict = Signal(name="cmp_verdict")
        m.d.comb += verdict.eq(step_verdict(x_q, cin_q, limit,
                                            go[names.index("uv")]))
        return go, verdict
