# amaranth: UnusedElaboratable=no
# Ref: paper eq. (1); SPEC.md §1 (Clarke transform) and §2 (current scaling)
import math
import re

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Const, Value, signed, unsigned

import foc_servo.sim.verify.clarke as verify_clarke
from foc_servo.hdl.clarke import Clarke, clarke_constants
from foc_servo.hdl.fixed import Q, UQ
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import clarke as model

OUTPUTS = ("a", "b", "c", "alpha", "beta")


def run_cycles(dut, cycles):
    """Drive ``dut`` one clock per entry of ``cycles`` and record the outputs cycle by cycle.

    Each entry is ``None`` (``i.valid`` low, inputs unchanged) or a dict with ``code`` (per phase),
    optionally ``gain`` and ``offset`` (per phase; they stay as set until changed) and ``valid``
    (default true). Returns a list, one per clock from the first input clock on, of
    ``(valid, {output: value})`` as seen during that clock.
    """
    record = []

    async def testbench(ctx):
        for entry in list(cycles) + [None] * (dut.latency + 1):
            if entry is None:
                ctx.set(dut.i.valid, 0)
            else:
                ctx.set(dut.i.valid, entry.get("valid", True))
                ctx.set(dut.i.payload, {p: entry["code"][k] for k, p in enumerate(dut.phases)})
                for key in ("gain", "offset"):
                    if key in entry:
                        for k, p in enumerate(dut.phases):
                            ctx.set(getattr(dut, f"{key}_{p}"), entry[key][k])
            valid = ctx.get(dut.o.valid)
            payload = ctx.get(dut.o.payload)
            record.append((valid, {n: payload[n] for n in OUTPUTS}))
            await ctx.tick()

    simulate(dut, [testbench], name="test_clarke")
    return record


def run_samples(dut, samples):
    """Outputs (dict of int64 arrays) for back-to-back samples; checks their count."""
    record = run_cycles(dut, samples)
    got = [out for valid, out in record if valid]
    assert len(got) == len(samples)
    return {n: np.array([g[n] for g in got], dtype=np.int64) for n in OUTPUTS}


def model_of(dut, samples):
    codes, kwargs = [], {}
    for k, p in enumerate(dut.phases):
        codes.append(np.array([s["code"][k] for s in samples]))
        kwargs[f"gain_{p}"] = np.array([s["gain"][k] for s in samples])
        kwargs[f"offset_{p}"] = np.array([s["offset"][k] for s in samples])
    return model.clarke(*codes, **kwargs, width=dut.width, gain_frac=dut.gain_format.frac,
                        three_phase=dut.three_phase)


@pytest.mark.parametrize("kwargs, exc, message", [
    ({"width": 7}, TypeError, "Clarke width must be an integer from 8 to 28, not 7"),
    ({"width": 29}, TypeError, "Clarke width must be an integer from 8 to 28, not 29"),
    ({"width": 16.0}, TypeError, "Clarke width must be an integer from 8 to 28, not 16.0"),
    ({"width": True}, TypeError, "Clarke width must be an integer from 8 to 28, not True"),
    ({"adc_shape": 16}, TypeError,
     "Clarke adc_shape must be a Shape such as signed(16), not 16"),
    ({"adc_shape": signed(1)}, TypeError,
     "Clarke adc_shape must be 2 to 24 bits wide, not signed(1)"),
    ({"adc_shape": unsigned(25)}, TypeError,
     "Clarke adc_shape must be 2 to 24 bits wide, not unsigned(25)"),
    ({"gain_format": signed(18)}, TypeError,
     "Clarke gain_format must be a QFormat, not signed(18)"),
    ({"gain_format": UQ(18, 15)}, ValueError,
     "Clarke gain_format must be signed, not UQ(18, 15)"),
    ({"gain_format": Q(33, 15)}, TypeError,
     "Clarke gain_format must be 2 to 32 bits wide with 0 to 62 fractional bits, not Q(33, 15)"),
    ({"gain_format": Q(18, -1)}, TypeError,
     "Clarke gain_format must be 2 to 32 bits wide with 0 to 62 fractional bits, not Q(18, -1)"),
    ({"three_phase": 1}, TypeError, "Clarke three_phase must be a bool, not 1"),
])
def test_clarke_rejects_bad_parameters(kwargs, exc, message):
    with pytest.raises(exc, match=f"^{re.escape(message)}$"):
        Clarke(**kwargs)


