# Ref: paper eq. (1) (Clarke), (4)–(6) (Park / inverse Park by CORDIC), (7)–(9) (PI), Fig. 7
#      (SVPWM); SPEC.md §2 (current loop), §2.5 (DC-bus compensation); issue 5 item 4
"""The current loop: ADC sample → Clarke → Park → PI_d, PI_q → inverse Park → DC-bus
compensation → SVPWM → duties, once per accepted ADC sample.

One rotator serves both rotations (``tag`` 0: Park by −θ, ``tag`` 1: inverse Park by
θ + θ_lead); the two passes are serial in time. It is the sine-table :class:`~.rotator.Rotator`
(``rotator="table"``, default) or the unrolled :class:`~.cordic.Cordic` (``rotator="cordic"``);
both have the same ports; the table rotator takes 9 clocks (``L_cordic`` below), the CORDIC 8
at the defaults (the offsets below are for the table). Per accepted sample (``t`` = the clock
``i.valid`` is accepted; ``L_x`` the blocks' ``latency`` attributes)::

    t                     inputs latched (θ, θ_lead, references, mode bits, speed, U_dc)
    t + 1                 −θ and θ + θ_lead from the latched angles
    t + L_clarke          i_a, i_b, i_c, i_α, i_β                      → Cordic, tag 0, angle −θ
    t + 6 + L_cordic      i_d, i_q                                     → PI_d, PI_q
    t + 15 + L_pi         PI outputs; command stage (one register):
                              u_d = ol_ud                              if ol
                                    sat(PI_d + [ff]·(−ω·L·i_q))        otherwise
                              u_q = ol_uq                              if ol
                                    sat(PI_q + [ff]·(ω·(L·i_d + ψ)))   otherwise
    t + 22                u_d, u_q                                     → Cordic, tag 1, θ + θ_lead
    t + 22 + L_cordic     u_α, u_β                                     → DCBusCompensation
    t + 31 + L_dcbus      u_α·U_rated/U_dc (Q2.15: no angle error below 2)  → SVPWM
    t + 33 + L_svpwm      duties on ``o``                              (48 clocks with defaults)

Every stage puts at most one multiplier or about one carry chain between registers (100 MHz on
an ECP5, issue 7); the budget of issue 5 is ≤ 50 clocks.

``sat`` saturates to ``signed(width)``, nothing wraps except the binary angles. The decoupling
feed-forward (``ff_enable``) uses one multiplier four times (operands, product and rounding
each registered) while the PIs run (no extra latency); each term is then registered once more,
saturated to signed(w + 1) (the commands do not change: a PI output in signed(w) plus or minus a
term beyond ±2**w saturates as with ±2**w), so that the command stage adds w + 1 bits::

    n      = sat(round_shift(speed, 32 − w))                  Q1.(w−1) of N_FS (speed: Q1.31)
    ωL     = round_shift(ff_l · n, 14)                        Q3.(w−1), exact in signed(w + 2)
    e      = round_shift(ff_psi · n, 14)                      Q3.(w−1), exact in signed(w + 2)
    ff_d   = −round_shift(ωL · i_q, w − 1)                    exact in signed(w + 5)
    ff_q   = round_shift(ωL · i_d, w − 1) + e                 exact in signed(w + 5)

with ``ff_l = ω_e(N_FS)·L·I_FS / U_base`` and ``ff_psi = ω_e(N_FS)·ψ / U_base`` in UQ(16, 14)
(0 … 3.99994; ``U_base = (2/3)·U_rated``, the voltage of a modulation index of 1.0 after the
DC-bus compensation, ``ω_e(N_FS)`` the electrical angular speed at the full-scale speed).

The DC-bus gain ``U_rated/U_dc`` takes ``DCBusCompensation.gain_latency`` (38) clocks to compute,
longer than the path to the compensation (31): each sample is compensated with the bus voltage of
the *previous* accepted sample (1.0 before the first one).
"""


from amaranth.hdl import Assert, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .clarke import Clarke
from .cordic import Cordic
from .rotator import Rotator
from .dsp import MUL_WIDTH, check_mul_width, round_shift_signed, saturate_bits
from .fixed import is_int, check_param, UQ, Q, QFormat, round_shift
from .pi import PI
from .svpwm import SVPWM, DCBusCompensation

__all__ = ["CurrentLoop", "FF_FORMAT", "SPEED_WIDTH", "ADC_CHANNELS", "sample_handshake"]

