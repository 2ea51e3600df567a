# amaranth: UnusedElaboratable=no
# Ref: issue 4 item 8 (protection and fault latch)

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Const, Value, signed, unsigned

import foc_servo.sim.verify.protect as verify_protect
from foc_servo.hdl.fixed import abs_exceeds, shape_range
from foc_servo.hdl.protect import FAULTS, LIMITS, STEPS, Protection
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.protect import (INPUTS, RAM_INPUTS, pack_flags, protect_np,
                                          unpack_flags)

DEFAULTS = {"fault_n": 1, "oc_comp": 0, "i_valid": 0, "a": 0, "b": 0, "c": 0, "udc_valid": 0,
            "udc": 20000, "speed_valid": 0, "speed": 0, "encoder_illegal": 0, "hall_invalid": 0,
            "encoder_hall": 0, "oc_limit": 1000, "ov_limit": 30000, "uv_limit": 10000,
            "uv_enable": 0, "os_limit": 1000, "mask": (1 << len(FAULTS)) - 1, "clear": 0}


def _drive(ctx, dut, v):
    """Every input of ``dut`` (a Protection) from the values ``v`` (names as DEFAULTS)."""
    ctx.set(dut.fault_n, v["fault_n"])
    ctx.set(dut.oc_comp, v["oc_comp"])
    ctx.set(dut.i.valid, v["i_valid"])
    ctx.set(dut.i.payload, {p: v[p] for p in "abc"})
    ctx.set(dut.udc.valid, v["udc_valid"])
    ctx.set(dut.udc.payload, v["udc"])
    ctx.set(dut.speed.valid, v["speed_valid"])
    ctx.set(dut.speed.payload, v["speed"])
    for r in ("encoder_illegal", "hall_invalid", "encoder_hall", "oc_limit", "ov_limit",
              "uv_limit", "uv_enable", "os_limit", "clear"):
        ctx.set(getattr(dut, r), v[r])
    ctx.set(dut.mask, {name: (v["mask"] >> k) & 1 for k, name in enumerate(FAULTS)})


def run_clocks(steps):
    """Drive one clock per entry of ``steps`` (a dict of the inputs that differ from
    :data:`DEFAULTS` in that clock) and return the outputs seen in each clock, checked against
    the golden model clock by clock."""
    cols = {k: np.array([s.get(k, DEFAULTS[k]) for s in steps], dtype=np.int64) for k in INPUTS}
    dut = Protection()
    record = []

    async def testbench(ctx):
        for s in steps:
            _drive(ctx, dut, {**DEFAULTS, **s})
            record.append({
                "trip": ctx.get(dut.trip),
                "present": ctx.get(dut.present.as_value()),
                "first": ctx.get(dut.first.as_value()),
                "seen": ctx.get(dut.seen.as_value()),
                "uv_armed": ctx.get(dut.uv_armed),
            })
            await ctx.tick()

    simulate(dut, [testbench], name="test_protect")
    exp = protect_np(cols)
    for key in ("trip", "present", "first", "seen", "uv_armed"):
        np.testing.assert_array_equal([r[key] for r in record], exp[key], err_msg=key)
    return record


def flags(*names):
    return pack_flags(names)


@pytest.mark.parametrize("kwargs, message", [
    ({"current_width": 3}, r"^Protection current_width must be an integer from 4 to 32, not 3$"),
    ({"current_width": 16.0},
     r"^Protection current_width must be an integer from 4 to 32, not 16\.0$"),
    ({"speed_width": 33}, r"^Protection speed_width must be an integer from 4 to 32, not 33$"),
    ({"udc_shape": 16}, r"^Protection udc_shape must be a Shape of 2 to 32 bits such as "
                        r"signed\(16\), not 16$"),
    ({"udc_shape": unsigned(40)}, r"^Protection udc_shape must be a Shape of 2 to 32 bits "
                                  r"such as signed\(16\), not unsigned\(40\)$"),
    ({"uv_arm_chain": 1}, r"^Protection uv_arm_chain must be a bool, not 1$"),
    ({"trip_register": None}, r"^Protection trip_register must be a bool, not None$"),
    ({"limits": 1},
     r"^Protection limits must be a string, one of 'ports', 'ram', 'ram16', not 1$"),
    ({"limits": "ram", "limit_init": (1, 2, 3)},
     r"^Protection limit_init must be 4 integers from 0 to 2\*\*32 - 1 \(the words of "
     r"oc_limit, ov_limit, uv_limit, os_limit\), not \(1, 2, 3\)$"),
    ({"limits": "ram", "limit_init": (1, 2, 3, 1 << 32)},
     r"^Protection limit_init must be 4 integers .*, not \(1, 2, 3, 4294967296\)$"),
])
def test_protect_parameter_validation(kwargs, message):
    with pytest.raises(TypeError, match=message):
        Protection(**kwargs)


