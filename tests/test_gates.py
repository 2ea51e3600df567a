# Ref: SPEC.md §4 (complementary gates, dead time, enable, trip); issue 4 item 6
import gc
import re
import warnings

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import UnusedElaboratable

from foc_servo.boards.area import ports
from foc_servo.hdl.gates import Gates, dead_n_const
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.gates import check_gates, gates as gates_model


def run_gates(stim, *, dead_width=8, dead_n=False, wrap=False, prev_pwm=False):
    """Drive Gates clock by clock from ``stim`` (dict of arrays: ``pwm`` (T, 3), ``dead``,
    ``enable``, ``trip`` (T,)); return the outputs during each clock, ``high``, ``low`` (T, 3).
    ``dead_n``: ``Gates(dead_n=True)``, its port driven with :func:`dead_n_const` of ``dead``."""
    dut = Gates(dead_width=dead_width, dead_n=dead_n, wrap=wrap, prev_pwm=prev_pwm)
    t_len = len(stim["dead"])
    high = np.zeros((t_len, 3), dtype=np.int64)
    low = np.zeros((t_len, 3), dtype=np.int64)

    async def testbench(ctx):
        for t in range(t_len):
            p = stim["pwm"][t]
            ctx.set(dut.pwm, {"a": int(p[0]), "b": int(p[1]), "c": int(p[2])})
            if dead_n:
                ctx.set(dut.dead_n, dead_n_const(int(stim["dead"][t]), dead_width))
            else:
                ctx.set(dut.dead_time, int(stim["dead"][t]))
            ctx.set(dut.enable, int(stim["enable"][t]))
            ctx.set(dut.trip, int(stim["trip"][t]))
            h, lo = ctx.get(dut.high), ctx.get(dut.low)
            high[t] = [h.a, h.b, h.c]
            low[t] = [lo.a, lo.b, lo.c]
            await ctx.tick()

    simulate(dut, [testbench], name="test_gates")
    return high, low


def constant(t_len, pwm=(0, 0, 0), dead=3, enable=1, trip=0):
    return {"pwm": np.tile(np.array(pwm), (t_len, 1)), "dead": np.full(t_len, dead),
            "enable": np.full(t_len, enable), "trip": np.full(t_len, trip)}


@pytest.mark.parametrize("value", [0, 17, 8.0, True])
def test_gates_parameter_validation(value):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)     # the half-built object
        with pytest.raises(TypeError, match=re.escape(
                f"Gates dead_width must be an integer from 1 to 16, not {value!r}") + "$"):
            Gates(dead_width=value)
        gc.collect()


@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_convert_to_verilog(dead_n):
    dut = Gates(dead_n=dead_n)
    assert "module" in verilog.convert(dut, ports=ports(dut))
    assert dut.dead_input == ("dead_n" if dead_n else "dead_time")


def test_gates_dead_n_parameter_validation():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        with pytest.raises(TypeError, match=r"^Gates dead_n must be a bool, not 1$"):
            Gates(dead_n=1)
        with pytest.raises(TypeError, match=r"^Gates wrap must be a bool, not 1$"):
            Gates(wrap=1)
        with pytest.raises(TypeError, match=r"^Gates prev_pwm must be a bool, not 1$"):
            Gates(prev_pwm=1)
        gc.collect()


@pytest.mark.parametrize("dead_width", [1, 3, 8])
def test_gates_dead_n_const_is_the_gateware_operand(dead_width):
    """:func:`dead_n_const` (the register file's reset value, the tests' drive) equals
    :func:`~foc_servo.hdl.gates.dead_n` (the gateware's, ``Gates(dead_n=False)`` and the Top's
    operand) on every code."""
    from amaranth.hdl import Module, Signal
    from foc_servo.hdl.gates import dead_n
    m = Module()
    d = Signal(dead_width)
    out = Signal(dead_width)
    m.d.comb += out.eq(dead_n(d))
    bad = []

    async def bench(ctx):
        for v in range(1 << dead_width):
            ctx.set(d, v)
            if ctx.get(out) != dead_n_const(v, dead_width):
                bad.append(v)

    simulate(m, [bench], name="test_gates_dead_n")
    assert not bad


