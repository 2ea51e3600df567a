# Ref: hdl/deadtime_comp.py; hdl/gates.py (dead time); issue 6 (dead-time compensation)
import gc
import re
import warnings

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import UnusedElaboratable

from foc_servo.boards.area import ports
from foc_servo.hdl.deadtime_comp import DeadTimeComp
from foc_servo.sim import scenarios as S
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import deadtime_comp as model
from foc_servo.sim.models.svpwm import pwm_high_clocks, pwm_levels

N = 2500                    # half period at 50 MHz, 10 kHz


# --- parameters ---------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, message", [
    ({"width": 7}, "DeadTimeComp width must be an integer from 8 to 23, not 7"),
    ({"width": 16.0}, "DeadTimeComp width must be an integer from 8 to 23, not 16.0"),
    ({"count_width": 25}, "DeadTimeComp count_width must be an integer from 4 to 24, not 25"),
    ({"clocks_width": 0}, "DeadTimeComp clocks_width must be an integer from 1 to 16, not 0"),
    ({"shift_width": True}, "DeadTimeComp shift_width must be an integer from 1 to 5, not True"),
    ({"shift_width": 6}, "DeadTimeComp shift_width must be an integer from 1 to 5, not 6"),
])
def test_deadtime_comp_parameter_validation(kwargs, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)     # the half-built object
        with pytest.raises(TypeError, match=f"^{re.escape(message)}$"):
            DeadTimeComp(**kwargs)
        gc.collect()


def test_deadtime_comp_one_count_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^DeadTimeComp one_count must be a bool, not 1$"):
        DeadTimeComp(one_count=1)


def test_deadtime_comp_clamp_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^DeadTimeComp clamp must be a bool, not 1$"):
        DeadTimeComp(clamp=1)


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # attributes only
def test_deadtime_comp_attributes_and_verilog():
    dut = DeadTimeComp()
    assert dut.latency == 0 and dut.comp_latency == 21
    assert DeadTimeComp(shift_width=2).comp_latency == 9
    assert "module" in verilog.convert(dut, ports=ports(dut))


# --- HDL against the golden model, clock by clock -----------------------------------------------

def run_dut(stim, **params):
    """Drive the block clock by clock from ``stim`` (arrays per clock: ``phase_valid``, ``phase``
    (T, 3), ``duty`` (T, 3), ``symmetric``, ``clocks``, ``shift``); return ``comp`` and
    ``o`` (T, 3) during each clock and ``o.valid``."""
    dut = DeadTimeComp(**params)
    t_len = len(stim["phase_valid"])
    comp = np.zeros((t_len, 3), dtype=np.int64)
    out = np.zeros((t_len, 3), dtype=np.int64)
    valid = np.zeros(t_len, dtype=np.int64)

    async def testbench(ctx):
        for t in range(t_len):
            ph, du = stim["phase"][t], stim["duty"][t]
            ctx.set(dut.phase.valid, int(stim["phase_valid"][t]))
            ctx.set(dut.phase.payload, {p: int(v) for p, v in zip("abc", ph)})
            ctx.set(dut.i.valid, int(stim["duty_valid"][t]))
            ctx.set(dut.i.payload, {p: int(v) for p, v in zip("abc", du)})
            ctx.set(dut.o.ready, 1)
            for name in ("symmetric", "clocks", "shift"):
                ctx.set(getattr(dut, name), int(stim[name][t]))
            c, o = ctx.get(dut.comp), ctx.get(dut.o.payload)
            comp[t] = [c.a, c.b, c.c]
            out[t] = [o.a, o.b, o.c]
            valid[t] = ctx.get(dut.o.valid)
            assert ctx.get(dut.i.ready) == 1
            await ctx.tick()

    simulate(dut, [testbench], name="test_deadtime_comp")
    return comp, out, valid


