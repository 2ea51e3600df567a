# amaranth: UnusedElaboratable=no
# Ref: paper eq. (4)–(6) (CORDIC vector rotation with ±90° pre-rotation), SPEC.md §2.1
"""Tests of :class:`foc_servo.hdl.cordic.Cordic`, its golden model and its verification run."""

import math

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Fragment, signed

from foc_servo.hdl.cordic import Cordic, CordicParams
from foc_servo.sim.models.cordic import rotate, rotate_ideal, rotate_trace
from foc_servo.sim.verify.cordic import corner_cases, run

from rotation_common import (FS, check_latency_cycle_by_cycle,
                             check_park_inverse_park_round_trip, signal_ports,
                             random_vectors as _random, simulate_vectors as _simulate_vectors)


# --- parameter validation --------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, message", [
    ({"width": 3}, TypeError, r"^Cordic width must be an integer of at least 8, not 3$"),
    ({"width": 16.0}, TypeError, r"^Cordic width must be an integer of at least 8, not 16\.0$"),
    ({"width": True}, TypeError, r"^Cordic width must be an integer of at least 8, not True$"),
    ({"stages": 3}, TypeError,
     r"^Cordic stages must be None or an integer of at least 4, not 3$"),
    ({"stages": "18"}, TypeError,
     r"^Cordic stages must be None or an integer of at least 4, not '18'$"),
    ({"angle_width": 3}, TypeError,
     r"^Cordic angle_width must be None or an integer of at least 4, not 3$"),
    ({"guard_bits": -1}, TypeError,
     r"^Cordic guard_bits must be None or a non-negative integer, not -1$"),
    ({"iterations_per_stage": 0}, TypeError,
     r"^Cordic iterations_per_stage must be a positive integer, not 0$"),
    ({"tag_width": -2}, TypeError, r"^Cordic tag_width must be a non-negative integer, not -2$"),
    ({"stages": 6, "iterations_per_stage": 7}, ValueError,
     r"^Cordic iterations_per_stage must be at most stages = 6, not 7$"),
])
def test_cordic_parameter_validation(kwargs, exc, message):
    with pytest.raises(exc, match=message):
        Cordic(**kwargs)
    with pytest.raises(exc, match=message):
        rotate([0], [0], [0], **kwargs)


def test_cordic_defaults_and_latency_formula():
    c = Cordic()
    assert (c.width, c.stages, c.angle_width, c.iterations_per_stage, c.tag_width) == \
        (16, 18, 16, 1, 0)
    p = c.params
    assert c.latency == p.tree_levels + p.stages + 1
    # The gain constant is within 2**-(W+3) of 1/A_n and its CSD digits sum back to it.
    assert abs(p.gain_constant * p.gain / (1 << p.gain_shift) - 1) <= 2.0 ** -19
    assert sum(d << s for d, s in p.gain_digits) == p.gain_constant
    assert all(d in (-1, 1) for d, _ in p.gain_digits)
    for k in (1, 2, 3, 5, p.stages):
        q = CordicParams(iterations_per_stage=k)
        assert q.latency == math.ceil((p.tree_levels + p.stages) / k) + 1
    with pytest.raises(AttributeError):
        c.latency = 3
    Fragment.get(c, None)


def test_cordic_payload_layouts():
    c = Cordic(width=12, angle_width=14, tag_width=3)
    assert set(c.i.payload.shape().members) == {"x", "y", "theta", "tag"}
    assert c.i.payload.shape()["theta"].shape.width == 14
    assert c.o.payload.shape()["x"].shape == signed(12)
    assert set(c.o.payload.shape().members) == {"x", "y", "tag"}
    Fragment.get(c, None)
    c = Cordic()
    assert set(c.o.payload.shape().members) == {"x", "y"}
    assert "tag" not in c.i.payload.shape().members
    Fragment.get(c, None)


# --- golden model ----------------------------------------------------------------------------

def test_cordic_model_against_float_one_million_vectors():
    x, y, theta = _random(1_000_000, seed=11)
    cx, cy, ct = corner_cases()
    x, y, theta = (np.concatenate(a) for a in ((x, cx), (y, cy), (theta, ct)))
    gx, gy = rotate(x, y, theta)
    ix, iy = rotate_ideal(x, y, theta)
    err = np.concatenate([gx - ix, gy - iy])
    assert np.max(np.abs(err)) <= 2.0            # target; measured ≈ 0.9
    assert math.sqrt(np.mean(err ** 2)) <= 0.7   # target; measured ≈ 0.30 (rounding alone: 0.29)
    assert abs(np.mean(err)) < 0.01              # no bias from the floor shifts


def test_cordic_model_internal_values_fit_hardware_widths():
    x, y, theta = _random(200_000, seed=12)
    cx, cy, ct = corner_cases()
    x, y, theta = (np.concatenate(a) for a in ((x, cx), (y, cy), (theta, ct)))
    p = CordicParams()
    t = rotate_trace(x, y, theta)
    limit = 1 << (p.data_width - 1)
    for v in t["xs"] + t["ys"]:
        assert -limit <= v.min() and v.max() < limit
    for (lo, hi), z in zip(p.z_ranges, t["zs"]):
        assert lo <= z.min() and z.max() <= hi
    # The bound is not loose: full-scale corners come within a factor √2·(1 + ε) of the limit.
    assert max(np.abs(v).max() for v in t["xs"] + t["ys"]) > limit / 2