def test_clarke_interface_members():
    dut = Clarke(adc_shape=unsigned(12), gain_format=Q(20, 14), width=18, three_phase=True)
    assert dut.i.payload.shape().size == 36
    for p in "abc":
        assert dut.i.payload[p].shape() == unsigned(12)
        assert getattr(dut, f"gain_{p}").shape() == signed(20)
        assert getattr(dut, f"offset_{p}").shape() == signed(13)
    for n in OUTPUTS:
        assert dut.o.payload[n].shape() == signed(18)
    assert not hasattr(Clarke(), "gain_c") and not hasattr(Clarke(), "offset_c")


@pytest.mark.parametrize("width", range(8, 29))
def test_clarke_constants_error_below_quarter_lsb(width):
    frac, k_beta, k_alpha = clarke_constants(width)
    assert frac == width + 2
    assert (frac, k_beta, k_alpha) == model.clarke_constants(width)
    # Worst-case sums: |i_a + 2 i_b| <= 3 * 2**(w-1) (β), |2 i_a - i_b - i_c| <= 2**(w+1) (α).
    err_beta = 3 * 2 ** (width - 1) * abs(k_beta - 2 ** frac / math.sqrt(3)) / 2 ** frac
    err_alpha = 2 ** (width + 1) * abs(k_alpha - 2 ** frac / 3) / 2 ** frac
    assert err_beta < 0.25 and err_alpha < 0.25
    dut = Clarke(width=width, three_phase=True)
    assert (dut.const_frac, dut.k_beta, dut.k_alpha) == (frac, k_beta, k_alpha)