def random_stim(rng, t_len, *, width=16, count_width=16, clocks_width=8, shift_width=4):
    """Random inputs with corner values mixed in; configuration changes now and then."""
    fs = 1 << (width - 1)
    corners = np.array([-fs, -fs + 1, -1, 0, 1, fs - 1, 2, -2, 3, -3])
    phase = rng.integers(-fs, fs, size=(t_len, 3))
    small = rng.integers(max(-300, -fs), min(301, fs), size=(t_len, 3))
    pick = rng.random((t_len, 3))
    phase = np.where(pick < 0.3, small, phase)
    phase = np.where(pick > 0.85, rng.choice(corners, size=(t_len, 3)), phase)
    # One configuration per block of clocks (as the register file changes them at boundaries);
    # the currents arrive as one-clock strobes, some closer together than the computation.
    blocks = -(-t_len // 40)
    def per_block(values):
        return np.repeat(values, 40)[:t_len]
    scale = per_block(rng.integers(4, (1 << count_width) - 1, size=blocks))
    duty = np.minimum(rng.integers(0, 1 << count_width, size=(t_len, 3)), scale[:, None])
    duty = np.where(rng.random((t_len, 3)) < 0.1, scale[:, None], duty)
    duty = np.where(rng.random((t_len, 3)) < 0.1, 0, duty)
    near = np.maximum(scale[:, None] - rng.integers(0, 8, size=(t_len, 3)), 0)
    duty = np.where(rng.random((t_len, 3)) < 0.1, near, duty)
    stim = {
        "phase_valid": (rng.random(t_len) < 0.12).astype(np.int64),
        "phase": phase,
        "duty_valid": (rng.random(t_len) < 0.5).astype(np.int64),
        "duty": duty,
        "symmetric": per_block(rng.integers(0, 2, size=blocks)),
        "clocks": per_block(np.where(rng.random(blocks) < 0.2, (1 << clocks_width) - 1,
                                     rng.integers(0, 1 << clocks_width, size=blocks))),
        "shift": per_block(rng.integers(0, 1 << shift_width, size=blocks)),
    }
    # Duties just below the top of the count range (the block's upper clamp; drawn last, so
    # the other inputs are those of the earlier stimulus).
    top = (1 << count_width) - 1 - rng.integers(0, 8, size=(t_len, 3))
    stim["duty"] = np.where(rng.random((t_len, 3)) < 0.05, top, duty)
    return stim


def model_of(stim, shift_width=4, count_width=16):
    return model.deadtime_comp(stim["phase_valid"], stim["phase"], stim["duty"],
                               stim["symmetric"], stim["clocks"], stim["shift"],
                               shift_width=shift_width, count_width=count_width)


@pytest.mark.parametrize("seed, params", [
    (1, {}),
    (2, {}),
    (3, {"width": 12, "count_width": 10, "clocks_width": 5, "shift_width": 3}),
    (4, {"width": 23, "count_width": 24, "clocks_width": 16, "shift_width": 5}),
    (5, {"width": 8, "count_width": 12, "clocks_width": 9, "shift_width": 2}),  # w − 1 < C
    # clamp=False (the iCE40's form): o is the sum duty + comp unclamped, signed(count_width + 2)
    (6, {"clamp": False}),
    (7, {"width": 12, "count_width": 10, "clocks_width": 5, "shift_width": 3, "clamp": False}),
    # one_count=True (the iCE40's and the Spartan-7's sequencer)
    (8, {"one_count": True}),
    (9, {"width": 23, "count_width": 24, "clocks_width": 16, "shift_width": 5,
         "one_count": True}),
    (10, {"width": 12, "count_width": 10, "clocks_width": 5, "shift_width": 3, "clamp": False,
          "one_count": True}),
])
def test_deadtime_comp_matches_model_bit_for_bit(seed, params):
    rng = np.random.default_rng(seed)
    gen = {k: v for k, v in params.items() if k not in ("clamp", "one_count")}
    clamp = params.get("clamp", True)
    stim = random_stim(rng, 3000, **gen)
    comp, out, valid = run_dut(stim, **params)
    m_comp, m_out = model_of(stim, params.get("shift_width", 4), params.get("count_width", 16))
    np.testing.assert_array_equal(comp, m_comp)
    np.testing.assert_array_equal(out, m_out if clamp else stim["duty"] + m_comp)
    if not clamp:
        top = (1 << params.get("count_width", 16)) - 1
        assert np.any(out < 0) and np.any(out > top)       # both beyond the clamps
        return
    np.testing.assert_array_equal(valid, stim["duty_valid"])
    # The stimulus reached the interesting cases: saturated, linear, both clamps of o.
    v = stim["phase_valid"] == 1
    sym, clocks = stim["symmetric"][v][:, None], stim["clocks"][v][:, None]
    tr = np.abs(model.trapezoid(stim["phase"][v], clocks, stim["shift"][v][:, None], sym))
    lim = np.where(sym == 1, (clocks + 1) >> 1, clocks)
    assert np.any((tr == lim) & (lim > 0)) and np.any((tr > 0) & (tr < lim))
    top = (1 << params.get("count_width", 16)) - 1
    assert np.any((out == 0) & (stim["duty"] > 0)) and np.any(
        (out == top) & (stim["duty"] < top))


@pytest.mark.parametrize("symmetric", [0, 1])
def test_deadtime_comp_output_beyond_full_scale_gives_the_full_scale_levels(symmetric):
    """The block clamps at 2**count_width − 1, not at the timer's full scale: the timer's levels
    of every corrected duty are those of the duty clamped to the full scale of the mode it runs
    in (:func:`pwm_levels`, which the timer's own tests check clock by clock)."""
    n = 40
    fs = n if symmetric else 2 * n
    for duty in (0, 1, fs - 3, fs - 1, fs):
        for comp in (-255, -5, -1, 0, 1, 2, 5, 255):
            o = int(model.apply(duty, comp, count_width=8))
            clamped = min(max(duty + comp, 0), fs)
            np.testing.assert_array_equal(pwm_levels(o, n, symmetric),
                                          pwm_levels(clamped, n, symmetric))


@pytest.mark.parametrize("one_count", [False, True])
def test_deadtime_comp_latency_cycle_by_cycle(one_count):
    t_len = 80
    z = np.zeros(t_len, dtype=np.int64)
    for shift, sym in ((0, 0), (3, 0), (3, 1), (11, 1)):
        stim = {"phase_valid": z.copy(), "phase": np.zeros((t_len, 3), dtype=np.int64),
                "duty_valid": z + 1, "duty": np.full((t_len, 3), 1000),
                "symmetric": z + sym, "clocks": z + 50, "shift": z + shift}
        stim["phase_valid"][10] = 1
        k = shift + sym
        small = min(3 << k, 32767)
        stim["phase"][10] = [30000, -30000, small]
        comp, out, _ = run_dut(stim, one_count=one_count)
        want = model.trapezoid(stim["phase"][10], 50, shift, sym)
        assert want.all()
        # Phase a from 13 + k, b one clock later, c two (one shared clamp and negation).
        for ph in range(3):
            np.testing.assert_array_equal(comp[:13 + k + ph, ph], 0)
            np.testing.assert_array_equal(comp[13 + k + ph:, ph], want[ph])
        np.testing.assert_array_equal(out[15 + k:], 1000 + comp[15 + k:])
        assert 5 + k <= DeadTimeComp().comp_latency == 5 + (1 << 4)


def test_deadtime_comp_trapezoid_shape():
    i = np.arange(-2000, 2001)
    # Asymmetric, C = 50, band 4: slope 1/16 (magnitude truncated), ±50 beyond 800 LSB.
    c = model.trapezoid(i, 50, 4, 0)
    ideal = np.clip(i / 16, -50, 50)
    assert np.max(np.abs(c - ideal)) <= 1
    np.testing.assert_array_equal(c[i >= 0], np.minimum(i[i >= 0] // 16, 50))
    assert c[i == 800] == 50 and c[i == 799] == 49 and c[i == -801] == -50
    assert not c[(i >= -16) & (i < 16)].any()
    # Odd-symmetric about −1/2 LSB: i and −1 − i get opposite corrections.
    np.testing.assert_array_equal(model.trapezoid(-1 - i, 50, 4, 0), -c)
    # Symmetric PWM: the same trapezoid in clocks of high time (2 per compare count).
    cs = model.trapezoid(i, 50, 4, 1)
    assert np.max(np.abs(2 * cs - c)) <= 1 and cs.max() == 25 and cs.min() == -25
    assert model.trapezoid(30000, 33, 0, 1) == 17             # odd C rounds up in symmetric
    # Off: all zero.
    assert not model.trapezoid(i, 0, 4, 1).any()


# --- physics: the correction restores the volt-seconds the gates lose ---------------------------

@pytest.mark.parametrize("symmetric", [0, 1])
@pytest.mark.parametrize("dead", [1, 7, 50])
@pytest.mark.parametrize("sign", [1, -1])
def test_deadtime_comp_restores_high_time(symmetric, dead, sign):
    """With the current beyond the band, the terminal (gate model + freewheeling diode) is high
    exactly as long as the uncorrected PWM level: the loss ``sign·d`` is gone (symmetric mode, odd
    ``d``: within the one clock of the compare's 2-clock resolution)."""
    n = 200
    for compare in (60, 100, 143):
        ideal = int(pwm_high_clocks(compare, n, symmetric))
        lost = model.terminal_high_clocks(compare, sign, half_period=n, symmetric=symmetric,
                                          dead_time=dead)
        assert lost == ideal - sign * dead                  # what the dead time costs
        comp = int(model.trapezoid(sign * 30000, dead, 4, symmetric))
        duty = int(model.apply(compare, comp))
        fixed = model.terminal_high_clocks(duty, sign, half_period=n, symmetric=symmetric,
                                           dead_time=dead)
        assert abs(fixed - ideal) <= (dead % 2 if symmetric else 0)


# --- the plant: the whole Top (compiled engine) against the PMSM and its inverter ---------------

def _current_step(*, rpm=0.0, dead_time_s=1e-6, duration_s=5.5e-3):
    """Held-rotor i_q step 0 → 10 A (at a stiff ``rpm``), tuned by ``Servo.tune`` (which writes
    the compensation for ``dead_time_s``; ``None``: off). Returns (result, time from the write,
    i_d, i_q)."""
    kw = {}
    if rpm:
        kw = {"omega_m0": rpm * 2 * np.pi / 60, "theta_m0": S._start_angle(S.DEFAULT_MOTOR)}
    res = S.current_step(iq_a=10.0, duration_s=duration_s,
                         setup_kw={"tune_kw": {"dead_time_s": dead_time_s}}, **kw)
    s = res.series
    return res, s["t_s"] - res.metrics["t0_s"], s["i_d_a"], s["i_q_a"]


def test_deadtime_comp_plant_current_step_held_rotor():
    """Without compensation the dead time's 3.1 V takes the current to 9.67 A after the rise and
    it creeps back with L/R = 7.7 ms (9.68 A at 1 ms, 9.82 A at 5 ms). With it the step is the
    technical optimum's own (≈ 4.3 % overshoot, then flat): within ±1 % from 0.8 ms on."""
    res, t, i_d, i_q = _current_step()
    assert res.cosim.servo().get_many(["dtc_clocks", "dtc_band"]) == pytest.approx(
        {"dtc_clocks": 1e-6, "dtc_band": 3})
    assert i_q.max() < 10.5                                 # TO overshoot, nothing more
    after = t >= 0.8e-3
    assert np.all(np.abs(i_q[after] - 10.0) <= 0.1), i_q[after].min()
    late = t >= 1.0e-3
    assert abs(np.mean(i_q[late]) - 10.0) < 0.01           # the 3.1 V error is gone
    assert np.max(np.abs(i_d[after])) < 0.05


def test_deadtime_comp_plant_1000_rpm_not_worse():
    """At 1000 r/min (rotor driven) the dead time distorts the phase voltages (6th harmonic in
    d–q) and lowers i_q; the compensation must reduce both errors, not add ripple."""
    errs = {}
    for name, dead in (("on", 1e-6), ("off", None)):
        _, t, i_d, i_q = _current_step(rpm=1000.0, dead_time_s=dead, duration_s=6e-3)
        w = t >= t[-1] - 3e-3
        errs[name] = (np.sqrt(np.mean(i_d[w] ** 2)), np.sqrt(np.mean((i_q[w] - 10.0) ** 2)),
                      np.std(i_q[w]))
    on, off = errs["on"], errs["off"]
    assert on[0] < 0.6 * off[0] and on[1] < 0.3 * off[1] and on[2] <= off[2], errs


# --- the iCE40's form: the clamp in the timer (Top(timer_clamp)) ---------------------------------

@pytest.mark.parametrize("seed, count_width, clk_hz, pwm_hz", [
    (1, 8, 1e6, 25e3),          # N = 20: compares from 2**6 up saturate, sums up to 2 * 255
    (2, 16, 1e6, 50e3),         # N = 10, the Top's count width
    (3, 6, 0.8e6, 100e3),       # N = 4: the level counter 4 bits, sums from 2**6 up
])
def test_deadtime_comp_unclamped_into_a_signed_timer_gives_the_same_levels(seed, count_width,
                                                                           clk_hz, pwm_hz):
    """``DeadTimeComp(clamp=False)`` into ``PWMTimer(signed_duty=True)`` (the iCE40's form)
    against ``DeadTimeComp()`` into ``PWMTimer()``, side by side on one stimulus: the same
    ``pwm`` levels, ``comp``, ``period_start`` and ``sample`` in every clock, with sums below 0,
    above the counter's and the port's range, and duty writes often on the period's last clock."""
    from amaranth.hdl import Module
    from foc_servo.hdl.svpwm import PWMTimer
    pairs = []
    m = Module()
    for clamp in (True, False):
        dtc = DeadTimeComp(width=12, count_width=count_width, clocks_width=8, shift_width=2,
                           clamp=clamp)
        timer = PWMTimer(clk_hz=clk_hz, pwm_hz=pwm_hz, count_width=count_width,
                         signed_duty=not clamp)
        m.submodules[f"dtc_{clamp}"], m.submodules[f"timer_{clamp}"] = dtc, timer
        m.d.comb += [timer.duty.valid.eq(dtc.o.valid), timer.duty.payload.eq(dtc.o.payload),
                     dtc.o.ready.eq(timer.duty.ready)]
        pairs.append((dtc, timer))
    per = pairs[0][1].period
    rng = np.random.default_rng(seed)
    t_len = 60 * per
    top = (1 << count_width) - 1
    edges = [0, 1, 2, per // 2, per - 1, per, per + 1, top - 1, top]
    seen = {"low": 0, "high": 0}
    rec = {False: [], True: []}

    async def testbench(ctx):
        sym = 0
        for t in range(t_len):
            if rng.random() < 0.02:
                sym ^= 1
            boundary = t % per == per - 1
            phase = {p: int(rng.integers(-2048, 2048)) if rng.random() < 0.7 else
                     int(rng.choice([-2048, -1, 0, 2047])) for p in "abc"}
            duty = {p: int(rng.choice(edges)) if rng.random() < 0.5 else
                    int(rng.integers(0, top + 1)) for p in "abc"}
            pv = int(rng.random() < 0.1)
            dv = int(rng.random() < (0.5 if boundary else 0.1))
            clocks = int(rng.choice([0, 1, 5, 255])) if rng.random() < 0.3 else \
                int(rng.integers(0, 256))
            shift = int(rng.integers(0, 4))
            for dtc, timer in pairs:
                ctx.set(dtc.phase.valid, pv)
                ctx.set(dtc.phase.payload, phase)
                ctx.set(dtc.i.valid, dv)
                ctx.set(dtc.i.payload, duty)
                for sig, v in ((dtc.symmetric, sym), (timer.symmetric, sym),
                               (dtc.clocks, clocks), (dtc.shift, shift)):
                    ctx.set(sig, v)
            for dtc, timer in pairs:
                p, c = ctx.get(timer.pwm), ctx.get(dtc.comp)
                rec[dtc.clamp].append((p.a, p.b, p.c, c.a, c.b, c.c, ctx.get(timer.period_start),
                                       ctx.get(timer.sample)))
            if dv:
                raw = ctx.get(pairs[1][0].o.payload)
                for p in "abc":
                    seen["low"] += raw[p] < 0
                    seen["high"] += raw[p] > top
            await ctx.tick()

    simulate(m, [testbench], name="test_dtc_timer_clamp")
    np.testing.assert_array_equal(np.array(rec[False]), np.array(rec[True]))
    levels = np.array(rec[True])[:, :3]
    assert seen["low"] > 10 and seen["high"] > 10 and 0.1 < levels.mean() < 0.9
