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

from rotation_common import (check_corners_saturate_never_wrap, check_latency_cycle_by_cycle,
                             check_park_inverse_park_round_trip,
                             check_park_inverse_park_round_trip_model,
                             check_quarter_turns_and_small_angles, check_zero_vector_stays_zero,
                             model_error_one_million_vectors, signal_ports,
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
    err = model_error_one_million_vectors(rotate, rotate_ideal, corner_cases)
    assert np.max(np.abs(err)) <= 1.0            # measured ≈ 0.9
    assert math.sqrt(np.mean(err ** 2)) <= 0.31  # measured ≈ 0.30 (rounding alone: 0.29)


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
    assert CordicParams().angle_width == 16
    check_corners_saturate_never_wrap(rotate)


def test_cordic_quarter_turns_and_small_angles():
    check_quarter_turns_and_small_angles(rotate, rotate_ideal)


def test_cordic_zero_vector_stays_zero():
    check_zero_vector_stays_zero(rotate)


def test_cordic_park_inverse_park_round_trip_model():
    check_park_inverse_park_round_trip_model(rotate)


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
