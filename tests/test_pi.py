# amaranth: UnusedElaboratable=no
# Ref: paper eq. (7)–(9); SPEC.md §2.2
import re

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Fragment, Signal, Value

from foc_servo.hdl.fixed import Q, UQ
from foc_servo.hdl.pi import PI
from foc_servo.sim.harness import simulate
from foc_servo.sim.models.pi import PIModel
from foc_servo.sim.verify.pi import run

KP_ONE = 1 << 8              # 1.0 in the default UQ(16, 8)
KX_ONE = 1 << 16             # 1.0 in the default UQ(16, 16) (not representable: max is 0.99998)
HI, LO = 32767, -32768


def drive(dut, samples, *, clear_before=()):
    """Feed ``samples`` (dicts with ref, fb, kp, kx, lim_lo, lim_hi) one at a time; return the list
    of (out, sat, integrator) read on each strobe. ``clear_before`` lists sample indices before
    which ``clear`` is pulsed for one clock."""
    results = []

    async def testbench(ctx):
        for k, s in enumerate(samples):
            if k in clear_before:
                ctx.set(dut.clear, 1)
                await ctx.tick()
                ctx.set(dut.clear, 0)
            ctx.set(dut.kp, s["kp"])
            ctx.set(dut.kx, s["kx"])
            ctx.set(dut.lim_lo, s["lim_lo"])
            ctx.set(dut.lim_hi, s["lim_hi"])
            ctx.set(dut.i.payload, {"ref": s["ref"], "fb": s["fb"]})
            ctx.set(dut.i.valid, 1)
            await ctx.tick().until(dut.i.ready)
            ctx.set(dut.i.valid, 0)
            *_, out, sat, integ = await ctx.tick().sample(
                dut.o.payload, dut.sat, dut.integrator).until(dut.o.valid)
            results.append((out, sat, integ))

    simulate(dut, [testbench], name="pi_drive")
    return results


def samples_of(ref, fb, *, kp=KP_ONE, kx=0, lim_lo=LO, lim_hi=HI):
    ref = np.broadcast_to(ref, np.broadcast(ref, fb).shape)
    fb = np.broadcast_to(fb, ref.shape)
    return [dict(ref=int(r), fb=int(f), kp=kp, kx=kx, lim_lo=lim_lo, lim_hi=lim_hi)
            for r, f in zip(ref, fb)]


def model_of(samples, model=None, **params):
    model = model or PIModel(**params)
    out = []
    for s in samples:
        o, sat = model.step(s["ref"], s["fb"], s["kp"], s["kx"], s["lim_lo"], s["lim_hi"])
        out.append((o, sat, model.integrator))
    return out