#: Format of the decoupling scale inputs ``ff_l`` and ``ff_psi``.
FF_FORMAT = UQ(16, 14)
#: Width of the ``speed`` input, Q1.31 of the full-scale speed.
SPEED_WIDTH = 32
#: Fields of the ADC sample stream (as :class:`~.adc.AdcInterface` produces it).
ADC_CHANNELS = ("ia", "ib", "udc", "aux")

#: The ``rotator`` choices of :class:`CurrentLoop`.
ROTATORS = ("table", "cordic")

#: Cordic ``tag`` values.
TAG_PARK, TAG_INVERSE = 0, 1


def sample_handshake(m, loop):
    """The sample handshake of a current loop (:class:`CurrentLoop`, and
    :class:`~.foc_engine.EngineCurrentLoop`): a sample on ``loop.i`` is accepted unless ``busy``
    (or in the clock its duties are taken, ``done``); one arriving while busy is dropped and
    strobes ``overrun``, counted (saturating) in ``overruns``; ``count`` counts the ``done``
    transfers. Drives ``done``, ``overrun``, ``busy``, ``count``, ``overruns`` into ``m``.

    Returns
    -------
    (accept, done) : (Value, Value)
        The clock a sample is accepted; the clock the duties are taken (``o.valid & o.ready``).
    """
    done = loop.o.valid & loop.o.ready
    accept = loop.i.valid & (~loop.busy | done)
    m.d.comb += [loop.done.eq(done), loop.overrun.eq(loop.i.valid & ~accept)]
    with m.If(accept):
        m.d.sync += loop.busy.eq(1)
    with m.Elif(done):
        m.d.sync += loop.busy.eq(0)
    with m.If(done):
        m.d.sync += loop.count.eq(loop.count + 1)
    overruns_max = (1 << len(loop.overruns)) - 1
    with m.If(loop.overrun & (loop.overruns != overruns_max)):
        m.d.sync += loop.overruns.eq(loop.overruns + 1)
    return accept, done


