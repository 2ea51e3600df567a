# Ref: paper eq. (7)–(9) (speed PI); SPEC.md §2.5, §4 (modes); issue 5 items 3 and 5
"""Gateware :class:`~foc_servo.hdl.servo.Servo` and :class:`~foc_servo.hdl.scope.Scope` against
their golden models, clock by clock, over seeded random sequences.

Servo: segments of random speed-PI gains, current limits (symmetric, asymmetric, narrow, equal,
inverted), speed-loop rate dividers and loop periods; random register writes (mode, references,
open-loop angle source, angle and frequency), protection trips, extra speed samples that find the
PI busy; the speed feedback comes from a crude plant (speed integrates the i_q reference the
model outputs), so steps drive the PI into the current limit, wind it up and let it recover, with
occasional full-scale speed values. The reference profile gets random slews (0, 1 LSB, small,
large, the maximum), feed-forwards (0, random, ±full scale), reference delays and integrator
holds, changed between speed-loop runs (mid-ramp too; the speed loop reads its inputs during a
run, as the register file leaves them between loop boundaries), loop periods of at least the
speed loop's interval, and speed references that reverse through zero or land exactly a whole
number of slews away.

Scope: random arm/force/trigger strobes, strobe densities, decimation, pre-trigger counts (0 and
depth − 1 included), channel selects (invalid codes included) and read addresses every clock;
each finished capture is also read back from the model and compared with the samples as taken
(trigger sample at index ``pretrigger``).

To keep Python out of the per-clock work, a simulation-only wrapper packs every input into one
``stim`` signal and every output into one ``resp`` signal: one ``ctx.set`` and one ``ctx.get``
per clock, compared as integers against the model's packed outputs.
"""

import numpy as np

from amaranth.hdl import Cat, Module, Value
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from ...hdl.fixed import shape_range
from ...hdl.scope import Scope, ScopeState
from ...hdl.servo import DELAY_FRAC, AngleMode, Mode, Servo
from ..harness import Progress, simulate
from ..models.scope import ScopeModel
from ..models.servo import SERVO_INPUTS, ServoModel

__all__ = ["run", "run_servo", "run_scope", "Packed"]

CLOCK_HZ = 50e6


class Packed(wiring.Component):
    """Simulation-only wrapper: ``stim`` drives the listed inputs of ``dut`` (concatenated in
    order), ``resp`` is the concatenation of the listed outputs. :meth:`pack` and :meth:`unpack`
    convert between dicts of integers and those words."""

    def __init__(self, dut, inputs, outputs):
        self._dut = dut
        self._inputs = {k: Value.cast(v) for k, v in inputs.items()}
        self._outputs = {k: Value.cast(v) for k, v in outputs.items()}

        def fields(values):
            out, offset = [], 0
            for name, v in values.items():
                shape = v.shape()
                out.append((name, offset, shape.width, shape.signed))
                offset += shape.width
            return out, offset

        self._in_fields, in_width = fields(self._inputs)
        self._out_fields, out_width = fields(self._outputs)
        super().__init__({"stim": In(in_width), "resp": Out(out_width)})

    @staticmethod
    def _pack(fields, values):
        word = 0
        for name, offset, width, _ in fields:
            word |= (int(values[name]) & ((1 << width) - 1)) << offset
        return word

    @staticmethod
    def _unpack(fields, word):
        out = {}
        for name, offset, width, signed in fields:
            v = (word >> offset) & ((1 << width) - 1)
            if signed and v >> (width - 1):
                v -= 1 << width
            out[name] = v
        return out

    def pack_inputs(self, values):
        return self._pack(self._in_fields, values)

    def pack_outputs(self, values):
        return self._pack(self._out_fields, values)

    def unpack_outputs(self, word):
        return self._unpack(self._out_fields, word)

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = self._dut
        m.d.comb += Cat(*self._inputs.values()).eq(self.stim)
        m.d.comb += self.resp.eq(Cat(*self._outputs.values()))
        return m


def _log_uniform(rng, lo, hi):
    bits = rng.uniform(0, np.log2(hi + 1))
    return int(min(max(int(2.0 ** bits) - 1, lo), hi))


