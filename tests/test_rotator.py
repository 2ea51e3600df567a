# amaranth: UnusedElaboratable=no
# Ref: paper eq. (4)–(6) (vector rotation), SPEC.md §2.1; issue 7
"""Tests of :class:`foc_servo.hdl.rotator.Rotator`, its golden model and its verification run."""

import math

import numpy as np
import pytest
from amaranth.back import rtlil, verilog
from amaranth.hdl import Fragment, signed

from foc_servo.hdl.rotator import Rotator, RotatorParams
from foc_servo.sim.models.rotator import rotate, rotate_ideal, rotate_trace, trig
from foc_servo.sim.verify.rotator import corner_cases, run

from rotation_common import (FS, check_corners_saturate_never_wrap, check_latency_cycle_by_cycle,
                             check_park_inverse_park_round_trip,
                             check_park_inverse_park_round_trip_model,
                             check_quarter_turns_and_small_angles, check_zero_vector_stays_zero,
                             model_error_one_million_vectors, signal_ports,
                             random_vectors as _random, simulate_vectors)

def _simulate_vectors(dut, vectors, spacing=None):
    """One vector every ``spacing`` clocks, default the rotator's interval."""
    return simulate_vectors(dut, vectors, dut.interval if spacing is None else spacing)


# --- parameter validation --------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, message", [
    ({"width": 7}, TypeError, r"^Rotator width must be an integer from 8 to 24, not 7$"),
    ({"width": 25}, TypeError, r"^Rotator width must be an integer from 8 to 24, not 25$"),
    ({"width": 16.0}, TypeError, r"^Rotator width must be an integer from 8 to 24, not 16\.0$"),
    ({"width": True}, TypeError, r"^Rotator width must be an integer from 8 to 24, not True$"),
    ({"angle_width": 3}, TypeError,
     r"^Rotator angle_width must be None or an integer of at least 4, not 3$"),
    ({"table_bits": 0}, TypeError,
     r"^Rotator table_bits must be None or a positive integer, not 0$"),
    ({"table_bits": "9"}, TypeError,
     r"^Rotator table_bits must be None or a positive integer, not '9'$"),
    ({"tag_width": -1}, TypeError,
     r"^Rotator tag_width must be a non-negative integer, not -1$"),
    ({"table_bits": 14}, ValueError,
     r"^Rotator table_bits must be at most angle_width − 3 = 13, not 14$"),
    ({"table_bits": 8}, ValueError,
     r"^Rotator table_bits must be at least 9 for width 16 \(interpolation error\), not 8$"),
    ({"width": 12, "angle_width": 18, "table_bits": 7}, ValueError,
     r"^Rotator table_bits must be at least angle_width − 9 = 9, not 7$"),
    ({"registered": 1}, TypeError, r"^Rotator registered must be a bool, not 1$"),
    ({"angle_width": 11}, ValueError,
     r"^Rotator angle_width must be at least 12 for width 16, not 11$"),
])
def test_rotator_parameter_validation(kwargs, exc, message):
    with pytest.raises(exc, match=message):
        Rotator(**kwargs)
    with pytest.raises(exc, match=message):
        rotate([0], [0], [0], **kwargs)


def test_rotator_defaults_and_attributes():
    r = Rotator()
    assert (r.width, r.angle_width, r.table_bits, r.tag_width) == (16, 16, 9, 0)
    assert (r.latency, r.interval, r.registered) == (6, 4, False)
    r2 = Rotator(registered=True)
    assert (r2.latency, r2.interval, r2.registered) == (9, 5, True)
    p = r.params
    assert p.interp_bits == 4 and p.table_frac == 18
    assert len(p.table_words) == 512 and max(p.table_words) < 1 << 36
    # kd(D) is the largest value below 2**(W−1) at this shift; the ROM folds the mirror in.
    assert p.kd[-1] < 1 << 15 <= round(2 * p.kd[-1])
    assert p.kd_rom == p.kd[:16] + [p.kd[16 - d] for d in range(16)]
    # Wide angles raise the default table size to keep the kd ROM small.
    assert RotatorParams(angle_width=20).table_bits == 11
    assert RotatorParams(width=8).table_bits == 5
    assert RotatorParams(width=24).table_bits == 15
    assert RotatorParams(width=12, angle_width=16).table_bits == 7
    with pytest.raises(AttributeError):
        r.latency = 3
    Fragment.get(r, None)


