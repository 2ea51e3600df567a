# Ref: paper Fig. 1 (system structure), Fig. 2 (FPGA controller); SPEC.md §4; issue 5 item 6
"""The whole servo controller between its pins: every block, wired to the register file.

::

    uart_rx/tx ─ HostLink ─ bus ─ RegisterFile ─ (every register ↔ its block port)
    enc_a/b/z, hall ─ EncoderFrontEnd (own 2-flop sync + filter) ─ θ_e, count, step/up ─ MTSpeed
    PWMTimer ─ sample ─ AdcInterface (adc_cs_n, adc_sclk, adc_sdo) ─ CurrentLoop ─ duties ─
        DeadTimeComp (+ trapezoid of CurrentLoop.phase, combinational) ─ PWMTimer
    PWMTimer.pwm ─ Gates (dead time, enable = Servo.enable, trip) ─ gate_h, gate_l
    fault_n, oc_comp ─ FFSynchronizer (2 flops) ─ Protection ─ trip ─ Gates, Servo
    EncoderFrontEnd illegal, hall_fault, plausibility (encoder/Hall check) ─ Protection
    Servo (modes, speed loop, open-loop angle) ─ θ, references ─ CurrentLoop; ref_step ─ Scope
    MTSpeed speed × theta_lead register ─ LeadAngle ─ θ_lead ─ CurrentLoop (inverse Park θ + θ_lead)
        (current_loop="engine": the program computes θ_lead from the speed and the register)

Timing within one PWM period (``period_start`` = ``pos`` 0):

* ``period_start``: the register file commits staged writes (``commit``), the Servo copies the
  mode and runs its open-loop accumulator (``loop``), the M/T speed window closes (``update``);
* ``sample`` (period centre by default): the ADC converts; ``AdcInterface.latency`` clocks later
  the current loop starts (θ, references latched), its duties load at the next period boundary.

So the control parameters change only while the current loop is idle, as its inputs require,
provided the loop finishes before the period ends (``pwm_sample_custom`` must not put the sample
within :attr:`Top.loop_latency` = ``AdcInterface.latency`` + the current loop's latency clocks of
the period end: 95 with the pipelined loop, 216 with ``current_loop="engine"``, at 50 MHz).

**Register commit with** ``regs_staging="bram"`` (the staging registers in a block RAM,
:class:`~.regs.RegisterFile`): the commit is a copy of one word per clock, so it starts
:attr:`Top.commit_clocks` (49) clocks before ``period_start`` (at ``pos = 2N − commit_clocks``)
and every new value is in place in the ``period_start`` clock. Every block that samples its
registers at a period event then sees one commit's values whole: the Servo's ``loop`` and the
M/T ``update`` at ``period_start``, ``theta_lead`` and the speed loop after ``mt.o.valid``, the
current loop from the sample on, and the PWM timer's mode, latched in the period's last clock:
``pwm_symmetric`` is the copy's last word (changed at the end of that clock, after the latch),
so the timer changes mode one boundary later together with the duties computed for the new
scale, as with ``"ff"``. Differences from ``"ff"``: the Servo's ``loop`` strobe at
``period_start`` sees the new values (``"ff"``: the old ones, the new from the next period), so
a ``mode`` write takes effect one PWM period earlier (the gates, the current loop and the speed
loop start, or stop, at that boundary, not the next; references the blocks read after
``period_start``, e.g. ``speed_ref`` in the speed loop's run, act in the same period with
both; docs/AREA.md §7.60: why ``sim step``'s ss_err_pct differs between the two);
inputs read in every clock (the encoder's configuration, ``dead_time``, the sample point)
change word by word over the copy, a register group within its few consecutive clocks (the
encoder's ``enc_lines``, ``enc_pole_pairs`` and ``enc_z_offset`` and their change strobes in
three consecutive clocks: one configuration sequence of the decoder, as one commit with
"ff"); a frame whose ``lock`` falls in the copy window (or is high at its start) is applied a
period later; and the current loop must be idle in the window too (the sample not within
``loop_latency + commit_clocks`` clocks of the period end).

**Engine configuration in RAM** (``current_loop="engine"`` with ``regs_staging="bram"``, the
iCEBreaker): the register file holds no flip-flops for the current loop's 16 configuration
registers (:data:`ENGINE_CONFIG`: Clarke gains and offsets, PI gains and limits, decoupling
``L`` and ``ψ``, ``theta_lead``, ``u_rated``); its commit copy writes them through its
``export`` port into the loop engine's configuration RAM in the clocks the flip-flops would
have changed (``EngineCurrentLoop(config="ram")``), so the loop sees the same values in the
same clocks. (One exception, in the reset walk's 63 clocks after a domain reset: the
flip-flops would have held the reset values at once, the RAM gets them word by word.) The
loop's eight status values (``st_i_alpha`` … ``st_u_beta``, the scope's sources of the same
names) are in the engine's status RAM (``EngineCurrentLoop(status="ram")``), read through one
read port each by the register file (``RegisterFile(status_ram=...)``) and the scope
(``Scope(ram_sources=...)``): the same values in the same clocks as from the registers (a
domain reset does not clear the RAM, where it cleared the registers).

**Speed-loop configuration in RAM** (``regs_staging="bram"``, either current loop): the same for
the speed loop's gains, slew and feed-forward (:data:`SPEED_LOOP_CONFIG`: ``pi_speed_kp``,
``pi_speed_kx``, ``speed_slew``, ``speed_ff_iq``), the export port's words after the engine's,
into the speed loop's configuration RAM (``Servo(config="ram")``, :class:`~.servo.SpeedLoop`).
The loop reads them only during a run, which starts at M/T's result after ``period_start`` and
ends ~125 clocks later, while the copy runs before ``period_start``: the PWM period must leave
room for both (as it did for the loop's ports, which the copy changed too). The reset walk
writes them too, so no run starts while it lasts (``RegisterFile.export_walk`` holds off the
Servo's speed strobe): after a reset the first M/T result (~40 clocks later) is not used, the
speed loop runs from the next one (only visible when ``mode``'s reset value is SPEED; the
default, DISABLED, runs no loop).

**Speed loop on the engine** (``speed_loop="engine"``, only with ``current_loop="engine"`` and
``regs_staging="bram"``: the iCEBreaker): no :class:`~.servo.SpeedLoop`; the loop engine runs
the speed loop as a second program (``EngineCurrentLoop(speed=True)``), bit for bit the same
results. The speed words go into the engine's configuration RAM after its 16 (one export
port, all 20 words); M/T's strobe (held off in the reset walk, as above), the speed
reference, the i_q limits, ``speed_div``, ``speed_ref_delay``, ``speed_int_hold`` and the
Servo's ``speed_clear`` go to the engine, whose i_q reference, ``sat`` and ``ref_int`` come
back into the Servo (``Servo(speed_loop="engine")``). The run starts at M/T's strobe if the
engine is idle and gives its i_q reference 228 … 233 clocks later (``speed_timing``; the
SpeedLoop: 120), so a centred sample still sees this period's reference while half a period
exceeds ``MTSpeed.latency + 1 + speed_latency`` (checked: ``ValueError``; at 10 kHz and 33 MHz
half a period is ≈ 1 650 clocks, against 38 + 1 + 233). The run reads M/T's output register
itself (``EngineCurrentLoop.speed_read`` clocks after its start, no latch), which holds for a
period from the strobe, longer than a run's wait for a current-loop sample (``interval``) and
that read (checked too). **Sample-point limit:** a
current-loop sample that arrives during a speed run waits for it (and a speed run for a
current-loop sample): a ``pwm_sample_point`` (``pwm_sample_custom``) that puts the sample
(+ ``AdcInterface.latency``) within ≈ 233 clocks after M/T's strobe, i.e. within
≈ ``MTSpeed.latency + 233`` clocks after ``period_start``, delays its duties by up to the speed run's 228 instructions (they may then
load a period late) and takes the previous period's i_q reference; the M/T strobe must
likewise not fall in a current-loop run, i.e. the sample must come more than
``AdcInterface.latency + EngineCurrentLoop.interval`` clocks before the period end (the limit
of ``loop_latency`` above, a little longer). Not checked in gateware (the registers are
run-time values); the default centred sample is far from both.

**M/T on the engine** (``mt_engine``, only with ``current_loop="engine"``,
``regs_staging="bram"`` and ``mt_k_export``; docs/AREA.md §7.64, §7.82): M/T keeps its window
logic (``MTSpeed(arith="engine")``) and hands each accepted update's operands to the loop
engine, whose run ``mt`` (``EngineCurrentLoop(mt=True)``) does the multiply and divide; ``k``
is ``mt_k``'s two export words, the last exported, in the engine's configuration RAM (after
its own words; moved down over the speed loop's words when the speed loop is the Servo's).
Three behaviour changes against M/T's own arithmetic: (1) the TC span is 27 bits
(:data:`MT_ENGINE_TC_WIDTH`; the engine's ``DIV`` divisor is its multiplier's signed 28-bit
operand): an edge interval of 2**27 … 2**28 clocks (4.03 … 8.05 s at 33.333 MHz) reads
stopped, i.e. speeds below ≈ 0.00075 r/min at 20 000 counted edges per turn; (2) the result
comes :attr:`Top.mt_latency` clocks after ``period_start`` (1 + the run's
``EngineCurrentLoop.mt_latency``: 113 against ``MTSpeed.latency`` 38), when the engine is idle
at ``period_start`` (the sample-point limit of "Speed loop on the engine": the sample must
come more than ``AdcInterface.latency + EngineCurrentLoop.interval`` clocks before the period
end; an M/T request that finds a current-loop program running waits for its END, and a sample
that arrives during the M/T run waits for the run's ``length``, 110 clocks, which
``sample_hold`` includes); (3) with the speed loop on the engine its run starts at M/T's
strobe, i.e. after the M/T run (the start arbitration: a current-loop sample first, then the
M/T run, then a speed run; each requested run waits while another runs), so its i_q reference
is ready ``mt_latency + 1 + speed_latency`` clocks after ``period_start`` (checked against half
a period, as above); after a reset, M/T's first (stopped) result comes after the register
file's reset walk (72 clocks on the iCEBreaker) and requests a speed run, where M/T's own
result (38 clocks) fell in the walk, which holds the run off. Every M/T output (speed,
stopped, fresh) is otherwise ``MTSpeedModel``'s with the 27-bit TC (tests:
``test_top_mt_engine_speed_matches_the_model``, ``tests/test_engine_mt.py``).

**Delay compensation.** The current loop's Park rotation uses θ_e at the sample; its inverse
Park uses ``θ_e + θ_lead``, ``θ_lead = speed/N_FS · theta_lead`` (:class:`LeadAngle`), the angle
the rotor turns in ``t_lead`` when the register holds ``ω_e(N_FS)·t_lead``. The new duties act
from the next period boundary (T/2 after a centred sample) for one period, so their mean is
``t_lead = 1/pwm_hz`` after the sample (``host.tuning.lead_angle``). ``θ_lead`` is computed from
each M/T result (``mt.o.valid``, after the register commit of the same period start) and is
ready ``MTSpeed.latency + 1 + LeadAngle.latency`` clocks after ``period_start`` (56 at 50 MHz);
a sample taken earlier uses the previous period's value. With ``current_loop="engine"`` there is
no LeadAngle: the engine computes the same ``θ_lead`` in its program from the speed it latches
at the sample (M/T's output register itself) and the register; the same value whenever the
sample comes more than ``LeadAngle.latency + 2`` clocks after ``mt.o.valid`` (always, unless
``pwm_sample_point`` puts it within ``MTSpeed.latency + LeadAngle.latency + 2`` clocks after
``period_start``); a sample in that window (``mt.o.valid``'s own clock included) uses the new
speed (the pipelined loop: the previous period's θ_lead), as its feed-forward does.

**The speed's consumers.** With the pipelined loop M/T's result reaches the current loop and
the protection's overspeed check through one register (``cl_speed``), LeadAngle as the 16-bit
rounded speed through another (``lead_n``), and the strobe that starts LeadAngle and samples
the overspeed verdict through a third (``speed_valid_q``): all one clock after ``mt.o.valid``
(ECP5 Fmax: M/T's output register fans out across the die; the rounding to 16 bits and the
32-bit ``|speed| > os_limit`` compare behind it were the whole top's critical paths,
docs/AREA.md). With ``current_loop="engine"`` (the iCE40 top) there is no ``cl_speed``: the
engine and the overspeed check take M/T's output register (which changes only in the clock of
``mt.o.valid``, so the overspeed verdict at ``speed_valid_q`` is the same; the engine latches
the new speed at a sample in ``mt.o.valid``'s own clock, where ``cl_speed`` held the old one).
The Servo's speed loop, the scope and ``st_speed`` take M/T's output itself.

**References.** The current loop takes the Servo's ``id_ref`` and ``iq_ref`` through a register
(the one the trace records, ``i_d_ref`` / ``i_q_ref``): a clock after the Servo forms them from
the register file, the mode and the speed PI (ECP5 Fmax: the clamp and mode multiplexer in
front of the loop's sample latch, docs/AREA.md). The loop latches them at its sample, which the
commit, the mode copy (``period_start``) and the timing rule above keep clear of, so only a
speed-PI result in the sample's own clock changes what it latches: the previous result, the new
one at the next sample. (A trip lowers ``enable`` at once and the loop's PIs are then held
cleared whatever the references.)

**References in the engine's RAM** (``current_loop="engine"``, ``speed_loop="engine"``,
``regs_staging="bram"``: the iCEBreaker; :data:`ENGINE_REFS`, docs/AREA.md §7.69): ``ol_u_d``,
``ol_u_q``, ``i_d_ref``, ``i_q_ref``, ``pi_speed_lim_lo`` and ``pi_speed_lim_hi`` are words of the
engine's configuration RAM after its 16 (the export port, before the speed loop's four): no
flip-flops in the register file, no reference registers here, no latches in the engine, and the
Servo's reference outputs (its mode multiplexer and i_q clamp) unused. The program forms the
references as the Servo did (``EngineCurrentLoop(refs="ram")``: ``i_d = i_d_ref``; i_q the
set-point clamped to the limits in CURRENT mode, the speed run's result in SPEED mode; the open-loop
voltages under ``OL``; the speed run's limits from the same words), reading the words while it
runs, where the latches took the ports at the sample: the same values, since the commit copy
and the mode copy come while the loop is idle (the timing rule above); a speed run's result
that a sample waiting behind it (the sample-point limit of "Speed loop on the engine") reads is
that run's (the latch took the previous one; the trace already showed that run's). The scope's
``i_d_ref`` / ``i_q_ref`` come from the engine's status RAM, which the program writes with the
references it used (two words after the eight status values, in the scope's RAM only), each
read as 0 here (the RAM's never-written word) unless the mode one clock before the sampled
clock was CURRENT or SPEED: the values the registers would have held, a trip in the middle of a pass included (the tests:
``test_top_scope_reads_the_engine_references_as_the_registers_held_them``,
``tests/test_engine_refs.py``).

**Scope trigger.** The Servo's ``ref_step`` strobes at the first loop strobe that sees the
value of a host write to the mode or a reference (:data:`REF_STEP_REGISTERS`): the top flags
such a write at its ``ack`` (an address look-up on the bus, not a compare of the values) and
passes the flag to the Servo (``ref_change``) in the clock the register file takes the commit
that applies it (``"ff"``: ``commit`` with ``lock`` low, the Servo's strobe at the *next*
``period_start``, as its loop sees the old values in the commit's clock; ``"bram"``: the
copy's export-port writes, the strobe at the ``period_start`` that ends the copy). So a frame
writing an unchanged value triggers too (session 11 and before compared ≈ 100 register bits
with their values at the previous strobe, docs/AREA.md "Session 12"); for a changed value the
strobe is in the same clock as before. ``ref_step`` reaches the scope through a register, one
clock later (ECP5 Fmax, when it was the compare: docs/AREA.md, "Session 11"). The trigger
sample is the first sample taken at or after the trigger's clock, so the capture differs only
if a current-loop ``done`` falls in the clock of the loop strobe itself: that sample is then
the last pre-trigger sample and the next one the trigger sample.

**Status.** Besides the blocks' own outputs, the top keeps wrapping 16-bit counters of current-
loop overruns (``st_overruns``), dropped ADC strobes (``st_adc_overruns``) and speed-loop runs,
and the sticky ``st_loop_flags`` (over-modulation, PI_d / PI_q / speed PI saturation, DC-bus gain
limit), set by any loop completing with the condition and cleared by ``clear_faults``. The host
link's 16-bit counters (``st_link_*``) count the frames before the one that reads them. With
``regs_staging="bram"`` these eight counters (:data:`TOP_COUNTERS` and the link's) and
``st_current_loops`` (the current loop's passes, :data:`RAM_LOOP_COUNTERS`; with
``ram_loop_count``, the iCE40's) are words
of the register file's staging RAM, counted from strobes (``RegisterFile(counters=...)``,
docs/AREA.md §7.59): a read returns the same value as from flip-flops, but a register access
taken in the clock of a count (or while one is pending) waits until the count is written (two
clocks a count, more behind a commit copy), so a link frame whose accesses meet a speed-loop
run, an overrun or a dropped byte is answered that much later. The link's four reply counters
count after the frame's last access (never delayed); the Top checks that the PWM period and two
UART bytes last at least ``count_interval`` clocks (no count is lost).
``st_udc`` (and the scope's ``u_dc``) is the U_dc code the current loop latched with the last
sample it accepted (its ``udc`` output, the protection's too), a clock after the ADC's
``o.valid``; a sample the loop drops (an overrun) does not change it (before session 12 the
ADC held the code of every conversion in a register of its own, 16 FF).

**Protection limits in RAM** (``prot_limits="ram"``, with ``regs_staging="bram"``: the
iCEBreaker, docs/AREA.md §7.77): the register file holds no flip-flops for ``prot_oc_limit``,
``prot_ov_limit``, ``prot_uv_limit`` and ``prot_os_limit`` (:data:`PROT_LIMITS`); its staging
RAM's writes of them (a host write's ``t + 1``, the reset walk) go through its ``mirror`` port
into the protection's limit RAM (``Protection(limits="ram")``), so a limit write acts one
clock later than the flip-flops did, and the protection compares the sampled causes one per
clock on one comparator: an over-current, over-/under-voltage or over-speed verdict reaches
``trip`` :attr:`~.protect.Protection.step_latency` clocks after its sample (2 … 4; the limit
ports' form: 1), the pin causes as before (:attr:`fault_latency`).

A driver fault (``fault_n`` low) reaches the gates in :attr:`Top.fault_latency` clocks: 2 clocks
of synchroniser, 1 in :class:`~.protect.Protection` (``present`` register, ``trip`` follows
combinationally), 1 in :class:`~.gates.Gates` (registered outputs). Only the gates and the
``led`` pin take ``trip`` straight from the protection; the Servo (its mode, the loops' clears)
and the ``st_trip`` status see it through a register, one clock later, so that the trip's wide
fan-out into the loops is off the path from ``present`` (docs/AREA.md §7.12).
"""

