# amaranth: UnusedElaboratable=no
# Ref: paper eq. (7)–(9) (speed PI); SPEC.md §2.5, §4 (operating modes)
import math

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Const, Value

from foc_servo.hdl.fixed import Q, UQ, clamp_np, shape_range
from foc_servo.hdl.servo import SPEED_CONFIG, AngleMode, Mode, Servo, SpeedLoop
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.servo import SERVO_INPUTS, ServoModel, SpeedLoopModel
from foc_servo.sim.verify.servo import Packed, run, run_servo

KP_ONE = 1 << 12                 # 1.0 in the default UQ(24, 12)
KX_ONE = 1 << 24                 # 1.0 in UQ(24, 24) (not representable)
SPEED_1667 = round(1667 / 12000 * 2 ** 31)     # 1667 r/min at N_FS = 12 000 r/min, Q1.31

DISABLED, OPEN_LOOP, CURRENT, SPEED = (m.value for m in Mode)
_LOOP = SpeedLoop()
LAT, IV, RL = _LOOP.latency, _LOOP.interval, _LOOP.ref_latency    # 124, 125, 13 by default


def base_inputs(**kw):
    d = {name: 0 for name in SERVO_INPUTS}
    d.update(iq_lim_lo=-32768, iq_lim_hi=32767, speed_kp=KP_ONE)
    d.update(kw)
    return d


#: :class:`Servo`'s configuration inputs in :data:`SPEED_CONFIG` order.
SERVO_CONFIG = ("speed_kp", "speed_kx", "speed_slew", "iq_ff")


def config_writes(seq, keys):
    """``config="ram"``: the per-clock values of the configuration inputs ``keys`` (in
    :data:`SPEED_CONFIG` order) in ``seq`` as writes on the ``config`` port. A value that differs
    in clock ``t`` from clock ``t − 1`` is written in the clocks just before ``t`` (one word per
    clock, the changed words in order, the last in ``t − 1``), so that the RAM holds it from
    ``t``. Returns ``(init, seq)``: the RAM's initial words (``seq[0]``'s values) and ``seq``
    with the configuration inputs replaced by what the RAM holds in each clock (for the model)
    and the port's ``cfg_valid``, ``cfg_index``, ``cfg_data`` added."""
    init = [seq[0][k] for k in keys]
    writes = [None] * len(seq)
    for t in range(1, len(seq)):
        changed = [j for j, k in enumerate(keys) if seq[t][k] != seq[t - 1][k]]
        for i, j in enumerate(changed):
            c = t - len(changed) + i
            assert c >= 0 and writes[c] is None, f"config writes for clock {t} collide"
            writes[c] = (j, seq[t][keys[j]])
    ram, out = list(init), []
    for t, i in enumerate(seq):
        j, value = writes[t] or (0, 0)
        out.append({**i, **dict(zip(keys, ram)), "cfg_valid": int(writes[t] is not None),
                    "cfg_index": j, "cfg_data": value & 0xFFFF_FFFF})
        if writes[t] is not None:
            ram[j] = value
    return [v & 0xFFFF_FFFF for v in init], out


def _config_signals(port):
    return {"cfg_valid": port.valid, "cfg_index": port.index, "cfg_data": port.data}


def _build(cls, names, seq, params):
    """``cls(**params)`` for a clock-by-clock bench, and the input sequence it takes: with
    ``params["config"] == "ram"`` (popped) the configuration inputs ``names`` become writes of
    its configuration port (:func:`config_writes`). Returns ``(ram, dut, seq)``."""
    ram = params.pop("config", "ports") == "ram"
    if not ram:
        return ram, cls(**params), seq
    init, seq = config_writes(seq, names)
    return ram, cls(config="ram", config_init=init, **params), seq


def servo_clocks(seq, **params):
    """Drive :class:`Servo` with one input dict per clock; return the gateware's outputs per
    clock, after checking them against :class:`ServoModel` clock by clock. With
    ``config="ram"`` the configuration inputs reach it as writes (:func:`config_writes`)."""
    ram, dut, seq = _build(Servo, SERVO_CONFIG, seq, params)
    model = ServoModel(**params)
    want = [model.clock({n: i[n] for n in SERVO_INPUTS}) for i in seq]
    signals = {n: getattr(dut, n) for n in SERVO_INPUTS
               if n not in ("speed_valid", "speed") and not (ram and n in SERVO_CONFIG)}
    signals.update(speed_valid=dut.speed.valid, speed=dut.speed.payload.speed)
    if ram:
        signals.update(_config_signals(dut.speed_config))
    bench = Packed(dut, signals, {n: getattr(dut, n) for n in want[0]})
    got = []

    async def testbench(ctx):
        for i in seq:
            ctx.set(bench.stim, bench.pack_inputs(i))
            got.append(bench.unpack_outputs(ctx.get(bench.resp)))
            await ctx.tick()

    simulate(bench, [testbench], name="servo_clocks")
    for t, (g, w) in enumerate(zip(got, want)):
        assert g == w, f"clock {t}: gateware {g} model {w}"
    return got


LOOP_KEYS = ("valid", "speed", "speed_ref", "kp", "kx", "lim_lo", "lim_hi", "rate_div", "clear",
             "speed_slew", "iq_ff", "ref_delay", "int_hold")


def speed_loop_clocks(seq, **params):
    """Drive :class:`SpeedLoop` with per-clock dicts (:data:`LOOP_KEYS`); return (o_valid,
    o_payload, sat, ref_int) per clock, checked against the model. With ``config="ram"`` the
    configuration inputs reach it as writes (:func:`config_writes`)."""
    ram, dut, seq = _build(SpeedLoop, SPEED_CONFIG, seq, params)
    model = SpeedLoopModel(**params)
    want = [model.clock(*(i[k] for k in LOOP_KEYS)) for i in seq]
    signals = {k: getattr(dut, k) for k in LOOP_KEYS
               if k not in ("valid", "speed") and not (ram and k in SPEED_CONFIG)}
    signals.update(valid=dut.i.valid, speed=dut.i.payload.speed)
    if ram:
        signals.update(_config_signals(dut.config))
    bench = Packed(dut, signals, {"o_valid": dut.o.valid, "o_payload": dut.o.payload,
                                  "sat": dut.sat, "ref_int": dut.ref_int})
    got = []

    async def testbench(ctx):
        for i in seq:
            ctx.set(bench.stim, bench.pack_inputs(i))
            o = bench.unpack_outputs(ctx.get(bench.resp))
            got.append((o["o_valid"], o["o_payload"], o["sat"], o["ref_int"]))
            await ctx.tick()

    simulate(bench, [testbench], name="speed_loop_clocks")
    assert got == want
    return got, model