def test_rotator_payload_layouts_match_the_cordic():
    r = Rotator(width=12, angle_width=14, tag_width=3)
    assert set(r.i.payload.shape().members) == {"x", "y", "theta", "tag"}
    assert r.i.payload.shape()["theta"].shape.width == 14
    assert r.o.payload.shape()["x"].shape == signed(12)
    assert set(r.o.payload.shape().members) == {"x", "y", "tag"}
    Fragment.get(r, None)
    r = Rotator()
    assert set(r.o.payload.shape().members) == {"x", "y"}
    assert "tag" not in r.i.payload.shape().members


# --- golden model ----------------------------------------------------------------------------

def test_rotator_trig_every_angle_against_float():
    # Every one of the 2**16 angles: the integer sine and cosine against math.sin/cos, and
    # the multiplier operands within signed(16).
    theta = np.arange(1 << 16)
    t = trig(theta)
    rad = theta * 2 * math.pi / (1 << 16)
    err = np.concatenate([t["cos"] - np.cos(rad) * 2 ** 16, t["sin"] - np.sin(rad) * 2 ** 16])
    assert np.max(np.abs(err)) <= 0.75          # rounding 0.5 + table/interpolation; meas. 0.70
    for name in ("s_o", "c_o"):
        assert -FS <= t[name].min() and t[name].max() < FS
    # Exact at the quarter turns (gain exactly 1) and sin = cos at 45°.
    q = theta[::1 << 14]
    assert list(t["cos"][q]) == [1 << 16, 0, -(1 << 16), 0]
    assert list(t["sin"][q]) == [0, 1 << 16, 0, -(1 << 16)]
    e = (1 << 13) + np.arange(4) * (1 << 14)
    assert np.all(np.abs(t["cos"][e]) == np.abs(t["sin"][e]))
    # The folding covers the octant exactly: a = k·D + d runs over 0 … 8192.
    a = t["k"] * 16 + t["d"]
    assert a.min() == 0 and a.max() == 1 << 13 and np.all((t["d"] >= 0) & (t["d"] <= 16))


@pytest.mark.parametrize("params", [
    {"width": 8}, {"width": 12, "angle_width": 16}, {"width": 18, "angle_width": 20},
    {"width": 24}, {"width": 10}, {"width": 16, "angle_width": 19, "table_bits": 10},
])
def test_rotator_trig_operands_fit_other_configurations(params):
    p = RotatorParams(**params)
    theta = np.arange(0, 1 << p.angle_width, 1 << max(0, p.angle_width - 16))
    t = trig(theta, **params)
    lo, hi = -(1 << (p.width - 1)), (1 << (p.width - 1)) - 1
    for name in ("s_o", "c_o", "kd"):
        assert lo <= t[name].min() and t[name].max() <= hi
    rad = theta * 2 * math.pi / (1 << p.angle_width)
    scale = 2.0 ** p.width
    assert np.max(np.abs(t["cos"] - np.cos(rad) * scale)) <= 0.75
    assert np.max(np.abs(t["sin"] - np.sin(rad) * scale)) <= 0.75


def test_rotator_model_against_float_one_million_vectors():
    err = model_error_one_million_vectors(rotate, rotate_ideal, corner_cases)
    assert np.max(np.abs(err)) <= 1.1            # measured 0.985 (CORDIC ≈ 0.9)
    assert math.sqrt(np.mean(err ** 2)) <= 0.31  # measured 0.303 (CORDIC ≈ 0.30)


@pytest.mark.parametrize("params", [{"width": 8}, {"width": 12, "angle_width": 16},
                                    {"width": 20}, {"width": 24}])
def test_rotator_model_against_float_other_widths(params):
    p = RotatorParams(**params)
    x, y, theta = _random(200_000, seed=12, width=p.width, angle_width=p.angle_width)
    gx, gy = rotate(x, y, theta, **params)
    ix, iy = rotate_ideal(x, y, theta, width=p.width, angle_width=p.angle_width)
    err = np.concatenate([gx - ix, gy - iy])
    assert np.max(np.abs(err)) <= 1.1 and math.sqrt(np.mean(err ** 2)) <= 0.32