def _profile(rng, sw, delay_max):
    """Random reference-profile registers (slew, feed-forward, delay, integrator hold)."""
    slew_max = (1 << sw) - 1
    slew = int(rng.choice([0, 0, 1, slew_max, _log_uniform(rng, 1, 1 << (sw - 8)),
                           _log_uniform(rng, 1, 1 << (sw - 14)),
                           _log_uniform(rng, 1, slew_max)]))
    ff = int(rng.choice([0, 0, -32768, 32767, int(rng.integers(-32768, 32768)),
                         int(rng.integers(-2000, 2000))]))
    delay = int(rng.choice([0, 0, int(rng.integers(0, 1 << DELAY_FRAC)),
                            int(rng.integers(0, delay_max))]))
    return dict(speed_slew=slew, iq_ff=ff, speed_ref_delay=delay,
                speed_int_hold=int(rng.random() < 0.5))


def _limits(rng):
    kind = rng.choice(["full", "sym", "sym", "sym", "asym", "narrow", "equal", "inverted"],
                      p=[0.15, 0.35, 0.15, 0.1, 0.15, 0.04, 0.03, 0.03])
    if kind == "full":
        return -32768, 32767
    if kind == "sym":
        a = _log_uniform(rng, 1024, 32767)
        return -a, a
    if kind == "asym":
        lo, hi = sorted(int(x) for x in rng.integers(-32768, 32768, 2))
        return lo, hi
    if kind == "narrow":
        lo = int(rng.integers(-32768, 32767 - 64))
        return lo, lo + int(rng.integers(0, 65))
    if kind == "equal":
        v = int(rng.integers(-32768, 32768))
        return v, v
    lo, hi = sorted(int(x) for x in rng.integers(-32768, 32768, 2))
    return max(hi, lo + 1), lo