import math
import numbers
from collections.abc import Mapping

from amaranth.hdl import Cat, Module, Mux, Signal, Value, signed, unsigned
from amaranth.lib import wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

from .adc import AdcInterface
from .deadtime_comp import DeadTimeComp
from .dsp import MUL_WIDTH, check_mul_width
from .encoder import EncoderFrontEnd
from .fixed import at_least, check_bool, check_choice, round_shift, saturate
from .foc import SPEED_WIDTH, CurrentLoop
from .foc_engine import CONFIG as ENGINE_CONFIG_SPECIALS
from .foc_engine import REF_CONFIG_WORDS as ENGINE_REF_WORDS
from .foc_engine import REF_STATUS as ENGINE_REF_STATUS
from .foc_engine import STATUS as ENGINE_STATUS
from .foc_engine import EngineCurrentLoop
from .gates import Gates
from .gates import dead_n as gates_dead_n_value
from .gates import dead_n_const as gates_dead_n_const
from .hostlink import COUNTERS, HostLink
from .mt_speed import MTSpeed
from .protect import FAULTS, LIMIT_FORMS, LIMITS, Protection
from .regmap import (LINK_COUNTERS, LOOP_FLAG_FIELDS, MT_EDGES, MT_EDGES_PER_LINE, Access, Scales,
                     build_regmap, mt_k_for)
from .regs import STAGINGS as REGS_STAGINGS
from .regs import Derived, RegisterFile, staging_slots
from .scope import RAMS as SCOPE_RAMS
from .scope import Scope
from .servo import SPEED_CONFIG, SPEED_LOOPS, Servo
from .svpwm import PWMTimer, pwm_half_period

__all__ = ["Top", "LeadAngle", "regmap_address_map"]

#: Width of the PWM counter, the duties and ``pwm_sample_point``.
COUNT_WIDTH = 16
#: Synchroniser flops on ``fault_n`` and ``oc_comp``.
SYNC_STAGES = 2

#: ``prot_limits="ram"``: the registers mirrored into the protection's limit RAM, in its word
#: order (:data:`~.protect.LIMITS`).
PROT_LIMITS = tuple(f"prot_{name}" for name in LIMITS)
#: Values of ``Top(current_loop=...)``: :class:`~.foc.CurrentLoop`,
#: :class:`~.foc_engine.EngineCurrentLoop`.
CURRENT_LOOPS = ("pipelined", "engine")
#: The registers of the loop engine's configuration RAM (``current_loop="engine"``,
#: ``regs_staging="bram"``), in its word order (:data:`~.foc_engine.CONFIG`).
ENGINE_CONFIG = tuple({
    "gain_a": "clarke_gain_a", "gain_b": "clarke_gain_b", "off_a": "clarke_offset_a",
    "off_b": "clarke_offset_b", "kp_d": "pi_d_kp", "kx_d": "pi_d_kx", "lo_d": "pi_d_lim_lo",
    "hi_d": "pi_d_lim_hi", "kp_q": "pi_q_kp", "kx_q": "pi_q_kx", "lo_q": "pi_q_lim_lo",
    "hi_q": "pi_q_lim_hi", "ff_l": "decouple_l", "ff_psi": "decouple_psi",
    "klead": "theta_lead", "urat": "u_rated",
}[name] for name in ENGINE_CONFIG_SPECIALS)
#: The registers read as the loop engine's configuration-RAM words after :data:`ENGINE_CONFIG`
#: (``EngineCurrentLoop(refs="ram")``: the engine's speed run with its configuration RAM, the
#: iCEBreaker's), in its word order (:data:`~.foc_engine.REF_CONFIG_WORDS`): no flip-flops in
#: the register file, no latches in the engine, no mode multiplexer or i_q clamp in the Servo,
#: no reference registers in the top (module docstring, "References").
ENGINE_REFS = tuple({"ol_ud": "ol_u_d", "ol_uq": "ol_u_q", "idset": "i_d_ref",
                     "iqset": "i_q_ref", "ilo": "pi_speed_lim_lo",
                     "ihi": "pi_speed_lim_hi"}[name] for name in ENGINE_REF_WORDS)