@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_all_off_at_reset_then_dead_time_before_first_turn_on(dead_n):
    stim = constant(12, pwm=(1, 0, 1), dead=5)
    high, low = run_gates(stim, dead_n=dead_n, prev_pwm=dead_n)
    # Clock 0: reset state, and the wanted state appears (a change: the count starts at 1).
    # Both off for clocks 0 … 5, the wanted side on from clock 1 + 5.
    assert not high[:6].any() and not low[:6].any()
    np.testing.assert_array_equal(high[6:], np.tile([1, 0, 1], (6, 1)))
    np.testing.assert_array_equal(low[6:], np.tile([0, 1, 0], (6, 1)))


@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_edge_timing_cycle_by_cycle(dead_n):
    dead = 4
    stim = constant(40, pwm=(0, 0, 0), dead=dead)
    stim["pwm"][15:30, 0] = 1                       # phase a: a pulse of 15 clocks
    high, low = run_gates(stim, dead_n=dead_n, prev_pwm=dead_n)
    # Low side on after reset; the rising pwm edge at 15 turns it off at 16, the high side on
    # dead clocks later (20); the falling edge at 30 turns the high side off at 31, low on at 35.
    np.testing.assert_array_equal(np.flatnonzero(high[:, 0]), np.arange(16 + dead, 31))
    assert low[16 - 1, 0] and not low[16:16 + dead + 11, 0].any() and low[35:, 0].all()
    assert high[:, 1:].sum() == 0
    assert check_gates(high, low, stim["dead"], stim["pwm"]) == {
        "overlap": 0, "short_dead": 0, "runts": 0}


@pytest.mark.parametrize("dead", [1, 6, 20])
@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_pulse_shorter_than_dead_time_is_dropped(dead, dead_n):
    t0 = 2 * dead + 5                               # low side on by then
    stim = constant(t0 + 3 * dead + 10, dead=dead)
    stim["pwm"][t0:t0 + dead - 1, 0] = 1            # high pulse one clock short of the dead time
    stim["pwm"][t0:t0 + dead, 1] = 1                # exactly the dead time
    stim["pwm"][t0:t0 + dead + 1, 2] = 1            # one clock longer
    high, low = run_gates(stim, dead_n=dead_n, prev_pwm=dead_n)
    assert low[t0].all()
    assert not high[:, 0].any() and not high[:, 1].any()        # dropped: no runt
    # A pulse of L clocks gives L − dead clocks on the high side.
    np.testing.assert_array_equal(np.flatnonzero(high[:, 2]), [t0 + dead + 1])
    # The low side of the dropped pulse turns back on after a full dead time, never overlapping.
    assert low[-1].all()
    assert check_gates(high, low, stim["dead"], stim["pwm"]) == {
        "overlap": 0, "short_dead": 0, "runts": 0}


@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_trip_and_enable_force_all_off_within_one_clock(dead_n):
    stim = constant(60, pwm=(1, 0, 1), dead=2)
    stim["trip"][20:23] = 1
    stim["enable"][40:45] = 0
    stim["pwm"][41:52, 1] = 1                       # pwm changes while disabled
    high, low = run_gates(stim, dead_n=dead_n, prev_pwm=dead_n)
    assert Gates.trip_latency == 1
    assert (high[19] | low[19]).all()
    assert not high[21:24].any() and not low[21:24].any()      # off the clock after trip
    assert not high[41:46].any() and not low[41:46].any()
    # Back on only after the dead time: trip released at 23, first turn-on at 23 + 1 + 2.
    assert not (high[24:26] | low[24:26]).any() and (high[26] | low[26]).all()
    assert (high[48] | low[48]).all() and not (high[47] | low[47]).any()
    assert check_gates(high, low, stim["dead"], stim["pwm"]) == {
        "overlap": 0, "short_dead": 0, "runts": 0}


@pytest.mark.parametrize("dead_n", [False, True])
def test_gates_zero_dead_time_acts_as_one_clock(dead_n):
    stim = constant(20, dead=0)
    stim["pwm"][8:14, 0] = 1
    high, low = run_gates(stim, dead_n=dead_n, prev_pwm=dead_n)
    np.testing.assert_array_equal(np.flatnonzero(high[:, 0]), np.arange(10, 15))
    assert not low[9, 0] and not low[15, 0] and low[16, 0]