@pytest.mark.parametrize("kwargs, exc, msg", [
    (dict(width=3), TypeError, r"^PI width must be an integer of at least 4, not 3$"),
    (dict(width="16"), TypeError, r"^PI width must be an integer of at least 4, not '16'$"),
    (dict(width=True), TypeError, r"^PI width must be an integer of at least 4, not True$"),
    (dict(kp_format=16), TypeError, r"^PI kp_format must be a QFormat, not 16$"),
    (dict(kx_format=(16, 16)), TypeError, r"^PI kx_format must be a QFormat, not \(16, 16\)$"),
    (dict(int_guard=-1), TypeError, r"^PI int_guard must be a non-negative integer, not -1$"),
    (dict(int_guard=2.0), TypeError, r"^PI int_guard must be a non-negative integer, not 2\.0$"),
    (dict(width=40, kx_format=UQ(24, 24)), ValueError,
     r"^PI parameters need a 65-bit intermediate value; at most 62 bits are supported "
     r"\(width 40, kp_format UQ\(16, 8\), kx_format UQ\(24, 24\), int_guard 8\)$"),
])
def test_pi_parameter_validation(kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        PI(**kwargs)
    with pytest.raises(exc, match=msg):
        PIModel(**kwargs)


def test_pi_interface_and_attributes():
    dut = PI(width=12, kp_format=Q(12, 6), kx_format=UQ(10, 14), int_guard=3)
    assert (dut.width, dut.kp_format, dut.kx_format, dut.int_guard) == (
        12, Q(12, 6), UQ(10, 14), 3)
    assert dut.kp.shape() == Q(12, 6).shape and dut.kx.shape() == UQ(10, 14).shape
    assert dut.integrator.shape().width == 15 and dut.integrator.shape().signed
    assert dut.o.payload.shape().width == 12 and dut.o.signature.always_ready
    assert dut.latency >= 1 and dut.interval >= 1
    Fragment.get(dut, platform=None)                      # elaborates with these formats


def test_pi_error_saturates():
    # kp = 0.5: an unsaturated E = ∓65535 would wrap to ±1 in 16 bits; saturated it is -32768 /
    # 32767, so the output is -16384 / +16384 (16383.5 rounded away from zero).
    dut = PI()
    s = samples_of(np.array([LO, HI, LO, 0]), np.array([HI, LO, LO, 0]), kp=KP_ONE // 2)
    got = drive(dut, s)
    assert [g[0] for g in got] == [-16384, 16384, 0, 0]
    assert got == model_of(s)
    # With kx = 0.25 the integrator sees E[n] + E[n-1] = -32768 + 32767 = -1 on the second sample.
    s = samples_of(np.array([LO, HI]), np.array([HI, LO]), kp=0, kx=KX_ONE // 4)
    got = drive(PI(), s)
    assert [g[2] for g in got] == [-(32768 << 8) // 4, -(32768 << 8) // 4 + (-(1 << 8) // 4)]
    assert got == model_of(s)


def test_pi_output_saturation():
    s = (samples_of([5000, 500, -5000, -500], 0, lim_lo=-1000, lim_hi=1000) +
         samples_of([400, -400], 0, lim_lo=77, lim_hi=77) +
         # lim_lo > lim_hi: `clamp` semantics on the integrator (I -> ±300·2^g) and the output.
         samples_of([0, 1000, -1000], 0, lim_lo=300, lim_hi=-300))
    got = drive(PI(), s)
    assert [g[:2] for g in got] == [(1000, 1), (500, 0), (-1000, 1), (-500, 0),
                                    (77, 1), (77, 1),
                                    (300, 1), (-300, 1), (300, 1)]
    assert got == model_of(s)


def test_pi_windup_and_recovery():
    lim = 2000
    kx = KX_ONE // 64
    # 1) A long positive error with kp = 0 winds the integrator up to exactly lim·2^g, where the
    #    clamp holds it (I + dI > lim·2^g on every later sample).
    up = samples_of(0, np.full(120, -1000), kp=0, kx=kx, lim_lo=-lim, lim_hi=lim)
    # 2) With kp = 1 the output is pinned at the limit (sat) and the integrator does not move.
    pinned = samples_of(0, np.full(10, -1000), kx=kx, lim_lo=-lim, lim_hi=lim)
    # 3) The error changes sign: E[n] + E[n-1] = 700 is still positive, yet the output leaves the
    #    limit on this very sample (I sits at the limit, P = -300 pulls the output inside).
    down = samples_of(0, np.full(30, 300), kx=kx, lim_lo=-lim, lim_hi=lim)
    model = PIModel()
    clamped = []
    for s in up:
        model.step(s["ref"], s["fb"], s["kp"], s["kx"], s["lim_lo"], s["lim_hi"])
        clamped.append(model.last["clamped"])
    assert sum(clamped) > 50
    got = drive(PI(), up + pinned + down)
    assert got == model_of(up + pinned + down)
    integ = [g[2] for g in got]
    assert max(integ) == lim << 8 and min(integ) >= 0
    assert got[len(up) - 1] == (lim, 0, lim << 8)
    n = len(up) + len(pinned)
    assert all(g == (lim, 1, lim << 8) for g in got[len(up):n])
    assert got[n] == (lim - 300, 0, lim << 8)
    assert all(g[1] == 0 for g in got[n:])
    assert integ[n + 1] < integ[n] and got[n + 1][0] < got[n][0]        # then it unwinds

    # 3) Conditional integration: P alone pins the output (kp = 4, E = 1000 > 500), so the
    #    integrator holds at 0 instead of winding up; it integrates again at the sign change.
    held = samples_of(0, np.full(40, -1000), kp=4 * KP_ONE, kx=kx, lim_lo=-500, lim_hi=500)
    back = samples_of(0, np.full(5, 50), kp=4 * KP_ONE, kx=kx, lim_lo=-500, lim_hi=500)
    got = drive(PI(), held + back)
    assert got == model_of(held + back)
    assert all(g == (500, 1, 0) for g in got[:len(held)])
    assert got[len(held)][1] == 0 and got[len(held)][2] > 0
    assert got[len(held) + 2][2] < got[len(held) + 1][2]


def test_pi_clear():
    dut = PI()
    log = {}

    async def testbench(ctx):
        ctx.set(dut.kp, KP_ONE)
        ctx.set(dut.kx, KX_ONE // 8)
        ctx.set(dut.lim_lo, LO)
        ctx.set(dut.lim_hi, HI)
        ctx.set(dut.i.payload, {"ref": 0, "fb": -3000})
        for _ in range(8):                              # wind the integrator up a little
            ctx.set(dut.i.valid, 1)
            await ctx.tick().until(dut.i.ready)
            ctx.set(dut.i.valid, 0)
            await ctx.tick().until(dut.o.valid)
        log["before"] = (ctx.get(dut.o.payload), ctx.get(dut.integrator))
        # Accept one more sample, abandon it half-way with clear.
        ctx.set(dut.i.valid, 1)
        await ctx.tick().until(dut.i.ready)
        ctx.set(dut.i.valid, 0)
        await ctx.tick().repeat(dut.latency // 2)
        ctx.set(dut.clear, 1)
        ctx.set(dut.i.valid, 1)                         # accepted and dropped while clear is high
        ready, strobes = [], 0
        for _ in range(3):
            ready.append(ctx.get(dut.i.ready))
            await ctx.tick()
            strobes += ctx.get(dut.o.valid)
        ctx.set(dut.clear, 0)
        ctx.set(dut.i.valid, 0)
        log["during"] = (ready, strobes)
        for _ in range(2 * dut.latency):
            strobes += ctx.get(dut.o.valid)
            await ctx.tick()
        log["after"] = (strobes, ctx.get(dut.o.payload), ctx.get(dut.sat), ctx.get(dut.integrator),
                        ctx.get(dut.i.ready))
        # A fresh sample after clear: E[n-1] = 0 and I = 0, as a new model.
        ctx.set(dut.i.payload, {"ref": 0, "fb": -3000})
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        ctx.set(dut.i.valid, 0)
        *_, out, integ = await ctx.tick().sample(dut.o.payload, dut.integrator).until(dut.o.valid)
        log["fresh"] = (out, integ)

    simulate(dut, [testbench], name="pi_clear")
    assert log["before"][0] > 3000 and log["before"][1] > 0
    assert log["during"] == ([1, 1, 1], 0)
    assert log["after"] == (0, 0, 0, 0, 1)
    model = PIModel()
    want = model.step(0, -3000, KP_ONE, KX_ONE // 8, LO, HI)[0], model.integrator
    assert log["fresh"] == want


def test_pi_tustin_step_response():
    # Float Tustin PI: O = Kp·E + I, I[n] = I[n-1] + Kx·(E[n] + E[n-1]), no limits reached.
    kp, kx, n, g = 300, 1500, 200, 8                 # Kp = 1.171875, Kx = 0.02288818359375
    err = np.r_[np.zeros(5, dtype=np.int64), np.full(n - 5, 100)]
    s = samples_of(err, 0, kp=kp, kx=kx)
    got = np.array([g_[0] for g_ in drive(PI(), s)])
    ideal, integ, e_prev = [], 0.0, 0.0
    for e in err.astype(float):
        integ += kx / 2**16 * (e + e_prev)
        e_prev = e
        ideal.append(kp / 2**8 * e + integ)
    ideal = np.array(ideal)
    # Each dI is rounded to 2^-g (≤ 2^-(g+1) error each), plus the final rounding to 1 LSB.
    bound = 0.5 + np.arange(1, n + 1) * 2.0 ** -(g + 1)
    assert np.all(np.abs(got - ideal) <= bound)
    assert got[-1] > 900 and np.all(np.diff(got[5:]) >= 0)


def test_pi_latency():
    dut = PI()
    trace = []

    async def testbench(ctx):
        ctx.set(dut.kp, KP_ONE)
        ctx.set(dut.lim_lo, LO)
        ctx.set(dut.lim_hi, HI)
        # Previous output 1234 held until the next strobe.
        ctx.set(dut.i.payload, {"ref": 1234, "fb": 0})
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        ctx.set(dut.i.payload, {"ref": -77, "fb": 0})
        while not ctx.get(dut.o.valid):
            await ctx.tick()
        # Cycle 0: strobe of 1234 and acceptance of -77; i.valid stays high throughout.
        for cycle in range(2 * dut.latency + 1):
            trace.append((cycle, ctx.get(dut.i.ready), ctx.get(dut.o.valid),
                          ctx.get(dut.o.payload)))
            await ctx.tick()
            if cycle == 0:
                ctx.set(dut.i.payload, {"ref": 555, "fb": 0})

    simulate(dut, [testbench], name="pi_latency")
    lat = dut.latency
    for cycle, ready, valid, out in trace:
        if cycle == 0:
            assert (ready, valid, out) == (1, 1, 1234)
        elif cycle < lat:
            assert (ready, valid, out) == (0, 0, 1234), cycle
        elif cycle == lat:
            assert (ready, valid, out) == (1, 1, -77), cycle     # next input accepted here
        else:
            assert ready == (cycle == 2 * lat) and valid == (cycle == 2 * lat), cycle
            assert out == (555 if cycle == 2 * lat else -77), cycle
    assert dut.interval == lat


def test_pi_random_vs_model():
    r = run(2500, seed=1)
    assert r["mismatches"] == 0, r["first_mismatch"]
    assert r["vectors"] >= 2500 and r["clocks"] >= r["vectors"] * 6
    for key in ("saturated_samples", "windup_samples", "held_samples", "recoveries",
                "error_saturations", "clears"):
        assert r[key] > 0, key


@pytest.mark.parametrize("params", [
    dict(width=12, kp_format=Q(12, 6), kx_format=UQ(10, 14), int_guard=0),
    dict(width=16, kp_format=Q(16, 12), kx_format=Q(18, 20), int_guard=4),
    dict(width=8, kp_format=UQ(8, 2), kx_format=UQ(8, 3), int_guard=12),
])
def test_pi_random_vs_model_other_formats(params):
    r = run(600, seed=2, **params)
    assert r["mismatches"] == 0, r["first_mismatch"]


def test_pi_converts_to_verilog():
    # o.ready is Const(1) (always_ready), which convert() cannot take as a port
    # (amaranth-lang/amaranth#1574): list the signal ports explicitly.
    dut = PI()
    ports = [Value.cast(value) for _, _, value in dut.signature.flatten(dut)]
    text = verilog.convert(dut, name="pi", ports=[p for p in ports if isinstance(p, Signal)])
    assert re.search(r"^module pi\(", text, re.M)
    for port in (r"input \[31:0\] i__payload", r"output \[15:0\] o__payload",
                 r"input \[15:0\] kp", r"input clear", r"output \[23:0\] integrator"):
        assert re.search(rf"^\s*{port};", text, re.M), port


@pytest.mark.slow
def test_pi_100k_vs_model():
    r = run(100_000)
    assert r["mismatches"] == 0, r["first_mismatch"]
    assert r["vectors"] >= 100_000
    for key in ("saturated_samples", "windup_samples", "recoveries", "clears"):
        assert r[key] > 100, key