#: The registers of the speed loop's configuration words (``regs_staging="bram"``), in its word
#: order (:data:`~.servo.SPEED_CONFIG`).
SPEED_LOOP_CONFIG = tuple({"kp": "pi_speed_kp", "kx": "pi_speed_kx", "speed_slew": "speed_slew",
                           "iq_ff": "speed_ff_iq"}[name] for name in SPEED_CONFIG)


#: The registers whose host writes raise the Servo's ``ref_change`` (its ``mode``,
#: ``speed_ref``, ``id_set``, ``iq_set``, ``ud_set``, ``uq_set``): the scope's reference-step
#: trigger (module docstring, "Scope trigger"). All shadowed.
#: Width of M/T's time count TC (at TCLK = the system clock): no encoder edge within
#: ``2**MT_TC_WIDTH`` clocks reads as stopped — 8.05 s at 33.333 MHz, 2.68 s at 100 MHz, i.e.
#: below ≈ 0.0004 / 0.0011 r/min at 20 000 counted edges per turn. 28 instead of MTSpeed's
#: default 32 (129 s) saves 26 iCE40 logic cells (AREA.md §7.51).
MT_TC_WIDTH = 28
#: ``Top(mt_engine=True)``: the TC span, 27 bits (the engine's ``DIV`` divisor is its
#: multiplier's signed 28-bit operand, docs/AREA.md §7.64): 4.03 s at 33.333 MHz, i.e. speeds
#: below ≈ 0.00075 r/min at 20 000 counted edges per turn read stopped.
MT_ENGINE_TC_WIDTH = 27

#: The top's own wrapping 16-bit status counters (speed-loop runs, current-loop overruns,
#: dropped ADC strobes), at most one count per PWM period each.
TOP_COUNTERS = ("st_speed_loops", "st_overruns", "st_adc_overruns")
#: With ``regs_staging="bram"`` also the current-loop passes (the duty transfers, ``done``, at
#: most one a PWM period) are counted in the staging RAM (docs/AREA.md §7.78); with ``"ff"``
#: ``st_current_loops`` is the loop's own ``count`` (its low 16 bits).
RAM_LOOP_COUNTERS = ("st_current_loops",)

REF_STEP_REGISTERS = ("mode", "speed_ref", "i_d_ref", "i_q_ref", "ol_u_d", "ol_u_q")


def _addr_in(addr, addrs):
    """``addr`` is one of the word addresses ``addrs``, as logic: per aligned group of 8 words
    one compare of the bits above the low 3 and one look-up of the low 3 (not a 16-bit compare
    per address)."""
    low = addr[:3]
    hits = [(addr[3:] == hi) & Cat(*(low == a & 7 for a in sorted(addrs) if a >> 3 == hi)).any()
            for hi in sorted({a >> 3 for a in addrs})]
    return Cat(*hits).any()


def _raw(port):
    """The plain bits of a port (a data View / EnumView, or a Value)."""
    return port.as_value() if hasattr(port, "as_value") else Value.cast(port)


def _latencies(loop):
    """Every sample → ``o.valid`` latency of a current loop (one for :class:`CurrentLoop`, one
    per program path for :class:`EngineCurrentLoop`)."""
    return loop.latencies if isinstance(loop, EngineCurrentLoop) else [loop.latency]


def _is_hz(value):
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


def _operands(scope, regmap, gates_dead_n=False):
    """The blocks' operands that are functions of a register's value: register name →
    ``(shape, value, const)`` (:class:`~.regs.Derived`'s fields; the port's shape, the function
    as logic of the raw value and as a Python function of its bits). With ``regs_staging="bram"``
    the register file's flip-flops hold the operand (``RegisterFile(derived=...)``: the function
    where they load, fewer bits for the channel codes and the pre-trigger); with ``"ff"`` the
    function sits between the register and the port."""
    def minus_one(v):
        # "every n, 0 acts as 1" (speed_div, scope_decim) → the blocks' "every x + 1".
        return Mux(v == 0, 0, v - 1)

    pw = len(scope.pretrigger)
    # scope_chanN is 8 bits, Scope.sel sel_width bits: a code beyond the source list must still
    # record 0, so out-of-range codes saturate to the first unused code (not truncate, which
    # would alias them onto real sources). `chan ≥ n_src` against the constant as logic
    # (fixed.at_least), not on a carry chain (iCE40: 6 logic cells each).
    n_src = len(scope.source_names)
    unused = min(n_src, (1 << scope.sel_width) - 1)
    sw = scope.sel_width
    ops = {
        "speed_div": (unsigned(regmap["speed_div"].width), minus_one,
                      lambda x: max(x, 1) - 1),
        "scope_decim": (unsigned(regmap["scope_decim"].width), minus_one,
                        lambda x: max(x, 1) - 1),
        # scope_pretrig is 16 bits, Scope.pretrigger log2(depth): clamp to depth − 1 (any bit
        # from log2(depth) up: an OR, not a compare's carry chain).
        "scope_pretrig": (unsigned(pw), lambda v: Mux(v[pw:].any(), scope.depth - 1, v[:pw]),
                          lambda x: scope.depth - 1 if x >> pw else x),
    }
    for c in range(scope.channels):
        ops[f"scope_chan{c}"] = (
            unsigned(sw), lambda v: Mux(v[sw:].any() | at_least(v[:sw], n_src), unused, v[:sw]),
            lambda x: unused if x >= n_src else x)
    if gates_dead_n:
        # The gates' turn-on compare operand ~(max(dead_time, 1) − 1) (Gates(dead_n=True)).
        dw = regmap["dead_time"].width
        ops["dead_time"] = (unsigned(dw), gates_dead_n_value,
                            lambda x: gates_dead_n_const(x, dw))
    return ops


def regmap_address_map(regmap):
    """The host link's address map of a register map: ``rw`` and ``strobe`` words writable,
    ``ro`` / ``const`` words and the windows read-only, every other address absent (so the link
    rejects a bad burst before its first access: all or nothing)."""
    regions = [(addr, addr + 1, r.access in (Access.RW, Access.STROBE))
               for addr, r, _ in regmap.words()]
    regions += [(w.addr, w.addr + w.size, False) for w in regmap.windows]
    return tuple(regions)


class LeadAngle(wiring.Component):
    """The inverse-Park angle advance ``θ_lead = n · k``: one sequential shift-and-add
    multiplication per start (16 clocks, one adder), for :attr:`CurrentLoop.theta_lead`.

    ::

        n     = saturate(round_shift(speed, 16), signed(16))   Q1.15 of N_FS (as CurrentLoop's n;
                                                               formed by the caller, Top)
        theta = round_shift(n · k, 15) mod 2**16               BinaryAngle(16)

    ``k`` is the advance at full-scale speed, UQ0.16 of a turn (the ``theta_lead`` register:
    ``ω_e(N_FS)·t_lead``), so ``theta`` is the electrical angle turned in ``t_lead`` at the
    speed ``n`` (negative for a negative speed: it wraps as an angle). The product is computed MSB
    first, ``acc ← 2·acc + k[15 − i]·n``, exact in ``signed(33)``; rounding half away from zero.
    (The rounding of the 32-bit speed to ``n`` is the caller's: ``Top`` registers it once beside
    M/T's output, so that it shares no logic with the current loop's own rounding.)

    Members
    -------
    n : In(signed(16))
        Speed, Q1.15 of N_FS; latched at ``start``.
    k : In(unsigned(16))
        Advance at full-scale speed, UQ0.16 turns; latched at ``start``.
    start : In(1)
        Strobe: compute from ``n`` and ``k`` (restarts a computation in progress).
    theta : Out(unsigned(16))
        The last result, BinaryAngle(16); changes only when a computation completes.

    Attributes
    ----------
    latency : int
        Clocks from ``start`` (clock ``t``) to the new ``theta`` (clock ``t + latency``): 17.
    """

    latency = 17

    n: In(signed(16))
    k: In(unsigned(16))
    start: In(1)
    theta: Out(unsigned(16))

    def elaborate(self, platform):
        m = Module()
        n = Signal(signed(16))
        k = Signal(16)
        acc = Signal(signed(33))
        steps = Signal(range(17))
        acc_next = Signal(signed(33))
        m.d.comb += acc_next.eq((acc << 1) + Mux(k[15], n, 0))
        with m.If(self.start):
            m.d.sync += [n.eq(self.n), k.eq(self.k), acc.eq(0), steps.eq(16)]
        with m.Elif(steps != 0):
            m.d.sync += [acc.eq(acc_next), k.eq(k << 1), steps.eq(steps - 1)]
            with m.If(steps == 1):
                m.d.sync += self.theta.eq(round_shift(acc_next, 15))
        return m