def _servo_stimulus(count, rng, model, dut):
    """Inputs of ``count`` clocks and the model's outputs, generated together (the plant closes
    the loop through the model). Returns (inputs list, outputs list, figures)."""
    sl = model.speed_loop
    kp_fmt, kx_fmt = dut.loop_params["kp_format"], dut.loop_params["kx_format"]
    sw = dut.loop_params["speed_width"]
    s_lo, s_hi = shape_range(dut.speed_ref.shape())
    p_lo, p_hi = shape_range(dut.ol_freq.shape())
    div_max = (1 << dut.loop_params["div_width"]) - 1
    delay_max = 1 << dut.loop_params["delay_width"]
    regs = {name: 0 for name in SERVO_INPUTS}
    regs.update(iq_lim_lo=-32768, iq_lim_hi=32767, speed_kp=1 << max(kp_fmt.frac, 0))
    # The speed loop's inputs are changed only between runs (the register file changes them
    # at loop boundaries, thousands of clocks apart; the model checks it): writes wait here.
    pending = {}
    interval = sl.interval
    period, offset, phase, seg_left = interval + 20, 3, 0, 0
    slow = max(interval // 24, 1)       # event rates per loop period as with 24-clock periods
    trip_left = 0
    omega = 0.0                                 # plant speed, raw Q1.(sw-1)
    gain = 0.0
    figures = dict(speed_runs=0, speed_saturated=0, speed_windup=0, recoveries=0,
                   dropped_runs=0, mode_changes=0, trips=0, ref_steps=0, rotating_clocks=0,
                   ramp_runs=0, ramp_ends=0, ramp_reversals=0, ramp_cleared=0,
                   ff_full_scale_runs=0, ff_clamped_runs=0, held_runs=0, delayed_runs=0,
                   slew_max_runs=0)
    prev_last = None
    prev_active = 0
    inputs, outputs = [], []
    last_iq = 0
    for _ in range(count):
        # Segment: new loop timing and (when the PI is idle) new gains, limits, rate divider.
        if seg_left <= 0:
            period = int(rng.integers(interval, interval + 81))
            offset = int(rng.integers(0, period))
            seg_left = int(rng.integers(300, 3000)) * slow
            kp = 0 if rng.random() < 0.05 else _log_uniform(rng, 0, kp_fmt.max_raw >> 4)
            kx = 0 if rng.random() < 0.05 else _log_uniform(rng, 1 << 8, kx_fmt.max_raw >> 6)
            lo, hi = _limits(rng)
            div = int(rng.choice([0, 0, 0, 1, 2, 3, int(rng.integers(0, div_max + 1))]))
            pending.update(speed_kp=kp, speed_kx=kx, iq_lim_lo=lo, iq_lim_hi=hi,
                           speed_rate_div=div)
            gain = float(rng.choice([0.0, 2.0 ** (sw - 16 - 4), 2.0 ** (sw - 16 - 2),
                                     2.0 ** (sw - 16)], p=[0.1, 0.3, 0.3, 0.3]))
        seg_left -= 1
        if rng.random() < 1 / (700 * slow):
            pending.update(_profile(rng, sw, delay_max))

        # Register writes (a write of a reference or the mode raises ref_change, as Top's
        # commit of one does).
        regs["ref_change"] = 0
        if rng.random() < 1 / (120 * slow):
            what = rng.choice(["mode", "mode", "mode", "speed_ref", "speed_ref", "iq_set",
                               "id_set", "ud_set", "uq_set", "ol_src", "ol_theta", "ol_freq"])
            if what == "mode":
                regs["mode"] = int(rng.choice([0, 1, 2, 3, 3, 3]))
                regs["ref_change"] = 1
            elif what == "speed_ref":
                r = rng.random()
                ref = pending.get("speed_ref", regs["speed_ref"])
                slew = pending.get("speed_slew", regs["speed_slew"])
                if r < 0.15:
                    ref = int(rng.choice([s_lo, s_hi, 0]))
                elif r < 0.25:                  # reversal through zero
                    ref = int(np.clip(-ref, s_lo, s_hi))
                elif r < 0.35:                  # a whole number of slews away: lands exactly
                    k = int(rng.integers(-6, 7))
                    ref = int(np.clip(sl.ref_int + k * slew, s_lo, s_hi))
                elif r < 0.6:
                    ref = int(rng.integers(s_lo // 4, s_hi // 4))
                else:
                    ref = int(np.clip(ref + rng.integers(-(1 << (sw - 8)), 1 << (sw - 8)),
                                      s_lo, s_hi))
                pending["speed_ref"] = ref
            elif what in ("iq_set", "id_set", "ud_set", "uq_set"):
                regs[what] = int(rng.integers(-32768, 32768))
                regs["ref_change"] = 1
            elif what == "ol_src":
                regs["ol_src"] = int(rng.integers(0, 4))
            elif what == "ol_theta":
                regs["ol_theta"] = int(rng.integers(0, 1 << 16))
            else:
                regs["ol_freq"] = int(rng.choice([p_lo, p_hi, int(rng.integers(p_lo, p_hi))]))
        # Trip pulses.
        if trip_left == 0 and rng.random() < 1 / (3000 * slow):
            trip_left = int(rng.integers(1, 60 * slow))
            figures["trips"] += 1
        regs["trip"] = int(trip_left > 0)
        trip_left = max(trip_left - 1, 0)

        if pending and not sl.busy:
            regs["ref_change"] |= "speed_ref" in pending
            regs.update(pending)
            pending = {}
        # Strobes: loop boundary, speed sample (plus rare extra ones, which find the PI busy).
        regs["loop"] = int(phase == 0)
        valid = phase == offset or rng.random() < 1 / 400
        regs["speed_valid"] = int(valid)
        phase = (phase + 1) % period
        regs["theta_meas"] = int(rng.integers(0, 1 << 16))
        if valid:
            omega += gain * last_iq - omega / 256 + rng.normal(0, 2.0 ** (sw - 20))
            omega = float(np.clip(omega, s_lo, s_hi))
            speed = int(round(omega))
            if rng.random() < 0.01:
                speed = int(rng.choice([s_lo, s_hi, s_hi - 1, s_lo + 1]))
            regs["speed"] = speed

        runs = sl.runs
        dropped = sl.dropped
        ref_before, ff_before = sl.ref_int, sl.ff
        out = model.clock(regs)
        inputs.append(dict(regs))
        outputs.append(out)
        last_iq = out["iq_ref"]
        figures["dropped_runs"] += sl.dropped - dropped
        if sl.runs != runs:
            last = sl.pi.last
            figures["speed_runs"] += 1
            figures["speed_saturated"] += last["sat"]
            figures["speed_windup"] += bool(last["clamped"] or last["held"])
            if (prev_last is not None and prev_last["sat"]
                    and (prev_last["clamped"] or prev_last["held"])
                    and not last["sat"] and last["e"] * prev_last["e"] < 0):
                figures["recoveries"] += 1
            prev_last = last
            moving = sl.plan != regs["speed_ref"]             # after this run's update
            figures["ramp_runs"] += moving
            figures["ramp_ends"] += (ref_before != sl.plan and sl.plan == regs["speed_ref"]
                                     and regs["speed_slew"] != 0)
            figures["ramp_reversals"] += ((ref_before > 0) != (sl.plan > 0)
                                          and regs["speed_slew"] != 0)
            figures["ff_full_scale_runs"] += moving and abs(regs["iq_ff"]) >= 32767
            figures["ff_clamped_runs"] += moving and abs(sl.ff) != abs(regs["iq_ff"])
            figures["held_runs"] += sl.hold
            figures["delayed_runs"] += regs["speed_ref_delay"] >> DELAY_FRAC != 0
            figures["slew_max_runs"] += regs["speed_slew"] == (1 << sw) - 1
        elif ff_before != 0 and sl.ff == 0 and out["speed_clear"]:
            figures["ramp_cleared"] += 1
        figures["mode_changes"] += out["active"] != prev_active
        prev_active = out["active"]
        figures["ref_steps"] += out["ref_step"]
        figures["rotating_clocks"] += (out["active"] == Mode.OPEN_LOOP.value and
                                       regs["ol_src"] == AngleMode.ROTATING.value)
    return inputs, outputs, figures


def _compare_run(bench, stims, resps, label, progress, name):
    """Simulate ``bench`` (a :class:`Packed`), one stim word per clock, comparing resp words."""
    result = {"mismatches": 0, "first_mismatch": None}
    total = len(stims)
    bar = Progress(label, total, enabled=progress)

    async def testbench(ctx):
        for k in range(total):
            ctx.set(bench.stim, stims[k])
            got = ctx.get(bench.resp)
            if got != resps[k]:
                result["mismatches"] += 1
                if result["first_mismatch"] is None:
                    g, w = bench.unpack_outputs(got), bench.unpack_outputs(resps[k])
                    result["first_mismatch"] = {
                        "clock": k, "got": {n: g[n] for n in g if g[n] != w[n]},
                        "expected": {n: w[n] for n in g if g[n] != w[n]}}
            await ctx.tick()
            if not k & 1023:
                bar.update(k)
        bar.close()

    sim_s = simulate(bench, [testbench], clock_hz=CLOCK_HZ, name=name)
    result.update(vectors=total, clocks=total, sim_s=sim_s,
                  clocks_per_s=total / sim_s if sim_s else 0.0)
    return result


def run_servo(count=100_000, *, seed=0, progress=False, **params):
    """:class:`Servo` (with its :class:`SpeedLoop`) against :class:`ServoModel` for ``count``
    clocks; ``params`` go to both.

    Returns
    -------
    dict
        ``mismatches`` (clocks with any output different), ``vectors`` = ``clocks`` (compared
        clocks), ``sim_s``, ``clocks_per_s``, ``first_mismatch``; ``speed_runs`` (speed-PI runs),
        ``speed_saturated`` (runs whose output sat at the current limit), ``speed_windup`` (runs
        with the integrator clamped or held), ``recoveries`` (pinned with a wound-up integrator,
        then inside the limits on the first run after the error changed sign),
        ``dropped_runs`` (speed samples that found the PI busy), ``mode_changes``, ``trips``,
        ``ref_steps``, ``rotating_clocks``; of the reference profile: ``ramp_runs`` (runs whose
        reference had not reached ``speed_ref``), ``ramp_ends`` (runs landing on it),
        ``ramp_reversals`` (runs whose reference crossed zero), ``ramp_cleared`` (a moving
        profile left SPEED mode), ``ff_full_scale_runs`` (moving with ``|iq_ff|`` at full
        scale), ``ff_clamped_runs`` (moving, feed-forward clamped to a current limit),
        ``held_runs`` (integrator held), ``delayed_runs`` (reference delay ≥ 1 run),
        ``slew_max_runs`` (the largest slew).
    """
    dut = Servo(**params)
    model = ServoModel(**params)
    rng = np.random.default_rng(seed)
    inputs, outputs, figures = _servo_stimulus(count, rng, model, dut)
    signals = {name: getattr(dut, name) for name in SERVO_INPUTS
               if name not in ("speed_valid", "speed")}
    signals["speed_valid"] = dut.speed.valid
    signals["speed"] = dut.speed.payload.speed
    bench = Packed(dut, signals, {name: getattr(dut, name) for name in outputs[0]})
    stims = [bench.pack_inputs(i) for i in inputs]
    resps = [bench.pack_outputs(o) for o in outputs]
    result = _compare_run(bench, stims, resps, "servo", progress, "servo")
    result.update(figures)
    return result


def _scope_stimulus(count, rng, model, dut):
    names = model.names
    shapes = model.sources
    depth, n = model.depth, model.channels
    n_codes = 1 << dut.sel_width
    dec_max = (1 << dut.decim_width) - 1
    regs = dict(strobe=0, decim=0, pretrigger=0, trig_src=0, arm=0, force=0, trigger=0,
                rd_addr=0, sel=[int(c) % n_codes for c in range(n)])
    strobe_p = 0.5
    figures = dict(captures=0, triggers=0, triggers_ignored=0, arms=0, wraps=0,
                   capture_order_errors=0, pretrigger_max_captures=0, pretrigger_zero_captures=0)
    taken, trig_at, pre_at_trigger = [], None, 0
    pending = None          # (clock, expected ring): a capture checked once its last sample is in
    ring_writes = 0
    inputs, outputs = [], []
    read_seq = None
    src_values = {name: rng.integers(*shape_range(shapes[name]), count, endpoint=True).tolist()
                  for name in names}
    for k in range(count):
        r = rng.random()
        if r < 1 / 500:
            strobe_p = float(rng.choice([1.0, 0.5, 0.2, 0.05]))
        if rng.random() < 1 / 300:
            what = rng.choice(["sel", "decim", "pretrigger", "trig_src"])
            if what == "sel":
                regs["sel"] = [int(x) for x in rng.integers(0, n_codes, n)]
            elif what == "decim":
                regs["decim"] = int(rng.choice([0, 0, 1, 2, 3, int(rng.integers(0, dec_max + 1))
                                                if rng.random() < 0.05 else 0]))
            elif what == "pretrigger":
                regs["pretrigger"] = int(rng.choice([0, depth - 1, depth // 2,
                                                     int(rng.integers(0, depth))]))
            else:
                regs["trig_src"] = int(rng.integers(0, 2))
        idle = model.state == ScopeState.IDLE.value
        regs["arm"] = int(rng.random() < (1 / 50 if idle else 1 / 20000))
        regs["force"] = int(rng.random() < (1 / 30 if model.state == ScopeState.PRE.value
                                            else 1 / 500))
        regs["trigger"] = int(rng.random() < 1 / 40)
        regs["strobe"] = int(rng.random() < strobe_p)
        src = {name: src_values[name][k] for name in names}
        regs["src"] = src
        # Read addresses: after a capture a sequential read of the whole window, else random.
        if read_seq is not None and read_seq < n * depth:
            c, i = divmod(read_seq, depth)
            regs["rd_addr"] = (c << (depth.bit_length() - 1)) | i
            read_seq += 1
        else:
            read_seq = None
            regs["rd_addr"] = int(rng.integers(0, 1 << dut.addr_width))

        state, wp, captures = model.state, model.wr_ptr, model.captures
        ignored = model.triggers_ignored
        # A sample's channel c records its source c clocks after the strobe (one multiplexer).
        words = [model.sample({name: src_values[name][min(k + c, count - 1)] for name in names},
                              c) for c in range(n)]
        out = model.clock(regs)
        inputs.append(dict(regs))
        outputs.append(out)
        figures["triggers_ignored"] += model.triggers_ignored - ignored
        # Independent check of the capture order: the samples as taken since arm.
        if regs["arm"]:
            taken, trig_at, pending = [], None, None
            figures["arms"] += 1
            continue
        if model.wr_ptr != wp:
            taken.append(words)
            ring_writes += 1
            figures["wraps"] += model.wr_ptr == 0
        if state == ScopeState.PRE.value and model.state != ScopeState.PRE.value:
            figures["triggers"] += 1
            trig_at = len(taken) - (model.wr_ptr != wp)
            pre_at_trigger = model.pre
        if model.captures != captures:
            figures["captures"] += 1
            figures["pretrigger_max_captures"] += pre_at_trigger == depth - 1
            figures["pretrigger_zero_captures"] += pre_at_trigger == 0
            want = taken[trig_at - pre_at_trigger:trig_at - pre_at_trigger + depth]
            pending = (k + n, want)           # the last channel lands in the RAM then
            read_seq = 0 if rng.random() < 0.3 else None
        if pending is not None and k == pending[0]:
            got = [[model.read(i, c) for c in range(n)] for i in range(depth)]
            if len(pending[1]) != depth or got != pending[1]:
                figures["capture_order_errors"] += 1
            pending = None
    return inputs, outputs, figures


def run_scope(count=100_000, *, seed=0, progress=False, down_counts=False, **params):
    """:class:`Scope` against :class:`ScopeModel` for ``count`` clocks; ``params`` go to both,
    ``down_counts`` to the Scope (its counters' form; one model for both).

    Returns
    -------
    dict
        ``mismatches`` (clocks with any output different, plus captures whose read-back differs
        from the samples as taken), ``vectors`` = ``clocks``, ``sim_s``, ``clocks_per_s``,
        ``first_mismatch``; ``captures``, ``triggers``, ``triggers_ignored`` (before the
        pre-trigger part was full), ``arms``, ``wraps`` (ring write pointer wrapped),
        ``capture_order_errors``, ``pretrigger_max_captures``, ``pretrigger_zero_captures``.
    """
    dut = Scope(**params, down_counts=down_counts)
    model = ScopeModel(**params)
    rng = np.random.default_rng(seed)
    inputs, outputs, figures = _scope_stimulus(count, rng, model, dut)
    signals = {f"src.{name}": dut.src[name] for name in model.names}
    signals.update({f"sel.{c}": dut.sel[c] for c in range(model.channels)})
    signals.update({name: getattr(dut, name) for name in
                    ("strobe", "decim", "pretrigger", "trig_src", "arm", "force", "trigger",
                     "rd_addr")})
    bench = Packed(dut, signals, {name: getattr(dut, name) for name in outputs[0]})

    def flat(i):
        d = {k: v for k, v in i.items() if k not in ("src", "sel")}
        d.update({f"src.{k}": v for k, v in i["src"].items()})
        d.update({f"sel.{c}": v for c, v in enumerate(i["sel"])})
        return d

    stims = [bench.pack_inputs(flat(i)) for i in inputs]
    resps = [bench.pack_outputs(o) for o in outputs]
    result = _compare_run(bench, stims, resps, "scope", progress, "scope")
    result["mismatches"] += figures["capture_order_errors"]
    result.update(figures)
    return result


def run(count=100_000, *, seed=0, progress=False, scope=None, servo_count=None, **params):
    """Both checks: :func:`run_servo` (``params``; ``servo_count`` clocks, ``count`` if
    ``None``) and :func:`run_scope` (the dict ``scope`` of Scope parameters, defaults if
    ``None``, ``count`` clocks).

    Returns
    -------
    dict
        ``mismatches``, ``vectors``, ``clocks``, ``sim_s`` summed over both, and every figure of
        each prefixed ``servo_`` / ``scope_``.
    """
    servo = run_servo(count if servo_count is None else servo_count, seed=seed,
                      progress=progress, **params)
    scope_r = run_scope(count, seed=seed, progress=progress, **(scope or {}))
    result = {k: servo[k] + scope_r[k] for k in ("mismatches", "vectors", "clocks", "sim_s")}
    result.update({f"servo_{k}": v for k, v in servo.items()})
    result.update({f"scope_{k}": v for k, v in scope_r.items()})
    return result