@pytest.mark.parametrize("kwargs, message", [
    ({"limits": "rom"}, r"^Protection limits must be one of 'ports', 'ram', 'ram16', "
                        r"not 'rom'$"),
    ({"limit_init": (0, 0, 0, 0)},
     r"^Protection limit_init applies only to limits='ram' or 'ram16', not limits='ports'$"),
])
def test_protect_parameter_values(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Protection(**kwargs)


def test_protect_latency_each_input():
    latency = verify_protect.measure_latency()
    assert set(latency) == set(FAULTS)
    assert latency == {name: Protection.latency for name in FAULTS}


def test_protect_latency_cycle_by_cycle_external_pin():
    rec = run_clocks([{}, {}, {"fault_n": 0}, {}, {}, {}])
    assert [r["trip"] for r in rec] == [0, 0, 0, 1, 1, 1]
    assert [r["present"] for r in rec] == [0, 0, 0, flags("external"), 0, 0]
    assert rec[4]["first"] == rec[4]["seen"] == flags("external")


def test_protect_first_cause_kept():
    rec = run_clocks([{}, {"hall_invalid": 1}, {}, {"oc_comp": 1}, {"oc_comp": 1},
                      {"fault_n": 0}, {}, {}])
    assert all(r["trip"] for r in rec[2:])
    assert rec[-1]["first"] == flags("hall")
    assert rec[-1]["seen"] == flags("hall", "overcurrent_comparator", "external")


def test_protect_simultaneous_faults_all_in_first():
    rec = run_clocks([{}, {"encoder_illegal": 1, "hall_invalid": 1}, {}, {}])
    assert unpack_flags(rec[-1]["first"]) == ("encoder", "hall")


def test_protect_clear_only_when_gone():
    steps = ([{}, {"oc_comp": 1}] + [{"oc_comp": 1, "clear": 1}] * 3   # clear while present
             + [{"oc_comp": 1}, {}, {"clear": 1}, {}, {}])
    rec = run_clocks(steps)
    assert [r["trip"] for r in rec] == [0, 0, 1, 1, 1, 1, 1, 1, 0, 0]
    assert rec[-1]["first"] == rec[-1]["seen"] == 0


def test_protect_latch_holds_after_fault_goes():
    rec = run_clocks([{}, {"encoder_illegal": 1}] + [{}] * 20)
    assert all(r["trip"] for r in rec[2:]) and rec[-1]["present"] == 0


def test_protect_sampled_cause_held_until_next_sample():
    # An over-current sample: its verdict holds (no clear) until a sample within the limit.
    steps = ([{}, {"i_valid": 1, "b": 1001}, {}, {"clear": 1}, {"clear": 1},
              {"i_valid": 1, "b": -1000}, {"clear": 1}, {}])
    rec = run_clocks(steps)
    assert [r["trip"] for r in rec] == [0, 0, 1, 1, 1, 1, 1, 0]


def test_protect_overcurrent_limits_and_most_negative_current():
    top = {"oc_limit": 32767}
    rec = run_clocks([{**top, "i_valid": 1, "a": -32768}, top,       # |−32768| > 32767: trips
                      {**top, "i_valid": 1, "a": 0}, {**top, "clear": 1}, top,
                      {"oc_limit": 32768, "i_valid": 1, "c": -32768}, {},  # |i| = limit: no trip
                      {**top, "i_valid": 1, "c": 32767}, top])              # i = limit: no trip
    assert [r["trip"] for r in rec] == [0, 1, 1, 1, 0, 0, 0, 0, 0]
    assert rec[1]["present"] == flags("overcurrent_a")


def test_protect_over_voltage_and_over_speed():
    rec = run_clocks([{"udc_valid": 1, "udc": 30000}, {}, {"udc_valid": 1, "udc": 30001}, {},
                      {"udc_valid": 1, "udc": 20000, "clear": 1}, {"clear": 1}, {},
                      {"speed_valid": 1, "speed": -1001}, {}])
    assert [r["trip"] for r in rec] == [0, 0, 0, 1, 1, 1, 0, 0, 1]
    assert rec[3]["present"] == flags("overvoltage")
    assert rec[8]["present"] == flags("overspeed")


def test_protect_undervoltage_arming():
    low = {"uv_enable": 1, "udc_valid": 1, "udc": 5000}
    steps = ([low] * 4                                   # power-up: bus low, not armed
             + [{"uv_enable": 1, "udc_valid": 1, "udc": 10001}, {"uv_enable": 1}]   # arms
             + [low, {"uv_enable": 1}, {"uv_enable": 1, "clear": 1}]   # trips; clear refused
             + [{"uv_enable": 0}, {"uv_enable": 0, "clear": 1}, {"uv_enable": 0}])
    rec = run_clocks(steps)
    assert [r["uv_armed"] for r in rec] == [0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 0, 0]
    assert [r["trip"] for r in rec] == [0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 0]
    assert rec[7]["present"] == flags("undervoltage")


def test_protect_mask_ignores_cause():
    mask = (1 << len(FAULTS)) - 1 - flags("hall")
    rec = run_clocks([{"mask": mask, "hall_invalid": 1}] * 3 + [{"mask": mask}] * 2
                     + [{"hall_invalid": 1}, {}])
    assert [r["trip"] for r in rec] == [0, 0, 0, 0, 0, 0, 1]


@pytest.mark.parametrize("trip_register", [True, False])
def test_protect_random_fault_sequences_vs_model(trip_register):
    """Both forms of the trip's OR (``trip_register``: the ECP5's flip-flop of its own, the
    iCE40's OR of ``present``), every output in every clock against the model."""
    result = verify_protect.run(6000, seed=3, trip_register=trip_register)
    assert result["mismatches"] == 0, result
    assert result["trips"] > 20 and result["clears"] > 20
    assert result["fault_latency_clk_max"] == 1


def test_protect_converts_to_verilog():
    dut = Protection()
    # amaranth 0.5.10's convert() cannot take a Component whose interface holds constants (the
    # always-ready streams' `ready`, amaranth-lang/amaranth#1574): list the ports without them.
    ports = [Value.cast(v) for _, _, v in dut.signature.flatten(dut)]
    ports = [p for p in ports if not isinstance(p, Const)]
    text = verilog.convert(dut, name="protection", ports=ports)
    assert "module protection" in text and "trip" in text


@pytest.mark.slow
def test_protect_100k_random_clocks_vs_model():
    result = verify_protect.run(100_000)
    assert result["mismatches"] == 0, result


def test_protect_magnitude_compare_exhaustive_small_width():
    """``|v| > limit`` without forming ``|v|`` (``~v >= limit`` for v < 0, the whole top's
    100 MHz): every 5-bit current and speed against every 5-bit limit, against Python's
    ``abs(v) > limit`` (the most negative value included)."""
    n = 5
    dut = Protection(current_width=n, speed_width=n)
    cases = [(v, lim) for v in range(-(1 << (n - 1)), 1 << (n - 1)) for lim in range(1 << n)]
    seen = []

    async def testbench(ctx):
        ctx.set(dut.mask, {name: 1 for name in FAULTS})
        for v, lim in cases:
            ctx.set(dut.oc_limit, lim)
            ctx.set(dut.os_limit, lim)
            ctx.set(dut.i.valid, 1)
            ctx.set(dut.i.payload, {"a": v, "b": 0, "c": 0})
            ctx.set(dut.speed.valid, 1)
            ctx.set(dut.speed.payload, v)
            await ctx.tick()
            present = ctx.get(dut.present)
            seen.append((present.overcurrent_a, present.overspeed))

    simulate(dut, [testbench])
    expect = [(int(abs(v) > lim),) * 2 for v, lim in cases]
    assert seen == expect
    assert sum(e[0] for e in expect) > 100         # both verdicts well represented


def _run_against_model(dut, cols):
    """Drive ``dut`` with the per-clock columns ``cols`` (:data:`INPUTS`) and compare every
    output in every clock with :func:`protect_np`."""
    n = len(cols["fault_n"])
    record = []

    async def testbench(ctx):
        for t in range(n):
            _drive(ctx, dut, {k: int(cols[k][t]) for k in INPUTS})
            record.append((ctx.get(dut.trip), ctx.get(dut.present.as_value()),
                           ctx.get(dut.first.as_value()), ctx.get(dut.seen.as_value()),
                           ctx.get(dut.uv_armed)))
            await ctx.tick()

    simulate(dut, [testbench])
    exp = protect_np(cols)
    got = np.array(record)
    for k, key in enumerate(("trip", "present", "first", "seen", "uv_armed")):
        np.testing.assert_array_equal(got[:, k], exp[key], err_msg=key)
    return exp


@pytest.mark.parametrize("uv_arm_chain", [False, True])
@pytest.mark.parametrize("udc_shape", [signed(4), unsigned(3)])
def test_protect_udc_compares_exhaustive_small_width(udc_shape, uv_arm_chain):
    """Over-voltage ``udc > ov_limit``, under-voltage ``udc < uv_limit`` and the arming's
    ``udc > uv_limit`` share one inverted U_dc on two carry chains (the third verdict is the
    second chain's sum all ones), or the arming has a third chain (``uv_arm_chain``, the
    ECP5's form): every code against every limit (both at once), with the check disarmed every
    seventh clock (in order, then shuffled) so that the arming is seen anew, against the
    model."""
    lo, hi = shape_range(udc_shape)
    pairs = [(u, lim) for u in range(lo, hi + 1) for lim in range(lo, hi + 1)]
    pairs = pairs + [pairs[k] for k in np.random.default_rng(7).permutation(len(pairs))]
    steps = []
    for k, (u, lim) in enumerate(pairs):
        steps.append({"udc_valid": 1, "udc": u, "ov_limit": lim, "uv_limit": lim,
                      "uv_enable": int(k % 7 != 0), "clear": 1})
    cols = {k: np.array([s.get(k, DEFAULTS[k]) for s in steps], dtype=np.int64) for k in INPUTS}
    exp = _run_against_model(Protection(udc_shape=udc_shape, uv_arm_chain=uv_arm_chain), cols)
    bits = exp["present"]
    assert ((bits & flags("overvoltage")) != 0).sum() > 20
    assert ((bits & flags("undervoltage")) != 0).sum() > 5
    assert exp["uv_armed"].sum() > 20


@pytest.mark.parametrize("v_width, limit_width", [(5, 5), (6, 3), (3, 6), (2, 1)])
def test_abs_exceeds_exhaustive_mixed_widths(v_width, limit_width):
    """:func:`abs_exceeds` (one carry chain, carry-in ``~sign``) equals Python's
    ``abs(v) > limit`` for every value and limit, also when the widths differ."""
    from amaranth.hdl import Module, Signal
    from amaranth.sim import Simulator
    v = Signal(signed(v_width))
    lim = Signal(unsigned(limit_width))
    out = Signal()
    m = Module()
    m.d.comb += out.eq(abs_exceeds(v, lim))
    cases = [(a, b) for a in range(-(1 << (v_width - 1)), 1 << (v_width - 1))
             for b in range(1 << limit_width)]
    seen = []

    async def testbench(ctx):
        for a, b in cases:
            ctx.set(v, a)
            ctx.set(lim, b)
            seen.append(ctx.get(out))

    sim = Simulator(m)
    sim.add_testbench(testbench)
    sim.run()
    assert seen == [int(abs(a) > b) for a, b in cases]


# --- limits="ram": the limit RAM and the sequential compare (docs/AREA.md §7.77) -------------

RAM_FORMS = pytest.mark.parametrize("limits", ["ram", "ram16"])


@RAM_FORMS
def test_protect_ram_latency_each_input(limits):
    """The pins as in the parallel form (1 clock to ``trip``); each sampled cause 1 + the steps
    before it later (``step_latency``: the first over-current 2, the third 4)."""
    dut = Protection(limits=limits)
    latency = verify_protect.measure_latency(limits=limits)
    pins = set(FAULTS) - set(dut.step_latency)
    assert latency == {**{name: 1 for name in pins}, **dut.step_latency}
    assert dut.step_latency == {"overcurrent_a": 2, "overcurrent_b": 3, "overcurrent_c": 4,
                                "overvoltage": 2, "undervoltage": 3, "overspeed": 2}


@RAM_FORMS
@pytest.mark.parametrize("trip_register", [True, False])
def test_protect_ram_random_fault_sequences_vs_model(trip_register, limits):
    """The iCE40's form: every output in every clock against the model (its limit RAM and
    step sequencer), the limits written through ``limit_wr`` (segments' four words in four
    clocks, random rewrites: steps wait for them)."""
    # ("ram16" with a 32-bit speed, as the Top's: the over-speed limit's upper half in flops)
    result = verify_protect.run(6000, seed=3, trip_register=trip_register, limits=limits,
                                speed_width=32 if limits == "ram16" else 16)
    assert result["mismatches"] == 0, result
    assert result["trips"] > 20 and result["clears"] > 20
    assert result["fault_latency_clk_max"] == 4


def _ram_case_cols(cases, udc_cases, speed_scale=1):
    """Columns (RAM_INPUTS) that, per case, write the four limits, then take one sample of
    every stream (the currents a, b, c = v, −v, v; U_dc u; speed v) and hold it for 8 clocks
    with ``clear`` high: every step compared once per case, on limits just written."""
    steps = []
    for (v, lim), (u, ulim) in zip(cases, udc_cases):
        words = (lim, ulim & 0xFFFF_FFFF, ulim & 0xFFFF_FFFF,
                 lim * speed_scale + (speed_scale > 1))
        for k in range(len(LIMITS)):
            steps.append({"lim_valid": 1, "lim_index": k, "lim_data": words[k],
                          "uv_enable": 1})
        sample = {"a": v, "b": -v if -v <= 15 else v, "c": v, "udc": u,
                  "speed": v * speed_scale + (speed_scale > 1) * (v & 1),
                  "uv_enable": 1, "clear": 1}
        steps.append({**sample, "i_valid": 1, "udc_valid": 1, "speed_valid": 1})
        steps += [sample] * 8
    default = {**DEFAULTS, "lim_valid": 0, "lim_index": 0, "lim_data": 0}
    return {k: np.array([st.get(k, default[k]) for st in steps], dtype=np.int64)
            for k in RAM_INPUTS}


@RAM_FORMS
@pytest.mark.parametrize("udc_shape", [signed(4), unsigned(3)])
def test_protect_ram_compares_exhaustive_small_width(udc_shape, limits):
    """The one comparator of every step (:func:`~foc_servo.hdl.protect.step_compare`): every
    5-bit current and speed against every 5-bit limit (the most negative value included), and
    every U_dc code against every U_dc limit (over-voltage, under-voltage, arming), each on a
    limit just written, against the model clock by clock; the model's verdicts are Python's
    ``abs(v) > limit`` and plain compares. (``"ram16"``: the speed 7 bits wide, its limit's
    upper 2 bits in flip-flops.)"""
    n = 5
    dut = Protection(current_width=n, speed_width=n if limits == "ram" else n + 2,
                     udc_shape=udc_shape, limits=limits)
    cases = [(v, lim) for v in range(-(1 << (n - 1)), 1 << (n - 1)) for lim in range(1 << n)]
    lo, hi = shape_range(udc_shape)
    upairs = [(u, lim) for u in range(lo, hi + 1) for lim in range(lo, hi + 1)]
    rng = np.random.default_rng(5)
    udc_cases = [upairs[k] for k in rng.integers(0, len(upairs), size=len(cases))]
    udc_cases[:len(upairs)] = upairs
    scale = 1 if limits == "ram" else 4     # (speed and its limit over 7 bits)
    result, exp, _ = verify_protect.compare(dut, _ram_case_cols(cases, udc_cases, scale))
    assert result["mismatches"] == 0, result
    bits = exp["present"]
    for name in ("overcurrent_a", "overcurrent_b", "overspeed", "overvoltage", "undervoltage"):
        assert ((bits & flags(name)) != 0).sum() > 50, name
    assert exp["uv_armed"].sum() > 1000


@RAM_FORMS
def test_protect_ram_steps_wait_for_writes_and_share_the_comparator(limits):
    """A sample's steps in STEPS order, one per clock, none in a ``limit_wr`` clock; a limit
    written in clock w is used by the steps taken after w (against the model)."""
    base = {"lim_valid": 0, "lim_index": 0, "lim_data": 0}
    held = {"a": 1001, "b": 999, "c": -1001, "speed": -1001, "udc": 30001}
    steps = [{**base, "lim_valid": 1, "lim_index": k, "lim_data": v}
             for k, v in ((0, 1000), (1, 30000), (3, 1000))]
    steps += [{**base, **held, "i_valid": 1, "speed_valid": 1, "udc_valid": 1}]      # clock 3
    steps += [{**base, **held, "lim_valid": int(k in (1, 2)), "lim_index": 0,
               "lim_data": 1001} for k in range(12)]    # oc_limit 1001 written in 5 and 6
    default = {**DEFAULTS, **base}
    cols = {k: np.array([st.get(k, default[k]) for st in steps], dtype=np.int64)
            for k in RAM_INPUTS}
    result, exp, _ = verify_protect.compare(Protection(limits=limits), cols)
    assert result["mismatches"] == 0, result
    seen = [unpack_flags(p) for p in exp["present"]]
    # oc_a taken in 3 (present in 5), oc_b in 4, none in 5 and 6, oc_c in 7 (limit 1001: not
    # over), ov in 8 (present in 10), uv 9, arm 10, os 11 (present in 13)
    assert seen[4] == () and seen[5] == ("overcurrent_a",)
    assert "overvoltage" not in seen[9] and "overvoltage" in seen[10]
    assert "overspeed" not in seen[12] and "overspeed" in seen[13]
    assert not any("overcurrent_c" in f or "overcurrent_b" in f for f in seen)


def test_protect_ram_model_steps_are_the_documented_order():
    """STEPS: the three currents, then U_dc's over-voltage, under-voltage and arming, then the
    speed (the order the class docstring and the latencies state)."""
    assert [s[0] for s in STEPS] == ["oc_a", "oc_b", "oc_c", "ov", "uv", "arm", "os"]
    assert [s[2] for s in STEPS] == ["oc_limit"] * 3 + ["ov_limit", "uv_limit", "uv_limit",
                                                         "os_limit"]


def test_protect_ram16_widths():
    """``"ram16"``: the RAM as wide as the currents and U_dc, the comparator as the speed."""
    assert Protection(speed_width=32, limits="ram").ram_width == 32
    assert Protection(speed_width=32, limits="ram16").ram_width == 16
    assert Protection(speed_width=8, limits="ram16").ram_width == 16
    assert Protection().ram_width is None


@pytest.mark.slow
@RAM_FORMS
def test_protect_ram_100k_random_clocks_vs_model(limits):
    """The iCE40's forms as the Top builds them (32-bit speed, the OR of ``present``)."""
    result = verify_protect.run(100_000, limits=limits, trip_register=False, speed_width=32)
    assert result["mismatches"] == 0, result


@RAM_FORMS
def test_protect_ram_step_takes_the_payload_of_its_pick_clock(limits):
    """A step's operand is the payload of the clock it is taken in (registered beside the
    RAM's word, iCE40 Fmax), not of its compare clock: a current over the limit in its valid
    clock only trips ``overcurrent_a`` (taken then), not ``_b`` / ``_c`` (taken later, on the
    payload then within the limit); the speed likewise."""
    base = {"lim_valid": 0, "lim_index": 0, "lim_data": 0}
    steps = [{**base, "lim_valid": 1, "lim_index": k, "lim_data": 1000} for k in (0, 3)]
    steps += [{**base, "i_valid": 1, "a": -2000, "b": 2000, "c": 2000,
               "speed_valid": 1, "speed": 0}]
    steps += [{**base, "speed": 5000}] + [base] * 8
    default = {**DEFAULTS, **base}
    cols = {k: np.array([st.get(k, default[k]) for st in steps], dtype=np.int64)
            for k in RAM_INPUTS}
    result, exp, _ = verify_protect.compare(Protection(limits=limits), cols)
    assert result["mismatches"] == 0, result
    seen = set().union(*(unpack_flags(p) for p in exp["present"]))
    assert seen == {"overcurrent_a"}