class CurrentLoop(wiring.Component):
    """Field-oriented current loop, one computation per accepted ADC sample (trigger driven).

    Sequential: a sample is accepted when the loop is idle (or in the clock its duties are
    taken); a sample arriving while ``busy`` is dropped, counted in ``overruns`` and flagged on
    ``overrun``. Run it once per PWM period (sample at the centre) or twice (peak and valley): the
    loop only needs ``latency`` clocks between samples.

    Parameters
    ----------
    width : int
        Width ``w`` of currents, references, voltage commands and limits, all Q1.(w−1): currents
        of the current full scale I_FS, voltages (modulation indices) of (2/3)·U_dc. 8 … 23.
    adc_width : int
        Width of the ADC codes (signed), 4 … 24 (16 for the AD7380-4).
    angle_width : int
        Width of θ, a ``BinaryAngle(angle_width)`` (a full turn is ``2**angle_width``), 4 … 32.
    count_width : int
        Width of the SVPWM scale and the duties, 4 … 24.
    rotator : str
        The shared rotator of Park and inverse Park: ``"table"`` (default,
        :class:`~.rotator.Rotator`: quarter-wave sine table in block RAM + 2 multipliers, 9 clocks,
        registered for ≥ 100 MHz on ECP5; ≈ 480 LUT4) or ``"cordic"``
        (:class:`~.cordic.Cordic`, unrolled, no RAM and no multiplier; ≈ 2 240 LUT4).
    iterations_per_stage : int
        CORDIC iterations per pipeline register (3: 8 clocks per pass at 16 bits); used by
        ``rotator="cordic"`` only.
    clarke_gain_format, kp_format, kx_format, int_guard, gain_limit
        Passed to :class:`~.clarke.Clarke` (``gain_format``), :class:`~.pi.PI` (both regulators)
        and :class:`~.svpwm.DCBusCompensation`.
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None`` (:mod:`~.dsp`:
        18 ECP5 / Xilinx, the default; ``None`` iCE40: products not split), passed to Clarke, the
        PIs, the DC-bus compensation and the SVPWM: it chooses how their products are split into
        partial products, never a result.

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"ia", "ib", "udc", "aux": signed(adc_width)}),
        always_ready=True))
        ADC sample (``AdcInterface.o``): phase-current codes ``ia``, ``ib``, bus-voltage code
        ``udc`` (negative codes count as 0), ``aux`` unused. Each transfer triggers the loop.
    theta : In(unsigned(angle_width))
        Electrical angle θ_e at the sampling instant (latched with the sample): Park rotates by −θ.
    theta_lead : In(unsigned(angle_width))
        Added (wrapping) to θ for the inverse Park, e.g. ω·1.5·T_pwm to compensate the delay until
        the duties act; 0 for none. Latched with the sample.
    id_ref, iq_ref : In(signed(w))
        Current references, Q1.(w−1) of I_FS, latched with the sample.
    enable : In(1)
        Closed-loop current control. Latched with the sample: while it (or ``ol_enable``) was low
        the PIs are held cleared (integrator and previous error 0, output 0).
    ol_enable : In(1)
        Open-loop override, latched with the sample: u_d, u_q come from ``ol_ud``, ``ol_uq``
        (PIs cleared, no feed-forward); θ is whatever drives ``theta``.
    ol_ud, ol_uq : In(signed(w))
        Open-loop voltage commands, Q1.(w−1), latched with the sample.
    ff_enable : In(1)
        d–q decoupling feed-forward (off by default), latched with the sample; only acts in closed
        loop.
    speed : In(signed(32))
        Mechanical speed, Q1.31 of N_FS, latched with the sample (for the feed-forward).
    ff_l, ff_psi : In(unsigned(16))
        Feed-forward scales, UQ(16, 14): ``ω_e(N_FS)·L·I_FS / U_base`` and
        ``ω_e(N_FS)·ψ / U_base`` (module docstring).
    gain_a, gain_b : In(clarke_gain_format.shape)
        Current scaling, current LSB per ADC LSB (Q(18, 15) by default).
    offset_a, offset_b : In(signed(adc_width + 1))
        Zero-current codes.
    kp_d, kx_d, kp_q, kx_q : In(kp_format.shape), In(kx_format.shape)
        PI gains (``kx = K_i·T_s/2``), raw formats of :class:`~.pi.PI`.
    lim_lo_d, lim_hi_d, lim_lo_q, lim_hi_q : In(signed(w))
        PI output limits, Q1.(w−1).
    u_rated : In(unsigned(adc_width))
        Rated bus voltage as an ADC code (DC-bus compensation: u · U_rated / U_dc).
    scale : In(unsigned(count_width))
        Count of a 100 % duty (``PWMTimer.full_scale``).
    o : Out(stream.Signature(data.StructLayout({"a", "b", "c": unsigned(count_width)})))
        Duties in counts, for ``PWMTimer.duty`` (held until ``o.ready``).
    overmod : Out(1)
        The last command was outside the hexagon (scaled back along its angle).
    phase : Out(stream.Signature(data.StructLayout({"a", "b", "c": signed(w)}),
        always_ready=True))
        Scaled phase currents (``c = sat(−a − b)``), ``latency_clarke`` clocks after the sample:
        for :class:`~.protect.Protection`. Holds between samples.
    udc : Out(stream.Signature(signed(adc_width), always_ready=True))
        Bus-voltage code, one clock after the sample (for :class:`~.protect.Protection`).
    i_alpha, i_beta, i_d, i_q, u_d, u_q, u_alpha, u_beta : Out(signed(w))
        Status / scope values of the last sample, Q1.(w−1) (u_α, u_β before the DC-bus
        compensation). Each updates when its stage completes and then holds.
    sat_d, sat_q : Out(1)
        The PI's last output was clamped to a limit.
    dc_limited : Out(1)
        The DC-bus gain is at its limit (bus too low).
    busy : Out(1)
        A sample is in flight (from the clock after acceptance to the duty transfer).
    overrun : Out(1)
        One-clock strobe: a sample arrived while busy and was dropped.
    overruns : Out(16)
        Dropped samples, saturating.
    count : Out(32)
        Completed loops (duty transfers), wrapping.
    done : Out(1)
        One-clock strobe with each duty transfer: every status value of this sample is final.

    Configuration inputs (gains, limits, scaling, ``ff_l``, ``ff_psi``, ``u_rated``, ``scale``)
    must not change while ``busy`` (the register file updates them at loop boundaries).

    Attributes
    ----------
    latency : int
        Clocks from the accepted sample to ``o.valid``: the sum of :attr:`stage_latency`.
    stage_latency : dict of str to int
        ``clarke``, ``park``, ``pi``, ``command``, ``inverse_park``, ``dcbus``, ``svpwm``.
    dq_latency : int
        Clocks from the accepted sample to ``i_d``/``i_q`` being updated (visible).
    phase_latency : int
        Clocks from the accepted sample to the ``phase`` transfer (the Clarke stage).

    Raises
    ------
    TypeError
        A parameter of the wrong type or outside its basic range (sub-blocks check theirs).
    """

    def __init__(self, *, width=16, adc_width=16, angle_width=16, count_width=16,
                 rotator="table", iterations_per_stage=3, clarke_gain_format=Q(18, 15),
                 kp_format=UQ(16, 8), kx_format=UQ(16, 16), int_guard=8, gain_limit=2.0,
                 mul_width=MUL_WIDTH):
        for name, value, lo, hi in (("width", width, 8, 23), ("adc_width", adc_width, 4, 24),
                                    ("angle_width", angle_width, 4, 32),
                                    ("count_width", count_width, 4, 24)):
            check_param("CurrentLoop", name, value, lo, hi)
        if rotator not in ROTATORS:
            raise ValueError(f"CurrentLoop rotator must be one of {', '.join(ROTATORS)}, "
                             f"not {rotator!r}")
        if not is_int(iterations_per_stage) or iterations_per_stage < 1:
            raise TypeError(f"CurrentLoop iterations_per_stage must be a positive integer, "
                            f"not {iterations_per_stage!r}")
        if not isinstance(clarke_gain_format, QFormat):
            raise TypeError(f"CurrentLoop clarke_gain_format must be a QFormat, "
                            f"not {clarke_gain_format!r}")
        mw = self._mul_width = check_mul_width("CurrentLoop", mul_width)
        self._width = width
        self._adc_width = adc_width
        self._angle_width = angle_width
        self._count_width = count_width
        self._clarke = Clarke(width=width, adc_shape=signed(adc_width),
                              gain_format=clarke_gain_format, mul_width=mw)
        self._rotator = rotator
        if rotator == "table":
            self._cordic = Rotator(width=width, angle_width=angle_width, tag_width=1,
                                   registered=True)
        else:
            self._cordic = Cordic(width=width, angle_width=angle_width,
                                  iterations_per_stage=iterations_per_stage, tag_width=1)
        self._pi_d = PI(width=width, kp_format=kp_format, kx_format=kx_format,
                        int_guard=int_guard, mul_width=mw)
        self._pi_q = PI(width=width, kp_format=kp_format, kx_format=kx_format,
                        int_guard=int_guard, mul_width=mw)
        self._dcbus = DCBusCompensation(width=width, out_width=width + 1, adc_width=adc_width,
                                        gain_limit=gain_limit, mul_width=mw)
        self._svpwm = SVPWM(width=width + 1, frac=width - 1, count_width=count_width,
                            mul_width=mw)
        self._stage_latency = {
            "clarke": self._clarke.latency,
            "park": self._cordic.latency,
            "pi": self._pi_d.latency,
            "command": 1,
            "inverse_park": self._cordic.latency,
            "dcbus": self._dcbus.latency,
            "svpwm": self._svpwm.latency,
        }

        w, aw = width, angle_width
        sw = signed(w)
        members = {
            "i": In(stream.Signature(data.StructLayout(
                {name: signed(adc_width) for name in ADC_CHANNELS}), always_ready=True)),
            "theta": In(unsigned(aw)),
            "theta_lead": In(unsigned(aw)),
            "id_ref": In(sw),
            "iq_ref": In(sw),
            "enable": In(1),
            "ol_enable": In(1),
            "ol_ud": In(sw),
            "ol_uq": In(sw),
            "ff_enable": In(1),
            "speed": In(signed(SPEED_WIDTH)),
            "ff_l": In(FF_FORMAT.shape),
            "ff_psi": In(FF_FORMAT.shape),
            "gain_a": In(clarke_gain_format.shape),
            "gain_b": In(clarke_gain_format.shape),
            "offset_a": In(signed(adc_width + 1)),
            "offset_b": In(signed(adc_width + 1)),
            "kp_d": In(kp_format.shape),
            "kx_d": In(kx_format.shape),
            "lim_lo_d": In(sw),
            "lim_hi_d": In(sw),
            "kp_q": In(kp_format.shape),
            "kx_q": In(kx_format.shape),
            "lim_lo_q": In(sw),
            "lim_hi_q": In(sw),
            "u_rated": In(unsigned(adc_width)),
            "scale": In(unsigned(count_width)),
            "o": Out(stream.Signature(data.StructLayout(
                {p: unsigned(count_width) for p in "abc"}))),
            "overmod": Out(1),
            "phase": Out(stream.Signature(data.StructLayout({p: sw for p in "abc"}),
                                          always_ready=True)),
            "udc": Out(stream.Signature(signed(adc_width), always_ready=True)),
            **{name: Out(sw) for name in ("i_alpha", "i_beta", "i_d", "i_q",
                                          "u_d", "u_q", "u_alpha", "u_beta")},
            "sat_d": Out(1),
            "sat_q": Out(1),
            "dc_limited": Out(1),
            "busy": Out(1),
            "overrun": Out(1),
            "overruns": Out(16),
            "count": Out(32),
            "done": Out(1),
        }
        super().__init__(members)

    width = property(lambda self: self._width)
    adc_width = property(lambda self: self._adc_width)
    angle_width = property(lambda self: self._angle_width)
    count_width = property(lambda self: self._count_width)
    mul_width = property(lambda self: self._mul_width)
    stage_latency = property(lambda self: dict(self._stage_latency))
    latency = property(lambda self: sum(self._stage_latency.values()))
    cordic_params = property(lambda self: self._cordic.params)
    pi_widths = property(lambda self: self._pi_d.widths)

    @property
    def phase_latency(self):
        return self._stage_latency["clarke"]

    @property
    def dq_latency(self):
        s = self._stage_latency
        return s["clarke"] + s["park"] + 1

    def elaborate(self, platform):
        m = Module()
        w, aw = self._width, self._angle_width
        sw = signed(w)
        m.submodules.clarke = clarke = self._clarke
        m.submodules.cordic = cordic = self._cordic
        m.submodules.pi_d = pi_d = self._pi_d
        m.submodules.pi_q = pi_q = self._pi_q
        m.submodules.dcbus = dcbus = self._dcbus
        m.submodules.svpwm = svpwm = self._svpwm

        # --- Trigger, busy, overrun, loop counter ------------------------------------------------
        accept, done = sample_handshake(m, self)

        # --- Per-sample inputs, latched with the sample -------------------------------------------
        theta = Signal(unsigned(aw))
        theta_lead = Signal(unsigned(aw))
        theta_park = Signal(unsigned(aw))       # −θ, one clock after the sample
        theta_inv = Signal(unsigned(aw))        # θ + θ_lead, one clock after the sample
        id_ref = Signal(sw)
        iq_ref = Signal(sw)
        run = Signal()                      # closed loop: PIs run (else held cleared)
        ol = Signal()
        ol_ud = Signal(sw)
        ol_uq = Signal(sw)
        ff_run = Signal()
        n_spd = Signal(sw)                 # speed, Q1.(w−1)
        with m.If(accept):
            m.d.sync += [
                theta.eq(self.theta),
                theta_lead.eq(self.theta_lead),
                id_ref.eq(self.id_ref),
                iq_ref.eq(self.iq_ref),
                run.eq(self.enable & ~self.ol_enable),
                ol.eq(self.ol_enable),
                ol_ud.eq(self.ol_ud),
                ol_uq.eq(self.ol_uq),
                ff_run.eq(self.ff_enable & self.enable & ~self.ol_enable),
                n_spd.eq(saturate_bits(round_shift(self.speed, SPEED_WIDTH - w), sw)),
                self.udc.payload.eq(self.i.payload.udc),
            ]
        m.d.sync += self.udc.valid.eq(accept)
        # The angle sums from the latched inputs, a clock later (Park needs −θ at
        # t + L_clarke, the inverse Park θ + θ_lead at t + 21): no adder behind the encoder's.
        accepted = Signal()
        m.d.sync += accepted.eq(accept)
        with m.If(accepted):
            m.d.sync += [theta_park.eq(-theta), theta_inv.eq(theta + theta_lead)]

        # --- Clarke ------------------------------------------------------------------------------
        m.d.comb += [
            clarke.i.valid.eq(accept),
            clarke.i.payload.a.eq(self.i.payload.ia),
            clarke.i.payload.b.eq(self.i.payload.ib),
            clarke.gain_a.eq(self.gain_a),
            clarke.gain_b.eq(self.gain_b),
            clarke.offset_a.eq(self.offset_a),
            clarke.offset_b.eq(self.offset_b),
            self.phase.valid.eq(clarke.o.valid),
            self.phase.payload.a.eq(clarke.o.payload.a),
            self.phase.payload.b.eq(clarke.o.payload.b),
            self.phase.payload.c.eq(clarke.o.payload.c),
            self.i_alpha.eq(clarke.o.payload.alpha),
            self.i_beta.eq(clarke.o.payload.beta),
        ]

        # --- The Cordic, shared: Park (tag 0) then inverse Park (tag 1) --------------------------
        cmd_valid = Signal()
        with m.If(clarke.o.valid):
            m.d.comb += [
                cordic.i.payload.x.eq(clarke.o.payload.alpha),
                cordic.i.payload.y.eq(clarke.o.payload.beta),
                cordic.i.payload.theta.eq(theta_park),
                cordic.i.payload.tag.eq(TAG_PARK),
            ]
        with m.Else():
            m.d.comb += [
                cordic.i.payload.x.eq(self.u_d),
                cordic.i.payload.y.eq(self.u_q),
                cordic.i.payload.theta.eq(theta_inv),
                cordic.i.payload.tag.eq(TAG_INVERSE),
            ]
        m.d.comb += cordic.i.valid.eq(clarke.o.valid | cmd_valid)
        park_valid = cordic.o.valid & (cordic.o.payload.tag == TAG_PARK)
        inv_valid = cordic.o.valid & (cordic.o.payload.tag == TAG_INVERSE)
        with m.If(park_valid):
            m.d.sync += [self.i_d.eq(cordic.o.payload.x), self.i_q.eq(cordic.o.payload.y)]
        with m.If(inv_valid):
            m.d.sync += [self.u_alpha.eq(cordic.o.payload.x),
                         self.u_beta.eq(cordic.o.payload.y)]

        # --- PI_d, PI_q ---------------------------------------------------------------------------
        for pi, ref, fb, axis in ((pi_d, id_ref, cordic.o.payload.x, "d"),
                                  (pi_q, iq_ref, cordic.o.payload.y, "q")):
            m.d.comb += [
                pi.clear.eq(~run),
                pi.i.valid.eq(park_valid),
                pi.i.payload.ref.eq(ref),
                pi.i.payload.fb.eq(fb),
                pi.kp.eq(getattr(self, f"kp_{axis}")),
                pi.kx.eq(getattr(self, f"kx_{axis}")),
                pi.lim_lo.eq(getattr(self, f"lim_lo_{axis}")),
                pi.lim_hi.eq(getattr(self, f"lim_hi_{axis}")),
                getattr(self, f"sat_{axis}").eq(pi.sat),
            ]
        # The PI latency counted from the Park result (the PIs give no strobe while cleared).
        pi_delay = [park_valid]
        for k in range(1, pi_d.latency + 1):
            s = Signal(name=f"pi_wait{k}")
            m.d.sync += s.eq(pi_delay[-1])
            pi_delay.append(s)
        pi_done = pi_delay[-1]
        m.d.comb += Assert(~(pi_done & run) | (pi_d.o.valid & pi_q.o.valid),
                           "CurrentLoop: PI result missing")

        # --- Decoupling feed-forward: one multiplier, four products -------------------------------
        # Operands registered, then the product, then its rounding (with the product's sign
        # from the operands'): one multiplier or one adder per clock. ff_d is kept as
        # +round(ωL·i_q) and subtracted in the command stage; ff_q folds e into its rounding:
        # round_shift(p, s) + e = (p + e·2**s + 2**(s−1) − [p < 0]) >> s.
        accept_delay = [accept]
        for k in range(1, 4):
            s_ = Signal(name=f"ff_step{k}")
            m.d.sync += s_.eq(accept_delay[-1])
            accept_delay.append(s_)
        wide = signed(w + 2)
        op_a = Signal(wide)
        op_b = Signal(sw)
        prod = Signal(signed(2 * w + 2))
        prod_neg = Signal()
        wl = Signal(wide)                   # ω·L, Q3.(w−1)
        emf = Signal(wide)                  # ω·ψ, Q3.(w−1)
        ff_d = Signal(signed(w + 5))        # +round(ω·L·i_q): subtracted from PI_d
        ff_q = Signal(signed(w + 5))
        with m.If(accept_delay[1]):
            m.d.sync += [op_a.eq(self.ff_l), op_b.eq(n_spd)]
        with m.Elif(accept_delay[2]):
            m.d.sync += [op_a.eq(self.ff_psi), op_b.eq(n_spd)]
        with m.Elif(pi_delay[1]):
            m.d.sync += [op_a.eq(wl), op_b.eq(self.i_q)]
        with m.Elif(pi_delay[2]):
            m.d.sync += [op_a.eq(wl), op_b.eq(self.i_d)]
        m.d.sync += [prod.eq(op_a * op_b), prod_neg.eq(op_a[-1] ^ op_b[-1])]
        # ω·L and ω·ψ are ready long before the Park result (t + 4 < t + dq_latency).
        with m.If(accept_delay[3]):
            m.d.sync += wl.eq(round_shift_signed(prod, FF_FORMAT.frac, prod_neg))
        emf_step = Signal()
        m.d.sync += emf_step.eq(accept_delay[3])
        with m.If(emf_step):
            m.d.sync += emf.eq(round_shift_signed(prod, FF_FORMAT.frac, prod_neg))
        with m.If(pi_delay[3]):
            m.d.sync += ff_d.eq(round_shift_signed(prod, w - 1, prod_neg))
        with m.If(pi_delay[4]):
            m.d.sync += ff_q.eq(round_shift_signed(prod + (emf << (w - 1)), w - 1, prod_neg))

        # The feed-forward terms as the command stage adds them, a clock after each is formed
        # and before the PI result: 0 unless ``ff_run``, saturated to signed(w + 1). That changes
        # no command: a PI output p lies in signed(w), so p ∓ f saturates to the same end of
        # signed(w) for f beyond ±2**w as for f at ±2**w (p − (2**w − 1) ≤ −2**(w−1), p + 2**w ≥
        # 2**(w−1), and alike for u_q); the command's adder and saturation are w + 2 bits wide
        # instead of w + 6 (a path to 100 MHz on the ECP5, docs/AREA.md).
        if pi_d.latency < 6:
            raise NotImplementedError("CurrentLoop: the feed-forward terms need a PI latency "
                                      f"of at least 6 clocks, not {pi_d.latency}")
        ffc_d = Signal(signed(w + 1))
        ffc_q = Signal(signed(w + 1))
        with m.If(pi_delay[4]):
            m.d.sync += ffc_d.eq(Mux(ff_run, saturate_bits(ff_d, signed(w + 1)), 0))
        with m.If(pi_delay[5]):
            m.d.sync += ffc_q.eq(Mux(ff_run, saturate_bits(ff_q, signed(w + 1)), 0))

        # --- Command stage ------------------------------------------------------------------------
        with m.If(pi_done):
            m.d.sync += [
                self.u_d.eq(Mux(ol, ol_ud, saturate_bits(pi_d.o.payload - ffc_d, sw))),
                self.u_q.eq(Mux(ol, ol_uq, saturate_bits(pi_q.o.payload + ffc_q, sw))),
            ]
        m.d.sync += cmd_valid.eq(pi_done)

        # --- DC-bus compensation, SVPWM -----------------------------------------------------------
        udc = self.i.payload.udc
        m.d.comb += [
            dcbus.u_rated.eq(self.u_rated),
            dcbus.u_dc.valid.eq(accept),
            dcbus.u_dc.payload.eq(Mux(udc[-1], 0, udc)),
            dcbus.i.valid.eq(inv_valid),
            dcbus.i.payload.alpha.eq(cordic.o.payload.x),
            dcbus.i.payload.beta.eq(cordic.o.payload.y),
            self.dc_limited.eq(dcbus.limited),
            svpwm.scale.eq(self.scale),
        ]
        wiring.connect(m, dcbus=dcbus.o, svpwm=svpwm.i)
        m.d.comb += [
            self.o.valid.eq(svpwm.o.valid),
            self.o.payload.a.eq(svpwm.o.payload.a),
            self.o.payload.b.eq(svpwm.o.payload.b),
            self.o.payload.c.eq(svpwm.o.payload.c),
            svpwm.o.ready.eq(self.o.ready),
        ]
        with m.If(done):
            m.d.sync += self.overmod.eq(svpwm.o.payload.overmod)
        return m