def _random_stim(rng, t_len, *, longest, random_start, dead, enables, trips):
    """Random PWM runs of 1 … ``longest − 1`` clocks a phase (starting low, or at random),
    the given dead time per clock, and disabled / tripped stretches: ``enables`` and ``trips``
    are ``(count, start_margin, shortest, longest)`` (starts in 0 … t_len − start_margin,
    lengths shortest … longest − 1)."""
    pwm = np.zeros((t_len, 3), dtype=np.int64)
    for k in range(3):
        t, level = 0, int(rng.integers(0, 2)) if random_start else 0
        while t < t_len:
            n = int(rng.integers(1, longest))
            pwm[t:t + n, k] = level
            t, level = t + n, 1 - level
    dead = dead(rng)
    stretches = []
    for count, margin, lo, hi in (enables, trips):
        mask = np.zeros(t_len, dtype=np.int64)
        for s in rng.integers(0, t_len - margin, count):
            mask[s:s + int(rng.integers(lo, hi))] = 1
        stretches.append(mask)
    return {"pwm": pwm, "dead": dead, "enable": 1 - stretches[0], "trip": stretches[1]}


def _against_model(stim, *, dead_width=8, dead_n=False, wrap=False, prev_pwm=False):
    """Run ``stim``; the outputs equal the model's in every clock and keep the rules."""
    high, low = run_gates(stim, dead_width=dead_width, dead_n=dead_n, wrap=wrap,
                          prev_pwm=prev_pwm)
    exp_h, exp_l = gates_model(stim["pwm"], stim["dead"], stim["enable"], stim["trip"],
                               dead_width=dead_width)
    np.testing.assert_array_equal(high, exp_h)
    np.testing.assert_array_equal(low, exp_l)
    assert check_gates(high, low, stim["dead"], stim["pwm"]) == {
        "overlap": 0, "short_dead": 0, "runts": 0}
    return high, low


@pytest.mark.parametrize("dead_n, wrap, prev_pwm", [(False, False, False), (False, True, False),
                                                    (True, True, False), (True, True, True),
                                                    (False, False, True)])
def test_gates_random_sequences_against_model_and_rules(dead_n, wrap, prev_pwm):
    t_len = 4000
    stim = _random_stim(np.random.default_rng(7), t_len, longest=26, random_start=False,
                        dead=lambda rng: np.repeat(rng.integers(0, 16, t_len // 200), 200),
                        enables=(8, 40, 1, 40), trips=(12, 10, 1, 6))
    high, low = _against_model(stim, dead_n=dead_n, wrap=wrap, prev_pwm=prev_pwm)
    assert high.sum() > 1000 and low.sum() > 1000       # the stimulus did switch


def test_gates_checker_catches_rule_breaks():
    pwm = np.zeros((10, 3), dtype=np.int64)
    high = np.zeros((10, 3), dtype=np.int64)
    low = np.zeros((10, 3), dtype=np.int64)
    low[:4, 0] = 1
    high[5:, 0] = 1                                 # 1 clock off, dead time 3: short dead time
    pwm[4:, 0] = 1
    high[6, 1] = low[6, 1] = 1                      # overlap (and two turn-ons without dead time)
    pwm[4:6, 2] = 1
    high[6, 2] = 1                                  # follows a 2-clock pwm pulse: a runt
    r = check_gates(high, low, np.full(10, 3), pwm)
    # Runts: a (pwm high for 1 clock), b (pwm low), c.
    assert r == {"overlap": 1, "short_dead": 1, "runts": 3}


@pytest.mark.parametrize("dead_n, wrap, prev_pwm", [(False, False, False), (False, True, False),
                                                    (True, True, False), (True, True, True)])
def test_gates_count_wraps_only_where_it_is_not_read(dead_n, wrap, prev_pwm):
    """The off count without saturation (``wrap``, hdl/gates.py): with a 3-bit dead time it
    wraps many times in long disabled or tripped stretches and in stretches at the largest
    dead time (7: the count reaches 6 and the switch turns on), and the dead time changes at
    random while counts run; the outputs equal the model's (a saturating count) in every
    clock. (``wrap=False``: the saturating form on the same stimulus.)"""
    def dead(rng):
        d = rng.choice([0, 1, 6, 7], 3000)
        d[1000:1600] = 7                            # the largest dead time for a while
        return d

    stim = _random_stim(np.random.default_rng(11), 3000, longest=40, random_start=True,
                        dead=dead, enables=(10, 100, 9, 100), trips=(6, 30, 9, 30))
    high, low = _against_model(stim, dead_width=3, dead_n=dead_n, wrap=wrap,
                               prev_pwm=prev_pwm)
    assert high.sum() > 500 and low.sum() > 500