class Top(wiring.Component):
    """The servo controller on its pins (module docstring).

    Parameters
    ----------
    clk_hz : float
        System clock, Hz (50 MHz and 33.333 MHz are the supported builds), 1 MHz … 500 MHz.
    pwm_hz : float
        PWM frequency (the current-loop rate), Hz; the actual one is :attr:`pwm_hz_actual`
        (the period is a whole even number of clocks below ``2**16``).
    baud : float
        Host-link UART bit rate, bit/s, at most ``clk_hz / 8``.
    scales : Scales or None
        System scales for the identification registers and the clock-dependent reset values;
        ``None``: :class:`~.regmap.Scales` defaults at this ``clk_hz`` and the actual PWM
        frequency. Its ``clk_hz`` must equal ``clk_hz`` and its ``pwm_hz`` the requested or the
        actual PWM frequency (the identification register reports the actual one).
    dead_time_s : float or None
        Reset value of the ``dead_time`` register, s (rounded to whole clocks, 1 … 255);
        ``None``: the register map's default (1 µs).
    sclk_hz : float
        Highest ADC SCLK frequency (:class:`~.adc.AdcInterface`).
    max_words : int
        Longest host-link burst (:class:`~.hostlink.HostLink`); PING reports it and the host
        library splits longer transfers. 16 (was 64: −80 LUT4 of frame buffer addressing).
    mt_edges : str
        Encoder edges the M/T speed block counts: ``"x4"`` (default, :data:`~.regmap.MT_EDGES`)
        every quadrature state change (the encoder's ``step``/``up``: 4 edges per line, exact
        through reversals), or ``"a_rising"`` the A-rising position (``a_rise``: 1 edge per
        line). Sets the ``mt_k`` reset value (:func:`~.regmap.mt_k_for` with its edges per line)
        unless ``resets`` gives one.
    resets : mapping of str to int, optional
        Reset (power-up) values of ``rw`` registers, raw, e.g. ``{"theta_lead": 5243}``: a build
        that starts with tuned gains, or a simulation that starts configured without host writes.
        Each value must fit its register's format.
    mul_width : int
        Signed operand width of the target's hard multiplier, 8 … 25, or ``None``: 18 (default;
        ECP5 ``MULT18X18D``, Xilinx ``DSP48``); ``None`` for the iCE40 (products not split: yosys
        maps them onto 16 × 16 ``SB_MAC16`` better than a split can, :mod:`~.dsp`). Passed to the
        pipelined current loop, whose wide products are split into partial products of this size
        (the speed loop accepts it but multiplies by shift and add, no hard multiplier); it
        changes the netlist, never a result.
    current_loop : str
        The current loop's implementation: ``"pipelined"`` (default, :class:`~.foc.CurrentLoop`:
        one pipeline stage per operation, 46–48 clocks) or ``"engine"``
        (:class:`~.foc_engine.EngineCurrentLoop`: the same results from a program on one
        micro-sequenced datapath, 134–232 clocks, ≈ 1/3 of the LUTs, 4 multipliers; docs/ENGINE.md).
        Only the timing differs (:attr:`loop_latency`); ``mul_width`` does not apply to the engine.
    scope_ram : str
        The trace buffer's RAM (:class:`~.scope.Scope` ``ram``): ``"bram"`` (default, a
        :class:`~amaranth.lib.memory.Memory`, simulates) or ``"ice40_spram"`` (one iCE40 UP5K
        ``SB_SPRAM256KA`` instead of 16 ``SB_RAM40_4K``; synthesis only, the iCE40 boards' choice).
    regs_staging : str
        The register file's staging registers (:class:`~.regs.RegisterFile` ``staging``):
        ``"ff"`` (default, flip-flops; ``commit`` at ``period_start``) or ``"bram"`` (one block
        RAM; the commit copy runs over the :attr:`commit_clocks` clocks before ``period_start``,
        module docstring; the iCEBreaker's and the Arty S7's choice: −≈ 600 FF; its flip-flops
        of ``speed_div``, ``scope_decim``, ``scope_pretrig`` and ``scope_chan0…3`` (and
        ``dead_time`` with ``gates_dead_n``) then hold the blocks' operands,
        ``RegisterFile(derived=...)``).
    uv_arm_chain : bool
        :class:`~.protect.Protection` ``uv_arm_chain``: the under-voltage arming's compare on a
        carry chain of its own (the same verdicts; the ECP5 board's choice, for its Fmax;
        default ``False``, two chains, fewer iCE40 cells).
    scope_down_counts : bool
        :class:`~.scope.Scope` ``down_counts``: the scope's pre-trigger fill and post-trigger
        samples counted down to zero (the same captures; the iCE40's choice and the default,
        fewer iCE40 cells; ``False`` fewer LUT6 on the Spartan-7).
    timer_clamp : bool
        The dead-time compensation's clamp in the PWM timer: :class:`~.deadtime_comp.DeadTimeComp`
        ``clamp=False`` passes its unclamped sums to :class:`~.svpwm.PWMTimer`
        ``signed_duty=True`` (the same levels; the iCE40's choice and the default: the timer's
        shadow and active flip-flops pack with their LUTs; ``False`` clamped in the compensation,
        the ECP5's and the Spartan-7's netlist of before, docs/AREA.md §7.72).
    timer_sample_split : bool
        :class:`~.svpwm.PWMTimer` ``sample_split``: the ADC strobe's two equalities selected
        after them (the same strobes; the iCE40's choice and the default; ``False`` the
        ECP5's and the Spartans' netlist of before, docs/AREA.md §7.79).
    gates_wrap : bool
        :class:`~.gates.Gates` ``wrap``: the off counts without saturation (the same gate
        outputs; the iCE40's and the Spartan-7's choice and the default; ``False`` the ECP5's
        netlist of before, docs/AREA.md §7.80).
    gates_prev_pwm : bool
        :class:`~.gates.Gates` ``prev_pwm``: the gates' "wanted state unchanged" from the
        previous ``pwm`` levels and ``run`` (the same gate outputs; the iCE40's choice and the
        default; ``False`` the ECP5's and the Spartans' netlist of before, docs/AREA.md §7.86).
    adc_marker : bool
        :class:`~.adc.AdcInterface` ``marker``: the read frame's bits counted by a marker bit
        in the first channel's shift register instead of a counter (the same pins and codes:
        that register is read only between a frame's last bit and the next sample strobe;
        the iCE40's choice and the default; ``False`` the ECP5's and the Spartans' netlist
        of before, docs/AREA.md §7.86).
    timer_one_adder : bool
        :class:`~.svpwm.PWMTimer` ``one_adder``: the triangle counter on one adder (the same
        outputs; the iCE40's and the Spartan-7's choice and the default; ``False`` the ECP5's
        netlist of before: with it the ULX3S missed 100 MHz on seed 3, docs/AREA.md §7.80).
    dtc_one_count : bool
        :class:`~.deadtime_comp.DeadTimeComp` ``one_count``: its sequence on one count (the
        same corrections; the iCE40's and the Spartan-7's choice and the default; ``False`` the
        ECP5's netlist of before, docs/AREA.md §7.79).
    gates_dead_n : bool
        :class:`~.gates.Gates` ``dead_n``: the gates take their turn-on compare's operand
        ``~(max(dead_time, 1) − 1)`` (:func:`~.gates.dead_n`) instead of ``dead_time``; with
        ``regs_staging="bram"`` the register file's flip-flops hold it (``Derived``), so no
        decrement and zero test sit in front of the compares (the same gate outputs; the
        iCE40's choice and the default; ``False`` the ECP5's and the Spartans' netlist of
        before, docs/AREA.md §7.79).
    trip_register : bool
        :class:`~.protect.Protection` ``trip_register``: ``present``'s OR in a flip-flop of
        its own (the same trip; the ECP5 board's choice, for its Fmax; default ``False``, the
        OR of ``present``'s flip-flops, fewer iCE40 cells).
    link_read_hold : bool
        :class:`~.hostlink.HostLink` ``read_hold``: the link's frame-buffer read address from
        registered flags (the same replies and accesses; the ECP5 board's choice, for its Fmax;
        default ``False``, fewer iCE40 cells).
    prot_limits : str
        :class:`~.protect.Protection` ``limits``: ``"ports"`` (default) the protection's limits
        are the register file's flip-flops, one comparator per sampled cause; ``"ram"`` (needs
        ``regs_staging="bram"``; the iCE40's choice, docs/AREA.md §7.77) they are mirrored
        from the register file's staging RAM writes (``RegisterFile(mirror=...)``) into the
        protection's limit RAM and compared one step per clock: a sampled cause (over-current,
        over-/under-voltage, over-speed) then reaches the gates 1 … 7 clocks later
        (:attr:`Protection.step_latency`; the pin causes as before) and a limit write acts one
        clock later; ``"ram16"`` the same with a limit RAM of one iCE40 block RAM (two with
        ``"ram"``) and the over-speed limit's upper 16 bits in flip-flops (+39 logic cells on the
        iCEBreaker, docs/AREA.md §7.77).
    enc_fold_reload : bool
        :class:`~.encoder.GlitchFilter` ``fold_reload``: the filter counters' reload select in
        their decrement's LUTs (the same filtered pins; the iCE40's choice and the default,
        fewer logic cells; ``False`` the ECP5's and the Spartan-7's netlist of before, fewer
        LUT6, docs/AREA.md §7.76).
    enc_plausibility_complement : bool
        :class:`~.encoder.EncoderFrontEnd` ``plausibility_complement``: the encoder/Hall check's
        differences as ``~d`` and ``d_prev − d`` (the same outputs; the iCE40's choice and the
        default, 12 logic cells fewer for the encoder alone; ``False`` the ECP5's and the
        Spartan-7's netlist of before, docs/AREA.md §7.84).
    mt_chunk_multipliers : bool
        :class:`~.mt_speed.MTSpeed` ``chunk_multipliers``: one multiplier per 16-bit chunk of
        ``mt_k`` (three), no chunk select (the same speeds in the same clocks; the iCE40's
        choice and the default: 7 of the UP5K's 8 SB_MAC16, fewer logic cells; ``False`` one
        multiplier, the ECP5's and the Spartan-7's netlist of before, docs/AREA.md §7.76).
    mt_k_export : bool
        ``mt_k`` (shadowed: it changes only in a commit, before ``period_start``) not a
        register-file flip-flop but a word pair of its ``export`` port, loaded into three
        16-bit registers here that feed M/T's multipliers as they are (``MTSpeed(k_steady=
        True)``; iCE40: the SB_MAC16s' own A registers, no logic cell). Needs
        ``regs_staging="bram"`` and ``mt_chunk_multipliers``; the registers hold 0 from
        power-up until the register file's reset walk writes ``mt_k`` (no M/T result reads
        ``k`` that early: the PWM period must exceed the walk, checked). The same speeds; the
        iCE40's choice (default ``False``: it needs the block-RAM staging).
    mt_engine : bool
        M/T speed's arithmetic on the loop engine (docs/AREA.md §7.64, §7.82): ``MTSpeed(arith=
        "engine")`` keeps the window logic, the engine runs its multiply and divide as the run
        ``mt`` (``EngineCurrentLoop(mt=True)``), ``k`` (``mt_k``'s two export words) in its
        configuration RAM. Needs ``current_loop="engine"``, ``regs_staging="bram"``,
        ``mt_k_export`` and not ``mt_chunk_multipliers`` (no multiplier left in M/T).
        **Behaviour** (module docstring, "M/T on the engine"): the TC span 27 bits
        (:data:`MT_ENGINE_TC_WIDTH`: edge intervals of 2**27 … 2**28 clocks read stopped), the
        result :attr:`mt_latency` clocks after ``period_start`` (``MTSpeed.latency`` + 75 on
        the iCEBreaker), the speed run after it. Default ``False``; the iCE40's choice
        (``boards.build.MT_ENGINE``).
    ram_loop_count : bool
        With ``regs_staging="bram"``: ``st_current_loops`` counted in the register file's
        staging RAM from the loop's ``done`` (:data:`RAM_LOOP_COUNTERS`; the same values, an
        access in a count's clock acked two clocks later, module docstring "Status"; the
        iCE40's choice and the default, fewer iCE40 cells, docs/AREA.md §7.78); ``False`` the
        loop's own ``count`` (the Spartan-7's: fewer LUT6). No effect with ``"ff"``.
    link_compact : bool
        :class:`~.hostlink.HostLink` ``compact``: the link's iCE40 forms (the same replies and
        accesses in the same clocks, fewer iCE40 cells, longer paths; the iCE40 board's choice;
        default ``False``, the form of the other families' netlists); not with
        ``link_read_hold`` (``ValueError``).

    Members
    -------
    uart_rx : In(1, init=1)
        Host link receive pin (asynchronous; synchronised in the UART).
    uart_tx : Out(1, init=1)
        Host link transmit pin.
    enc_a, enc_b, enc_z : In(1)
        Encoder pins (asynchronous; synchronised and filtered in the encoder front end).
    hall : In(3)
        Hall pins, bit 0 = H_a (asynchronous).
    adc_cs_n, adc_sclk : Out(1)
        AD7380-4 chip select and serial clock (idle high).
    adc_sdo : In(4)
        AD7380-4 SDOA … SDOD (bit 0 = SDOA: phase a current; B: phase b; C: U_dc; D: unused).
    gate_h, gate_l : Out(3)
        High- and low-side gate drives, bit 0 = phase a, all low at reset.
    fault_n : In(1, init=1)
        Gate-driver fault, active low (asynchronous).
    oc_comp : In(1)
        Fast over-current comparator, active high (asynchronous).
    led : Out(2)
        Bit 0: trip (gates forced off); bit 1: encoder aligned by its index.

    Attributes
    ----------
    regmap : RegMap
        The register map built for :attr:`scales`.
    scales : Scales
    pwm_period : int
        Clocks per PWM period.
    pwm_hz_actual : float
    fault_latency : int
        Clocks from ``fault_n`` low at the pin (in clock ``t``) to all gates low (in clock
        ``t + fault_latency``): 2 synchroniser flops + :attr:`Protection.latency` +
        :attr:`Gates.trip_latency` = 4.
    loop_latency : int
        Clocks from the ``sample`` strobe to the duties: ADC + current loop (its worst case: the
        engine's latency depends on the program path, 134 … 232, docs/ENGINE.md).
    mt_edges : str
        The M/T edge mode (the parameter).
    mul_width : int
        The parameter.
    current_loop, scope_ram, regs_staging : str
        The parameters.
    uv_arm_chain, trip_register, link_read_hold, scope_down_counts, timer_clamp : bool
        The parameters.
    gates_dead_n, gates_wrap, timer_sample_split, timer_one_adder, dtc_one_count : bool
        The parameters.
    adc_marker, gates_prev_pwm : bool
        The parameters.
    link_compact, enc_fold_reload, enc_plausibility_complement : bool
        The parameters.
    mt_chunk_multipliers, mt_k_export, mt_engine : bool
        The parameters.
    mt_latency : int
        Clocks from ``period_start`` (M/T's update) to M/T's ``o.valid``: ``MTSpeed.latency``,
        or (``mt_engine``) the run's request, a clock after the update, + the run's
        ``EngineCurrentLoop.mt_latency`` (the engine idle at ``period_start``: module
        docstring, "M/T on the engine").
    ram_loop_count : bool
        ``st_current_loops`` is a counter of the staging RAM (the parameter with
        ``regs_staging="bram"``, else ``False``).
    commit_clocks : int
        Clocks the register commit takes: it starts ``commit_clocks`` clocks before
        ``period_start`` and the new values are all in place in the ``period_start`` clock
        (``"bram"``), or 1 (``"ff"``: the commit in the ``period_start`` clock, the new values
        from the clock after it).

    Raises
    ------
    TypeError
        A parameter of the wrong type.
    ValueError
        A frequency out of range, or parameters that do not agree.
    """

    def __init__(self, *, clk_hz=50e6, pwm_hz=10e3, baud=115_200, scales=None, dead_time_s=None,
                 sclk_hz=25e6, max_words=16, resets=None, mul_width=MUL_WIDTH,
                 mt_edges=MT_EDGES, current_loop="pipelined", scope_ram="bram",
                 regs_staging="ff", speed_loop="sequential", uv_arm_chain=False,
                 trip_register=False, link_read_hold=False, scope_down_counts=True,
                 timer_clamp=True, prot_limits="ports", enc_fold_reload=True,
                 enc_plausibility_complement=True,
                 mt_chunk_multipliers=True, mt_k_export=False, ram_loop_count=True,
                 link_compact=False, gates_dead_n=True, timer_sample_split=True,
                 timer_one_adder=True, gates_wrap=True,
                 dtc_one_count=True, adc_marker=True, gates_prev_pwm=True, mt_engine=False):
        mul_width = check_mul_width("Top", mul_width)
        check_bool("Top", "ram_loop_count", ram_loop_count)
        for name, value in (("clk_hz", clk_hz), ("pwm_hz", pwm_hz), ("baud", baud),
                            ("sclk_hz", sclk_hz)):
            if not _is_hz(value):
                raise TypeError(f"Top {name} must be a positive number in Hz, not {value!r}")
        if not 1e6 <= clk_hz <= 500e6:
            raise ValueError(f"Top clk_hz must be from 1 MHz to 500 MHz, not {clk_hz!r}")
        n = pwm_half_period(clk_hz, pwm_hz)
        if n < 4 or 2 * n >= 1 << COUNT_WIDTH:
            raise ValueError(f"Top pwm_hz must give a PWM period of 8 to {(1 << COUNT_WIDTH) - 2} "
                             f"clocks at clk_hz {clk_hz:g} Hz, not {pwm_hz!r} ({2 * n} clocks)")
        if baud * 8 > clk_hz:
            raise ValueError(f"Top baud must be at most clk_hz / 8 = {clk_hz / 8:g}, "
                             f"not {baud!r}")
        pwm_actual = clk_hz / (2 * n)
        if scales is None:
            scales = Scales(clk_hz=float(clk_hz), pwm_hz=pwm_actual)
        elif not isinstance(scales, Scales):
            raise TypeError(f"Top scales must be a Scales or None, not {scales!r}")
        else:
            if not math.isclose(scales.clk_hz, clk_hz, rel_tol=1e-9):
                raise ValueError(f"Top scales.clk_hz must equal clk_hz {clk_hz:g}, "
                                 f"not {scales.clk_hz!r}")
            if not any(math.isclose(scales.pwm_hz, f, rel_tol=1e-9) for f in (pwm_hz, pwm_actual)):
                raise ValueError(f"Top scales.pwm_hz must equal pwm_hz {pwm_hz:g} or the actual "
                                 f"{pwm_actual:g}, not {scales.pwm_hz!r}")
            scales = Scales(clk_hz=float(clk_hz), pwm_hz=pwm_actual, i_fs_a=scales.i_fs_a,
                            u_fs_v=scales.u_fs_v, n_fs_rpm=scales.n_fs_rpm)
        regmap = build_regmap(scales)
        if dead_time_s is not None:
            if (not isinstance(dead_time_s, numbers.Real) or isinstance(dead_time_s, bool)
                    or not math.isfinite(dead_time_s)):
                raise TypeError(f"Top dead_time_s must be a number of seconds or None, "
                                f"not {dead_time_s!r}")
            dead = round(dead_time_s * clk_hz)
            if not 1 <= dead <= 255:
                raise ValueError(f"Top dead_time_s must be 1 to 255 clocks at {clk_hz:g} Hz, "
                                 f"not {dead_time_s!r} ({dead} clocks)")
            regmap = regmap.with_constants({"dead_time": dead})
        if (not isinstance(max_words, int) or isinstance(max_words, bool)
                or not 1 <= max_words <= 255):
            raise TypeError(f"Top max_words must be an integer from 1 to 255, not {max_words!r}")
        check_choice("Top", "mt_edges", mt_edges, MT_EDGES_PER_LINE)
        if mt_edges != MT_EDGES:
            regmap = regmap.with_constants(
                {"mt_k": mt_k_for(scales, edges_per_line=MT_EDGES_PER_LINE[mt_edges])})
        check_choice("Top", "current_loop", current_loop, CURRENT_LOOPS)
        check_choice("Top", "scope_ram", scope_ram, SCOPE_RAMS)
        check_choice("Top", "regs_staging", regs_staging, REGS_STAGINGS)
        check_choice("Top", "prot_limits", prot_limits, LIMIT_FORMS)
        if prot_limits != "ports" and regs_staging != "bram":
            raise ValueError(f"Top prot_limits={prot_limits!r} needs regs_staging='bram' (the "
                             f"limits are mirrored from its staging RAM), not "
                             f"regs_staging={regs_staging!r}")
        if check_bool("Top", "mt_k_export", mt_k_export) and regs_staging != "bram":
            raise ValueError(f"Top mt_k_export needs regs_staging='bram', not {regs_staging!r}")
        if check_bool("Top", "mt_engine", mt_engine) and (
                (current_loop, regs_staging, mt_k_export, mt_chunk_multipliers)
                != ("engine", "bram", True, False)):
            raise ValueError(f"Top mt_engine needs current_loop='engine', regs_staging='bram', "
                             f"mt_k_export=True and mt_chunk_multipliers=False (k is two words "
                             f"of the engine's configuration RAM; M/T keeps no multiplier), "
                             f"not {current_loop!r}, {regs_staging!r}, {mt_k_export!r}, "
                             f"{mt_chunk_multipliers!r}")
        check_choice("Top", "speed_loop", speed_loop, SPEED_LOOPS)
        if speed_loop == "engine" and (current_loop, regs_staging) != ("engine", "bram"):
            raise ValueError(f"Top speed_loop='engine' needs current_loop='engine' and "
                             f"regs_staging='bram' (the speed run shares the engine and its "
                             f"configuration RAM), not current_loop={current_loop!r}, "
                             f"regs_staging={regs_staging!r}")
        if resets is not None:
            if not isinstance(resets, Mapping):
                raise TypeError(f"Top resets must be a mapping of register names to raw values "
                                f"or None, not {resets!r}")
            for name in resets:
                if name not in regmap or regmap[name].access is not Access.RW:
                    raise ValueError(f"Top resets may only set rw registers, not {name!r}")
            if dead_time_s is not None and "dead_time" in resets:
                raise ValueError("Top dead_time_s and resets['dead_time'] both set the dead "
                                 "time: give one")
            regmap = regmap.with_constants(dict(resets))   # Register checks each value's range
        assert all(regmap[n].shadow is not None for n in REF_STEP_REGISTERS)
        copy = len(staging_slots(regmap)) + 1               # RegisterFile.commit_clocks
        if regs_staging == "bram" and copy >= 2 * n:
            raise ValueError(f"Top regs_staging='bram' needs a PWM period longer than the "
                             f"register copy ({copy} clocks), not {2 * n} clocks")
        self._clk_hz = float(clk_hz)
        self._scales = scales
        self._regmap = regmap

        # Built here (after every check) so that their timing attributes are known.
        # "bram": the timer latches pwm_symmetric in the period's last clock, so that word is
        # copied in the copy's last clock (it changes after the latch, as with "ff").
        # The engine's and the speed loop's configuration registers in their RAMs (module
        # docstring): one export port, the engine's words first.
        cfg_ram = current_loop == "engine" and regs_staging == "bram"
        # ... and its status in its status RAM, read by the register file and the scope.
        self._status_ram = cfg_ram
        speed_ram = regs_staging == "bram"
        # ... and with its speed run too, the references in its configuration RAM; the scope
        # reads the ones it used from its status RAM (ENGINE_REFS).
        refs = cfg_ram and speed_loop == "engine"
        self._refs = refs
        self._scope = Scope(ram=scope_ram,
                            ram_sources=(ENGINE_STATUS + (ENGINE_REF_STATUS if refs else ())
                                         if cfg_ram else ()),
                            down_counts=scope_down_counts)
        # The operands of the blocks that take a function of a register's value (_operands):
        # with "bram" staging the register file's active flip-flops hold them (Derived).
        check_bool("Top", "gates_dead_n", gates_dead_n)
        self._operands = _operands(self._scope, regmap, gates_dead_n)
        # With "bram" staging the link's counters and the top's own (TOP_COUNTERS) are
        # counted in the staging RAM (RegisterFile(counters=...), from count strobes): no
        # 16-bit counter and no read multiplexer term each (docs/AREA.md §7.59).
        self._ram_counters = COUNTERS if regs_staging == "bram" else ()
        self._ram_loop_count = bool(self._ram_counters) and ram_loop_count
        self._regs = RegisterFile(regmap, staging=regs_staging,
                                  counters=(tuple(f"st_link_{n}" for n in self._ram_counters)
                                            + (TOP_COUNTERS if self._ram_counters else ())
                                            + (RAM_LOOP_COUNTERS if self._ram_loop_count
                                               else ())),
                                  copy_last=("pwm_symmetric",) if regs_staging == "bram" else (),
                                  export=((ENGINE_CONFIG + (ENGINE_REFS if refs else ())
                                           if cfg_ram else ())
                                          + (SPEED_LOOP_CONFIG if speed_ram else ())
                                          + (("mt_k",) if mt_k_export else ())),
                                  status_ram=(tuple(f"st_{n}" for n in ENGINE_STATUS)
                                              if cfg_ram else ()),
                                  changed=("enc_lines", "enc_pole_pairs", "enc_z_offset"),
                                  **({"mirror": PROT_LIMITS} if prot_limits != "ports" else {}),
                                  derived=({n: Derived(*op) for n, op in self._operands.items()}
                                           if regs_staging == "bram" else None))
        # The RAM counters lose no count if commits and the top's counts (one per PWM period
        # at most) and the link's (one per reply, at least 8 wire bytes of 10 bit times; one
        # per dropped frame, at least two bytes: the loss, a 0x00, the next loss) come
        # count_interval clocks apart.
        gap = min(clk_hz / pwm_hz, 20 * clk_hz / baud)
        if self._ram_counters and gap < self._regs.count_interval:
            raise ValueError(f"Top: the counters in the register file's RAM need the PWM "
                             f"period and 2 UART bytes to last at least "
                             f"{self._regs.count_interval} clocks, not {gap:g}")
        exported = [r.name for _, r, _ in self._regs.export_words]
        # (speed_loop="engine": the speed words go into the engine's RAM with its own.)
        self._speed_export = (exported.index(SPEED_LOOP_CONFIG[0])
                              if speed_ram and speed_loop != "engine" else None)
        self._speed_loop = speed_loop
        self._link = HostLink(clk_hz=clk_hz, baud=baud, max_words=max_words,
                              address_map=regmap_address_map(regmap),
                              counter_width=regmap["st_link_frames_ok"].width,
                              strobed=self._ram_counters, read_hold=link_read_hold,
                              compact=link_compact)
        self._timer = PWMTimer(clk_hz=clk_hz, pwm_hz=pwm_hz, count_width=COUNT_WIDTH,
                               signed_duty=timer_clamp, sample_split=timer_sample_split,
                               one_adder=timer_one_adder)
        # No code held between samples: the current loop latches i_a, i_b and U_dc with the
        # sample, so the payload is the shift registers (no FF; held=("udc",) until session
        # 11, all three before that); st_udc and the scope take the loop's latched U_dc (its
        # `udc` output, module docstring "Status").
        self._adc = AdcInterface(clk_hz=clk_hz, sclk_hz=sclk_hz, held=(), marker=adc_marker)
        self._mul_width = mul_width
        self._current_loop = current_loop
        # mt_engine: mt_k's two words (the last exported) follow the engine's own in its RAM.
        self._mt_k_words = [i for i, (_, r, _) in enumerate(self._regs.export_words)
                            if r.name == "mt_k"]
        n_cfg = len(ENGINE_CONFIG) + (len(ENGINE_REFS) + len(SPEED_LOOP_CONFIG)
                                      if speed_loop == "engine" else 0)
        self._n_cfg = n_cfg
        mt_init = ([self._regs.export_init[i] for i in self._mt_k_words] if mt_engine else [])
        self._loop = (CurrentLoop(count_width=COUNT_WIDTH, mul_width=mul_width)
                      if current_loop == "pipelined" else
                      EngineCurrentLoop(count_width=COUNT_WIDTH, config="ram",
                                        config_init=self._regs.export_init[:n_cfg] + mt_init,
                                        status="ram", speed=speed_loop == "engine",
                                        refs="ram" if refs else "ports", mt=mt_engine)
                      if cfg_ram else
                      EngineCurrentLoop(count_width=COUNT_WIDTH))
        self._dtc = DeadTimeComp(width=self._loop.width, count_width=COUNT_WIDTH,
                                 clocks_width=regmap["dtc_clocks"].width,
                                 shift_width=regmap["dtc_band"].width, clamp=not timer_clamp,
                                 one_count=dtc_one_count)
        # (the decoder's configuration after reset: the registers', which give no change strobe)
        self._encoder = EncoderFrontEnd(lines_init=regmap["enc_lines"].reset,
                                        pole_pairs_init=regmap["enc_pole_pairs"].reset,
                                        z_offset_init=regmap["enc_z_offset"].reset,
                                        fold_reload=enc_fold_reload,
                                        plausibility_complement=enc_plausibility_complement)
        if mt_engine:
            self._mt = MTSpeed(clk_hz=clk_hz, edge_mode=mt_edges, tc_width=MT_ENGINE_TC_WIDTH,
                               arith="engine")
            # The run's request a clock after period_start; the engine is idle then (the
            # sample-point limit, module docstring): its result mt_latency after it.
            self._mt_latency = 1 + self._loop.mt_latency
        else:
            self._mt = MTSpeed(clk_hz=clk_hz, edge_mode=mt_edges, tc_width=MT_TC_WIDTH,
                               chunk_multipliers=mt_chunk_multipliers,
                               k_steady=mt_k_export)
            self._mt_latency = self._mt.latency
        # mt_k from the export port: its words' indices (above); the PWM period outlasts the
        # reset walk (before it the registers hold 0; M/T's first result after a reset is a
        # stopped one, whose product is 0 whatever k, and the next comes a period later).
        if mt_k_export and not 2 * n > self._regs.reset_clocks + 2:
            raise ValueError(f"Top mt_k_export needs a PWM period longer than the register "
                             f"file's reset walk ({self._regs.reset_clocks + 2} clocks), not "
                             f"{2 * n}")
        k = self._speed_export
        self._servo = Servo(kp_format=regmap["pi_speed_kp"].fmt,
                            kx_format=regmap["pi_speed_kx"].fmt, mul_width=mul_width,
                            speed_loop=speed_loop,
                            **({} if k is None else dict(
                                config="ram",
                                config_init=self._regs.export_init[k:k + len(SPEED_CONFIG)])))
        if speed_loop == "engine":
            # The speed run starts at M/T's strobe (≈ MTSpeed.latency after period_start);
            # a centred sample must come after its i_q reference (module docstring,
            # "Speed loop on the engine").
            due = self._mt_latency + 1 + self._loop.speed_latency
            if self._timer.period // 2 <= due:
                raise ValueError(f"Top speed_loop='engine' needs half a PWM period longer "
                                 f"than M/T's latency + the speed run ({due} clocks), not "
                                 f"{self._timer.period // 2} clocks (pwm_hz {pwm_hz!r} at "
                                 f"clk_hz {clk_hz:g})")
            # The run reads M/T's output register itself (no latch: EngineCurrentLoop's
            # ``speed``), which must hold from the strobe to that read: at most a current-loop
            # program (interval) and speed_read later; the next strobe comes a period later.
            hold = self._loop.interval + self._loop.speed_read
            if self._timer.period <= hold:          # pragma: no cover (implied by the above)
                raise ValueError(f"Top speed_loop='engine' needs a PWM period longer than the "
                                 f"speed run's read of M/T's speed ({hold} clocks), not "
                                 f"{self._timer.period} clocks")
        if current_loop == "engine":
            # The engine reads the ADC's ia, ib shift registers itself (no latch), up to
            # sample_hold clocks after the sample; they hold until the next conversion's first
            # bit, which comes after the next sample strobe: more than a period less the
            # ADC's latency after o.valid.
            hold = self._timer.period - self._adc.latency
            if hold <= self._loop.sample_hold:
                raise ValueError(f"Top current_loop='engine' needs a PWM period longer than "
                                 f"the ADC's latency + the engine's sample hold "
                                 f"({self._adc.latency + self._loop.sample_hold} clocks), not "
                                 f"{self._timer.period} clocks")
        # θ_lead: LeadAngle beside the pipelined loop; the engine computes it in its program.
        self._lead = LeadAngle() if current_loop == "pipelined" else None
        self._protect = Protection(speed_width=32, uv_arm_chain=uv_arm_chain,
                                   trip_register=trip_register, limits=prot_limits,
                                   **({"limit_init": tuple(self._regs.mirror_init)}
                                      if prot_limits != "ports" else {}))
        self._gates = Gates(dead_n=gates_dead_n, wrap=gates_wrap, prev_pwm=gates_prev_pwm)
        if cfg_ram and self._scope.channels > self._loop.status_quiet:   # pragma: no cover
            raise ValueError(f"Top: the scope's {self._scope.channels} channels are sampled "
                             f"after the engine's done, which leaves only "
                             f"{self._loop.status_quiet} clocks without a status write")

        super().__init__({
            "uart_rx": In(1, init=1),
            "uart_tx": Out(1, init=1),
            "enc_a": In(1),
            "enc_b": In(1),
            "enc_z": In(1),
            "hall": In(3),
            "adc_cs_n": Out(1, init=1),
            "adc_sclk": Out(1, init=1),
            "adc_sdo": In(4),
            "gate_h": Out(3),
            "gate_l": Out(3),
            "fault_n": In(1, init=1),
            "oc_comp": In(1),
            "led": Out(2),
        })

    clk_hz = property(lambda self: self._clk_hz)
    scales = property(lambda self: self._scales)
    regmap = property(lambda self: self._regmap)
    pwm_period = property(lambda self: self._timer.period)
    pwm_hz_actual = property(lambda self: self._clk_hz / self._timer.period)
    mt_edges = property(lambda self: self._mt.edge_mode)
    fault_latency = property(lambda self: SYNC_STAGES + Protection.latency + Gates.trip_latency)
    loop_latency = property(lambda self: self._adc.latency + self._loop.latency)
    mul_width = property(lambda self: self._mul_width)
    current_loop = property(lambda self: self._current_loop)
    speed_loop = property(lambda self: self._speed_loop)
    scope_ram = property(lambda self: self._scope.ram)
    regs_staging = property(lambda self: self._regs.staging)
    uv_arm_chain = property(lambda self: self._protect.uv_arm_chain)
    trip_register = property(lambda self: self._protect.trip_register)
    prot_limits = property(lambda self: self._protect.limits)
    scope_down_counts = property(lambda self: self._scope.down_counts)
    timer_clamp = property(lambda self: self._timer.signed_duty)
    ram_loop_count = property(lambda self: self._ram_loop_count)
    gates_dead_n = property(lambda self: self._gates.dead_input == "dead_n")
    timer_sample_split = property(lambda self: self._timer.sample_split)
    timer_one_adder = property(lambda self: self._timer.one_adder)
    gates_wrap = property(lambda self: self._gates.wrap)
    adc_marker = property(lambda self: self._adc.marker)
    gates_prev_pwm = property(lambda self: self._gates.prev_pwm)
    dtc_one_count = property(lambda self: self._dtc.one_count)
    link_read_hold = property(lambda self: self._link.read_hold)
    enc_fold_reload = property(lambda self: self._encoder.fold_reload)
    enc_plausibility_complement = property(lambda self: self._encoder.plausibility_complement)
    mt_chunk_multipliers = property(lambda self: self._mt.chunk_multipliers)
    mt_k_export = property(lambda self: bool(self._mt_k_words))
    mt_engine = property(lambda self: self._mt.arith == "engine")
    mt_latency = property(lambda self: self._mt_latency)
    link_compact = property(lambda self: self._link.compact)
    commit_clocks = property(lambda self: self._regs.commit_clocks)

    def _mt_k(self, m, exp):
        """``mt_k`` from the register file's export port (``mt_k_export``): three 16-bit
        registers (no reset, 0 at power-up: SB_MAC16 input registers) loaded from its two
        words in the clocks its flip-flops would load."""
        lo, hi = self._mt_k_words
        chunks = [Signal(16, name=f"mt_k{c}", reset_less=True) for c in range(3)]
        with m.If(exp.valid & (exp.index == lo)):
            m.d.sync += [chunks[0].eq(exp.data[:16]), chunks[1].eq(exp.data[16:])]
        with m.If(exp.valid & (exp.index == hi)):
            m.d.sync += chunks[2].eq(exp.data[:16])
        return Cat(*chunks)

    def elaborate(self, platform):
        m = Module()
        m.submodules.regs = regs = self._regs
        m.submodules.link = link = self._link
        m.submodules.timer = timer = self._timer
        m.submodules.adc = adc = self._adc
        m.submodules.current_loop = cl = self._loop
        m.submodules.dtc = dtc = self._dtc
        m.submodules.encoder = enc = self._encoder
        m.submodules.mt_speed = mt = self._mt
        m.submodules.servo = servo = self._servo
        m.submodules.protect = prot = self._protect
        m.submodules.gates = gates = self._gates
        m.submodules.scope = scope = self._scope
        if self._lead is not None:
            m.submodules.lead = lead = self._lead

        # --- pins ---------------------------------------------------------------------------
        fault_n = Signal(init=1)
        oc_comp = Signal()
        m.submodules.fault_sync = FFSynchronizer(self.fault_n, fault_n, init=1,
                                                 stages=SYNC_STAGES)
        m.submodules.oc_sync = FFSynchronizer(self.oc_comp, oc_comp, stages=SYNC_STAGES)
        # The trip for everything but the gates, one clock late (module docstring).
        trip_q = Signal()
        m.d.sync += trip_q.eq(prot.trip)
        m.d.comb += [
            link.rx.eq(self.uart_rx),
            self.uart_tx.eq(link.tx),
            enc.a.eq(self.enc_a), enc.b.eq(self.enc_b), enc.z.eq(self.enc_z),
            enc.hall.eq(self.hall),
            self.adc_cs_n.eq(adc.cs_n),
            self.adc_sclk.eq(adc.sclk),
            adc.sdo.eq(self.adc_sdo),       # straight to the shift registers (see AdcInterface)
            self.gate_h.eq(Cat(gates.high.a, gates.high.b, gates.high.c)),
            self.gate_l.eq(Cat(gates.low.a, gates.low.b, gates.low.c)),
            self.led.eq(Cat(prot.trip, enc.aligned)),
        ]

        # --- data path ----------------------------------------------------------------------
        wiring.connect(m, link=link.bus, regs=regs.bus)
        if self.mt_engine:                  # M/T's arithmetic on the engine (mt_engine)
            wiring.connect(m, mt_speed=mt.run, current_loop=cl.mt_run)
            wiring.connect(m, current_loop=cl.mt_res, mt_speed=mt.res)
        wiring.connect(m, adc=adc.o, current_loop=cl.i)
        # Dead-time compensation between the duties and the timer's shadow register (no added
        # latency); its currents (Clarke) must be ready before this sample's duties.
        assert cl.phase_latency + dtc.comp_latency < min(_latencies(cl))
        wiring.connect(m, current_loop=cl.o, dtc=dtc.i)
        wiring.connect(m, dtc=dtc.o, timer=timer.duty)
        wiring.connect(m, current_loop=cl.phase, protect=prot.i)
        m.d.comb += [dtc.phase.valid.eq(cl.phase.valid),        # fan-out (always ready)
                     dtc.phase.payload.eq(cl.phase.payload)]
        wiring.connect(m, current_loop=cl.udc, protect=prot.udc)
        speed = mt.o.payload.speed
        # The current loop's copy of the speed, a clock behind M/T's output register (ECP5 Fmax:
        # the loop rounds and saturates it to 16 bits at its sample latch, across the die from
        # M/T; the loop latches it at its sample, thousands of clocks after an update).
        # The protection's overspeed verdict takes the same copy, LeadAngle the speed rounded
        # to 16 bits in a register of its own beside it (`lead_n`: the same rounding of the
        # same register in LeadAngle and the current loop was shared by yosys, one carry chain
        # driving two latches across the die), with M/T's strobe a clock later too
        # (`speed_valid_q`; module docstring, "The speed's consumers"). The engine (the iCE40
        # top) takes M/T's register itself, as does the protection then (−32 FF, docs/AREA.md
        # "Session 12": the register holds from its o.valid clock on, so at speed_valid_q it
        # is the copy's value).
        speed_valid_q = Signal()
        m.d.sync += speed_valid_q.eq(mt.o.valid)
        engine_speed = self._speed_loop == "engine"
        speed_valid = mt.o.valid if regs.staging == "ff" else mt.o.valid & ~regs.export_walk
        if self._current_loop == "pipelined":
            cl_speed = Signal.like(speed)
            m.d.sync += cl_speed.eq(speed)
        else:
            cl_speed = speed
        if self._lead is not None:
            lead_n = Signal(signed(16))
            m.d.sync += lead_n.eq(saturate(round_shift(speed, SPEED_WIDTH - 16), signed(16)))
            m.d.comb += [
                # θ_lead = speed · theta_lead, recomputed from each new M/T speed (the register
                # commits at period_start, before mt.o.valid): ready period_start + mt.latency
                # + 1 + LeadAngle.latency, before the ADC sample unless pwm_sample_point is that
                # early.
                lead.n.eq(lead_n),
                lead.k.eq(regs.theta_lead),
                lead.start.eq(speed_valid_q),
                cl.theta_lead.eq(lead.theta),
            ]
        else:
            # The engine: θ_lead from the speed it latches at the sample (M/T's register)
            # and the theta_lead register, in its program (EngineCurrentLoop.lead_k).
            if not hasattr(cl, "config"):                   # (else in its RAM, below)
                m.d.comb += cl.lead_k.eq(regs.theta_lead)
        m.d.comb += [
            # Loop boundary: staged registers, mode, open-loop angle, speed window.
            regs.commit.eq(timer.period_start if regs.staging == "ff" else
                           timer.position == timer.period - regs.commit_clocks),
            servo.loop.eq(timer.period_start),
            mt.update.eq(timer.period_start),
            adc.sample.eq(timer.sample),
            cl.scale.eq(timer.full_scale),

            # x4: every count of the decoder; a_rising: the counts that are an A rising edge.
            mt.edge.step.eq(enc.step if mt.edge_mode == "x4" else enc.a_rise),
            mt.edge.neg.eq(~enc.up),
            # ("bram": no speed-loop run starts in the register file's reset walk, which
            # writes the loop's configuration words: module docstring.) The SpeedLoop's, or
            # (speed_loop="engine") the engine's speed run's.
            *([cl.speed_valid.eq(speed_valid)] if engine_speed else [
                servo.speed.valid.eq(speed_valid), servo.speed.payload.eq(mt.o.payload)]),
            servo.theta_meas.eq(enc.theta),
            servo.trip.eq(trip_q),

            cl.theta.eq(servo.theta),
            cl.enable.eq(servo.enable),
            cl.ol_enable.eq(servo.ol_enable),
            # (the engine's references in its RAM: no ports, ENGINE_REFS)
            *([] if self._refs else [cl.ol_ud.eq(servo.ol_ud), cl.ol_uq.eq(servo.ol_uq)]),
            cl.speed.eq(cl_speed),

            prot.fault_n.eq(fault_n),
            prot.oc_comp.eq(oc_comp),
            prot.speed.valid.eq(speed_valid_q),
            prot.speed.payload.eq(cl_speed),
            prot.encoder_illegal.eq(enc.illegal),
            prot.hall_invalid.eq(enc.hall_fault),
            prot.encoder_hall.eq(enc.plausibility),

            gates.pwm.eq(timer.pwm),
            gates.enable.eq(servo.enable),
            gates.trip.eq(prot.trip),

            scope.strobe.eq(cl.done),       # one sample per current-loop computation
        ]
        # The reference-step trigger a clock late (module docstring, "Scope trigger"). A host
        # write to one of REF_STEP_REGISTERS (at its ack; the address and we are held until
        # then) stays pending in `ref_dirty` until a commit that is taken applies it: "ff" a
        # commit with lock low (lock is high from a frame's first access to its last ack, so
        # no write is acked in such a clock), "bram" a copy, seen by its export-port writes
        # (accesses are held off while it reads the RAM; none is acked then). That clock
        # raises the Servo's ref_change.
        ref_dirty = Signal()
        ref_write = (regs.bus.ack & regs.bus.we
                     & _addr_in(regs.bus.addr, [self._regmap[n].addr for n in REF_STEP_REGISTERS]))
        if regs.staging == "ff":
            committed = regs.commit & ~regs.bus.lock
        else:                           # (always an export port: the speed loop's words)
            committed = regs.export.valid
        m.d.comb += servo.ref_change.eq(ref_dirty & committed)
        m.d.sync += ref_dirty.eq(ref_write | (ref_dirty & ~committed))
        m.d.sync += scope.trigger.eq(servo.ref_step)

        # --- registers → blocks (register name ≠ port name in places) -----------------------
        # The current loop's configuration: the register file's active values, or (the engine
        # with "bram" staging) the register file's export port into the engine's RAM.
        exp = regs.export if "export" in regs.signature.members else None

        def operand(name):
            """A block's operand that is a function of register ``name`` (_operands): the
            register file's Out member itself if it holds it (Derived), else the function of
            the raw value."""
            if name in regs.derived:
                return getattr(regs, name)
            return self._operands[name][1](getattr(regs, name))

        if hasattr(cl, "config"):
            # The export port's first words (indices 0 … len(ENGINE_CONFIG) − 1; with the
            # engine's speed run the speed loop's words after them too: all of them).
            n_cfg = self._n_cfg
            # (`index < n_cfg` against the constant as logic, fixed.at_least: no carry chain)
            if self.mt_engine:
                # (mt_k's words, the last exported, after the engine's: contiguous with the
                # speed loop on the engine, else moved down over the speed loop's words)
                lo = self._mt_k_words[0]
                mt_words = at_least(exp.index, lo)
                in_cfg = ~at_least(exp.index, n_cfg)
                m.d.comb += [cl.config.valid.eq(exp.valid & (in_cfg | mt_words)),
                             cl.config.index.eq(exp.index if lo == n_cfg else
                                                Mux(mt_words, exp.index - (lo - n_cfg),
                                                    exp.index)),
                             cl.config.data.eq(exp.data)]
            else:
                m.d.comb += [cl.config.valid.eq(exp.valid & ~at_least(exp.index, n_cfg)),
                             cl.config.index.eq(exp.index), cl.config.data.eq(exp.data)]
        else:
            m.d.comb += [
                cl.kp_d.eq(regs.pi_d_kp), cl.kx_d.eq(regs.pi_d_kx),
                cl.lim_lo_d.eq(regs.pi_d_lim_lo), cl.lim_hi_d.eq(regs.pi_d_lim_hi),
                cl.kp_q.eq(regs.pi_q_kp), cl.kx_q.eq(regs.pi_q_kx),
                cl.lim_lo_q.eq(regs.pi_q_lim_lo), cl.lim_hi_q.eq(regs.pi_q_lim_hi),
                cl.gain_a.eq(regs.clarke_gain_a), cl.offset_a.eq(regs.clarke_offset_a),
                cl.gain_b.eq(regs.clarke_gain_b), cl.offset_b.eq(regs.clarke_offset_b),
                cl.ff_l.eq(regs.decouple_l),
                cl.ff_psi.eq(regs.decouple_psi),
                cl.u_rated.eq(regs.u_rated),
            ]
        # The speed loop's inputs go to the Servo's SpeedLoop or (speed_loop="engine") to the
        # engine's speed run (below, in the places the SpeedLoop's take), whose results go
        # back into the Servo.
        if engine_speed:
            m.d.comb += [cl.speed_clear.eq(servo.speed_clear),
                         servo.sl_iq.valid.eq(cl.speed_o.valid),
                         servo.sl_iq.payload.eq(cl.speed_o.payload),
                         servo.sl_sat.eq(cl.speed_sat), servo.sl_ref_int.eq(cl.speed_ref_int)]
            if not self._refs:
                m.d.comb += [cl.iq_lim_lo.eq(regs.pi_speed_lim_lo),
                             cl.iq_lim_hi.eq(regs.pi_speed_lim_hi)]
        sl = cl if engine_speed else servo
        m.d.comb += [
            servo.mode.eq(regs.mode),
            sl.speed_ref.eq(regs.speed_ref),
            # (the engine's references in its RAM: the Servo's id_ref, iq_ref unused, ENGINE_REFS)
            *([] if self._refs else [servo.id_set.eq(regs.i_d_ref),
                                     servo.iq_set.eq(regs.i_q_ref)]),
            servo.ol_src.eq(regs.ol_angle_mode),
            # (the engine's references in its RAM: the Servo's ol_ud, ol_uq unused too)
            *([] if self._refs else [servo.ud_set.eq(regs.ol_u_d),
                                     servo.uq_set.eq(regs.ol_u_q)]),
            servo.ol_theta.eq(regs.ol_angle),
            servo.ol_freq.eq(regs.ol_freq),

            cl.ff_enable.eq(regs.decouple_enable),

            timer.symmetric.eq(regs.pwm_symmetric),
            timer.sample_custom.eq(regs.pwm_sample_custom),
            timer.sample_point.eq(regs.pwm_sample_point),
            (gates.dead_n.eq(operand("dead_time")) if self._gates.dead_input == "dead_n" else
             gates.dead_time.eq(regs.dead_time)),
            dtc.symmetric.eq(regs.pwm_symmetric),
            dtc.clocks.eq(regs.dtc_clocks),
            dtc.shift.eq(regs.dtc_band),

            *([] if self._refs else [servo.iq_lim_lo.eq(regs.pi_speed_lim_lo),
                                     servo.iq_lim_hi.eq(regs.pi_speed_lim_hi)]),
            sl.speed_rate_div.eq(operand("speed_div")),
            sl.speed_ref_delay.eq(regs.speed_ref_delay),
            sl.speed_int_hold.eq(regs.speed_int_hold),
            *([] if self.mt_engine else [mt.k.eq(self._mt_k(m, exp) if self._mt_k_words
                                                 else regs.mt_k)]),

            enc.lines.eq(regs.enc_lines),
            enc.pole_pairs.eq(regs.enc_pole_pairs),
            enc.z_offset.eq(regs.enc_z_offset),
            # (the decoder keeps no copy of them: the register file tells it of a change)
            enc.lp_changed.eq(regs.enc_lines_changed | regs.enc_pole_pairs_changed),
            enc.z_changed.eq(regs.enc_z_offset_changed),
            enc.hall_offset.eq(regs.enc_hall_offset),
            enc.length.eq(regs.enc_filter),
            enc.realign.eq(regs.enc_realign),
            enc.hall_tolerance.eq(regs.prot_eh_tolerance),
            enc.hall_misses.eq(regs.prot_eh_misses),

            *([prot.oc_limit.eq(regs.prot_oc_limit), prot.ov_limit.eq(regs.prot_ov_limit),
               prot.uv_limit.eq(regs.prot_uv_limit)] if prot.limits == "ports" else []),
            prot.uv_enable.eq(regs.prot_uv_enable),
            *([prot.os_limit.eq(regs.prot_os_limit)] if prot.limits == "ports" else []),
            _raw(prot.mask).eq(_raw(regs.prot_mask)),      # same FAULTS bit order (checked below)
            prot.clear.eq(regs.clear_faults),

            scope.decim.eq(operand("scope_decim")),
            scope.pretrigger.eq(operand("scope_pretrig")),
            scope.trig_src.eq(regs.scope_trig_src),
            scope.arm.eq(regs.scope_arm),
            scope.force.eq(regs.scope_force),
        ]
        # The speed loop's gains, slew and feed-forward: the register file's active values, or
        # ("bram") its export port's words from index ``_speed_export`` on into the speed
        # loop's RAM; with the speed loop on the engine, in its configuration RAM (above).
        if self._speed_loop != "engine":
            if self._speed_export is None:
                m.d.comb += [servo.speed_kp.eq(regs.pi_speed_kp),
                             servo.speed_kx.eq(regs.pi_speed_kx),
                             servo.speed_slew.eq(regs.speed_slew),
                             servo.iq_ff.eq(regs.speed_ff_iq)]
            else:
                k = self._speed_export
                # (with mt_k exported its words come after the speed loop's)
                ours = exp.valid & (exp.index >= k)
                if self._mt_k_words:
                    ours &= exp.index < k + len(SPEED_CONFIG)
                m.d.comb += [servo.speed_config.valid.eq(ours),
                             servo.speed_config.index.eq(exp.index - k),
                             servo.speed_config.data.eq(exp.data)]
        assert tuple(regs.prot_mask.shape().members) == FAULTS
        if prot.limits != "ports":
            # The limits mirrored from the register file's staging RAM (one clock after the
            # flip-flops would have changed) into the protection's limit RAM.
            assert [r.name for _, r, _ in regs.mirror_words] == list(PROT_LIMITS)
            wiring.connect(m, regs=regs.mirror, protect=prot.limit_wr)
        # The scope's channel selects: the codes clamped (_operands).
        for c in range(scope.channels):
            m.d.comb += scope.sel[c].eq(operand(f"scope_chan{c}"))
        # Window: 12-bit word offset = channel · 1024 + index; 16-bit samples zero-extended
        # (the host sign-extends the signed sources).
        m.d.comb += [
            scope.rd_addr.eq(regs.scope_rd_addr),
            regs.scope_rd_data.eq(scope.rd_data),
        ]
        src = scope.src
        # θ and the current references through registers (the Servo selects θ and clamps or
        # selects the references by mode): in the trace one clock late (docs/AREA.md §7.12).
        # The current loop latches the same registered references (ECP5 Fmax: the register
        # file's i_q_ref → the Servo's clamp and mode mux → the loop's sample latch was the
        # whole top's critical path, docs/AREA.md §7.34); they change a clock later than the
        # Servo's outputs, which the loop, latching them at its sample, sees only for a
        # speed-PI result in the clock of the sample (module docstring, "References").
        theta_q = Signal.like(servo.theta)
        if not self._refs:
            id_ref_q = Signal.like(servo.id_ref)
            iq_ref_q = Signal.like(servo.iq_ref)
            m.d.sync += [theta_q.eq(servo.theta), id_ref_q.eq(servo.id_ref),
                         iq_ref_q.eq(servo.iq_ref)]
            m.d.comb += [cl.id_ref.eq(id_ref_q), cl.iq_ref.eq(iq_ref_q)]
        else:
            m.d.sync += theta_q.eq(servo.theta)
        m.d.comb += [
            src.speed.eq(speed),
            src.speed_ref.eq(regs.speed_ref),
            *([] if self._refs else [src.i_d_ref.eq(id_ref_q), src.i_q_ref.eq(iq_ref_q)]),
            src.theta.eq(theta_q),
            src.u_dc.eq(cl.udc.payload),
        ]
        # The loop's status: its ports, or (the engine's status RAM) one read port of it each
        # for the register file and the scope (the scope samples it in the engine's quiet
        # clocks after done: checked in __init__).
        if self._refs:
            # The references the engine used, from its status RAM (written by its program
            # while it runs, ENGINE_REFS), as the registers the scope took them from would
            # hold them: the Servo's of the clock before, 0 unless the mode was CURRENT or
            # SPEED then. A channel reading one in clock c (its data in c + 1) reads the RAM's
            # word that is never written (0, ``status_zero``) instead unless that mode held in
            # c − 1 (``run_q``). (Equal to the registers' unless a commit or a mode copy falls
            # in the run, which the top's timing keeps out of it: module docstring.)
            run_q = Signal()
            probe, addr = cl.status_probe, scope.ram_rd.addr
            m.d.sync += run_q.eq(servo.enable & ~servo.ol_enable)
            m.d.comb += [probe.addr.eq(Mux((addr >= len(ENGINE_STATUS)) & ~run_q,
                                           cl.status_zero, addr)),
                         probe.en.eq(scope.ram_rd.en), scope.ram_rd.data.eq(probe.data)]
        if self._status_ram:
            if not self._refs:
                wiring.connect(m, current_loop=cl.status_probe, scope=scope.ram_rd)
            wiring.connect(m, current_loop=cl.status_rd, regs=regs.status_rd)
        else:
            m.d.comb += [getattr(src, n).eq(getattr(cl, n)) for n in ENGINE_STATUS]
            m.d.comb += [getattr(regs, f"st_{n}").eq(getattr(cl, n)) for n in ENGINE_STATUS]

        # --- status registers ---------------------------------------------------------------
        # (with the counters in the register file's RAM: its count strobes, the same events)
        counted = {"st_speed_loops": servo.speed_valid, "st_overruns": cl.overrun,
                   "st_adc_overruns": adc.overrun}
        assert tuple(counted) == TOP_COUNTERS
        if self._ram_loop_count:
            counted["st_current_loops"] = cl.done
        for name, event in counted.items():
            if self._ram_counters:
                m.d.comb += getattr(regs, f"{name}_inc").eq(event)
            else:
                count = Signal(16, name=name[3:])
                with m.If(event):
                    m.d.sync += count.eq(count + 1)         # wraps, as documented
                m.d.comb += getattr(regs, name).eq(count)
        # Sticky loop flags, sampled when they are final: the current loop's one clock after its
        # duty transfer (overmod is registered then), the speed PI's one clock after its result.
        # clear_faults clears them all (a flag still true is set again by the next loop; one
        # seen in the clear's own clock is kept).
        # The angle as a status word straight from the encoder: θ is its register of the
        # decoder's angle (or the Hall angle) behind one multiplexer, not a sum and a wrap
        # compare (the register file's read multiplexer behind those was the whole top's
        # critical path on the ECP5, docs/AREA.md §7.8: this copy used to register it).
        theta_status = enc.theta
        flags = Signal(len(LOOP_FLAG_FIELDS))
        cl_done = Signal()
        speed_done = Signal()
        m.d.sync += [cl_done.eq(cl.done), speed_done.eq(servo.speed_valid)]
        seen = {
            "overmod": cl_done & cl.overmod, "sat_d": cl_done & cl.sat_d,
            "sat_q": cl_done & cl.sat_q, "dc_limited": cl_done & cl.dc_limited,
            "sat_speed": speed_done & servo.speed_sat,
        }
        assert tuple(seen) == LOOP_FLAG_FIELDS
        m.d.sync += flags.eq(Mux(regs.clear_faults, 0, flags) | Cat(*seen.values()))
        assert COUNTERS == LINK_COUNTERS
        for name in COUNTERS:
            if name in self._ram_counters:
                m.d.comb += getattr(regs, f"st_link_{name}_inc").eq(
                    getattr(link, f"{name}_strobe"))
            else:
                m.d.comb += getattr(regs, f"st_link_{name}").eq(getattr(link, name))
        m.d.comb += [
            regs.st_mode.eq(servo.active),
            regs.st_trip.eq(trip_q),
            _raw(regs.st_fault_present).eq(_raw(prot.present)),
            _raw(regs.st_fault_first).eq(_raw(prot.first)),
            _raw(regs.st_fault_seen).eq(_raw(prot.seen)),
            regs.st_enc_aligned.eq(enc.aligned),
            regs.st_position.eq(enc.count),
            regs.st_theta.eq(theta_status),
            regs.st_speed.eq(speed),
            regs.st_udc.eq(cl.udc.payload),
            # (16-bit register: wraps at 2**16; with "bram" a counter in the staging RAM)
            *([] if self._ram_loop_count else [regs.st_current_loops.eq(cl.count[:16])]),
            _raw(regs.st_loop_flags).eq(flags),
            regs.st_uv_armed.eq(prot.uv_armed),
            regs.st_enc_config_error.eq(enc.config_error),
            regs.st_enc_hall_error.eq(enc.hall_error),
            regs.scope_state.eq(scope.state),
            _raw(regs.scope_status).eq(Cat(scope.done, scope.pre_full)),
        ]
        return m