def test_rotator_corners_saturate_never_wrap():
    check_corners_saturate_never_wrap(rotate)


def test_rotator_quarter_turns_exact_and_small_angles():
    turn = 1 << 16
    check_quarter_turns_and_small_angles(rotate, rotate_ideal, (1, turn - 1, turn // 2 - 1,
                                                                turn // 8 - 1, turn // 8 + 1))
    # Every x, y of a grid passes θ = 0 unchanged and is swapped/negated exactly by π/2.
    g = np.arange(-FS, FS, 257)
    gx, gy = np.meshgrid(g, g)
    gx, gy = gx.ravel(), gy.ravel()
    ox, oy = rotate(gx, gy, 0)
    np.testing.assert_array_equal(ox, gx)
    np.testing.assert_array_equal(oy, gy)
    ox, oy = rotate(gx, gy, turn // 4)
    np.testing.assert_array_equal(ox, np.minimum(-gy, FS - 1))
    np.testing.assert_array_equal(oy, gx)


def test_rotator_odd_symmetric_and_zero_vector():
    # Half away from zero everywhere: rotating −v gives exactly −(rotated v) (no saturation
    # inside ±(2**15 − 1)/√2).
    x, y, theta = _random(200_000, seed=15)
    x, y = x // 2, y // 2
    ax, ay = rotate(x, y, theta)
    bx, by = rotate(-x, -y, theta)
    np.testing.assert_array_equal(bx, -ax)
    np.testing.assert_array_equal(by, -ay)
    check_zero_vector_stays_zero(rotate)


def test_rotator_park_inverse_park_round_trip_model():
    check_park_inverse_park_round_trip_model(rotate)


def test_rotator_model_trace_sums_exact():
    x, y, theta = _random(50_000, seed=16)
    t = rotate_trace(x, y, theta)
    # Σ = x·cos − y·sin at scale 2**16 is within a 2**16·(|x| + |y|)·0.75·2**−16 of the float.
    rad = theta * 2 * math.pi / (1 << 16)
    ideal = (x * np.cos(rad) - y * np.sin(rad)) * 2 ** 16
    assert np.all(np.abs(t["sigma_x"] - ideal) <= (np.abs(x) + np.abs(y)) * 0.75 + 1)


# --- gateware --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs", [{}, {"width": 12, "tag_width": 2},
                                    {"registered": True, "tag_width": 2}])
def test_rotator_latency_cycle_by_cycle(kwargs):
    model = {k: v for k, v in kwargs.items() if k != "tag_width"}
    check_latency_cycle_by_cycle(Rotator(**kwargs), lambda x, y, t: rotate(x, y, t, **model))


def test_rotator_named_corners_gateware_bit_exact():
    dut = Rotator()
    x, y, theta = corner_cases()
    out = _simulate_vectors(dut, [{"x": int(a), "y": int(b), "theta": int(t)}
                                  for a, b, t in zip(x, y, theta)])
    ex, ey = rotate(x, y, theta)
    np.testing.assert_array_equal(np.array(out), np.stack([ex, ey], axis=1))


def _rounding_edge_vectors(count=2_000_000, seed=21):
    """Vectors whose exact sum Σx or Σy lies at a rounding tie (±2**15 mod 2**16) or one off,
    of both signs, plus ones that round exactly onto the saturation limits."""
    x, y, theta = _random(count, seed)
    t = rotate_trace(x, y, theta)
    pick = np.zeros(count, dtype=bool)
    for name in ("sigma_x", "sigma_y"):
        frac = t[name] % (1 << 16)
        for off in (-1, 0, 1):
            for sign in (-1, 1):
                hit = np.flatnonzero((frac == (1 << 15) + off) & (np.sign(t[name]) == sign))
                pick[hit[:4]] = True
        for limit in ((FS - 1) << 16, -FS << 16):
            hit = np.flatnonzero(np.abs(t[name] - limit) < 1 << 15)
            pick[hit[:4]] = True
    return x[pick], y[pick], theta[pick]


@pytest.mark.parametrize("registered", [False, True])
def test_rotator_rounding_ties_and_limits_gateware_bit_exact(registered):
    x, y, theta = _rounding_edge_vectors()
    t = rotate_trace(x, y, theta)
    ties = np.concatenate([t["sigma_x"], t["sigma_y"]]) % (1 << 16) == 1 << 15
    assert len(x) >= 40 and np.count_nonzero(ties) >= 8
    dut = Rotator(registered=registered)
    out = _simulate_vectors(dut, [{"x": int(a), "y": int(b), "theta": int(c)}
                                  for a, b, c in zip(x, y, theta)])
    np.testing.assert_array_equal(np.array(out), np.stack([t["x"], t["y"]], axis=1))


@pytest.mark.parametrize("registered, latency, interval", [(False, 6, 4), (True, 9, 5)])
def test_rotator_random_vectors_gateware_vs_model(registered, latency, interval):
    r = run(3000, seed=1, registered=registered)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["vectors"] == 3000 + len(corner_cases()[0])
    assert r["latency_clk"] == latency
    assert r["throughput_per_clk"] == 1 / interval
    assert r["max_err_lsb"] <= 2.0 and r["rms_err_lsb"] <= 0.7


@pytest.mark.parametrize("params, spacing", [
    ({"width": 8}, None),
    ({"width": 12, "angle_width": 16, "tag_width": 2}, 5),
    ({"width": 10}, None),                                  # m = 0: d = 1 for the mirror
    ({"width": 12, "angle_width": 16, "table_bits": 7}, 9),  # m = 6, the largest kd ROM
    ({"width": 18, "angle_width": 20, "tag_width": 1}, None),
    ({"width": 24}, None),
    ({"width": 12, "tag_width": 3, "registered": True}, 6),
])
def test_rotator_other_configurations_vs_model(params, spacing):
    r = run(300, seed=3, spacing=spacing, **params)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["latency_clk"] == Rotator(**params).latency
    assert r["max_err_lsb"] <= 1.1


@pytest.mark.parametrize("registered", [False, True])
def test_rotator_rejects_vectors_closer_than_the_interval(registered):
    dut = Rotator(registered=registered)
    vectors = [{"x": 100, "y": 200, "theta": 300}] * 3
    with pytest.raises(AssertionError, match=rf"^Assertion violated: Rotator: a new vector "
                                             rf"less than {dut.interval} clocks after"):
        _simulate_vectors(dut, vectors, spacing=dut.interval - 1)


def test_rotator_park_inverse_park_round_trip_gateware():
    check_park_inverse_park_round_trip(Rotator(tag_width=16), Rotator(), n=100, spacing=4)


def test_rotator_table_is_a_synchronous_memory():
    # One memory of 2**table_bits words, read through a synchronous port: what yosys maps to
    # SB_RAM40_4K / DP16KD / RAMB18 (the area runs in docs/AREA.md check the mapping).
    dut = Rotator(tag_width=1)
    ports = signal_ports(dut)
    text = rtlil.convert(dut, name="rotator", ports=ports)
    assert text.count("cell $memrd_v2") == 1 and "parameter \\CLK_ENABLE 1\n" in text
    assert "memory width 36 size 512 \\table\n" in text


def test_rotator_converts_to_verilog():
    dut = Rotator(width=12, tag_width=2)
    ports = signal_ports(dut)
    text = verilog.convert(dut, name="rotator", ports=ports)
    assert "module rotator" in text
    for port in ("i__payload", "i__valid", "o__payload", "o__valid"):
        assert port in text


@pytest.mark.slow
@pytest.mark.parametrize("registered", [False, True])
def test_rotator_100k_vectors_targets(registered):
    r = run(100_000, registered=registered)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["vectors"] == 100_000 + len(corner_cases()[0])
    assert r["max_err_lsb"] <= 2.0
    assert r["rms_err_lsb"] <= 0.7
    assert r["latency_clk"] == Rotator(registered=registered).latency
    assert r["throughput_per_clk"] == 1 / Rotator(registered=registered).interval