def loop_inputs(**kw):
    d = dict(valid=0, speed=0, speed_ref=0, kp=KP_ONE, kx=0, lim_lo=-32768, lim_hi=32767,
             rate_div=0, clear=0, speed_slew=0, iq_ff=0, ref_delay=0, int_hold=0)
    d.update(kw)
    return d


@pytest.mark.parametrize("cls", [SpeedLoop, SpeedLoopModel])
@pytest.mark.parametrize("kwargs, exc, msg", [
    (dict(speed_width=15), TypeError,
     r"^SpeedLoop speed_width must be an integer from 16 to 48, not 15$"),
    (dict(speed_width="32"), TypeError,
     r"^SpeedLoop speed_width must be an integer from 16 to 48, not '32'$"),
    (dict(width=12), TypeError, r"^SpeedLoop width must be an integer of at least 16, not 12$"),
    (dict(width=True), TypeError,
     r"^SpeedLoop width must be an integer of at least 16, not True$"),
    (dict(width=33), ValueError, r"^SpeedLoop width must be at most speed_width 32, not 33$"),
    (dict(div_width=0), TypeError,
     r"^SpeedLoop div_width must be an integer from 1 to 16, not 0$"),
    (dict(delay_width=3), TypeError,
     r"^SpeedLoop delay_width must be an integer from 4 to 7, not 3$"),
    (dict(delay_width=8), TypeError,
     r"^SpeedLoop delay_width must be an integer from 4 to 7, not 8$"),
    (dict(kp_format=12), TypeError, r"^PI kp_format must be a QFormat, not 12$"),
    (dict(width=32, kx_format=UQ(32, 32)), ValueError,
     r"^PI parameters need a 65-bit intermediate value; at most 62 bits are supported "),
])
def test_speed_loop_parameter_validation(cls, kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        cls(**kwargs)


@pytest.mark.parametrize("cls", [Servo, ServoModel])
def test_servo_parameter_validation(cls):
    with pytest.raises(TypeError, match=r"^Servo phase_width must be an integer from 16 to 48, "
                                        r"not 8$"):
        cls(phase_width=8)
    with pytest.raises(ValueError, match=r"^SpeedLoop width must be at most speed_width 24, "
                                         r"not 32$"):
        cls(speed_width=24, width=32)


@pytest.mark.parametrize("cls", [SpeedLoop, Servo])
@pytest.mark.parametrize("kwargs, exc, msg", [
    (dict(config=1), TypeError, r"^{} config must be a string, one of 'ports', 'ram', not 1$"),
    (dict(config="rom"), ValueError, r"^{} config must be one of 'ports', 'ram', not 'rom'$"),
    (dict(config_init=[0, 0, 0]), ValueError,
     r"^{} config_init applies only to config='ram', not config='ports'$"),
    (dict(config="ram", config_init=[0, 0]), ValueError,
     r"^{} config_init must be a list of 4 32-bit words, not \[0, 0\]$"),
    (dict(config="ram", config_init=[0, -1, 0, 0]), ValueError,
     r"^{} config_init must be a list of 4 32-bit words, not \[0, -1, 0, 0\]$"),
    (dict(config="ram", speed_width=40), ValueError,
     r"^{} config='ram' needs speed_slew in one 32-bit word, not 40 bits$"),
    (dict(config="ram", width=16, int_guard=0, kp_format=UQ(33, 12)), ValueError,
     r"^{} config='ram' needs kp in one 32-bit word, not 33 bits$"),
])
def test_speed_config_validation(cls, kwargs, exc, msg):
    with pytest.raises(exc, match=msg.format(cls.__name__)):
        cls(**kwargs)


def test_speed_config_ports():
    # config="ram" replaces the ports of the configuration inputs by one RAM write port.
    ports = set(SpeedLoop().signature.members)
    ram = set(SpeedLoop(config="ram").signature.members)
    assert ports - ram == set(SPEED_CONFIG) and ram - ports == {"config"}
    assert SpeedLoop(config="ram").config_init == [0, 0, 0, 0]
    assert SpeedLoop().config_init is None and SpeedLoop().config_mode == "ports"
    ports = set(Servo().signature.members)
    ram = set(Servo(config="ram", config_init=[1, 2, 3, 4]).signature.members)
    assert ports - ram == set(SERVO_CONFIG) and ram - ports == {"speed_config"}
    assert Servo(config="ram").config_mode == "ram"


def test_servo_and_speed_loop_convert_to_verilog():
    for dut, name in ((Servo(), "servo"), (SpeedLoop(width=32, kp_format=Q(16, 8)), "loop"),
                      (Servo(config="ram"), "servo_ram")):
        # amaranth 0.5.10 convert() cannot take constant interface members (always-ready
        # streams' `ready`, amaranth-lang/amaranth#1574): list the ports without them.
        ports = [Value.cast(v) for _, _, v in dut.signature.flatten(dut)]
        ports = [p for p in ports if not isinstance(p, Const)]
        text = verilog.convert(dut, name=name, ports=ports)
        assert f"module {name}" in text


def test_speed_loop_latency_cycle_by_cycle():
    dut = SpeedLoop()
    # The program of a run (hdl/servo.py) fixes these; a change to it shows here.
    assert (dut.latency, dut.interval, dut.ref_latency) == (124, 125, 13)
    assert SpeedLoop(speed_width=24, width=16, delay_width=7).latency == 124
    seq = [loop_inputs() for _ in range(dut.latency + 10)]
    seq[3] = loop_inputs(valid=1, speed=-(1 << 20))             # E = 2^12 LSB of Q1.23
    got, _ = speed_loop_clocks(seq)
    strobes = [t for t, g in enumerate(got) if g[0]]
    assert strobes == [3 + dut.latency]
    assert got[3 + dut.latency][1] == 16                          # kp = 1: 2^12 >> 8
    assert all(g[1] == 16 for g in got[3 + dut.latency:])        # payload held


def test_speed_loop_rounds_speed_and_output():
    # Q1.31 → Q1.23 rounding half away from zero and saturation at full scale (2^31 - 1 rounds
    # to 2^23, saturated to 2^23 - 1); output Q1.23 → Q1.15 rounding.
    seq = []
    for fb in (-(1 << 7), (1 << 7) - 1, -(2 ** 31), 2 ** 31 - 1, 3 << 15, -(3 << 15)):
        seq += [loop_inputs(valid=1, speed=fb)] + [loop_inputs() for _ in range(IV - 1)]
    seq += [loop_inputs()]                                        # the last result's clock
    got, _ = speed_loop_clocks(seq)
    outs = [g[1] for g in got if g[0]]
    # fb -128 → E = round(128/256) = 1 (half away from zero) → O = 1 → i_q = round(1/256) = 0;
    # fb = -2^31 → E = 2^23 saturated to 2^23 - 1 → i_q 32768 rounded, limited at 32767.
    assert outs == [0, 0, 32767, -32768, -2, 2]


def test_speed_loop_saturates_at_current_limit_and_recovers():
    lim = 3000
    kx = KX_ONE >> 10
    # A large positive speed error pins i_q at +lim (sat), the integrator winds to the limit and
    # holds; the error changes sign and i_q leaves the limit on the very next run.
    seq = []
    for k in range(60):
        fb = -(1 << 29) if k < 40 else (1 << 24)
        seq += [loop_inputs(valid=1, speed=fb, speed_ref=0, kx=kx, lim_lo=-lim, lim_hi=lim)]
        seq += [loop_inputs(speed=fb, kx=kx, lim_lo=-lim, lim_hi=lim) for _ in range(IV + 1)]
    got, model = speed_loop_clocks(seq)
    outs = [(g[1], g[2]) for g in got if g[0]]
    assert all(o == (lim, 1) for o in outs[1:40])
    assert outs[40][1] == 0 and outs[40][0] < lim
    assert outs[41][0] < outs[40][0]                              # unwinding
    # Negative limit too, with the model: symmetric.
    seq = [dict(s, speed=-s["speed"]) for s in seq]
    got, _ = speed_loop_clocks(seq)
    outs = [(g[1], g[2]) for g in got if g[0]]
    assert all(o == (-lim, 1) for o in outs[1:40]) and outs[40][1] == 0


def test_speed_loop_rate_divider_and_clear():
    # rate_div = 2: every third sample runs, the first after clear included.
    # Samples IV apart, one run per three samples (the PI is idle again at the next run).
    seq = []
    for k in range(12):
        seq += [loop_inputs(valid=1, speed=-(1 << 20), rate_div=2)]
        seq += [loop_inputs(speed=-(1 << 20), rate_div=2) for _ in range(IV - 1)]
    seq[IV * 7 + 2] = loop_inputs(speed=-(1 << 20), rate_div=2, clear=1)   # between samples 7, 8
    seq += [loop_inputs(rate_div=2) for _ in range(LAT)]          # the last result's clock
    got, model = speed_loop_clocks(seq)
    strobes = [t for t, g in enumerate(got) if g[0]]
    assert strobes == [IV * k + LAT for k in (0, 3, 6, 8, 11)]
    assert got[IV * 7 + 3][:3] == (0, 0, 0)                       # cleared output
    assert model.runs == 5


def test_speed_loop_drops_runs_while_busy():
    # Samples while a run is in flight are dropped (their payload must not change the speed
    # the run reads: the model checks it).
    seq = [loop_inputs(speed=-(1 << 20)) for _ in range(IV)]
    seq += [loop_inputs(speed=-(1 << 21)) for _ in range(LAT + 2)]
    seq[0] = loop_inputs(valid=1, speed=-(1 << 20))
    seq[3] = loop_inputs(valid=1, speed=-(1 << 20))               # busy: dropped
    seq[IV - 1] = loop_inputs(valid=1, speed=-(1 << 20))          # still busy (the last clock)
    seq[IV] = loop_inputs(valid=1, speed=-(1 << 21))              # idle again: runs
    got, model = speed_loop_clocks(seq)
    assert [t for t, g in enumerate(got) if g[0]] == [LAT, IV + LAT]
    assert [g[1] for g in got if g[0]] == [16, 32]
    assert model.dropped == 2 and model.runs == 2


def test_speed_loop_integrates_an_error_of_0_01_percent():
    # 0.01 % of 1667 r/min (0.17 r/min) at N_FS = 12 000 r/min is ~29 LSB of Q1.23; with a small
    # integral gain (kx = 2^-16) the integrator still moves every run (16 guard bits), so the
    # steady-state error is driven below it.
    model = SpeedLoopModel()
    err = round(SPEED_1667 * 1e-4)
    steps = []
    for _ in range(5):
        model.pi.step(model._to_pi(err), 0, 0, KX_ONE >> 16, -32768 << 8, 32767 << 8)
        steps.append(model.pi.integrator)
    assert err >> 8 >= 28 and all(b > a for a, b in zip(steps, steps[1:]))


# --- reference profile: slew limiter, feed-forward, delay, integrator hold -----------------------

SLEW = 1 << 22                   # Q1.31: 2^14 LSB of the Q1.23 PI scale, 64 LSB of i_q at kp = 1


def profile_runs(n, period=IV, per_run=None, **kw):
    """``n`` speed-loop runs ``period`` clocks apart (the sample in each period's first clock),
    one clock of set-up before them and one after them (the last run's result comes
    ``latency`` = ``interval`` − 1 clocks after it).
    ``per_run(k)`` may return extra inputs for the clocks of run ``k``."""
    seq = [loop_inputs(**kw)]
    for k in range(n):
        extra = per_run(k) if per_run else {}
        seq += [loop_inputs(**dict(kw, **extra, valid=1))]
        seq += [loop_inputs(**dict(kw, **extra)) for _ in range(period - 1)]
    return seq + [loop_inputs(**dict(kw, **extra))]


def after_runs(got, n, period=IV):
    """(i_q, ref_int) after each of ``n`` runs of :func:`profile_runs` (``o.valid``'s clock;
    ``ref_int`` updates ``ref_latency`` clocks after the run)."""
    return [(got[1 + k * period + LAT][1], got[1 + k * period + RL][3]) for k in range(n)]


def test_profile_ramps_by_the_slew_and_lands_exactly():
    # kp = kx = 0: i_q is the feed-forward alone. Target 5.5 slews: five full steps with +F,
    # then the half step lands on speed_ref exactly and the feed-forward stops.
    target = 5 * SLEW + SLEW // 2
    seq = profile_runs(9, speed_ref=target, speed_slew=SLEW, iq_ff=1234, kp=0)
    got, model = speed_loop_clocks(seq)
    out = after_runs(got, 9)
    assert [r for _, r in out] == [SLEW * k for k in range(1, 6)] + [target] * 4
    assert [iq for iq, _ in out] == [1234] * 5 + [0] * 4
    assert [g[0] for g in got].count(1) == 9
    # The strobe comes latency clocks after the run, as without a profile.
    assert [t for t, g in enumerate(got) if g[0]] == [1 + IV * k + LAT for k in range(9)]


def test_profile_reverses_through_zero_from_the_measured_speed():
    # While clear, ref_int tracks the measured speed (slew != 0); the profile then runs down
    # through zero to -2.5 slews with -F, and lands exactly.
    start = 2 * SLEW + SLEW // 2
    seq = [loop_inputs(clear=1, speed=start, speed_slew=SLEW) for _ in range(3)]
    seq += profile_runs(7, speed=start, speed_ref=-start, speed_slew=SLEW, iq_ff=700, kp=0)
    got, _ = speed_loop_clocks(seq)
    assert [g[3] for g in got[1:4]] == [start] * 3                  # tracked while clear
    out = after_runs(got[3:], 7)
    assert [r for _, r in out] == [start - k * SLEW for k in range(1, 6)] + [-start] * 2
    assert [iq for iq, _ in out] == [-700] * 4 + [0] * 3


def test_profile_off_with_zero_slew_or_the_largest_slew():
    # Slew 0: the reference steps, the feed-forward is never applied, ref_int tracks speed_ref
    # (not the speed) while clear. The largest slew steps too, from the tracked speed.
    for slew, tracked in ((0, 5000), ((1 << 32) - 1, -77)):
        seq = [loop_inputs(clear=1, speed=-77, speed_ref=5000, speed_slew=slew)
               for _ in range(2)]
        seq += profile_runs(3, speed=-77, speed_ref=SPEED_1667, speed_slew=slew, iq_ff=999,
                            kp=0)
        got, _ = speed_loop_clocks(seq)
        assert got[1][3] == tracked
        assert after_runs(got[2:], 3) == [(0, SPEED_1667)] * 3


def test_profile_feed_forward_is_clamped_to_the_current_limits():
    # iq_ff beyond the limits, and the full-scale -F = +32768 (the negation of -32768):
    # clamped to the limit in the ramp's direction, which then holds i_q exactly (kp = 0).
    cases = [(5000, -1000, 2000, SLEW, 2000), (5000, -1000, 2000, -SLEW, -1000),
             (-32768, -32768, 32767, -SLEW, 32767), (-32768, 14091, 20621, -SLEW, 20621),
             (32767, 14091, 20621, -SLEW, 14091)]
    for ff, lo, hi, direction, want in cases:
        seq = profile_runs(3, speed_ref=8 * direction, speed_slew=1, iq_ff=ff, kp=0,
                           lim_lo=lo, lim_hi=hi)
        got, _ = speed_loop_clocks(seq)
        assert [iq for iq, _ in after_runs(got, 3)] == [want] * 3, (ff, lo, hi, direction)


def test_profile_pi_limits_leave_room_for_the_feed_forward():
    # F = 1000 with limits ±3000 and a huge speed error: the PI's share is pinned at
    # +2000 (up) or -4000 (down), the sum exactly at the limit with sat; its integrator winds
    # only to the shifted limit, so i_q leaves the limit on the first run after the error
    # changes sign (once the ramp has ended and F is gone).
    kx = KX_ONE >> 6
    for sign in (1, -1):
        def per_run(k):
            return dict(speed=(-sign << 28) if k < 12 else (sign << 26))
        seq = profile_runs(16, per_run=per_run, speed_ref=sign * 10 * SLEW, speed_slew=SLEW,
                           iq_ff=1000, kx=kx, lim_lo=-3000, lim_hi=3000)
        got, model = speed_loop_clocks(seq)
        out = after_runs(got, 16)
        sats = [got[1 + k * IV + LAT][2] for k in range(16)]
        assert [iq for iq, _ in out[:12]] == [sign * 3000] * 12 and all(sats[:12])
        assert abs(out[12][0]) < 3000 and not sats[12]
        assert model.pi.integrator * sign <= (3000 << 8 << 16)


@pytest.mark.parametrize("delay", [0, 1, 8, 8 + 3, 16 + 5, 24 + 7])
def test_profile_reference_delay_interpolates_the_ramp(delay):
    # kp = 1.0, kx = 0, fb = 0: i_q = round(to_pi(ref)/256), 64 LSB per slew. The PI's
    # reference is the ramp delayed by delay/8 runs (the fraction ignored below one run),
    # exact on a linear ramp; the ramp stops after 6 slews.
    n = 12
    seq = profile_runs(n, speed_ref=6 * SLEW, speed_slew=SLEW, ref_delay=delay)
    got, _ = speed_loop_clocks(seq)
    d = delay / 8 if delay >= 8 else 0
    want = [round(64 * min(max(k + 1 - d, 0), 6)) for k in range(n)]
    assert [iq for iq, _ in after_runs(got, n)] == want


def test_profile_integrator_hold_while_moving():
    # With int_hold the ramp's runs leave the integrator alone: i_q equals the kx = 0 response
    # while the profile moves, then integrates once it has landed.
    base = dict(speed_ref=4 * SLEW, speed_slew=SLEW, speed=-SLEW, kp=KP_ONE >> 4)
    no_i = after_runs(speed_loop_clocks(profile_runs(8, **base))[0], 8)
    held = after_runs(speed_loop_clocks(profile_runs(8, kx=KX_ONE >> 8, int_hold=1,
                                                     **base))[0], 8)
    free = after_runs(speed_loop_clocks(profile_runs(8, kx=KX_ONE >> 8, **base))[0], 8)
    assert held[:3] == no_i[:3] and free[0][0] > no_i[0][0]
    assert held[4][0] > no_i[4][0]                                  # landed: integrating


def test_profile_integrator_hold_until_the_delayed_reference_arrives():
    # Delay 2 runs: the profile lands in run 4, the PI's reference in run 6; the integrator
    # stays held until then (i_q as with kx = 0), and integrates from run 6 on.
    base = dict(speed_ref=4 * SLEW, speed_slew=SLEW, speed=-SLEW, kp=KP_ONE >> 4, ref_delay=16)
    no_i = after_runs(speed_loop_clocks(profile_runs(10, **base))[0], 10)
    got, model = speed_loop_clocks(profile_runs(10, kx=KX_ONE >> 8, int_hold=1, **base))
    held = after_runs(got, 10)
    assert [r for _, r in held][3:] == [4 * SLEW] * 7                # landed in run 4
    assert held[:5] == no_i[:5]                                     # runs 1 … 5: held
    assert all(h[0] > n[0] for h, n in zip(held[5:], no_i[5:]))     # then integrating
    # Without the delay the hold ends with the profile: run 4 (the landing step) is held,
    # run 5 integrates.
    base.update(ref_delay=0)
    no_i = after_runs(speed_loop_clocks(profile_runs(6, **base))[0], 6)
    held = after_runs(speed_loop_clocks(profile_runs(6, kx=KX_ONE >> 8, int_hold=1,
                                                     **base))[0], 6)
    assert held[:4] == no_i[:4] and held[4][0] > no_i[4][0]


def test_profile_clear_mid_ramp():
    # Leaving SPEED mode mid-ramp: output and feed-forward 0 at once, ref_int tracks the speed;
    # on re-entry the ramp restarts from the speed.
    seq = profile_runs(3, speed_ref=20 * SLEW, speed_slew=SLEW, iq_ff=500, kp=0)
    c = len(seq)
    seq += [loop_inputs(clear=1, speed=7 * SLEW, speed_slew=SLEW) for _ in range(4)]
    seq += profile_runs(2, speed=7 * SLEW, speed_ref=20 * SLEW, speed_slew=SLEW, iq_ff=500,
                        kp=0)
    got, _ = speed_loop_clocks(seq)
    assert got[c][1:] == (500, 0, 3 * SLEW)                       # the clock clear rises
    assert got[c + 1] == (0, 0, 0, 7 * SLEW)                        # cleared, tracking
    assert got[c + 4][3] == 7 * SLEW
    assert after_runs(got[c + 4:], 2) == [(500, 8 * SLEW), (500, 9 * SLEW)]


def test_profile_clear_mid_run():
    # clear while a run is in flight (before and after it updated ref_int, and one clock
    # before its result): the run is abandoned (no strobe), the output is 0 at once.
    for at in (1, RL - 1, RL + 5, LAT - 1):
        seq = profile_runs(1, speed_ref=20 * SLEW, speed_slew=SLEW, iq_ff=500, kx=KX_ONE >> 4)
        seq[1 + at] = loop_inputs(clear=1, speed=-3 * SLEW, speed_slew=SLEW)
        seq += profile_runs(1, speed=-3 * SLEW, speed_ref=20 * SLEW, speed_slew=SLEW,
                            iq_ff=500, kx=KX_ONE >> 4)
        got, model = speed_loop_clocks(seq)
        assert [t for t, g in enumerate(got) if g[0]] == [IV + 3 + LAT], at
        assert got[2 + at] == (0, 0, 0, -3 * SLEW) and model.runs == 2


def test_profile_run_in_the_first_clock_after_clear():
    # The bounds and the delayed reference are registers loaded from the tracked value in the
    # last clear clock, so a run right after clear starts from the speed of that clock: one
    # slew up from it, and with a delay of one run the PI sees it as its reference (E = 0).
    b = 5 * SLEW
    seq = [loop_inputs(clear=1, speed=0, speed_slew=SLEW) for _ in range(3)]
    seq += [loop_inputs(clear=1, speed=b, speed_slew=SLEW)]
    seq += [loop_inputs(valid=1, speed=b, speed_ref=b + 10 * SLEW, speed_slew=SLEW, iq_ff=100,
                        ref_delay=8)]
    seq += [loop_inputs(speed=b, speed_ref=b + 10 * SLEW, speed_slew=SLEW, iq_ff=100,
                        ref_delay=8) for _ in range(LAT)]
    got, _ = speed_loop_clocks(seq)
    assert got[4 + RL][3] == b + SLEW and got[4 + RL - 1][3] == b
    assert got[4 + LAT][:2] == (1, 100)


@pytest.mark.parametrize("sign", [1, -1])
def test_profile_bounds_round_to_the_pi_scale_exactly(sign):
    # A slew of 897 Q1.31 LSB (3.504 LSB of the Q1.23 PI scale) with kp = 256: i_q is the PI's
    # reference itself, to_pi(R_n) = round(n·897 / 256) half away from zero, so the rounding of
    # each bound (registered beside the bound) shows to the last bit, up and down.
    slew = 897
    n = 12
    seq = profile_runs(n, speed_ref=sign * 40 * slew, speed_slew=slew, kp=KP_ONE << 8)
    got, _ = speed_loop_clocks(seq)
    want = [int(math.copysign(math.floor(abs(sign * k * slew) / 256 + 0.5), sign))
            for k in range(1, n + 1)]
    assert [iq for iq, _ in after_runs(got, n)] == want


def test_profile_run_in_the_second_clock_after_a_one_clock_clear():
    # Mid-ramp (the delay taps differ), one clock of clear at speed b loads every tap with
    # to_pi(b); the interpolation's registered tap differences are zeroed with them, so a run
    # two clocks later with a fractional delay (1.5 runs) sees exactly b: E = 0, i_q = 0.
    b = 5 * SLEW
    kw = dict(speed_slew=SLEW, ref_delay=8 + 4)
    seq = profile_runs(4, speed=0, speed_ref=20 * SLEW, **kw)
    seq += [loop_inputs(clear=1, speed=b, **kw), loop_inputs(speed=b, **kw)]
    run = len(seq)
    seq += [loop_inputs(valid=1, speed=b, speed_ref=b + 10 * SLEW, **kw)]
    seq += [loop_inputs(speed=b, speed_ref=b + 10 * SLEW, **kw) for _ in range(LAT + 1)]
    got, _ = speed_loop_clocks(seq)
    assert [iq for _, iq, _, _ in got[run - 8:run - 2]] != [0] * 6   # the ramp ran before
    assert got[run + LAT][:2] == (1, 0)
    assert got[run + RL][3] == b + SLEW


def test_speed_loop_run_in_the_first_clock_after_power_on():
    # A run accepted in clock 0, a full-scale error against a 1/4 current limit. (Its first
    # control word is a constant, not the control ROM's output register, which is undefined
    # at power-on in hardware; the simulator starts it at 0, which happens to be harmless
    # here, so the speed_loop proof, not this test, guards that.)
    kw = dict(speed=-(1 << 30), speed_ref=1 << 30, lim_lo=-8192, lim_hi=8192)
    seq = [loop_inputs(valid=1, **kw)] + [loop_inputs(**kw) for _ in range(LAT)]
    got, _ = speed_loop_clocks(seq)
    assert got[LAT][:3] == (1, 8192, 1)


def test_servo_mode_changes_at_loop_boundary():
    seq = [base_inputs(mode=CURRENT, iq_set=1000, id_set=-200) for _ in range(12)]
    for t in (2, 8):
        seq[t] = dict(seq[t], loop=1)
    seq[5:] = [dict(s, mode=SPEED) for s in seq[5:]]
    got = servo_clocks(seq)
    assert [g["active"] for g in got] == [DISABLED] * 3 + [CURRENT] * 6 + [SPEED] * 3
    assert [g["enable"] for g in got] == [0] * 3 + [1] * 9
    assert all(g["iq_ref"] == 1000 and g["id_ref"] == -200 for g in got[3:9])
    assert all(g["iq_ref"] == 0 and g["id_ref"] == -200 and g["speed_clear"] == 0
               for g in got[9:])
    assert all(g["current_clear"] for g in got[:3]) and not any(g["current_clear"]
                                                                for g in got[3:])


def test_servo_trip_forces_disabled_until_next_loop_after_clear():
    seq = [base_inputs(mode=CURRENT, iq_set=500, loop=int(t % 5 == 0)) for t in range(25)]
    for t in range(7, 12):
        seq[t] = dict(seq[t], trip=1)
    got = servo_clocks(seq)
    act = [g["active"] for g in got]
    assert act[1:7] == [CURRENT] * 6
    assert act[7:16] == [DISABLED] * 9                 # tripped, then waits for a loop strobe
    assert act[16:] == [CURRENT] * 9                   # the mode register kept its value
    assert all(g["enable"] == 0 and g["iq_ref"] == 0 and g["current_clear"] for g in got[7:16])


def test_servo_current_mode_clamps_iq_to_the_current_limit():
    seq = [base_inputs(mode=CURRENT, loop=1, iq_set=v, iq_lim_lo=-1000, iq_lim_hi=2000)
           for v in (0, 5000, -5000, 1999, -1001, 32767)]
    got = servo_clocks(seq)
    assert [g["iq_ref"] for g in got[1:]] == [2000, -1000, 1999, -1000, 2000]


def test_servo_current_mode_clamp_extremes_and_random_vs_model():
    # Full-range operands (the compares' 17-bit differences overflow 16 bits), lo > hi, ties.
    rng = np.random.default_rng(13)
    ext = (-32768, -32767, -1, 0, 1, 32766, 32767)
    triples = [(v, lo, hi) for v in ext for lo in ext for hi in ext if (v + lo + hi) % 3 == 0]
    triples += [tuple(int(x) for x in rng.integers(-32768, 32768, 3)) for _ in range(60)]
    seq = [base_inputs(mode=CURRENT, loop=1, iq_set=v, iq_lim_lo=lo, iq_lim_hi=hi)
           for v, lo, hi in triples]
    got = servo_clocks(seq)
    want = [clamp_np(v, lo, hi) for v, lo, hi in triples]
    assert [g["iq_ref"] for g in got[1:]] == want[1:]


def test_servo_open_loop_angle_sources():
    freq = 0x0123_4567
    seq = [base_inputs(mode=OPEN_LOOP, ud_set=3000, uq_set=-4000, ol_theta=0x4000,
                       theta_meas=0x1234, ol_src=AngleMode.FIXED.value, loop=1)
           for _ in range(3)]
    seq += [dict(seq[0], ol_src=AngleMode.ROTATING.value, ol_freq=freq, loop=int(t % 3 == 0))
            for t in range(30)]
    seq += [dict(seq[0], ol_src=AngleMode.MEASURED.value) for _ in range(3)]
    seq += [dict(seq[0], ol_src=3) for _ in range(2)]
    got = servo_clocks(seq)
    assert all(g["ol_enable"] and (g["ol_ud"], g["ol_uq"]) == (3000, -4000) for g in got[1:])
    assert all(g["iq_ref"] == 0 and g["current_clear"] for g in got)
    assert [g["theta"] for g in got[1:3]] == [0x4000, 0x4000]
    rot = [g["theta"] for g in got[3:33]]
    # The accumulator starts at ol_theta and advances once per loop strobe (10 strobes).
    n = [sum(1 for t in range(k) if t % 3 == 0) for k in range(30)]
    assert rot == [((0x4000 << 16) + n[k] * freq) % 2 ** 32 >> 16 for k in range(30)]
    assert [g["theta"] for g in got[33:36]] == [0x1234] * 3
    assert [g["theta"] for g in got[36:]] == [0x4000] * 2       # unused code acts as FIXED
    # Negative frequency runs backwards and wraps through zero.
    seq = [dict(seq[5], ol_freq=-(1 << 30), loop=1) for _ in range(6)]
    got = servo_clocks(seq)
    assert [g["theta"] for g in got[1:]] == [0x4000, 0x0000, 0xC000, 0x8000, 0x4000]


def test_servo_reference_step_strobe():
    # Loop strobes at 0, 4, … 20. ref_change between strobes is seen at the next one; in a
    # strobe's own clock (8) at the one after; two (13, 14) give one step; the values
    # themselves do not count (a change without ref_change at 17: no step at 20).
    seq = [base_inputs(mode=SPEED, loop=int(t % 4 == 0), ref_change=int(t in (2, 8, 13, 14)))
           for t in range(24)]
    seq[17:] = [dict(s, speed_ref=SPEED_1667, iq_set=7, mode=CURRENT) for s in seq[17:]]
    got = servo_clocks(seq)
    assert [t for t, g in enumerate(got) if g["ref_step"]] == [4, 12, 16]


def test_servo_speed_mode_runs_the_speed_loop():
    seq = []
    for t in range(5 * 128):
        seq.append(base_inputs(mode=SPEED, loop=int(t % 128 == 0), speed_valid=int(t % 128 == 3),
                               speed=-(1 << 22), speed_kx=KX_ONE >> 4, id_set=11,
                               iq_lim_lo=-900, iq_lim_hi=900))
    got = servo_clocks(seq)
    valid = [t for t, g in enumerate(got) if g["speed_valid"]]
    # SPEED is active from clock 1 (latched by the loop strobe at clock 0): every sample runs.
    assert valid == [3 + 128 * k + LAT for k in range(5)]
    iq = [got[t]["iq_ref"] for t in valid]
    # E = 2^14 LSB of Q1.23: P = 64 LSB of i_q, the integrator adds 8 per run (4 on the first).
    assert iq == [68, 76, 84, 92, 100] and got[-1]["id_ref"] == 11


def test_servo_config_in_ram_gains_and_slew_change_between_runs():
    # Servo(config="ram"): the speed loop's kp, kx, slew and feed-forward as writes on
    # speed_config (the clocks before a run; from power-on config_init), changing every two
    # runs: the model's results clock by clock, the same outputs as with ports, and the new
    # values used.
    seq = []
    for t in range(7 * 128):
        p = max(0, t - 3) // 128       # the run's period; at most 3 words change at a time
        k = p // 2
        seq.append(base_inputs(mode=SPEED, loop=int(t % 128 == 0), speed_valid=int(t % 128 == 3),
                               speed=-(1 << 22), speed_ref=(k % 2) << 20,
                               speed_kp=KP_ONE * (1 + k), speed_kx=(KX_ONE >> 4) * (k % 3),
                               speed_slew=[0, 1 << 18, 3, 0][k], iq_ff=500 * (p in (3, 4)),
                               id_set=11,
                               iq_lim_lo=-2000, iq_lim_hi=2000))
    got = servo_clocks(seq, config="ram")
    assert got == servo_clocks(seq)
    iq = [g["iq_ref"] for g in got if g["speed_valid"]]
    # kx 0 in the first two runs; kp 1, 2, 3, 4 every two runs; slew 0, 2^18, 3, 0; iq_ff
    # 500 in runs 3 and 4 (added while the reference moves: run 4).
    assert iq[:2] == [64, 64] and len(set(iq[1:])) == 6
    assert [g["speed_ref_int"] for g in got if g["speed_valid"]] == [
        0, 0, 1 << 18, 2 << 18, (2 << 18) - 3, (2 << 18) - 6, 1 << 20]


def test_servo_enters_speed_mode_from_a_spinning_motor_with_a_profile():
    # DISABLED with the motor at +3 slews: speed_ref_int follows the measured speed; SPEED mode
    # then ramps from there down to speed_ref with -F, not from 0 (kp = 0: i_q = feed-forward).
    spd = 3 * SLEW
    seq = []
    for t in range(6 + 7 * IV + LAT):
        seq.append(base_inputs(mode=SPEED, loop=int(t == 4), speed_valid=int(t % IV == 6),
                               speed=spd, speed_ref=SLEW // 2, speed_slew=SLEW, iq_ff=321,
                               speed_kp=0))
    got = servo_clocks(seq)
    assert all(g["speed_ref_int"] == spd for g in got[1:6])
    runs = [t for t in range(len(seq)) if t % IV == 6 and t > 4][:7]
    assert [got[t + RL]["speed_ref_int"] for t in runs] == [2 * SLEW, SLEW] + [SLEW // 2] * 5
    assert [got[t + LAT]["iq_ref"] for t in runs[:5]] == [-321, -321, 0, 0, 0]


def test_servo_random_sequences_vs_model():
    # Loop periods of at least the speed loop's interval (~120 clocks): ~200 runs.
    result = run_servo(80_000, seed=7)
    assert result["mismatches"] == 0, result["first_mismatch"]
    assert result["speed_runs"] > 20 and result["mode_changes"] > 3 and result["ref_steps"] > 3
    assert result["ramp_runs"] > 10 and result["delayed_runs"] > 0 and result["held_runs"] > 0


def test_servo_random_sequences_vs_model_other_widths():
    # Narrow speed path (Q1.23 speed, 16-bit PI: no rounding shift at the output) and the
    # longest reference delay (7 taps). (Seed 6: the stimulus scales with the interval; seed 3's
    # sequence for interval 125 has no ramp.)
    result = run_servo(40_000, seed=6, speed_width=24, width=16, delay_width=7)
    assert result["mismatches"] == 0, result["first_mismatch"]
    assert result["ramp_runs"] > 0 and result["delayed_runs"] > 10


@pytest.mark.slow
def test_servo_and_scope_100k_clocks_vs_model():
    # The servo for 600 000 clocks (loop periods of at least the speed loop's interval).
    result = run(100_000, servo_count=600_000)
    assert result["mismatches"] == 0, (result["servo_first_mismatch"],
                                       result["scope_first_mismatch"])
    assert result["servo_recoveries"] > 0 and result["servo_speed_saturated"] > 100
    for figure in ("ramp_ends", "ramp_reversals", "ramp_cleared", "ff_full_scale_runs",
                   "ff_clamped_runs", "held_runs", "delayed_runs", "slew_max_runs"):
        assert result[f"servo_{figure}"] > 2, figure
    assert result["scope_captures"] >= 10 and result["scope_capture_order_errors"] == 0


def _corner_run_inputs(rng, dut, hold_prev):
    """Inputs of one random run of :func:`test_speed_loop_random_runs_with_corner_inputs`."""
    sw = dut.speed_width
    s_lo, s_hi = -(1 << (sw - 1)), (1 << (sw - 1)) - 1
    kp_min, kp_max = shape_range(dut.kp_format.shape)
    kx_min, kx_max = shape_range(dut.kx_format.shape)

    def pick(*choices):
        return choices[rng.randrange(len(choices))]

    lo, hi = pick((-32768, 32767), (-3000, 4000), (500, 500), (4000, -3000), (-32768, -32768),
                  (32767, 32767), tuple(sorted(rng.randint(-32768, 32767) for _ in range(2))))
    ref = pick(s_lo, s_hi, 0, hold_prev, rng.randint(s_lo, s_hi),
               hold_prev + rng.randint(-(1 << 24), 1 << 24))
    return dict(
        speed=pick(s_lo, s_hi, s_lo + 1, 0, -1, rng.randint(s_lo, s_hi),
                   rng.randint(s_lo >> 6, s_hi >> 6)),
        speed_ref=max(s_lo, min(s_hi, ref)),
        speed_slew=pick(0, 0, 1, (1 << sw) - 1, rng.randint(1, 1 << (sw - 6)),
                        rng.randint(1, 1 << (sw - 12))),
        iq_ff=pick(0, -32768, 32767, rng.randint(-32768, 32767)),
        ref_delay=rng.randint(0, (1 << dut.delay_width) - 1),
        int_hold=rng.randint(0, 1),
        kp=pick(0, kp_max, kp_min, rng.randint(kp_min, kp_max), rng.randint(0, 1 << 12)),
        kx=pick(0, kx_max, kx_min, rng.randint(kx_min, kx_max), rng.randint(0, 1 << 14)),
        lim_lo=lo, lim_hi=hi)


@pytest.mark.parametrize("params", [{}, dict(kx_format=UQ(24, 20)),
                                    dict(speed_width=24, width=16, delay_width=7),
                                    dict(width=20, kp_format=Q(16, 4), kx_format=Q(16, 20),
                                         int_guard=4),
                                    # no guard bits: the products' rounding shows in i_q
                                    dict(speed_width=24, width=16, int_guard=0)])
def test_speed_loop_random_runs_with_corner_inputs(params):
    # Runs at random spacing >= interval (and some samples dropped inside a run), with corner
    # inputs: full-scale speeds, inverted and equal limits, largest gains, kx = 0, integrator
    # hold, every reference delay, and clear at random points of a run. Clock by clock against
    # the model (the helper asserts equality); a dropped rounding bit anywhere shows here
    # (checked by mutation: the rounding increments of acc >> k and of the products).
    _corner_runs(params)


def _corner_runs(params, *, config="ports"):
    import random
    rng = random.Random(7 + len(params))
    dut = SpeedLoop(**params)
    # config="ram": the gains, slew and feed-forward of a run written in the 4 clocks before it.
    extra = 4 if config == "ram" else 0
    seq, prev = [loop_inputs() for _ in range(1 + extra)], 0
    for _ in range(40):
        kw = _corner_run_inputs(rng, dut, prev)
        prev = kw["speed_ref"]
        gap = dut.interval + extra + rng.choice([0, 0, 1, 7, rng.randrange(200)])
        run = [loop_inputs(**kw) for _ in range(gap)]
        run[0] = dict(run[0], valid=1)
        what = rng.random()
        if what < 0.3:                              # a sample inside the run: dropped
            k = rng.randrange(1, dut.interval)
            run[k] = dict(run[k], valid=1, speed=rng.randint(-(1 << 23), 1 << 23))
        elif what < 0.45:                           # clear inside the run
            k = rng.randrange(0, dut.interval)
            run[k] = dict(run[k], clear=1)
        seq += run
    seq += [loop_inputs(**kw) for _ in range(dut.latency)]
    got, model = speed_loop_clocks(seq, config=config, **params)
    assert model.runs >= 30 and sum(g[0] for g in got) >= 25


@pytest.mark.parametrize("params", [{}, dict(kx_format=UQ(24, 20)),
                                    dict(width=20, kp_format=Q(16, 4), kx_format=Q(16, 20),
                                         int_guard=4),
                                    dict(speed_width=24, width=16, delay_width=7)])
def test_speed_loop_config_in_ram_random_runs_with_corner_inputs(params):
    # config="ram": kp, kx, speed_slew and iq_ff in the loop's configuration RAM, each run's
    # written through the config port in the clocks before it (every word changes at most
    # runs; signed gains; a slew narrower than the word). The same runs as with ports, the
    # same results clock by clock (the model takes what the RAM holds).
    _corner_runs(params, config="ram")


def test_speed_loop_config_in_ram_timing_and_power_on():
    # The words hold config_init from power-on (a run in the first clocks uses them), a write
    # acts from the next clock (a run accepted in the clock after the last write uses it), and
    # the slew's non-zero flag follows its word (clear tracks the speed, not speed_ref).
    kw = dict(speed=-(1 << 20), kx=1 << 20)
    seq = [loop_inputs(valid=int(t == 1), **kw) for t in range(IV + 2)]
    seq += [loop_inputs(kp=3 * KP_ONE, valid=int(t == 0), **kw) for t in range(IV + 2)]
    seq += [loop_inputs(kp=3 * KP_ONE, clear=1, speed_slew=5, speed_ref=7, **kw)
            for t in range(4)]
    got, model = speed_loop_clocks(seq, config="ram")
    outs = [g[1] for g in got if g[0]]
    # P = kp·E: 16 (kp 1, E 2^12 LSB of Q1.23 → 16 of Q1.15), then 48 (kp 3) plus the integral.
    assert len(outs) == 2 and outs[0] == 16 + 1 and outs[1] == 48 + 1 + 2
    assert got[-1][3] == -(1 << 20)                 # slew ≠ 0: R tracks the speed


def test_speed_loop_product_rounding_shows_without_guard_bits():
    # int_guard = 0 and a 16-bit PI: P = round(kp·E / 2**12) and dI = round(kx·(E + E[n−1]) /
    # 2**24) are in i_q's LSBs, errors small enough that nothing saturates: every rounding
    # increment of the shift-add products (ties of either sign included) shows in i_q.
    import random
    rng = random.Random(11)
    params = dict(speed_width=24, width=16, int_guard=0)
    dut = SpeedLoop(**params)
    seq = [loop_inputs()]
    for k in range(60):
        kw = dict(speed=rng.randint(-3000, 3000) << 8 | rng.choice([0, 128, 127, 129]),
                  kp=rng.choice([rng.randint(0, 1 << 14), 2048, 6144]),
                  kx=rng.choice([rng.randint(0, 1 << 22), 1 << 23, 3 << 22]))
        seq += [loop_inputs(valid=1, **kw)] + [loop_inputs(**kw) for _ in range(dut.interval)]
    got, model = speed_loop_clocks(seq, **params)
    outs = [g for g in got if g[0]]
    assert len(outs) == 60 and sum(o[2] for o in outs) < 10       # mostly unsaturated


@pytest.mark.parametrize("kwargs, exc, msg", [
    (dict(speed_loop=1), TypeError, r"^Servo speed_loop must be a string, one of .*, not 1$"),
    (dict(speed_loop="dsp"), ValueError,
     r"^Servo speed_loop must be one of 'sequential', 'engine', not 'dsp'$"),
    (dict(speed_loop="engine"), ValueError,
     r"^Servo speed_loop='engine' needs kx_format UQ\(24, 20\) \(the engine's speed program is "
     r"written for it\), not UQ\(24, 24\)$"),
    (dict(speed_loop="engine", kx_format=UQ(24, 20), width=20), ValueError,
     r"^Servo speed_loop='engine' needs width 24 "),
    (dict(speed_loop="engine", kx_format=UQ(24, 20), div_width=4), ValueError,
     r"^Servo speed_loop='engine' needs div_width 8 "),
    (dict(speed_loop="engine", kx_format=UQ(24, 20), config="ram"), ValueError,
     r"^Servo speed_loop='engine' takes no config or config_init "),
])
def test_servo_speed_loop_validation(kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        Servo(**kwargs)


def test_servo_engine_speed_loop_ports():
    """``Servo(speed_loop="engine")``: no SpeedLoop and none of its inputs; the engine's
    results come in on ``sl_iq``, ``sl_sat``, ``sl_ref_int`` and leave as the SpeedLoop's
    would (``iq_ref`` in SPEED mode, ``speed_valid``, ``speed_sat``, ``speed_ref_int``)."""
    dut = Servo(speed_loop="engine", kx_format=UQ(24, 20))
    members = set(dut.signature.members)
    assert not members & {"speed", "speed_ref", "speed_kp", "speed_kx", "speed_rate_div",
                          "speed_slew", "iq_ff", "speed_ref_delay", "speed_int_hold",
                          "speed_config"}
    assert {"sl_iq", "sl_sat", "sl_ref_int", "speed_clear"} <= members
    seen = []

    async def testbench(ctx):
        ctx.set(dut.mode, Mode.SPEED)
        ctx.set(dut.loop, 1)
        await ctx.tick()
        ctx.set(dut.loop, 0)
        for k, (valid, iq, sat, ref) in enumerate([(1, -1234, 1, -5), (0, 77, 0, 1 << 30)]):
            ctx.set(dut.sl_iq.valid, valid)
            ctx.set(dut.sl_iq.payload, iq)
            ctx.set(dut.sl_sat, sat)
            ctx.set(dut.sl_ref_int, ref)
            seen.append((ctx.get(dut.iq_ref), ctx.get(dut.speed_valid), ctx.get(dut.speed_sat),
                         ctx.get(dut.speed_ref_int), ctx.get(dut.speed_clear)))
        ctx.set(dut.mode, Mode.CURRENT)
        ctx.set(dut.loop, 1)
        await ctx.tick()
        seen.append((ctx.get(dut.iq_ref), ctx.get(dut.speed_clear)))

    simulate(dut, [testbench], name="servo_engine_ports")
    assert seen == [(-1234, 1, 1, -5, 0), (77, 0, 0, 1 << 30, 0), (0, 1)]