def test_cordic_corners_saturate_never_wrap():
    p = CordicParams()
    turn = 1 << p.angle_width
    # (32767, 32767) by +45° → (0, 46341): y saturates to +32767.
    ox, oy = rotate([FS - 1, -FS, -FS], [FS - 1, -FS, FS - 1], [turn // 8, turn // 8, 0])
    assert abs(ox[0]) <= 1 and oy[0] == FS - 1
    # (−32768, −32768) by +45° → (0, −46341): saturates to −32768.
    assert abs(ox[1]) <= 1 and oy[1] == -FS
    # θ = 0 of (−32768, 32767) passes through.
    assert (ox[2], oy[2]) == (-FS, FS - 1)
    # θ = −π (raw 0x8000) negates; −(−32768) saturates to +32767.
    ox, oy = rotate([-FS, 12345], [FS - 1, -FS], [turn // 2, turn // 2])
    assert (ox[0], oy[0]) == (FS - 1, -(FS - 1))
    assert (ox[1], oy[1]) == (-12345, FS - 1)


def test_cordic_quarter_turns_and_small_angles():
    p = CordicParams()
    turn = 1 << p.angle_width
    x, y = 20000, -7000
    assert tuple(int(v[0]) for v in rotate([x], [y], [turn // 4])) == (-y, x)        # +π/2
    assert tuple(int(v[0]) for v in rotate([x], [y], [3 * turn // 4])) == (y, -x)    # −π/2
    assert tuple(int(v[0]) for v in rotate([x], [y], [0])) == (x, y)
    # ±1 LSB and just below π agree with the ideal to within one LSB.
    for raw in (1, turn - 1, turn // 2 - 1):
        gx, gy = rotate([x], [y], [raw])
        ix, iy = rotate_ideal([x], [y], [raw])
        assert abs(gx[0] - ix[0]) <= 1 and abs(gy[0] - iy[0]) <= 1


def test_cordic_zero_vector_stays_zero():
    theta = np.arange(0, 1 << 16, 7)
    ox, oy = rotate(np.zeros_like(theta), np.zeros_like(theta), theta)
    assert not ox.any() and not oy.any()


def test_cordic_park_inverse_park_round_trip_model():
    rng = np.random.default_rng(13)
    n = 200_000
    r = rng.uniform(0, FS - 1, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    x, y = np.round(r * np.cos(phi)).astype(np.int64), np.round(r * np.sin(phi)).astype(np.int64)
    theta = rng.integers(0, 1 << 16, n)
    dx, dy = rotate(x, y, (-theta) % (1 << 16))        # Park: rotate by −θ
    ax, ay = rotate(dx, dy, theta)                      # inverse Park: by +θ
    err = np.maximum(np.abs(ax - x), np.abs(ay - y))
    assert err.max() <= 2


# --- gateware --------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs", [{}, {"width": 12, "iterations_per_stage": 2, "tag_width": 2}])
def test_cordic_latency_cycle_by_cycle(kwargs):
    check_latency_cycle_by_cycle(Cordic(**kwargs), lambda x, y, t: rotate(x, y, t, **kwargs))


def test_cordic_named_corners_gateware_bit_exact():
    dut = Cordic()
    x, y, theta = corner_cases()
    out = _simulate_vectors(dut, [{"x": int(a), "y": int(b), "theta": int(t)}
                                  for a, b, t in zip(x, y, theta)])
    ex, ey = rotate(x, y, theta)
    np.testing.assert_array_equal(np.array(out), np.stack([ex, ey], axis=1))


def test_cordic_random_vectors_gateware_vs_model():
    r = run(3000, seed=1)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["vectors"] == 3000 + len(corner_cases()[0])
    assert r["latency_clk"] == CordicParams().latency
    assert r["throughput_per_clk"] == 1.0
    assert r["max_err_lsb"] <= 2.0 and r["rms_err_lsb"] <= 0.7
    assert r["clocks"] >= r["vectors"] and r["clk_per_s"] > 0


def test_cordic_width12_two_iterations_per_stage_tagged_vs_model():
    params = {"width": 12, "iterations_per_stage": 2, "tag_width": 2}
    r = run(1500, seed=2, **params)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["latency_clk"] == CordicParams(**params).latency
    assert r["throughput_per_clk"] == 1.0
    assert r["max_err_lsb"] <= 2.0 and r["rms_err_lsb"] <= 0.7


@pytest.mark.parametrize("params", [
    {"width": 8},
    {"width": 10, "guard_bits": 0},                     # no guard bits: output shift of 0
    {"width": 12, "guard_bits": 20},                    # F < G: no rounding term in the tree
    {"angle_width": 20, "iterations_per_stage": 3},     # registers straddle tree and iterations
    {"angle_width": 10, "stages": 8, "iterations_per_stage": 8, "tag_width": 1},
    {"width": 30, "stages": 34},                        # model in Python integers
])
def test_cordic_other_configurations_vs_model(params):
    r = run(200, seed=3, **params)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["latency_clk"] == CordicParams(**params).latency
    assert r["throughput_per_clk"] == 1.0


def test_cordic_park_inverse_park_round_trip_gateware():
    check_park_inverse_park_round_trip(Cordic(tag_width=16), Cordic(), n=150)


def test_cordic_converts_to_verilog():
    dut = Cordic(width=12, tag_width=2)
    ports = signal_ports(dut)
    text = verilog.convert(dut, name="cordic", ports=ports)
    assert "module cordic" in text
    for port in ("i__payload", "i__valid", "o__payload", "o__valid"):
        assert port in text


@pytest.mark.slow
def test_cordic_100k_vectors_targets():
    r = run(100_000)
    assert r["mismatches"] == 0 and r["outputs_missing"] == 0
    assert r["vectors"] == 100_000 + len(corner_cases()[0])
    assert r["max_err_lsb"] <= 2.0
    assert r["rms_err_lsb"] <= 0.7
    assert r["latency_clk"] == CordicParams().latency
    assert r["throughput_per_clk"] == 1.0
