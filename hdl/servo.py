# Ref: paper eq. (7)–(9) (speed PI), SPEC.md §2, §2.5, §4 (operating modes); issue 6 targets
#      (step 0 → 1667 r/min within 1.2·t_min, < 0.5 % overshoot; ramp 0.45 r/min per sample)
"""Speed loop and operating modes: what drives the current loop.

:class:`SpeedLoop` turns the M/T speed (Q1.(speed_width−1) of the full-scale speed N_FS) and the
speed reference into the i_q reference (Q1.15 of I_FS) through a reference profile generator and a
Tustin PI (the equations of :class:`~foc_servo.hdl.pi.PI`, paper eq. (7)–(9), bit for bit,
computed sequentially here) of ``width`` bits; the speed error
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

**Sequential datapath.** A run is a fixed program of 75 operations on one adder
``acc ← A + (B or ~B) + cin`` (width ``max(speed_width + 2, width + int_guard + 3, width + 4)``),
``A`` being 0, ``acc`` or ``acc >> k`` with the rounding increment of ``round_shift(acc, k)`` as
carry in, ``B`` the read port of a register file or one of the special sources (``R``, the
inputs ``speed_ref``, ``speed_slew``, and ``iq_ff``, ``lim_lo``, ``lim_hi`` times
``2**(width − 16)``, the multiplier's product); results are written from ``acc`` (truncated
when exact, else saturated to signed(width), that times ``2**int_guard``, or signed(16) by bit
tests), comparisons leave
flags (sign, zero of ``acc``) that steer later operations' selections. ``kx·(E + E[n−1])`` and
``kp·E`` come from a shift-add multiplier (one multiplier bit per clock on its own adder of
``width + 3`` bits, plus ``int_guard − frac`` for a gain whose product is shifted left, then right
shifts that keep the rounding bits): no hard multiplier.

**Register file.** The state and the temporaries are words of one RAM (a block RAM; width
``max(width + int_guard, speed_width)``, one write port and one read port whose data is
registered: an asynchronous port and a register, ``no_rw_check``, since no word is read in the
clock it is written): the integrator, ``E[n−1]``, the PI's limits (also times
``2**int_guard``), ``ff·2**(width − 16)``, the speed sample (written in the accepting clock), the
candidates and temporaries, and the reference history, a ring buffer of ``max_delay + 1``
slots: this run's ``to_pi(R[n−1])`` is written to slot ``slot``, tap ``k`` is read from slot
``slot − min(k, age)``, ``age`` counting the runs since ``clear`` (so that after ``clear`` every
tap is the first run's), and both advance at the end of a run. The integrator and ``E[n−1]``
read as 0 after ``clear`` until a run has ended (``zst``). A word written from ``acc`` in clock
``t`` is read by an operation in ``t + 2`` (its address is presented one clock ahead); ``R`` and the
output are flip-flops (readable in ``t + 1``). ``_program`` lists the operations; each is
placed in the earliest clock its operands allow, and the timing (``latency``, ``interval``,
``ref_latency``) follows from the list (:func:`speed_loop_timing`). Per run: profile and ``R``
(clocks 1 … 13), interpolation (``f·(b − a)`` as seven conditional additions), ``E``,
``kx·(E + E[n−1])`` (while the feed-forward and the PI limits are formed), ``dI``, ``I_c``,
``kp·E``, then ``U`` with the kept and with the new integrator, the conditional-integration
choice and the output rounding. The operand selects (the B source as a code, decoded into
the special sources' selects and the read address), write enables, flag captures and side
actions are registers, loaded one clock ahead from a ROM word read three clocks ahead and
registered (its constant bits, plus a one-hot bit per clock whose selections flags or
``ref_delay`` steer, gated with those terms): no decode of the step counter.
The longest path is then a register through the operand multiplexers and the adder into
``acc`` (100 MHz on an ECP5 is the target).

``P`` and ``dI`` enter the adder saturated to signed(width + int_guard + 2), which changes no
result: beyond that range ``P + I`` (or ``I + dI``) lies outside the limits·2**int_guard
whatever the integrator (``|I| ≤ 2**(width + int_guard − 1)``), so the comparisons, the clamped
values and ``sat`` are those of the exact values, and the sign of ``dI`` is kept.

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

from amaranth.hdl import Array, Assert, C, Cat, Module, Mux, Signal, Value, signed, unsigned
from amaranth.lib import stream, wiring
from amaranth.utils import ceil_log2, exact_log2
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from .bus import DATA_WIDTH, WordWriteSignature
from .dsp import MUL_WIDTH, check_mul_width, saturate_bits
from .fixed import is_int, UQ, BinaryAngle, check_choice
from .mt_speed import output_layout as mt_output_layout
from .pi import pi_widths
from .regmap import AngleMode, Mode

__all__ = ["SpeedLoop", "Servo", "Mode", "AngleMode", "IQ_WIDTH", "ANGLE", "DELAY_FRAC",
           "CONFIGS", "SPEED_LOOPS", "SPEED_CONFIG", "check_speed_loop", "check_speed_config",
           "speed_loop_timing"]

#: Width of the current references and modulation indices, Q1.15 (docs/ARCHITECTURE.md).
IQ_WIDTH = 16
#: The electrical angle format.
ANGLE = BinaryAngle(16)
#: :class:`Servo`'s ports of the :data:`SPEED_CONFIG` inputs (``config="ports"``).
_SERVO_CONFIG = ("speed_kp", "speed_kx", "speed_slew", "iq_ff")
#: Fraction bits of ``ref_delay`` (steps of 1/8 speed-loop run).
DELAY_FRAC = 3
#: Values of ``SpeedLoop(config=...)`` / ``Servo(config=...)``.
CONFIGS = ("ports", "ram")
#: Values of ``Servo(speed_loop=...)``: :class:`SpeedLoop` inside the Servo (``"sequential"``,
#: its own datapath) or the loop engine's speed run (``"engine"``,
#: ``EngineCurrentLoop(speed=True)`` beside the Servo; its results come in on ``sl_*``).
SPEED_LOOPS = ("sequential", "engine")
#: ``Servo(speed_loop="engine")``: the members that go (the speed loop's inputs; the top feeds
#: them to the engine), and the results that come in instead.
_ENGINE_GONE = ("speed", "speed_ref", "speed_kp", "speed_kx", "speed_rate_div", "speed_slew",
                "iq_ff", "speed_ref_delay", "speed_int_hold")
#: ``config="ram"``: the :class:`SpeedLoop` inputs held in its configuration RAM instead of
#: ports, in the order of the words of its ``config`` port (``config.index`` = position here).
SPEED_CONFIG = ("kp", "kx", "speed_slew", "iq_ff")


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


def check_speed_config(owner, config, config_init, speed_width, kp_format, kx_format):
    """Validate ``config`` and ``config_init`` of :class:`SpeedLoop` / :class:`Servo` (after
    :func:`check_speed_loop`); returns the initial words (``config="ram"``: ``config_init`` or all
    0; ``"ports"``: ``None``)."""
    check_choice(owner, "config", config, CONFIGS)
    if config_init is not None and config != "ram":
        raise ValueError(f"{owner} config_init applies only to config='ram', "
                         f"not config={config!r}")
    if config != "ram":
        return None
    widths = {"kp": kp_format.width, "kx": kx_format.width, "speed_slew": speed_width}
    for name, width in widths.items():
        if width > DATA_WIDTH:
            raise ValueError(f"{owner} config='ram' needs {name} in one {DATA_WIDTH}-bit word, "
                             f"not {width} bits")
    if config_init is None:
        return [0] * len(SPEED_CONFIG)
    if (not isinstance(config_init, (list, tuple)) or len(config_init) != len(SPEED_CONFIG)
            or not all(is_int(v) and 0 <= v < 1 << DATA_WIDTH for v in config_init)):
        raise ValueError(f"{owner} config_init must be a list of {len(SPEED_CONFIG)} "
                         f"{DATA_WIDTH}-bit words, not {config_init!r}")
    return list(config_init)


# --- The speed loop's micro-program ---------------------------------------------------------------
#
# One adder ``acc ← A + (B or ~B) + cin`` does all the arithmetic of a run; a shift-add multiplier
# (own small adder, one bit of the multiplier per clock) forms kx·(E + E[n−1]) and kp·E; a register
# file (block RAM) holds the state, the temporaries and the reference history. ``_program`` lists
# the operations in order and places each in the earliest clock its operands allow (a word written
# from ``acc`` is readable three clocks after the operation that formed the value, a flip-flop two;
# a flag steers the selection of an operation three clocks after that value). Everything here is
# Python at elaboration time: the timing (``latency``, ``interval``, the clock ``ref_int`` changes)
# follows from the list.


def speed_loop_timing(speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                      int_guard=16, delay_width=5):
    """Timing of :class:`SpeedLoop` with these parameters (validated first): a dict with
    ``latency``, ``interval``, ``ref_latency`` (clocks from an accepted run to the new
    ``ref_int``), ``clocks`` (clocks of a run's program) and ``mult_clocks``. The golden model
    takes its timing from here."""
    check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, 1, delay_width)
    max_delay = (1 << (delay_width - DELAY_FRAC)) - 1
    return _program(speed_width, width, kp_format, kx_format, int_guard, max_delay)[1]


class _Op:
    """One operation of the speed loop's program.

    ``a``: ``"Z"`` (0), ``"ACC"`` or ``("RND", k)`` (``round_shift(acc, k)``: ``acc >> k`` plus
    the rounding increment as carry in); or a list of ``(condition, a)`` chosen in order (the
    condition a function of the flags and inputs, evaluated when the operation is decoded).
    ``b``: a source name, ``None`` (0), or such a list. ``sub``: subtract ``b`` (``~b`` with carry
    in 1), a bool or a condition; ``cin``: the carry in when it is not ``sub``'s. ``wr``: dest →
    kind (``"raw"``, ``"w"``, ``"wg"`` (``"w"`` times ``2**g``), ``"q16"``) or (kind, condition):
    written from ``acc``
    in the clock after the operation. ``flags``: flag → ``"neg"``, ``"nneg"``, ``"nz"``, ``"pos"``
    of the result, captured in the clock after. ``uses``: flags the conditions read. ``act``:
    side actions in the operation's clock (``"mult_x"``, ``"mult_p"``: start a multiplication of
    ``acc``; ``"shin"``: advance the history ring).
    """

    def __init__(self, a="Z", b=None, *, sub=False, cin=None, wr=None, flags=None, uses=(),
                 act=()):
        self.a, self.b, self.sub, self.cin = a, b, sub, cin
        self.wr = dict(wr or {})
        self.flags = dict(flags or {})
        self.uses = tuple(uses)
        self.act = (act,) if isinstance(act, str) else tuple(act)
        self.clock = None

    def sources(self):
        out = []
        for sel in (self.a, self.b):
            if isinstance(sel, list):
                out += [s for _, s in sel]
            else:
                out.append(sel)
        return [s for s in out if isinstance(s, str) and s not in ("Z", "ACC")]

    @property
    def alu(self):
        return not (self.a == "Z" and self.b is None and not self.sub)


#: Words of the register file (block RAM) at fixed addresses; the history of ``to_pi(R)`` follows
#: them (``TP``, the tap of this run, and the taps ``TAPA`` = d − 1, ``TAPB`` = d it reads).
_RF_WORDS = ("CA", "CB", "EP", "LO_S", "HI_S", "LOG", "HIG", "I", "PR", "FFS", "SPD")


def _rf_address(name):
    """Address of a fixed register-file word (0 is not used: B code 0 is "no source")."""
    return _RF_WORDS.index(name) + 1


#: Register-file names read at a run-dependent history address (readiness follows ``TP``).
_ALIAS = {"TAPA": "TP", "TAPB": "TP"}
#: Destinations that are flip-flops (written from ``acc``, readable two clocks later); the others
#: are register-file words (readable three clocks later: written, then read one clock ahead).
_FF_DESTS = ("R", "OPAY")


def _program(sw, w, kp_format, kx_format, g, n_taps):
    """The operations of a run, placed in clocks; returns ``(ops, timing)``."""
    s_in, s_out = sw - w, w - IQ_WIDTH
    mw = max(kp_format.width, kx_format.width)
    sh_p, sh_x = kp_format.frac - g, kx_format.frac - g
    mult_clocks = {"mult_p": mw + max(sh_p, 0), "mult_x": mw + max(sh_x, 0)}

    def rnd(k):
        return ("RND", k) if k > 0 else "ACC"

    up = lambda f: f["snz"] & f["UPR"]                              # noqa: E731
    dn = lambda f: f["snz"] & f["DNR"]                              # noqa: E731
    updn = lambda f: up(f) | dn(f)                                  # noqa: E731

    def clamp_ops(hi, lo, fa, fl, wr):
        """Compare ``acc`` with ``hi``, ``lo`` (restoring it) and select the clamped value."""
        return [
            _Op("ACC", hi, sub=True, cin=0, flags={fa: "nneg"}),     # acc − hi − 1 ≥ 0: above
            _Op("ACC", hi, cin=1),
            _Op("ACC", lo, sub=True, flags={fl: "neg"}),             # acc − lo < 0: below
            _Op("ACC", lo),
            _Op([(lambda f: f[fa] | f[fl], "Z"), (None, "ACC")],
                [(lambda f: f[fa], hi), (lambda f: f[fl], lo)], uses=(fa, fl), wr=wr),
        ]

    ops = [
        # Profile: TP = to_pi(R[n−1]); D = speed_ref − R; up: D > S; dn: D + S < 0.
        _Op("Z", "R"),
        _Op(rnd(s_in), wr={"TP": "w"}),
        _Op("Z", "SREF"),
        _Op("ACC", "R", sub=True, flags={"DNZ": "nz"}),
        _Op("ACC", "S", sub=True, flags={"UPR": "pos"}),
        _Op("ACC", "S"),
        _Op("ACC", "S", flags={"DNR": "neg"}),
        # plan = R ± S (up / dn) or speed_ref → R.
        _Op("Z", [(updn, "R"), (None, "SREF")], uses=("UPR", "DNR")),
        _Op("ACC", [(updn, "S")], sub=dn, uses=("UPR", "DNR"), wr={"R": "raw"}),
    ]
    # ff·2**s_out = clamp(±iq_ff, lim_lo, lim_hi)·2**s_out (up / dn), else 0 (the inputs enter
    # the adder shifted left by s_out); the PI limits sat((lim − ff)·2**s_out) and the same
    # times 2**g. Placed while the multiplier forms kx·(E + E[n−1]).
    ff_ops = [_Op("Z", [(updn, "IQFF")], sub=dn, uses=("UPR", "DNR"))]
    ff_ops += clamp_ops("LIM_HI", "LIM_LO", "FA", "FL", None)
    sel = ff_ops[-1]                    # the select also gives 0 when the profile does not move
    sel.a = [(lambda f: ~updn(f) | f["FA"] | f["FL"], "Z"), (None, "ACC")]
    sel.b = [(lambda f: updn(f) & f["FA"], "LIM_HI"), (lambda f: updn(f) & f["FL"], "LIM_LO")]
    sel.uses = ("FA", "FL", "UPR", "DNR")
    sel.wr = {"FFS": "raw"}
    ff_ops += [
        _Op("Z", "LIM_LO"),
        _Op("ACC", "FFS", sub=True, wr={"LO_S": "w"}),
        _Op(wr={"LOG": "wg"}),          # acc kept: the same value, saturated, times 2**g
        _Op("Z", "LIM_HI"),
        _Op("ACC", "FFS", sub=True, wr={"HI_S": "w"}),
        _Op(wr={"HIG": "wg"}),
    ]
    # Interpolation a + round_shift(f·(b − a), 3), a = tap d − 1, b = tap d: CB = b − a, then
    # f·CB as f additions (2**DELAY_FRAC − 1 conditional ones).
    ops += [
        _Op("Z", "TAPB"),
        _Op("ACC", "TAPA", sub=True, wr={"CB": "raw"}),
    ]
    for k in range((1 << DELAY_FRAC) - 1):
        ops.append(_Op("Z" if k == 0 else "ACC",
                       [((lambda k: lambda f: f["frac"] > k)(k), "CB")]))
    ops += [
        _Op(rnd(DELAY_FRAC)),
        _Op("ACC", "TAPA", wr={"CB": "w"}),
        # d = 0: the reference is to_pi(plan) (R now holds the plan).
        _Op("Z", "R"),
        _Op(rnd(s_in), wr={"CB": ("w", lambda f: f["d0"])}),
        # mv: the delayed reference has not reached R[n−1].
        _Op("Z", "CB"),
        _Op("ACC", "TP", sub=True, flags={"MVD": "nz"}),
        # fb = to_pi(speed) → CA; E = sat(ref − fb) → CA; E + E[n−1].
        _Op("Z", "SPD"),
        _Op(rnd(s_in), wr={"CA": "w"}),
        _Op("Z", "CB"),
        _Op("ACC", "CA", sub=True, wr={"CA": "w"}),
        _Op("Z", "CA"),
        _Op("ACC", "EP"),
        _Op(act="mult_x", uses=("DNZ", "MVD")),                    # kx·(E + E[n−1])
        _Op("Z", "CA", wr={"EP": "w"}),                             # E[n−1] ← E
        *ff_ops,
        # dI, I + dI, I_c = clamp(I + dI, lo·2**g, hi·2**g) → PR; kp·E starts on E in acc.
        _Op("Z", "CA"),
        _Op("Z", "PRD", flags={"DIP": "pos", "DIN": "neg"}, act="mult_p"),
        _Op("ACC", "I"),
    ]
    ops += clamp_ops("HIG", "LOG", "GT", "LT", {"PR": "raw"})
    # U with the kept integrator → O_k (CB), then with I_c → O_c (CA).
    ops += [_Op("Z", "PRD"), _Op("ACC", "I"), _Op(rnd(g))]
    ops += clamp_ops("HI_S", "LO_S", "AK", "BK", {"CB": "w"})
    ops += [_Op("Z", "PRD"), _Op("ACC", "PR"), _Op(rnd(g))]
    ops += clamp_ops("HI_S", "LO_S", "AC", "BC", {"CA": "w"})
    hold = lambda f: (f["AC"] & f["DIP"]) | (f["BC"] & f["DIN"])   # noqa: E731
    ops += [
        _Op("Z", [(hold, "I"), (None, "PR")], uses=("AC", "BC", "DIP", "DIN"),
            wr={"I": "raw"}),
        _Op("Z", [(hold, "CB"), (None, "CA")], uses=("AC", "BC", "DIP", "DIN")),
        _Op("ACC", "FFS"),
        _Op(rnd(s_out), wr={"OPAY": "q16"}, uses=("AC", "BC", "AK", "BK", "DIP", "DIN")),
        _Op(act="shin"),
    ]

    # Placement.
    ready = {}                      # register / flag → first clock it may be read
    flag_ready = {}                 # flag → first clock an operation may be decoded with it
    clock = -1
    mult_ready = 0
    for op in ops:
        c = clock + 1
        for s in op.sources():
            s = _ALIAS.get(s, s)
            c = max(c, ready.get(s, 0))
            if s == "PRD":
                c = max(c, mult_ready)
        for fl in op.uses:
            c = max(c, flag_ready[fl])
        if "mult_x" in op.act or "mult_p" in op.act:
            c = max(c, mult_ready)
        op.clock = clock = c
        for dest in op.wr:
            ready[dest] = c + (2 if dest in _FF_DESTS else 3)
        for fl in op.flags:
            flag_ready[fl] = c + 3
        for kind in ("mult_x", "mult_p"):
            if kind in op.act:
                mult_ready = c + mult_clocks[kind] + 2
    # No operation reads a register-file word in the clock it is written (its address is
    # presented in the clock before the operation): the read port's transparency is moot.
    writes = {op.clock + 1: _ALIAS.get(d, d) for op in ops for d in op.wr if d not in _FF_DESTS}
    for op in ops:
        if writes.get(op.clock - 1) in {_ALIAS.get(s, s) for s in op.sources()}:
            raise RuntimeError(f"SpeedLoop program: clock {op.clock} reads "
                               f"{writes[op.clock - 1]} as it is written")
    last = clock + 1
    out_op = next(op for op in ops if "OPAY" in op.wr)
    r_op = next(op for op in ops if "R" in op.wr)
    timing = {"latency": out_op.clock + 3, "interval": last + 2, "ref_latency": r_op.clock + 3,
              "clocks": last + 1, "mult_clocks": mult_clocks}
    return ops, timing


class SpeedLoop(wiring.Component):
    """Reference profile and speed PI: M/T speed and speed reference → i_q reference (module
    docstring: equations).

    Runs on every ``rate_div + 1``-th valid speed sample (the first one after ``clear`` runs); a
    run that finds the loop still busy (samples less than :attr:`interval` clocks apart) is
    dropped and leaves the profile alone. The M/T block delivers one sample per PWM period,
    thousands of clocks apart.

    **Input timing.** A run is accepted in clock ``t`` (``i.valid``, decimation count 0, not
    busy, no ``clear``); ``i.payload.speed`` is latched then. The other inputs a run uses —
    ``speed_ref``, ``speed_slew``, ``iq_ff``, ``ref_delay``, ``int_hold``, ``kp``, ``kx``,
    ``lim_lo``, ``lim_hi`` — are read during the run, in clocks ``t + 1 … t + interval − 1``,
    and must hold their clock-``t`` values until then (:class:`SpeedLoopModel` raises if one
    changes). In the top the register file changes them only at the PWM period start; M/T's
    sample comes ~40 clocks after it, the run ends ~120 clocks later, and the current loop
    samples the new i_q reference thousands of clocks later (at the period centre).
    ``clear`` acts in its own clock (no long path behind it: it only resets registers and
    selects ``R``'s tracking input).

    **Configuration in RAM** (``config="ram"``). ``kp``, ``kx``, ``speed_slew`` and ``iq_ff``
    (:data:`SPEED_CONFIG`) are the four words of a RAM of their own (``max(kp, kx, speed)
    width`` bits, a block RAM: written only through the ``config`` port, initialised with
    ``config_init``), beside the register file. Its read port's address, presented a clock
    ahead like the register file's, is the slew's word, except for the operation whose B
    operand is the feed-forward (its word) and in the clock before a multiplication starts
    (that multiplication's gain; no operation that starts one reads the slew or the
    feed-forward): the slew and feed-forward special sources and the multiplier's gain load
    take the read data instead of the ports. ``speed_slew ≠ 0`` (the profile's on/off, read
    every clock while ``clear``) is a flip-flop loaded with the slew's word. The program, the
    results and the timing are those of ``config="ports"``. (As words of the register file's
    own RAM they would need a second source on its one write port: 32 multiplexer LUTs more on
    the iCE40; docs/AREA.md.)

    Parameters
    ----------
    speed_width : int
        Width of the speed, speed reference and slew, Q1.(speed_width−1) of N_FS (MTSpeed
        ``out_width``, 32 by default), 16 … 48.
    width : int
        Width of the speed PI (error, integrator scale, output), ``16 … speed_width``.
    kp_format, kx_format, int_guard
        Of the speed PI (as for :class:`~foc_servo.hdl.pi.PI`). ``kp`` is the gain in per-unit
        (I_FS per N_FS), ``kx = K_i·T_s/2`` with ``T_s`` the speed-loop period. The defaults,
        ``UQ(24, 12)`` (0 … 4096), ``UQ(24, 24)`` (0 … 1 in steps of 6·10⁻⁸) and 16 guard bits,
        keep a small ``kx`` integrating errors far below 0.01 % of full scale.
    div_width : int
        Width of ``rate_div``, 1 … 16.
    delay_width : int
        Width of ``ref_delay``, UQ(delay_width, 3): ``4 … 7`` (largest delay 1.875 … 15.875
        runs; the default 5 gives 0 … 3.875 and stores 3 past references).
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None``; checked and
        kept for the interface (the sequential multiplier uses no hard multiplier).
    config : str
        Where ``kp``, ``kx``, ``speed_slew`` and ``iq_ff`` (:data:`SPEED_CONFIG`) come from:
        ``"ports"`` (default) the members of those names; ``"ram"`` a four-word block RAM of
        the loop's, written through the ``config`` port (*Configuration in RAM* below; the
        iCEBreaker's top, whose register file then holds no flip-flops for them). Results and
        timing are the same.
    config_init : list of int
        ``config="ram"``: the four words' initial contents, 32-bit words in
        :data:`SPEED_CONFIG` order (the registers' reset values in their read format; default
        all 0). ``config="ram"`` needs ``kp_format``, ``kx_format`` and ``speed_width`` of at
        most 32 bits.

    Members
    -------
    i : In(stream.Signature(MTSpeed output layout, always_ready=True))
        The M/T speed (``wiring.connect`` it to :attr:`MTSpeed.o`); only ``speed`` is used
        (a stopped motor reads 0; the payload is held between strobes).
    speed_ref : In(signed(speed_width))
        Speed reference, Q1.(speed_width−1) of N_FS, read during a run (and every clock while
        ``clear`` with ``speed_slew = 0``). A host or DSP closing a position
        loop writes it (or, in current mode, the i_q reference).
    speed_slew : In(unsigned(speed_width))
        Largest change of ``ref_int`` per run, UQ1.(speed_width−1) of N_FS; 0: off (``ref_int``
        steps to ``speed_ref``). Read during a run (and while ``clear``).
    iq_ff : In(signed(16))
        Acceleration feed-forward ``J·α/K_t``, Q1.15 of I_FS, added with the direction of the
        profile while ``ref_int`` has not reached ``speed_ref`` (read during a run).
    ref_delay : In(unsigned(delay_width))
        UQ(delay_width, 3): the PI's reference is ``ref_int`` this many runs ago, interpolated
        linearly between runs; integer part 0: ``ref_int`` itself (the fraction is ignored).
        Read during a run.
    int_hold : In(1)
        Hold the PI's integrator (its ``kx`` is 0) in runs whose reference still moves
        (``ref_int`` has not reached ``speed_ref``, or the delayed reference has not reached
        ``ref_int``): the feed-forward supplies the acceleration.
    kp : In(kp_format.shape)
    kx : In(kx_format.shape)
    lim_lo, lim_hi : In(signed(16))
        i_q limits (the current limit), Q1.15 of I_FS. Gains, limits and the profile inputs
        must be stable while a run is in flight (see *Input timing*).
    config : In(WordWriteSignature(4))
        ``config="ram"`` only, instead of ``kp``, ``kx``, ``speed_slew`` and ``iq_ff``: a write
        of word ``index`` (:data:`SPEED_CONFIG` order; ``data`` the value zero-extended or, if
        signed, sign-extended to 32 bits, as the register file's export port carries it) in the
        ``valid`` clock; the loop uses it from the next clock, as it would a port that changed
        then. Never while a run is in flight or in its accepting clock (an ``Assert`` checks
        it): the same rule as for the ports.
    rate_div : In(unsigned(div_width))
        The loop runs on every ``rate_div + 1``-th speed sample.
    clear : In(1)
        While high: PI cleared (integrator 0), run in flight abandoned, output 0, feed-forward
        0, decimation counter restarted, ``ref_int`` and its history track ``i.payload.speed``
        (``speed_slew ≠ 0``) or ``speed_ref``.
    o : Out(stream.Signature(signed(16), always_ready=True))
        i_q reference, Q1.15 of I_FS, rounded half away from zero, within [lim_lo, lim_hi];
        ``valid`` strobes :attr:`latency` clocks after an accepted run, payload held (0 after
        reset and ``clear``; a run in flight when ``clear`` rises never strobes).
    sat : Out(1)
        The last output was clamped to a limit (updates with ``o.valid``).
    ref_int : Out(signed(speed_width))
        The profile's reference ``R``, Q1.(speed_width−1) of N_FS (updates :attr:`ref_latency`
        clocks after a run; 0 after reset).

    Attributes
    ----------
    latency : int
        Clocks from a valid speed sample that runs the loop to ``o.valid`` (124 with the
        defaults, also with ``delay_width`` 7; 120 with the top's ``kx_format`` UQ(24, 20)).
        Computed from the program of a run.
    interval : int
        Minimum clocks between runs: :attr:`latency` + 1.
    ref_latency : int
        Clocks from an accepted run to the new ``ref_int`` (13).
    max_delay : int
        Largest integer part of ``ref_delay``: ``2**(delay_width − 3) − 1``.
    """

    def __init__(self, *, speed_width=32, width=24, kp_format=UQ(24, 12), kx_format=UQ(24, 24),
                 int_guard=16, div_width=8, delay_width=5, mul_width=MUL_WIDTH, config="ports",
                 config_init=None):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                         delay_width)
        self._mul_width = check_mul_width("SpeedLoop", mul_width)
        self._config_init = check_speed_config("SpeedLoop", config, config_init, speed_width,
                                               kp_format, kx_format)
        self._config = config
        self._speed_width = speed_width
        self._width = width
        self._kp_format = kp_format
        self._kx_format = kx_format
        self._int_guard = int_guard
        self._div_width = div_width
        self._delay_width = delay_width
        self._ops, self._timing = _program(speed_width, width, kp_format, kx_format, int_guard,
                                           self.max_delay)
        self._alu_width = max(speed_width + 2, width + int_guard + 3, width + 4)
        members = {
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
        }
        if config == "ram":             # the configuration words through one RAM write port
            for name in SPEED_CONFIG:
                del members[name]
            members["config"] = In(WordWriteSignature(len(SPEED_CONFIG)))
        super().__init__(members)

    speed_width = property(lambda self: self._speed_width)
    width = property(lambda self: self._width)
    kp_format = property(lambda self: self._kp_format)
    kx_format = property(lambda self: self._kx_format)
    int_guard = property(lambda self: self._int_guard)
    div_width = property(lambda self: self._div_width)
    delay_width = property(lambda self: self._delay_width)
    mul_width = property(lambda self: self._mul_width)
    config_mode = property(lambda self: self._config)
    config_init = property(lambda self: None if self._config_init is None
                           else list(self._config_init))
    max_delay = property(lambda self: (1 << (self._delay_width - DELAY_FRAC)) - 1)
    latency = property(lambda self: self._timing["latency"])
    interval = property(lambda self: self._timing["interval"])
    ref_latency = property(lambda self: self._timing["ref_latency"])

    #: Register file as flip-flops (one signal ``rf_<word>`` per word, same timing) instead of a
    #: block RAM: set only by the formal proof, whose invariants name the words.
    _RF_IN_FFS = False

    def elaborate(self, platform):
        m = Module()
        sw, w, g = self._speed_width, self._width, self._int_guard
        kpf, kxf = self._kp_format, self._kx_format
        s_out = w - IQ_WIDTH
        n = self.max_delay
        ops, timing = self._ops, self._timing
        wa = self._alu_width
        wsat = w + g + 2                # P and dI saturated to this (see the module docstring)
        clocks = timing["clocks"]
        clear = self.clear

        # Decimation and acceptance.
        count = Signal(unsigned(self._div_width))
        running = Signal()
        step = Signal(range(clocks + 1))
        accept = Signal()
        m.d.comb += accept.eq(self.i.valid & (count == 0) & ~clear & ~running)
        with m.If(clear):
            m.d.sync += count.eq(0)
        with m.Elif(self.i.valid):
            m.d.sync += count.eq(Mux(count >= self.rate_div, 0, count + 1))

        # Register file: the words of ``_RF_WORDS`` at addresses 0, 1, …, then the history ring
        # of ``n + 1`` slots (``to_pi(R)`` of this run and the ``n`` before it) at ``h_base``, a
        # multiple of its size; one write port (from ``acc``, or the speed sample in the
        # accepting clock) and one synchronous read port (its address is presented one clock
        # ahead, from the next control word's ROM bits). The program never reads a word in the
        # clock it is written (``_program`` checks it, an ``Assert`` below), so the port needs no
        # read-during-write behaviour: it is an asynchronous port with its data registered here
        # (the engine's form, docs/ENGINE.md "Decisions"), the memory ``no_rw_check``. yosys
        # merges the register into an iCE40 block RAM's synchronous port without collision
        # logic; on the ECP5 (distributed RAM, asynchronous read) the RAM's read is in front of
        # the register, not between a registered address and the adder.
        n_slots = n + 1                 # a power of two
        slot_w = exact_log2(n_slots)
        h_base = -(-(len(_RF_WORDS) + 1) // n_slots) * n_slots
        rf_depth = 1 << ceil_log2(h_base + n_slots)
        rfw = max(w + g, sw, w + 1)
        rf_addr = {name: _rf_address(name) for name in _RF_WORDS}
        rf_rd_addr = Signal(range(rf_depth))
        rf_rd_data = Signal(signed(rfw))
        rf_wr_en = Signal()
        rf_wr_addr = Signal(range(rf_depth))
        rf_wr_data = Signal(signed(rfw))
        if self._RF_IN_FFS:
            words = [Signal(signed(rfw), name="rf_w0")]
            words += [Signal(signed(rfw), name=f"rf_{name.lower()}") for name in _RF_WORDS]
            words += [Signal(signed(rfw), name=f"rf_w{k}") for k in range(len(words), h_base)]
            words += [Signal(signed(rfw), name=f"rf_h{k}") for k in range(n_slots)]
            words += [Signal(signed(rfw), name=f"rf_w{k}")
                      for k in range(len(words), rf_depth)]
            # Not transparent, unlike the RAM's port: the same, since no word a run uses is read
            # in the clock it is written (the ``Assert`` below).
            m.d.sync += rf_rd_data.eq(Array(words)[rf_rd_addr])
            with m.If(rf_wr_en):
                m.d.sync += Array(words)[rf_wr_addr].eq(rf_wr_data)
        else:
            m.submodules.rf = rf = Memory(shape=signed(rfw), depth=rf_depth, init=[],
                                          attrs={"no_rw_check": 1})
            rf_wr = rf.write_port()
            rf_rd = rf.read_port(domain="comb")
            rf_rd_q = Signal(signed(rfw), reset_less=True)
            m.d.sync += rf_rd_q.eq(rf_rd.data)
            m.d.comb += [rf_rd.addr.eq(rf_rd_addr), rf_rd_data.eq(rf_rd_q),
                         rf_wr.en.eq(rf_wr_en), rf_wr.addr.eq(rf_wr_addr),
                         rf_wr.data.eq(rf_wr_data)]

        # The history ring: ``slot`` holds this run's tap 0 (``TP``), tap k is slot − k; ``age``
        # counts the runs since ``clear`` (up to n): a tap older than that reads the oldest
        # (after clear every tap is to_pi(R) of the first run). Both advance at ``shin``.
        slot = Signal(slot_w)
        age = Signal(range(n + 1))
        # After clear the integrator and E[n−1] read as 0 until the next run has ended (every
        # run writes them after reading them).
        zst = Signal(init=1)
        d_int = self.ref_delay[DELAY_FRAC:]
        d_frac = self.ref_delay[:DELAY_FRAC]

        def tap_addr(k):
            back = Mux(k > age, age, k)
            return Cat((slot - back)[:slot_w], C(h_base // n_slots, ceil_log2(rf_depth) - slot_w))

        d_a = Mux(d_int == 0, 0, d_int - 1)
        rf_addr_of = {"TP": tap_addr(C(0, 1)), "TAPA": tap_addr(d_a), "TAPB": tap_addr(d_int)}
        rf_addr_of.update(rf_addr)

        # Registers.
        R = Signal(signed(sw))
        regs = {"R": R, "OPAY": self.o.payload}
        acc = Signal(signed(wa))
        flag_names = sorted({f for op in ops for f in op.flags})
        flags = {f: Signal(name=f"flag_{f.lower()}") for f in flag_names}
        # ``config="ram"``: kp, kx, speed_slew and iq_ff in a RAM of their own (a block RAM: one
        # write port, the ``config`` port; one read port, its address presented a clock ahead:
        # the slew's word, the feed-forward's, or a gain's in the clock before its
        # multiplication starts);
        # ``speed_slew ≠ 0`` in a flip-flop loaded with the slew's word (the port's value from
        # the next clock on, as the RAM's word).
        ram = self._config == "ram"
        if ram:
            cfg = self.config
            cfg_index = {name: SPEED_CONFIG.index(name) for name in SPEED_CONFIG}
            cfg_w = max(kpf.width, kxf.width, sw)
            # (An asynchronous read port with a register behind it, which yosys merges into
            # the block RAM's synchronous port; ``no_rw_check``: no word is read in a clock that
            # writes it (writes come between runs), so no read-during-write emulation.)
            m.submodules.cfg_ram = cfg_ram = Memory(
                shape=unsigned(cfg_w), depth=len(SPEED_CONFIG),
                init=[v & ((1 << cfg_w) - 1) for v in self._config_init],
                attrs={"ram_style": "block", "no_rw_check": 1})
            cfg_wr = cfg_ram.write_port()
            cfg_rd = cfg_ram.read_port(domain="comb")
            cfg_q = Signal(cfg_w, reset_less=True)      # the RAM's read data
            m.d.sync += cfg_q.eq(cfg_rd.data)
            m.d.comb += [cfg_wr.en.eq(cfg.valid), cfg_wr.addr.eq(cfg.index),
                         cfg_wr.data.eq(cfg.data[:cfg_w])]
            slew_init = self._config_init[cfg_index["speed_slew"]] & ((1 << sw) - 1)
            snz = Signal(init=slew_init != 0)
            with m.If(cfg.valid & (cfg.index == cfg_index["speed_slew"])):
                m.d.sync += snz.eq(cfg.data[:sw].any())
        else:
            snz = Signal()
            m.d.comb += snz.eq(self.speed_slew != 0)
        # The run's decode reads ``speed_slew ≠ 0`` from a register (the input is stable during a
        # run; the 32-bit OR stays out of the control decode). ``clear``'s tracking uses ``snz``.
        snz_r = Signal()
        m.d.sync += snz_r.eq(snz)
        cond_in = dict(flags, snz=snz_r, d0=(d_int == 0), frac=d_frac)

        # Shift-add multiplier: {hi, lo} = mc · (multiplier), one multiplier bit per clock,
        # then right shifts with the rounding bits kept (half, sticky).
        mw = max(kpf.width, kxf.width)
        sh = {"mult_p": kpf.frac - g, "mult_x": kxf.frac - g}
        lsh = {k: max(-v, 0) for k, v in sh.items()}
        mcw = w + 1 + max(lsh.values())
        mc = Signal(signed(mcw))
        hi = Signal(signed(mcw + 1))
        lo = Signal(unsigned(mw))
        m_cnt = Signal(range(max(timing["mult_clocks"].values()) + 1))
        m_shift = Signal(range(mw + 1))           # iterations left that add
        m_signed = Signal()
        half = Signal()
        sticky = Signal()
        prod = Cat(lo, hi).as_signed()
        over = Signal()
        under = Signal()
        m.d.sync += [over.eq(~prod[-1] & prod[wsat - 1:].any()) if len(prod) > wsat else
                     over.eq(0),
                     under.eq(prod[-1] & ~prod[wsat - 1:].all()) if len(prod) > wsat else
                     under.eq(0)]
        if len(prod) > wsat:
            prd = Mux(over, (1 << (wsat - 1)) - 1,
                      Mux(under, -(1 << (wsat - 1)), prod[:wsat].as_signed()))
        else:
            prd = prod
        prd_inc = half & (~prod[-1] | sticky)
        # One adder: ``hi ± mc`` while multiplier bits remain (subtracted for a signed
        # multiplier's sign bit), ``hi + 0`` (a plain shift) after them.
        m_add = Signal()
        m_sub = Signal()
        m_t = Signal(signed(mcw + 2))
        m.d.comb += [m_add.eq(lo[0] & (m_shift != 0)),
                     m_sub.eq(m_signed & (m_shift == 1)),
                     m_t.eq(hi + Mux(m_add, Mux(m_sub, ~mc, mc), 0) + (m_add & m_sub))]
        with m.If(m_cnt != 0):
            m.d.sync += [m_cnt.eq(m_cnt - 1), hi.eq(m_t >> 1), lo.eq(Cat(lo[1:], m_t[0]))]
            with m.If(m_shift != 0):
                m.d.sync += m_shift.eq(m_shift - 1)
            with m.Else():
                m.d.sync += [half.eq(lo[0]), sticky.eq(sticky | half)]

        # Control word of the operation in the next clock (from the ROM below, registered).
        a_names = ["ACC"] + sorted({op_a[1] for op in ops
                                    for op_a in ([x for _, x in op.a] if isinstance(op.a, list)
                                                 else [op.a])
                                    if isinstance(op_a, tuple)})
        b_names = sorted({s for op in ops for s in op.sources() if s != "PRD"} | {"PRD"})
        a_sel = {k: Signal(name=f"a_{k if isinstance(k, str) else f'rnd{k}'}") for k in a_names}
        # B selects: one flip-flop per special source; the register-file words share one
        # (``b_rf``: B is the read port's data) and are told apart by the read address.
        b_sel = {k: Signal(name=f"b_{k.lower()}") for k in b_names if k not in rf_addr_of}
        b_rf = Signal()
        c_sub = Signal()
        c_cin = Signal()
        c_en = Signal()
        ctl_keys = ([("a", k) for k in a_sel] + [("b", k) for k in b_names]
                    + [("c", "sub"), ("c", "cin"), ("c", "en")])

        # Python-folded logic: a term is 0, 1 or a Value (flag-dependent).
        def t_and(x, y):
            if isinstance(x, int) and isinstance(y, int):
                return x & y
            if isinstance(x, int) or isinstance(y, int):
                c, v = (x, y) if isinstance(x, int) else (y, x)
                return v if c else 0
            return x & y

        def t_or(x, y):
            if isinstance(x, int) and isinstance(y, int):
                return x | y
            if isinstance(x, int) or isinstance(y, int):
                c, v = (x, y) if isinstance(x, int) else (y, x)
                return 1 if c else v
            return x | y

        def t_not(x):
            return 1 - x if isinstance(x, int) else ~x

        def cond(c):
            return 1 if c is None else Value.cast(c(cond_in))

        def decode(op):
            """Terms of the control word for ``op`` (in the order of ``ctl_keys``)."""
            if op is None or not op.alu:
                return [0] * len(ctl_keys)
            sel_v = {("a", k): 0 for k in a_sel}
            sel_v.update({("b", k): 0 for k in b_names})
            for field, sel in (("a", op.a), ("b", op.b)):
                choices = sel if isinstance(sel, list) else [(None, sel)]
                taken = 0
                for c, name in choices:
                    hit = t_and(cond(c), t_not(taken))
                    taken = t_or(taken, cond(c))
                    if name in (None, "Z"):
                        continue
                    key = name if field == "b" else name if name == "ACC" else name[1]
                    sel_v[field, key] = t_or(sel_v[field, key], hit)
            sub = cond(op.sub) if callable(op.sub) else int(op.sub)
            cin = sub if op.cin is None else op.cin
            return ([sel_v["a", k] for k in a_sel] + [sel_v["b", k] for k in b_names]
                    + [sub, cin, 1])

        by_clock = {op.clock: op for op in ops}
        # Events of a clock (registered one clock ahead, like the control word): writes and flag
        # captures of the operation before it, side actions of its own operation.
        wr_pairs = sorted({(d, k if isinstance(k, str) else k[0]) for op in ops
                           for d, k in op.wr.items()})
        ev_keys = ([("wr", *k) for k in wr_pairs] + [("flag", k) for k in flag_names]
                   + [("act", a) for a in ("shin", "mult_x", "mult_p")])
        ev_index = {key: i for i, key in enumerate(ev_keys)}

        def decode_events(c):
            """Terms of the event bits of clock ``c`` (in the order of ``ev_keys``)."""
            v = [0] * len(ev_keys)
            prev, now = by_clock.get(c - 1), by_clock.get(c)
            for dest, kind in (prev.wr.items() if prev else ()):
                kind, wc = kind if isinstance(kind, tuple) else (kind, None)
                v[ev_index["wr", dest, kind]] = cond(wc)
            for fl in (prev.flags if prev else ()):
                v[ev_index["flag", fl]] = 1
            for act in (now.act if now else ()):
                v[ev_index["act", act]] = 1
            return v

        # The control word and events of clock ``c`` (loaded in the clock before) come from a
        # ROM word. Three fields are codes (decoded in the loading clock): the B source (0: none;
        # one code per register-file name and special source), the register-file write (0: none;
        # one code per destination and kind) and the flags captured (one code per set of flags
        # an operation leaves); the rest are one bit each (A selects, carry, enable, the writes
        # of ``R`` and the output, side actions). A clock whose word depends on flags or
        # ``ref_delay`` (the selections they steer) has a one-hot "conditional" bit in the word,
        # ANDed with those terms. The ROM is read three clocks ahead into a register (synchronous
        # read port and one more register, so a block RAM's slow clock-to-out is off the path;
        # address ``step + 3``, 2 in the accepting clock), so the decode is a register and a few
        # gates, not a function of the step counter. The words of clocks 0 and 1 (loaded by the
        # accepting clock and the next, ``first``) are constants: the ROM's output is not
        # defined then (at power-on, after ``clear`` or the end of a run).
        keys = ctl_keys + ev_keys
        terms = [dict(zip(keys, decode(by_clock.get(c)) + decode_events(c)))
                 for c in range(clocks + 1)]
        rf_pairs = [(d, k) for d, k in wr_pairs if d not in _FF_DESTS]
        cap_sets = sorted({tuple(sorted(op.flags)) for op in ops if op.flags})
        # B codes: a register-file word's address, then the history names, then the specials
        # (so that the read address is the code, or a tap's address); write codes: kind and
        # address (the history slot of ``TP`` for its code).
        b_code = dict(rf_addr)
        for k in ("TP", "TAPA", "TAPB", *sorted(b_sel)):
            b_code[k] = len(b_code) + 1
        rf_code_max = b_code["TAPB"]
        ab = ceil_log2(max(rf_depth, rf_code_max + 1))
        wr_kinds = {"w": 0, "raw": 1, "wg": 2}
        groups = {                      # field → {key: code}
            "b": {("b", k): b_code[k] for k in b_names},
            "wrf": {("wr", d, k): (wr_kinds[k] << ab) | b_code[d] for d, k in rf_pairs},
        }
        grouped = {key for codes in groups.values() for key in codes}
        grouped |= {("flag", f) for f in flag_names}
        bits = [key for key in keys if key not in grouped]

        def cap_code(tc):
            if not all(isinstance(tc["flag", f], int) for f in flag_names):
                raise NotImplementedError("SpeedLoop: a conditional flag capture")
            got = tuple(f for f in flag_names if tc["flag", f])
            return cap_sets.index(got) + 1 if got else 0

        def code_terms(field, tc):
            """``(constant code, [(term, code)])`` of a code field in a clock's terms."""
            const, alts = 0, []
            for key, code in groups[field].items():
                t = tc[key]
                if isinstance(t, int):
                    const |= code if t else 0
                else:
                    alts.append((t, code))
            return const, alts

        widths = {"b": ceil_log2(max(b_code.values()) + 1), "wrf": ab + 2,
                  "cap": ceil_log2(len(cap_sets) + 1)}
        layout = {}                     # field → (offset, width) in the ROM word
        pos = len(bits)
        for field, fw in widths.items():
            layout[field] = (pos, fw)
            pos += fw
        n_f = pos
        cond_clocks = [c for c, tc in enumerate(terms[2:], 2)
                       if any(not isinstance(t, int) for t in tc.values())]
        n_c = len(cond_clocks)
        words = [0, 0]                  # clocks 0, 1: not read; clocks + 1: 0
        for c, tc in enumerate(terms[2:], 2):
            word = sum(1 << j for j, key in enumerate(bits)
                       if isinstance(tc[key], int) and tc[key])
            for field in ("b", "wrf"):
                word |= code_terms(field, tc)[0] << layout[field][0]
            word |= cap_code(tc) << layout["cap"][0]
            if c in cond_clocks:
                word |= 1 << (n_f + cond_clocks.index(c))
            words.append(word)
        m.submodules.ctl_rom = rom = Memory(shape=unsigned(n_f + n_c), depth=clocks + 2,
                                            init=words)
        rom_rd = rom.read_port()
        rom_q = Signal(n_f + n_c)
        m.d.sync += rom_q.eq(rom_rd.data)
        m.d.comb += rom_rd.addr.eq(Mux(running & ~clear & (step != clocks - 1), step + 3,
                                       Mux(accept, 2, 1)))
        first = Signal()                # the clock after an accept (step 0)
        m.d.sync += first.eq(accept)

        def expr(const, alts):
            v = const
            for t, code in alts:
                v = v | Mux(t, code, 0)
            return v

        # The control for the next clock: clock 0's terms on ``accept``, clock 1's on ``first``,
        # else the ROM word's (``arms``: those three per field). A code field's decodes are
        # made on each arm and then chosen (``pick``), so that ``accept`` (behind the Servo's
        # mode, ``clear``) meets only the last multiplexer in front of the control registers,
        # not the decodes too (ECP5 Fmax: ``active`` → ``b_prd``, docs/AREA.md §7.62).
        nv = {}                         # key / field → the value for the next clock (loading)

        def pick(arm_values):
            v0, v1, v2 = arm_values
            return Mux(accept, v0, Mux(first, v1, v2))

        for j, key in enumerate(bits):
            v = rom_q[j]
            for k, c in enumerate(cond_clocks):
                if not isinstance(terms[c][key], int):
                    v = v | (rom_q[n_f + k] & terms[c][key])
            nv[key] = pick((terms[0][key], terms[1][key], v))
        arms = {}                       # field → (clock 0's code, clock 1's, the ROM word's)
        for field in ("b", "wrf", "cap"):
            off, fw = layout[field]
            v = rom_q[off:off + fw]
            for k, c in enumerate(cond_clocks):
                if field != "cap":
                    const, alts = code_terms(field, terms[c])
                    if alts:
                        v = v | Mux(rom_q[n_f + k], expr(0, alts), 0)
            if field == "cap":
                c0, c1 = cap_code(terms[0]), cap_code(terms[1])
            else:
                c0, c1 = (expr(*code_terms(field, terms[c])) for c in (0, 1))
            arms[field] = tuple(C(x, fw) if isinstance(x, int) else Value.cast(x)[:fw]
                                for x in (c0, c1, v))
            sig = Signal(fw, name=f"next_{field}")
            m.d.comb += sig.eq(pick(arms[field]))
            nv[field] = sig

        def decoded(field, fn):
            """``fn`` of the field's value for the next clock, decoded on each arm."""
            return pick(tuple(fn(x) for x in arms[field]))

        for k in b_sel:
            nv["b", k] = decoded("b", lambda x, k=k: x == b_code[k])
        for f in flag_names:
            nv["flag", f] = decoded("cap", lambda x, f=f: Cat(
                *[x == j + 1 for j, s in enumerate(cap_sets) if f in s]).any())

        # The registered control: selects, carry, enable; events of FF destinations, flag
        # captures and side actions; the register file's B select and write port.
        ev_wr = {(d, k): Signal(name=f"wr_{d.lower()}_{k}") for d, k in wr_pairs
                 if d in _FF_DESTS}
        ev_flag = {f: Signal(name=f"cap_{f.lower()}") for f in flag_names}
        ev_act = {a: Signal(name=f"act_{a}") for a in ("shin", "mult_x", "mult_p")}
        wr_rf = Signal(name="wr_rf")
        wr_rf_addr = Signal(range(rf_depth), name="wr_rf_addr")
        wr_rf_raw = Signal(name="wr_rf_raw")
        wr_rf_g = Signal(name="wr_rf_g")
        ctl_load = [(a_sel[k], nv["a", k]) for k in a_sel]
        ctl_load += [(b_sel[k], nv["b", k]) for k in b_sel]
        # The integrator and E[n−1] read as 0 while ``zst`` (constant during a run).
        b_rf_v = decoded("b", lambda x: (x != 0) & (x <= rf_code_max)
                         & ~(zst & ((x == b_code["I"]) | (x == b_code["EP"]))))
        ctl_load += [(b_rf, b_rf_v), (c_sub, nv["c", "sub"]), (c_cin, nv["c", "cin"]),
                     (c_en, nv["c", "en"])]
        ev_load = [(ev_wr[k], nv[("wr", *k)]) for k in ev_wr]
        ev_load += [(ev_flag[f], nv["flag", f]) for f in flag_names]
        ev_load += [(ev_act[a], nv["act", a]) for a in ev_act]
        ev_load += [(wr_rf, decoded("wrf", lambda x: x[:ab] != 0)),
                    (wr_rf_addr, decoded("wrf", lambda x: Mux(x[:ab] == b_code["TP"],
                                                              rf_addr_of["TP"], x[:ab]))),
                    (wr_rf_raw, decoded("wrf", lambda x: x[ab:] == wr_kinds["raw"])),
                    (wr_rf_g, decoded("wrf", lambda x: x[ab:] == wr_kinds["wg"]))]
        # The read address (for the next clock, as ``next_b``) from the ROM word alone, not
        # from ``accept``, ``first`` or ``clear``: the operations of clocks 0 and 1, which those
        # select, read no register-file word (``b_rf`` is 0 then and after ``clear``), so the
        # RAM's read, in front of its data register, is on no path from the Servo's control.
        # The ROM's constant code gives the address (a fixed word's code is its address; a
        # history tap's, from ``slot``, ``age`` and ``ref_delay``, constant during a run); a
        # clock whose register-file word flags or ``ref_delay`` steer ORs in the address of
        # the word chosen (only fixed words are chosen so), the flags' only logic on the path.
        if any(not isinstance(terms[c]["b", k], int) or terms[c]["b", k]
               for c in (0, 1) for k in b_names if k in rf_addr_of):
            raise RuntimeError("SpeedLoop program: clock 0 or 1 reads the register file")
        off, fw = layout["b"]
        rom_b = rom_q[off:off + fw]
        rd_v = rom_b[:ab]
        for k in ("TP", "TAPA", "TAPB"):
            rd_v = Mux(rom_b == b_code[k], rf_addr_of[k], rd_v)
        for k, c in enumerate(cond_clocks):
            alts = [(terms[c]["b", name], rf_addr[name]) for name in b_names
                    if name in rf_addr_of and not isinstance(terms[c]["b", name], int)]
            if any(name in _ALIAS or name == "TP" for name in b_names
                   if name in rf_addr_of and not isinstance(terms[c]["b", name], int)):
                raise NotImplementedError("SpeedLoop: a history tap read under a condition")
            if alts:
                rd_v = rd_v | Mux(rom_q[n_f + k], expr(0, alts), 0)
        if ram:
            # The configuration RAM's address for the next clock: a multiplication's gain in the
            # clock that starts it (no operation that starts one reads the slew or the
            # feed-forward), the feed-forward for its operation, else the slew.
            assert not any(("mult_x" in op.act or "mult_p" in op.act)
                           and {"S", "IQFF"} & set(op.sources()) for op in ops)
            m.d.comb += cfg_rd.addr.eq(
                Mux(nv["act", "mult_x"], cfg_index["kx"],
                    Mux(nv["act", "mult_p"], cfg_index["kp"],
                        Mux(decoded("b", lambda x: x == b_code["IQFF"]), cfg_index["iq_ff"],
                            cfg_index["speed_slew"]))))
        m.d.comb += rf_rd_addr.eq(rd_v)
        # (Checked at each clock edge in every simulation and proved with ``speed_loop``.)
        m.d.sync += Assert(~(rf_wr_en & (rf_wr_addr == rf_rd_addr) & ~clear & (accept | running)
                             & b_rf_v),
                           "SpeedLoop: a register-file word read in the clock it is written")
        ctl = [s for s, _ in ctl_load]
        events = [s for s, _ in ev_load]

        with m.If(clear):
            m.d.sync += [running.eq(0), step.eq(0)] + [s.eq(0) for s in ctl + events]
        with m.Elif(accept | running):
            m.d.sync += [s.eq(v) for s, v in ctl_load + ev_load]
            with m.If(accept):
                m.d.sync += [running.eq(1), step.eq(0)]
            with m.Else():
                m.d.sync += step.eq(step + 1)
                with m.If(step == clocks - 1):
                    m.d.sync += running.eq(0)
        with m.Else():
            m.d.sync += [s.eq(0) for s in events]

        # The adder.
        a_val = 0
        cin_rnd = 0
        for k, sel in a_sel.items():
            if k == "ACC":
                a_val = a_val | Mux(sel, acc, 0)
            else:
                a_val = a_val | Mux(sel, acc >> k, 0)
                below = acc[:k - 1].any() if k > 1 else 0
                cin_rnd = cin_rnd | (sel & acc[k - 1] & (~acc[-1] | below))
        sources = {
            "R": R, "SREF": self.speed_ref, "S": cfg_q[:sw] if ram else self.speed_slew,
            "IQFF": (cfg_q[:IQ_WIDTH].as_signed() if ram else self.iq_ff) << s_out,
            "LIM_LO": self.lim_lo << s_out,
            "LIM_HI": self.lim_hi << s_out, "PRD": prd,
        }
        narrow_w = sw + 1
        narrow = 0
        wide = Mux(b_rf, rf_rd_data, 0)
        for name, sel in b_sel.items():
            v = Value.cast(sources[name])
            if len(v) + (0 if v.shape().signed else 1) <= narrow_w:
                narrow = narrow | Mux(sel, v, 0)
            else:
                wide = wide | Mux(sel, v, 0)
        b_n = Signal(signed(narrow_w))
        b_val = Signal(signed(wa))
        m.d.comb += [b_n.eq(narrow), b_val.eq(b_n | wide)]
        cin = c_cin | cin_rnd | (b_sel["PRD"] & prd_inc)
        res = Signal(signed(wa))
        exact = Signal(signed(wa + 2))
        m.d.comb += [res.eq(a_val + Mux(c_sub, ~b_val, b_val) + cin),
                     exact.eq(a_val + Mux(c_sub, ~b_val, b_val) + cin)]
        with m.If(c_en):
            m.d.sync += acc.eq(res)
            # The widths above are such that no operation wraps (checked in every simulation).
            m.d.comb += Assert(res == exact, "SpeedLoop: adder result wraps")

        # Writes, flags and side actions of the clock (the operation of the clock before writes
        # its result).
        def sat(value, width):
            # saturate_bits, its result signed(width) so that a wider register sign-extends it.
            out = Signal(signed(width))
            m.d.comb += out.eq(saturate_bits(value, signed(width)))
            return out

        acc_w = sat(acc, w)
        kinds = {"raw": acc, "q16": sat(acc, IQ_WIDTH)}
        # Register-file writes: raw (truncated: exact, proved), sat(acc, w), or that times 2**g;
        # the speed sample in the accepting clock (no run writes then).
        # The address and data select on ``accept`` without its ``~clear`` (``sample``): while
        # ``clear`` nothing is written, otherwise the two are equal; so the Servo's trip and
        # mode (``clear``) reach the RAM's write enable only, not its data (ECP5 Fmax, docs/
        # AREA.md §7.58).
        sample = Signal()
        m.d.comb += [
            sample.eq(self.i.valid & (count == 0) & ~running),
            rf_wr_en.eq((wr_rf & ~clear) | accept),
            rf_wr_addr.eq(Mux(sample, rf_addr["SPD"], wr_rf_addr)),
            rf_wr_data.eq(Mux(sample, self.i.payload.speed,
                              Mux(wr_rf_raw, acc, Mux(wr_rf_g, acc_w << g, acc_w)))),
            Assert(~(accept & wr_rf), "SpeedLoop: a run's write in the accepting clock"),
        ]
        if ram:
            # (The RAM's words are read during a run only: a write then would change a run's
            # input, as a port must not.)
            m.d.comb += Assert(~(cfg.valid & (accept | running)),
                               "SpeedLoop: a configuration write during a run")
        tests = {"neg": acc[-1], "nneg": ~acc[-1], "nz": acc.any(), "pos": ~acc[-1] & acc.any()}
        if ram:                         # the word read in the clock before (above)
            gain = {name: cfg_q[:f.width].as_signed() if f.signed else cfg_q[:f.width]
                    for name, f in (("KP", kpf), ("KX", kxf))}
        else:
            gain = {"KP": self.kp, "KX": self.kx}
        hold_i = self.int_hold & snz_r & (flags["DNZ"] | ((d_int != 0) & flags["MVD"]))
        hold_b = (flags["AC"] & flags["DIP"]) | (flags["BC"] & flags["DIN"])
        m.d.sync += self.o.valid.eq(0)                  # a strobe (set below)
        with m.If(~clear):
            for (dest, kind), en in ev_wr.items():
                with m.If(en):
                    m.d.sync += regs[dest].eq(kinds[kind])
                    if dest == "OPAY":
                        m.d.sync += [
                            self.o.valid.eq(1),
                            self.sat.eq(Mux(hold_b, flags["AK"] | flags["BK"],
                                            flags["AC"] | flags["BC"])),
                        ]
            flag_test = {fl: test for op in ops for fl, test in op.flags.items()}
            for fl, en in ev_flag.items():
                with m.If(en):
                    m.d.sync += flags[fl].eq(tests[flag_test[fl]])
            with m.If(ev_act["shin"]):
                m.d.sync += [slot.eq(slot + 1), age.eq(Mux(age == n, n, age + 1)), zst.eq(0)]
            for act in ("mult_x", "mult_p"):
                with m.If(ev_act[act]):
                    if act == "mult_x":
                        m.d.sync += [lo.eq(Mux(hold_i, 0, gain["KX"])), m_signed.eq(kxf.signed)]
                    else:
                        m.d.sync += [lo.eq(gain["KP"]), m_signed.eq(kpf.signed)]
                    m.d.sync += [mc.eq(acc << lsh[act]), hi.eq(0), half.eq(0), sticky.eq(0),
                                 m_cnt.eq(mw + max(sh[act], 0)), m_shift.eq(mw)]

        # Clear: run abandoned, state zeroed (the integrator and E[n−1] through ``zst``, the
        # history through ``age``), R tracks.
        track = Mux(snz, self.i.payload.speed, self.speed_ref)
        with m.If(clear):
            m.d.sync += [
                m_cnt.eq(0), m_shift.eq(0), age.eq(0), zst.eq(1), R.eq(track),
                self.o.payload.eq(0), self.sat.eq(0), self.o.valid.eq(0),
            ]
        m.d.comb += self.ref_int.eq(R)
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

    **Reference step.** ``ref_step`` strobes in a ``loop`` clock when ``ref_change`` was high in
    a clock after the previous ``loop`` strobe or in that strobe's own clock (a pending flag, set
    by ``ref_change``, cleared by ``loop``): the caller raises ``ref_change`` in the clock in
    whose end one of ``mode``, ``speed_ref``, ``id_set``, ``iq_set``, ``ud_set``, ``uq_set`` is
    loaded (:class:`~.top.Top`: a commit of a host write to one of their registers), so the
    first ``loop`` strobe that sees the new value strobes (the trace buffer's ``trigger``). A
    flag instead of a compare of the ≈ 100 bits with their values at the previous strobe
    (−98 flip-flops, docs/AREA.md "Session 12"): a write of an unchanged value strobes too.

    Parameters
    ----------
    speed_width, width, kp_format, kx_format, int_guard, div_width, delay_width, mul_width
        Of the :class:`SpeedLoop`.
    phase_width : int
        Width of the open-loop phase accumulator, 16 … 48.
    config, config_init
        Of the :class:`SpeedLoop`: ``config="ram"`` replaces ``speed_kp``, ``speed_kx``,
        ``speed_slew`` and ``iq_ff`` by ``speed_config``.
    speed_loop : str
        ``"sequential"`` (default): the :class:`SpeedLoop` inside. ``"engine"``: no speed loop
        here: the loop engine runs it (``EngineCurrentLoop(speed=True)``, beside the Servo,
        fed by the caller with the speed-loop inputs and ``speed_clear``); its results come in
        on ``sl_iq`` (``valid``, ``payload``), ``sl_sat``, ``sl_ref_int`` and leave as
        ``iq_ref`` (SPEED mode), ``speed_sat``, ``speed_valid``, ``speed_ref_int`` as they
        would from the SpeedLoop. The members ``speed``, ``speed_ref``, ``speed_kp``,
        ``speed_kx``, ``speed_rate_div``, ``speed_slew``, ``iq_ff``, ``speed_ref_delay``,
        ``speed_int_hold`` (and ``speed_config``) are then absent; the speed-loop parameters
        must be the program's (:data:`~.foc_engine.SPEED_PARAMS`), ``config`` is not given.

    Members
    -------
    loop : In(1)
        Loop-boundary strobe (the PWM ``period_start``).
    mode : In(Mode)
    trip : In(1)
        Protection trip (level).
    ol_src : In(AngleMode)
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
    ref_change : In(1)
        Strobe: a reference or the mode is loaded at the end of this clock (sets the
        reference-step flag, see above).
    speed_config : In(WordWriteSignature(4))
        ``config="ram"`` only, instead of ``speed_kp``, ``speed_kx``, ``speed_slew`` and
        ``iq_ff``: the :class:`SpeedLoop`'s ``config`` (writes into its configuration RAM).
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
        Reference-step strobe: ``loop`` with the flag set (see above).
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
                 int_guard=16, div_width=8, delay_width=5, phase_width=32, mul_width=MUL_WIDTH,
                 config="ports", config_init=None, speed_loop="sequential"):
        check_speed_loop(speed_width, width, kp_format, kx_format, int_guard, div_width,
                         delay_width)
        check_choice("Servo", "speed_loop", speed_loop, SPEED_LOOPS)
        if speed_loop == "engine":
            from .foc_engine import SPEED_PARAMS
            given = dict(speed_width=speed_width, width=width, kp_format=kp_format,
                         kx_format=kx_format, int_guard=int_guard, delay_width=delay_width)
            for name, value in given.items():
                if value != SPEED_PARAMS[name]:
                    raise ValueError(f"Servo speed_loop='engine' needs {name} "
                                     f"{SPEED_PARAMS[name]!r} (the engine's speed program is "
                                     f"written for it), not {value!r}")
            if div_width != 8:
                raise ValueError(f"Servo speed_loop='engine' needs div_width 8 (the engine's "
                                 f"rate_div), not {div_width!r}")
            if config != "ports" or config_init is not None:
                raise ValueError("Servo speed_loop='engine' takes no config or config_init "
                                 "(the configuration words are the engine's)")
        self._speed_loop = speed_loop
        mul_width = check_mul_width("Servo", mul_width)
        if not is_int(phase_width) or not 16 <= phase_width <= 48:
            raise TypeError(f"Servo phase_width must be an integer from 16 to 48, "
                            f"not {phase_width!r}")
        config_init = check_speed_config("Servo", config, config_init, speed_width, kp_format,
                                         kx_format)
        self._loop_params = dict(speed_width=speed_width, width=width, kp_format=kp_format,
                                 kx_format=kx_format, int_guard=int_guard, div_width=div_width,
                                 delay_width=delay_width, mul_width=mul_width, config=config,
                                 config_init=config_init)
        self._phase_width = phase_width
        self._speed_loop_timing = speed_loop_timing(speed_width, width, kp_format, kx_format,
                                                    int_guard, delay_width)
        a = ANGLE.shape
        q = signed(IQ_WIDTH)
        members = {
            "loop": In(1),
            "mode": In(Mode),
            "trip": In(1),
            "ol_src": In(AngleMode),
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
            "ref_change": In(1),
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
        }
        if config == "ram":             # SpeedLoop(config="ram"): its config port instead
            for name in _SERVO_CONFIG:
                del members[name]
            members["speed_config"] = In(WordWriteSignature(len(SPEED_CONFIG)))
        if speed_loop == "engine":      # the engine's speed run: its results come in
            for name in _ENGINE_GONE:
                del members[name]
            members.update({"sl_iq": In(stream.Signature(q, always_ready=True)),
                            "sl_sat": In(1), "sl_ref_int": In(signed(speed_width))})
        super().__init__(members)

    loop_params = property(lambda self: dict(self._loop_params))
    config_mode = property(lambda self: self._loop_params["config"])
    phase_width = property(lambda self: self._phase_width)
    speed_loop_latency = property(lambda self: self._speed_loop_timing["latency"])
    speed_loop = property(lambda self: self._speed_loop)

    def elaborate(self, platform):
        m = Module()
        pw = self._phase_width
        engine = self._speed_loop == "engine"
        if not engine:
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
        if engine:
            # The engine's speed run (cleared by ``speed_clear``): its results.
            sl_iq = self.sl_iq.payload
            m.d.comb += [self.speed_clear.eq(~is_speed),
                         self.speed_sat.eq(self.sl_sat), self.speed_valid.eq(self.sl_iq.valid),
                         self.speed_ref_int.eq(self.sl_ref_int)]
        else:
            sl_iq = sl.o.payload
            # The speed loop's ``clear`` from a copy of ``active == SPEED`` of its own (loaded
            # like ``active``): ``active`` drives the Servo's outputs too, and its decode and
            # fan-out were in front of the speed loop's control registers (ECP5 Fmax,
            # docs/AREA.md §7.62). ``trip`` still clears it in its own clock.
            sl_speed = Signal()
            with m.If(self.trip):
                m.d.sync += sl_speed.eq(0)
            with m.Elif(self.loop):
                m.d.sync += sl_speed.eq(self.mode == Mode.SPEED)
            m.d.sync += Assert(sl_speed == (active == Mode.SPEED),
                               "Servo: the speed loop's copy of the mode and active disagree")
            if self.config_mode == "ram":
                wiring.connect(m, speed_config=wiring.flipped(self.speed_config),
                               speed_loop=sl.config)
            else:
                m.d.comb += [getattr(sl, name).eq(getattr(self, port))
                             for name, port in zip(SPEED_CONFIG, _SERVO_CONFIG)]
            m.d.comb += [
                sl.speed_ref.eq(self.speed_ref),
                sl.lim_lo.eq(self.iq_lim_lo),
                sl.lim_hi.eq(self.iq_lim_hi),
                sl.rate_div.eq(self.speed_rate_div),
                sl.ref_delay.eq(self.speed_ref_delay),
                sl.int_hold.eq(self.speed_int_hold),
                sl.clear.eq(self.trip | ~sl_speed),
                self.speed_clear.eq(~is_speed),
                self.speed_sat.eq(sl.sat),
                self.speed_valid.eq(sl.o.valid),
                self.speed_ref_int.eq(sl.ref_int),
            ]

        # Open-loop phase accumulator.
        acc = Signal(unsigned(pw))
        rotating = is_ol & (self.ol_src == AngleMode.ROTATING)
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
                with m.Case(AngleMode.ROTATING):
                    m.d.comb += self.theta.eq(acc[pw - ANGLE.width:])
                with m.Case(AngleMode.MEASURED):
                    m.d.comb += self.theta.eq(self.theta_meas)
                with m.Default():
                    m.d.comb += self.theta.eq(self.ol_theta)
        # clamp(iq_set, lo, hi) with both compares written as lim ± ~iq_set (iq_set > hi ⇔
        # hi − iq_set < 0; iq_set < lo ⇔ lo + ~iq_set ≥ 0): the limits (registers, mostly
        # init-0 flip-flops on lo's side and init-1 on hi's, which a compare against them
        # would invert bit by bit) on the carries' non-inverted side, one ~iq_set for both.
        iq_over = (self.iq_lim_hi - self.iq_set)[-1]
        iq_under = ~(self.iq_lim_lo + ~self.iq_set)[-1]
        with m.If(is_cur):
            m.d.comb += [
                self.iq_ref.eq(Mux(iq_over, self.iq_lim_hi,
                                   Mux(iq_under, self.iq_lim_lo, self.iq_set))),
                self.id_ref.eq(self.id_set),
            ]
        with m.If(is_speed):
            m.d.comb += [self.iq_ref.eq(sl_iq), self.id_ref.eq(self.id_set)]

        # Reference step: a flag set by ref_change, strobed out and cleared at loop boundaries
        # (a change in the strobe's own clock is seen at the next one).
        step_pending = Signal()
        m.d.sync += step_pending.eq(self.ref_change | (step_pending & ~self.loop))
        m.d.comb += self.ref_step.eq(self.loop & step_pending)
        return m