def test_clarke_scaling_offset_gain():
    one = 1 << 15                   # 1.0 in Q(18, 15)
    dut = Clarke()
    samples = [
        # (code_a, code_b, gain_a, gain_b, offset_a, offset_b) -> (i_a, i_b)
        ((1000, -3), (one // 2, one // 2), (200, 0)),     # 0.5 * 800 = 400; -1.5 -> -2
        ((3, 1), (one // 2, one // 2), (0, 0)),           # 1.5 -> 2 (half away); 0.5 -> 1
        ((-1, 1000), (one // 2, -one), (0, 0)),           # -0.5 -> -1; polarity inverted: -1000
        ((-2000, 32767), (5 * one // 4, one), (100, -32768)),  # -2625; 65535 saturates
    ]
    got = run_samples(dut, [{"code": c, "gain": g, "offset": o} for c, g, o in samples])
    np.testing.assert_array_equal(got["a"], [400, 2, -1, -2625])
    np.testing.assert_array_equal(got["b"], [-2, 1, -1000, 32767])
    np.testing.assert_array_equal(got["c"], [-398, -3, 1001, -30142])
    np.testing.assert_array_equal(got["alpha"], got["a"])
    beta_ideal = (got["a"] + 2 * got["b"]) / math.sqrt(3)
    np.testing.assert_array_equal(got["beta"], np.clip(np.round(beta_ideal), -32768, 32767))
    assert got["beta"].tolist() == [229, 2, -1155, 32767]

    # Straight-binary 12-bit ADC, mid-scale offset, gain 16 maps the ADC range onto Q1.15.
    dut = Clarke(adc_shape=unsigned(12), gain_format=Q(18, 12))
    g16 = 16 << 12
    samples = [{"code": (4095, 0), "gain": (g16, g16), "offset": (2048, 2048)},
               {"code": (2048, 2049), "gain": (g16, -g16), "offset": (2048, 2048)}]
    got = run_samples(dut, samples)
    np.testing.assert_array_equal(got["a"], [32752, 0])
    np.testing.assert_array_equal(got["b"], [-32768, -16])
    np.testing.assert_array_equal(got["c"], [16, 16])
    np.testing.assert_array_equal(got["beta"], [round((32752 - 65536) / math.sqrt(3)),
                                                round(-32 / math.sqrt(3))])


def balanced(amplitude, gain, offset, frac, adc_shape, n=720, seed=0):
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-math.pi, math.pi, n)
    g_raw = round(gain * 2 ** frac)
    g = g_raw / 2 ** frac
    codes = [np.rint(amplitude / g * np.cos(theta - k * 2 * math.pi / 3)).astype(int) + offset
             for k in range(3)]
    lo, hi = (-(1 << (adc_shape.width - 1)), (1 << (adc_shape.width - 1)) - 1) \
        if adc_shape.signed else (0, (1 << adc_shape.width) - 1)
    assert all(lo <= c.min() and c.max() <= hi for c in codes)
    return theta, codes, g_raw


@pytest.mark.parametrize("three_phase", [False, True], ids=["two_phase", "three_phase"])
@pytest.mark.parametrize("amplitude, gain, offset, frac, adc_shape", [
    (32000, 1.0, 0, 15, signed(16)),
    (24000, 0.75, 123, 15, signed(16)),
    (31000, 0.06, 1 << 19, 12, unsigned(20)),
], ids=["unity", "gain0.75", "adc20u"])
def test_clarke_two_phase_balanced(three_phase, amplitude, gain, offset, frac, adc_shape):
    # Balanced sinusoidal currents of amplitude A: |(α, β)| = A within ~1 LSB, angle θ.
    dut = Clarke(adc_shape=adc_shape, gain_format=Q(18, frac), three_phase=three_phase)
    theta, codes, g = balanced(amplitude, gain, offset, frac, adc_shape)
    nph = len(dut.phases)
    samples = [{"code": tuple(int(c[k]) for c in codes[:nph]), "gain": (g,) * nph,
                "offset": (offset,) * nph} for k in range(theta.size)]
    got = run_samples(dut, samples)
    exp = model_of(dut, samples)
    for n in OUTPUTS:
        np.testing.assert_array_equal(got[n], exp[n])
    assert not exp["saturated"].any()

    # The block's own error against the float Clarke of its own scaled phase currents:
    # rounding (1/2 LSB) plus the constant's error (< 1/4 LSB).
    a, b, c = got["a"], got["b"], got["c"]
    if three_phase:
        alpha_f, beta_f = (2 * a - b - c) / 3, (b - c) / math.sqrt(3)
    else:
        alpha_f, beta_f = a, (a + 2 * b) / math.sqrt(3)
        np.testing.assert_array_equal(c, -a - b)
    assert np.abs(got["alpha"] - alpha_f).max() <= 0.5 + 1 / 6
    assert np.abs(got["beta"] - beta_f).max() <= 0.5 + 3 / 16

    # Against the ideal: magnitude and angle (the phase currents carry their own quantisation).
    mag = np.hypot(got["alpha"], got["beta"])
    err = mag - amplitude
    assert np.sqrt(np.mean(err ** 2)) < 0.6
    assert np.abs(err).max() < 2.0
    angle_err = np.angle(np.exp(1j * (np.arctan2(got["beta"], got["alpha"]) - theta)))
    assert np.abs(angle_err).max() < 2.0 / amplitude


def test_clarke_three_phase_rejects_zero_sequence():
    dut = Clarke(three_phase=True)
    one = 1 << 15
    theta, codes, _ = balanced(20000, 1.0, 0, 15, signed(16), n=256, seed=3)
    rng = np.random.default_rng(4)
    zero_seq = rng.integers(-8000, 8001, theta.size)
    plain = [{"code": tuple(int(c[k]) for c in codes), "gain": (one,) * 3, "offset": (0,) * 3}
             for k in range(theta.size)]
    common = [{"code": tuple(int(c[k] + zero_seq[k]) for c in codes), "gain": (one,) * 3,
               "offset": (0,) * 3} for k in range(theta.size)]
    got_plain = run_samples(dut, plain)
    got_common = run_samples(dut, common)
    # Unity gains scale the common mode exactly: α and β do not move by a single LSB, while the
    # phase currents do carry it.
    np.testing.assert_array_equal(got_common["alpha"], got_plain["alpha"])
    np.testing.assert_array_equal(got_common["beta"], got_plain["beta"])
    np.testing.assert_array_equal(got_common["a"] - got_plain["a"], zero_seq)
    np.testing.assert_array_equal(got_common["c"] - got_plain["c"], zero_seq)
    # A pure common mode gives exactly zero.
    pure = [{"code": (int(z),) * 3, "gain": (3 * one // 4,) * 3, "offset": (-77,) * 3}
            for z in zero_seq[:32]]
    got = run_samples(dut, pure)
    assert not got["alpha"].any() and not got["beta"].any()
    assert got["a"].any()


def test_clarke_saturates_extremes():
    g_max, g_min = (1 << 17) - 1, -(1 << 17)
    c_max, c_min = 32767, -32768
    o_max, o_min = 65535, -65536
    dut = Clarke()
    samples = [
        {"code": (c_max, c_max), "gain": (g_max, g_max), "offset": (o_min, o_min)},
        {"code": (c_max, c_max), "gain": (g_min, g_min), "offset": (o_min, o_min)},
        {"code": (c_min, c_min), "gain": (g_min, g_max), "offset": (o_max, o_max)},
        {"code": (c_min, c_max), "gain": (0, 0), "offset": (o_max, o_min)},
        {"code": (c_max, c_min), "gain": (g_min, g_max), "offset": (c_max, c_min)},
    ]
    got = run_samples(dut, samples)
    assert got["a"].tolist() == [32767, -32768, 32767, 0, 0]
    assert got["b"].tolist() == [32767, -32768, -32768, 0, 0]
    assert got["c"].tolist() == [-32768, 32767, 1, 0, 0]        # -a - b saturated, not wrapped
    assert got["alpha"].tolist() == got["a"].tolist()
    assert got["beta"].tolist() == [32767, -32768, round(-32769 / math.sqrt(3)), 0, 0]
    exp = model_of(dut, samples)
    for n in OUTPUTS:
        np.testing.assert_array_equal(got[n], exp[n])
    assert exp["saturated"].tolist() == [True, True, True, False, False]

    dut = Clarke(three_phase=True)
    samples = [
        {"code": (c_max, c_min, c_min), "gain": (g_max, g_max, g_max), "offset": (o_min, 0, 0)},
        {"code": (c_min, c_max, c_min), "gain": (1 << 15,) * 3, "offset": (0, 0, 0)},
        {"code": (c_max, c_min, c_max), "gain": (g_min, g_min, g_min), "offset": (o_min, 0, 0)},
    ]
    got = run_samples(dut, samples)
    assert got["a"].tolist() == [32767, -32768, -32768]
    assert got["b"].tolist() == [-32768, 32767, 32767]
    assert got["c"].tolist() == [-32768, -32768, -32768]
    # 2a - b - c = 131070 -> 43690 -> 32767;  -65535 / 3 = -21845;  (b - c) = 65535 -> 37837.
    assert got["alpha"].tolist() == [32767, -21845, -21845]
    assert got["beta"].tolist() == [0, 32767, 32767]


def test_clarke_latency():
    one = 1 << 15
    dut = Clarke()
    assert dut.latency == 6
    first = {"code": (100, 200), "gain": (one, one), "offset": (0, 0)}
    second = {"code": (-7, 5), "gain": (2 * one, one), "offset": (1, 0)}
    # One sample, a gap of three clocks with junk codes, gains and offsets (i.valid low), then three
    # samples back to back, the last with new gains while the others are in flight.
    junk = {"valid": False, "code": (-999, 999), "gain": (3, -one), "offset": (-5, 7)}
    cycles = [first, junk, None, junk, second, first,
              {"code": (1, 1), "gain": (-one, -one), "offset": (0, 0)}]
    record = run_cycles(dut, cycles)
    valid = [v for v, _ in record]
    lat = dut.latency
    expected_valid = [0] * len(record)
    for k, entry in enumerate(cycles):
        if entry is not None and entry.get("valid", True):
            expected_valid[k + lat] = 1
    assert valid == expected_valid
    assert record[lat][1]["a"] == 100 and record[lat][1]["b"] == 200
    assert record[lat][1]["beta"] == round(500 / math.sqrt(3))
    # Between samples the output holds the last valid result.
    for k in range(lat + 1, lat + 4):
        assert record[k][1] == record[lat][1]
    assert (record[lat + 4][1]["a"], record[lat + 4][1]["b"]) == (-16, 5)
    # The new gains of the last sample do not reach the samples already in flight.
    assert (record[lat + 5][1]["a"], record[lat + 5][1]["b"]) == (100, 200)
    assert (record[lat + 6][1]["a"], record[lat + 6][1]["b"]) == (-1, -1)
    # Nothing before the first sample arrives: outputs still at their reset value.
    for k in range(lat):
        assert record[k][1] == dict.fromkeys(OUTPUTS, 0)


@pytest.mark.parametrize("three_phase", [False, True], ids=["two_phase", "three_phase"])
def test_clarke_random_vs_model(three_phase):
    r = verify_clarke.run(3000, seed=1, three_phase=three_phase)
    assert r["mismatches"] == 0, r
    assert r["vectors"] > 3000 and r["saturated_vectors"] > 100
    assert r["clocks"] > r["vectors"]                    # i.valid gaps were exercised
    r = verify_clarke.run(1000, seed=2, three_phase=three_phase, width=12,
                          adc_shape=unsigned(14), gain_format=Q(16, 10))
    assert r["mismatches"] == 0, r


@pytest.mark.parametrize("mul_width", [None, 16, 12])
def test_clarke_random_vs_model_at_other_multiplier_widths(mul_width):
    """Unsplit products (the iCE40's setting), 16 and a narrower split: other partial products,
    the same bits."""
    dut = Clarke(mul_width=mul_width)
    assert dut.mul_width == mul_width
    r = verify_clarke.run(1500, seed=3, mul_width=mul_width)
    assert r["mismatches"] == 0, r
    assert r["saturated_vectors"] > 50


def test_clarke_bench_detects_a_wrong_output(monkeypatch):
    # The verification must be able to fail: corrupt one expected bit of one vector.
    real = verify_clarke.clarke_model

    def corrupted(*args, **kwargs):
        out = real(*args, **kwargs)
        out["beta"] = out["beta"].copy()
        out["beta"][1234] ^= 1
        return out

    monkeypatch.setattr(verify_clarke, "clarke_model", corrupted)
    r = verify_clarke.run(2000, seed=5, three_phase=False)
    assert r["mismatches"] == 1
    assert r["two_phase"]["first_mismatch"] == 1234


@pytest.mark.parametrize("three_phase", [False, True], ids=["two_phase", "three_phase"])
def test_clarke_converts_to_verilog(three_phase):
    dut = Clarke(three_phase=three_phase)
    # amaranth 0.5.10's convert() cannot take a Component whose interface holds constants (the
    # always-ready `i.ready`, amaranth-lang/amaranth#1574): list the ports, leaving those out.
    ports = [Value.cast(value) for _, _, value in dut.signature.flatten(dut)]
    ports = [port for port in ports if not isinstance(port, Const)]
    assert len(ports) == 4 + 2 * len(dut.phases)        # i/o payload and valid; gains; offsets
    text = verilog.convert(dut, name="clarke", ports=ports)
    assert "module clarke" in text and "o__payload" in text


@pytest.mark.slow
def test_clarke_100k_vs_model():
    r = verify_clarke.run(100_000, seed=0)
    assert r["mismatches"] == 0, r
    for mode in ("two_phase", "three_phase"):
        assert r[mode]["mismatches"] == 0
        assert r[mode]["vectors"] >= 100_000
        assert r[mode]["saturated_vectors"] > 1000
