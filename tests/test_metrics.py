# Ref: issue 6 items 4–5 (metrics; --plot/--csv); sim/metrics.py, sim/plots.py
"""Response metrics against analytic curves (first- and second-order steps, ramps with a known lag,
a synthetic load dip, sinusoidal ripple), edge cases and input errors; the PNG and CSV writers read
back independently."""

import csv
import json
import math
import struct

import numpy as np
import pytest

from foc_servo.host.tuning import t_min_s
from foc_servo.sim import metrics as M
from foc_servo.sim import plots as P

TAU = 2e-3                                  # s, time constant of the synthetic responses


def first_order(t, t0, y0, y1, tau=TAU):
    return np.where(t < t0, y0, y1 + (y0 - y1) * np.exp(-np.maximum(t - t0, 0) / tau))


def second_order(t, zeta, wn):
    """Unit step response of ωn²/(s² + 2ζωn·s + ωn²), ζ < 1."""
    wd = wn * math.sqrt(1 - zeta ** 2)
    phi = math.acos(zeta)
    return 1 - np.exp(-zeta * wn * t) / math.sqrt(1 - zeta ** 2) * np.sin(wd * t + phi)


def bisect(f, lo, hi, n=200):
    """Root of f in [lo, hi] (f changes sign), independent of the metrics' interpolation."""
    flo = f(lo)
    for _ in range(n):
        mid = 0.5 * (lo + hi)
        if (f(mid) > 0) == (flo > 0):
            lo, flo = mid, f(mid)
        else:
            hi = mid
    return 0.5 * (lo + hi)


# --- step metrics ----------------------------------------------------------------------------

@pytest.mark.parametrize("t0", [2e-3, 2.00037e-3])          # on and between samples
def test_first_order_step(t0):
    t = np.arange(0, 14 * TAU, TAU / 2000)
    y = first_order(t, t0, 0.0, 1667.0)
    assert M.rise_time(t, y, y0=0, y1=1667, t0=t0) == pytest.approx(math.log(9) * TAU, rel=1e-6)
    assert M.settling_time(t, y, target=1667, t0=t0) == pytest.approx(TAU * math.log(200),
                                                                       rel=1e-6)
    # ±2 % band: τ·ln 50.
    assert M.settling_time(t, y, target=1667, band=0.02, t0=t0) == pytest.approx(
        TAU * math.log(50), rel=1e-6)
    assert M.overshoot_pct(t, y, y0=0, y1=1667, t0=t0) == 0.0
    # Steady state over the last 2τ: e = 1667·exp(−(t − t0)/τ); exact mean and peak.
    w, end = 2 * TAU, t[-1] - t0
    ss = M.steady_state_error(t, y, 1667.0, window_s=w)
    mean = 1667 * TAU / w * (math.exp(-(end - w) / TAU) - math.exp(-end / TAU))
    assert ss.mean_err == pytest.approx(mean, rel=1e-4)
    assert ss.mean_pct == pytest.approx(100 * mean / 1667, rel=1e-4)
    assert ss.peak_pct == pytest.approx(100 * math.exp(-(end - w) / TAU), rel=1e-3)


def test_negative_step_band_relative_to_target():
    # 1000 → −500 r/min: the band is ±0.5 % of 500, so 1500·e^(−t/τ) = 2.5 → t = τ·ln 600.
    t = np.arange(0, 10 * TAU, TAU / 2000)
    y = first_order(t, 0.0, 1000.0, -500.0)
    assert M.rise_time(t, y, y0=1000, y1=-500) == pytest.approx(math.log(9) * TAU, rel=1e-6)
    assert M.settling_time(t, y, target=-500) == pytest.approx(TAU * math.log(600), rel=1e-6)
    assert M.overshoot_pct(t, y, y0=1000, y1=-500) == 0.0
    # A negative underdamped step overshoots below the target.
    t2 = np.linspace(0, 0.05, 50001)
    y2 = 1000 - 1500 * second_order(t2, 0.5, 600.0)
    assert M.overshoot_pct(t2, y2, y0=1000, y1=-500) == pytest.approx(
        100 * math.exp(-0.5 * math.pi / math.sqrt(0.75)), rel=1e-5)


@pytest.mark.parametrize("zeta", [0.15, 0.3, 0.6])
def test_second_order_overshoot_and_settling(zeta):
    wn = 2 * math.pi * 200
    wd = wn * math.sqrt(1 - zeta ** 2)
    t = np.arange(0, 12 / (zeta * wn) + 0.01, 2 * math.pi / wd / 20000)
    y = 1667 * second_order(t, zeta, wn)
    assert M.overshoot_pct(t, y, y0=0, y1=1667) == pytest.approx(
        100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)), rel=1e-5)
    # The deviation's extremes are at t_k = kπ/ωd with |dev| = e^(−ζωn·t_k); the last one outside
    # ±0.5 % is k = K, and the settling point is the one crossing of |dev| = 0.005 after it.
    k_last = math.floor(math.log(200) * wd / (zeta * wn * math.pi))
    t_k = k_last * math.pi / wd
    assert math.exp(-zeta * wn * t_k) > 0.005 > math.exp(-zeta * wn * (t_k + math.pi / wd))
    expected = bisect(lambda x: abs(second_order(np.array([x]), zeta, wn)[0] - 1) - 0.005,
                      t_k, t_k + math.pi / wd)
    settle = M.settling_time(t, y, target=1667)
    assert settle == pytest.approx(expected, rel=1e-6)
    # It left the band after first entering it (the "last entry" rule matters here).
    first_entry = t[np.argmax(np.abs(y / 1667 - 1) <= 0.005)]
    assert first_entry < settle


def test_settling_edge_cases():
    t = np.linspace(0, 0.1, 1001)
    # Never settles: a sustained oscillation wider than the band. It ends in the band (at a zero
    # crossing), so only the hold requirement tells it from a settled response.
    y = 1000 + 10 * np.sin(2 * np.pi * 100 * t)
    assert M.settling_time(t, y, target=1000) == pytest.approx(
        0.1 - math.asin(0.5) / (2 * math.pi * 100), abs=1e-6)
    assert M.settling_time(t, y, target=1000, hold_s=1e-3) is None
    assert M.load_step(t, y, t_step=0.0, ref=1000, hold_s=1e-3).recovery_s is None
    # A real settling passes the same hold; one shorter than hold_s does not.
    y = first_order(t, 0.0, 0.0, 1000.0, tau=5e-3)
    assert M.settling_time(t, y, target=1000, hold_s=0.05) == pytest.approx(5e-3 * math.log(200),
                                                                          rel=1e-4)
    assert M.settling_time(t, y, target=1000, hold_s=0.08) is None
    # Settles, then drifts out at the end of the record.
    y = np.where(t < 0.09, 1000.0, 1000 + 1000 * (t - 0.09))
    assert M.settling_time(t, y, target=1000) is None
    # In the band from the start: 0.
    assert M.settling_time(t, np.full_like(t, 1003.0), target=1000) == 0.0
    # Already at the start, the first sample counts from t0 on only.
    y = np.where(t < 0.05, 0.0, 1000.0)
    assert M.settling_time(t, y, target=1000, t0=0.05) == 0.0
    assert M.settling_time(t, y, target=1000, t0=0.0) == pytest.approx(0.05, abs=1e-4)


def test_rise_edge_cases():
    t = np.linspace(0, 0.01, 1001)
    # Never reaches 90 %: a first-order curve aiming at 80 %.
    assert M.rise_time(t, first_order(t, 0, 0, 800.0), y0=0, y1=1000) is None
    # Never reaches 10 %.
    assert M.rise_time(t, np.full_like(t, 50.0), y0=0, y1=1000) is None
    # A jump: both crossings inside the same sample interval, interpolated.
    y = np.where(t < 0.005, 0.0, 1000.0)
    assert M.rise_time(t, y, y0=0, y1=1000) == pytest.approx(0.8 * 1e-5, rel=1e-9)


def test_t_min_and_conversions():
    assert M.rpm_to_rad_s(1667) == pytest.approx(1667 * 2 * math.pi / 60, rel=1e-15)
    assert M.rad_s_to_rpm(M.rpm_to_rad_s(1667.0)) == pytest.approx(1667.0, rel=1e-15)
    np.testing.assert_allclose(M.rad_s_to_rpm(M.rpm_to_rad_s(np.array([-3.0, 0.2, 5000.0]))),
                               [-3.0, 0.2, 5000.0], rtol=1e-15)
    # J·Δω/(T_max − T_load) by hand; the same as the tuning module's r/min version.
    d_omega = 1667 * 2 * math.pi / 60
    assert M.t_min(2.47e-4, d_omega, 14.7) == pytest.approx(2.47e-4 * d_omega / 14.7, rel=1e-12)
    assert M.t_min(2.47e-4, -d_omega, 14.7, 4.9) == pytest.approx(2.47e-4 * d_omega / 9.8,
                                                                  rel=1e-12)
    assert M.t_min(2.47e-4, d_omega, 14.7) == pytest.approx(t_min_s(2.47e-4, 1667, 14.7),
                                                           rel=1e-12)
    with pytest.raises(ValueError, match=r"^t_load_nm 14\.7 N·m must be below t_max_nm 14\.7 "):
        M.t_min(2.47e-4, d_omega, 14.7, 14.7)
    with pytest.raises(ValueError, match=r"^t_load_nm 20 N·m must be below"):
        M.t_min(2.47e-4, d_omega, 14.7, 20)
    with pytest.raises(ValueError, match=r"^delta_omega_rad_s must be a finite number of rad/s, "
                                         r"not nan$"):
        M.t_min(2.47e-4, math.nan, 14.7)


def test_step_metrics_bundle():
    t = np.arange(0, 0.03, 1e-6)
    t0 = 1e-3
    y = first_order(t, t0, 0.0, 1667.0, tau=1e-3)
    m = M.step_metrics(t, y, y0=0, y1=1667, t0=t0, window_s=5e-3, j_kgm2=2.47e-4,
                       t_max_nm=14.7, t_load_nm=0.0)
    tmin = 2.47e-4 * 1667 * 2 * math.pi / 60 / 14.7
    assert m.t_min_s == pytest.approx(tmin, rel=1e-12)
    assert m.settle_s == pytest.approx(1e-3 * math.log(200), rel=1e-6)
    assert m.settle_ratio == pytest.approx(m.settle_s / tmin, rel=1e-12)
    assert m.rise_s == pytest.approx(1e-3 * math.log(9), rel=1e-6)
    assert m.overshoot_pct == 0.0 and m.t0_s == t0 and m.band == 0.005
    d = m.as_dict()
    assert {"settle_s", "t_min_s", "settle_ratio", "overshoot_pct", "ss_err_pct",
            "rise_s"} <= d.keys()
    json.dumps(d)                                     # plain floats: --json can print it
    # Without the mechanics: no t_min, no ratio; one of the two alone is an error.
    m2 = M.step_metrics(t, y, y0=0, y1=1667, t0=t0, window_s=5e-3)
    assert m2.t_min_s is None and m2.settle_ratio is None and m2.settle_s == m.settle_s
    with pytest.raises(ValueError, match=r"^j_kgm2 and t_max_nm must be given both or neither"):
        M.step_metrics(t, y, y0=0, y1=1667, window_s=5e-3, j_kgm2=1e-3)
    # t_min given directly: the same figures.
    m4 = M.step_metrics(t, y, y0=0, y1=1667, t0=t0, window_s=5e-3, t_min_s=tmin)
    assert m4.as_dict() == pytest.approx(m.as_dict(), rel=1e-12)
    with pytest.raises(ValueError, match=r"^t_min_s and j_kgm2/t_max_nm must not both be given$"):
        M.step_metrics(t, y, y0=0, y1=1667, window_s=5e-3, t_min_s=tmin, j_kgm2=1e-3,
                       t_max_nm=1.0)
    with pytest.raises(ValueError, match=r"^t_min_s must be above 0 s, not -1\.0 s$"):
        M.step_metrics(t, y, y0=0, y1=1667, window_s=5e-3, t_min_s=-1)
    # Never settles: settle_s and the ratio are None, the rest is still there.
    y3 = y + 20 * np.sin(2 * np.pi * 500 * t)
    m3 = M.step_metrics(t, y3, y0=0, y1=1667, t0=t0, window_s=5e-3, j_kgm2=2.47e-4,
                        t_max_nm=14.7)
    assert m3.settle_s is None and m3.settle_ratio is None and m3.overshoot_pct > 0


# --- steady state, ramp, load, ripple --------------------------------------------------------

def test_steady_state_error_offset_and_ripple():
    t = np.arange(0, 0.1, 1e-5)
    eps, amp, ref = 2e-4, 0.05, 500.0
    y = ref * (1 - eps) + amp * np.sin(2 * np.pi * 1000 * t)
    ss = M.steady_state_error(t, y, ref, window_s=0.02)      # 20 whole periods (± one sample)
    assert ss.mean_pct == pytest.approx(100 * eps, rel=1e-3)
    assert ss.mean_err == pytest.approx(ref * eps, rel=1e-3)   # positive: below the reference
    assert ss.peak_pct == pytest.approx(100 * (ref * eps + amp) / ref, rel=1e-6)
    # Above the reference: the same magnitude, mean_err negative; an array ref works the same.
    ss2 = M.steady_state_error(t, 2 * ref - y, np.full_like(t, ref), window_s=0.02)
    assert ss2.mean_pct == pytest.approx(ss.mean_pct)
    assert ss2.mean_err == pytest.approx(-ss.mean_err)


def test_ramp_tracking_known_lag():
    a, t_start, target = 4500.0, 0.01, 500.0              # r/min/s: 0.45 r/min per 100 µs sample
    t = np.arange(0, 0.2, 1e-5)
    ramp = lambda tt: np.clip(a * (tt - t_start), 0, target)  # noqa: E731
    ref = ramp(t)
    t_end = t_start + target / a
    # A pure delay L: error a·L during the ramp.
    lag = 1e-3
    y = ramp(t - lag)
    assert M.ramp_tracking_error(t, y, ref, t_start=t_start, t_end=t_end,
                                 full_scale=target) == pytest.approx(100 * a * lag / target,
                                                                     rel=1e-9)
    # A type-2 loop's start-up transient e = a·x·e^(−x/τ), x = t − t_start: peak a·τ/e at x = τ;
    # with an allowance of 3τ the largest counted error is a·3τ·e^(−3).
    x = np.maximum(t - t_start, 0)
    y = ref - a * x * np.exp(-x / TAU)
    full = M.ramp_tracking_error(t, y, ref, t_start=t_start, t_end=t_end, full_scale=target)
    assert full == pytest.approx(100 * a * TAU / math.e / target, rel=1e-6)
    allowed = M.ramp_tracking_error(t, y, ref, t_start=t_start, t_end=t_end, full_scale=target,
                                    allowance_s=3 * TAU)
    assert allowed == pytest.approx(100 * a * 3 * TAU * math.exp(-3) / target, rel=1e-6)
    # The bundle finds the ramp from ref and measures the steady state after it.
    y = y * (1 - 2e-4 * (t > t_end))
    rm = M.ramp_metrics(t, y, ref, window_s=0.05)
    assert rm.t_start_s == pytest.approx(t_start, abs=1e-5)
    assert rm.t_end_s == pytest.approx(t_end, abs=1e-5)
    assert rm.full_scale == target and rm.allowance_s == 0.0
    assert rm.track_err_pct == pytest.approx(full, rel=1e-6)
    assert rm.ss_err_pct == pytest.approx(0.02, rel=1e-3)
    assert {"track_err_pct", "ss_err_pct"} <= rm.as_dict().keys()
    with pytest.raises(ValueError, match=r"^window_s 0\.15 s reaches back into the ramp"):
        M.ramp_metrics(t, y, ref, window_s=0.15)


def test_load_step_dip_and_recovery():
    ref, dip, t_step = 1000.0, 20.0, 0.05
    t = np.arange(0, 0.2, 1e-6)
    x = np.maximum(t - t_step, 0) / TAU
    y = ref - dip * x * np.exp(1 - x)                      # dip D at x = 1, back to ref after
    res = M.load_step(t, y, t_step=t_step, ref=ref, band=0.005)
    assert res.dip_rpm == pytest.approx(dip, rel=1e-9)
    assert res.dip_pct == pytest.approx(100 * dip / ref, rel=1e-9)
    assert res.t_dip_s == pytest.approx(TAU, abs=1e-6)
    # Recovery: x·e^(1−x) = 0.005·ref/D for x > 1.
    level = 0.005 * ref / dip
    x_rec = bisect(lambda v: v * math.exp(1 - v) - level, 1.0, 50.0)
    assert res.recovery_s == pytest.approx(x_rec * TAU, rel=1e-6)
    # A dip inside the band: recovery 0; one that never recovers: None.
    assert M.load_step(t, ref - 1.0 * x * np.exp(1 - x), t_step=t_step, ref=ref).recovery_s == 0.0
    never = np.where(t < t_step, ref, ref - 30.0)
    res = M.load_step(t, never, t_step=t_step, ref=ref)
    assert res.recovery_s is None and res.dip_rpm == 30.0
    # Negative speed: the dip is the rise toward 0 (ref − y < 0), the percentage of |ref|.
    res = M.load_step(t, -y, t_step=t_step, ref=-ref)
    assert res.dip_rpm == pytest.approx(-dip) and res.dip_pct == pytest.approx(-100 * dip / ref)


def test_speed_ripple():
    f, amp, mean = 50.0, 0.01, 0.2                         # 0.2 r/min ± 0.01
    t = np.arange(0, 0.2 + 1e-9, 1 / f / 400)              # 400 samples a period: hits the peaks
    y = mean + amp * np.sin(2 * np.pi * f * t)
    r = M.speed_ripple(t, y, window_s=0.1)                 # 5 whole periods
    assert r.pkpk == pytest.approx(2 * amp, rel=1e-9)
    assert r.rms == pytest.approx(amp / math.sqrt(2), rel=1e-6)
    assert r.mean == pytest.approx(mean, rel=1e-9)
    # Non-uniform sampling, dense where the ripple is positive: the plain sample mean is biased,
    # the time-weighted mean is not.
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 0.1, 20000), rng.uniform(0, 0.1, 20000)
    t2 = np.unique(np.concatenate([u, v[np.sin(2 * np.pi * f * v) > 0]]))
    y2 = mean + amp * np.sin(2 * np.pi * f * t2)
    assert abs(y2.mean() - mean) > 0.1 * amp
    r2 = M.speed_ripple(t2, y2, window_s=t2[-1] - t2[0])
    assert r2.mean == pytest.approx(mean, abs=2e-3 * amp)
    assert r2.rms == pytest.approx(amp / math.sqrt(2), rel=2e-3)


# --- input errors ----------------------------------------------------------------------------

T = np.linspace(0, 1, 11)
Y = np.linspace(0, 10, 11)


@pytest.mark.parametrize("call, exc, message", [
    (lambda: M.rise_time([], [], y0=0, y1=1), ValueError,
     r"t must be a one-dimensional array of at least 2 samples, not an array of shape \(0,\)"),
    (lambda: M.rise_time(T, Y[:-1], y0=0, y1=1), ValueError,
     r"t and y must have the same length, not 11 and 10"),
    (lambda: M.rise_time(T[::-1], Y, y0=0, y1=1), ValueError,
     r"t must be strictly increasing, not t\[1\] = 0\.9 s after t\[0\] = 1\.0 s"),
    (lambda: M.rise_time(np.r_[T[:3], T[2:-1]], Y, y0=0, y1=1), ValueError,
     r"t must be strictly increasing, not t\[3\] = 0\.2 s after t\[2\] = 0\.2 s"),
    (lambda: M.rise_time(T, np.r_[Y[:5], np.nan, Y[6:]], y0=0, y1=1), ValueError,
     r"y must be finite, not y\[5\] = nan"),
    (lambda: M.overshoot_pct(np.r_[T[:-1], np.inf], Y, y0=0, y1=1), ValueError,
     r"t must be finite, not t\[10\] = inf"),
    (lambda: M.rise_time(T, ["a"] * 11, y0=0, y1=1), TypeError,
     r"y must be an array of real numbers, not \['a', .*"),
    (lambda: M.rise_time(T, np.ones((11, 2)), y0=0, y1=1), ValueError,
     r"y must be a one-dimensional array of at least 2 samples, not an array of shape \(11, 2\)"),
    (lambda: M.rise_time(T, Y, y0=5, y1=5), ValueError,
     r"y1 must differ from y0 \(a step of height 0 has no rise or overshoot\), not both 5\.0"),
    (lambda: M.overshoot_pct(T, Y, y0=0, y1="1"), TypeError, r"y1 must be a real number, not '1'"),
    (lambda: M.rise_time(T, Y, y0=0, y1=1, t0=2.0), ValueError,
     r"t0 must be within the record, 0\.0 to 1\.0 s, not 2\.0 s"),
    (lambda: M.settling_time(T, Y, target=0), ValueError,
     r"target must not be 0: the band is a fraction of \|target\|"),
    (lambda: M.settling_time(T, Y, target=1, band=1.5), ValueError,
     r"band must be a fraction above 0 and below 1, not 1\.5"),
    (lambda: M.settling_time(T, Y, target=1, hold_s=-1), ValueError,
     r"hold_s must be at least 0 s, not -1\.0 s"),
    (lambda: M.steady_state_error(T, Y, 1.0, window_s=2.0), ValueError,
     r"window_s 2\.0 s is longer than the record \(1\.0 s from t\[0\] to t\[-1\]\)"),
    (lambda: M.steady_state_error(T, Y, 1.0, window_s=0.01), ValueError,
     r"window_s 0\.01 s holds fewer than 2 samples; .*"),
    (lambda: M.steady_state_error(T, Y, 1.0, window_s=-1), ValueError,
     r"window_s must be above 0 s, not -1\.0 s"),
    (lambda: M.steady_state_error(T, Y, 0.0, window_s=0.5), ValueError,
     r"ref must not be 0 over the window: an error in % of it is undefined"),
    (lambda: M.steady_state_error(T, Y, Y[:5], window_s=0.5), ValueError,
     r"t and ref must have the same length, not 11 and 5"),
    (lambda: M.ramp_tracking_error(T, Y, Y, t_start=0.5, t_end=0.4, full_scale=10), ValueError,
     r"t_end must be after t_start \(0\.5 s\), not 0\.4 s"),
    (lambda: M.ramp_tracking_error(T, Y, Y, t_start=0, t_end=1, full_scale=0), ValueError,
     r"full_scale must be above 0, not 0\.0"),
    (lambda: M.ramp_tracking_error(T, Y, Y, t_start=0, t_end=0.5, full_scale=1, allowance_s=0.5),
     ValueError, r"allowance_s must be at least 0 s and shorter than the ramp \(0\.5 s\), "
                 r"not 0\.5 s"),
    (lambda: M.ramp_metrics(T, Y, np.ones(11), window_s=0.5), ValueError,
     r"ref never changes \(constant 1\.0\): no ramp to measure"),
    (lambda: M.ramp_metrics(T, Y, 1.0, window_s=0.5), TypeError,
     r"ref must be an array like y for a ramp, not 1\.0"),
    (lambda: M.load_step(T, Y, t_step=0.5, ref=0), ValueError,
     r"ref must not be 0: the dip and the band are relative to \|ref\|"),
    (lambda: M.load_step(T, Y, t_step=-1, ref=1), ValueError,
     r"t_step must be within the record, 0\.0 to 1\.0 s, not -1\.0 s"),
    (lambda: M.speed_ripple(T, Y, window_s=math.inf), ValueError,
     r"window_s must be finite, not inf"),
    (lambda: M.speed_ripple(T, Y, window_s=True), TypeError,
     r"window_s must be a real number, not True"),
])
def test_input_errors(call, exc, message):
    with pytest.raises(exc, match=rf"^{message}$"):
        call()


# --- plots and CSV ---------------------------------------------------------------------------

def _series(n=2001, extra=False):
    t = np.linspace(0, 0.02, n)
    ref = np.where(t < 2e-3, 0.0, 1667.0)
    s = {"t_s": t, "speed_rpm": first_order(t, 2e-3, 0.0, 1667.0),
         "speed_ref_rpm": ref, "i_alpha_a": 20 * np.sin(2 * np.pi * 4 * 1667 / 60 * t)}
    if extra:
        s["i_q_a"] = np.full(n, 14.7 / 2.0)
        s["load_nm"] = np.linspace(0, 4.9, n)
    return s


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24]), len(data)


def test_plot_response_png(tmp_path):
    import matplotlib.image
    s = _series(extra=True)
    m = M.step_metrics(s["t_s"], s["speed_rpm"], y0=0, y1=1667, t0=2e-3, window_s=2e-3,
                       j_kgm2=2.47e-4, t_max_nm=14.7)
    path = P.plot_response(s, tmp_path / "sub" / "step.png", title="step 0 → 1667 r/min",
                           metrics=m, dpi=80)
    assert path == tmp_path / "sub" / "step.png"
    (width, height), size = _png_size(path)
    assert (width, height) == (9 * 80, 6 * 80) and size > 20000
    # The speed trace (tab:blue) is drawn in the top axes, i_alpha (tab:red) in the bottom ones.
    rgb = matplotlib.image.imread(path)[..., :3] * 255
    rows = {}
    for name, color in (("speed", (0x1f, 0x77, 0xb4)), ("i_alpha", (0xd6, 0x27, 0x28))):
        near = np.all(np.abs(rgb - np.array(color)) < 60, axis=-1)
        assert near.sum() > 100, name
        rows[name] = np.flatnonzero(near.any(axis=1))
    assert 0.4 * height < rows["speed"].max() < 0.6 * height < rows["i_alpha"].max()
    assert rows["speed"].max() < rows["i_alpha"].min()  # top axes: 3/5 of the height
    # Without metrics, and with a plain dict of them.
    P.plot_response(_series(), tmp_path / "plain.png", title="plain", dpi=40)
    assert _png_size(tmp_path / "plain.png")[0] == (360, 240)
    P.plot_response(_series(), tmp_path / "d.png", title="d", metrics={"track_err_pct": 0.3},
                    dpi=40)
    with pytest.raises(ValueError, match=r"^series lacks speed_ref_rpm, i_alpha_a \(it has "
                                         r"t_s, speed_rpm\)$"):
        P.plot_response({"t_s": s["t_s"], "speed_rpm": s["speed_rpm"]}, tmp_path / "x.png",
                        title="x")
    bad = dict(s, i_q_a=s["i_q_a"][:-1])
    with pytest.raises(ValueError, match=r"^t_s and i_q_a must have the same length, not 2001 "
                                         r"and 2000$"):
        P.plot_response(bad, tmp_path / "x.png", title="x")
    assert not (tmp_path / "x.png").exists()


def test_write_csv_round_trip(tmp_path):
    s = _series(n=501, extra=True)
    s["t_s"] = s["t_s"] + 0.1 + 2e-8                     # 20 ns resolution at 0.1 s survives
    path = P.write_csv(s, tmp_path / "out" / "step.csv")
    with path.open(encoding="utf-8", newline="") as f:   # an independent reader
        rows = list(csv.reader(f))
    assert rows[0] == ["t_s (s)", "speed_rpm (r/min)", "speed_ref_rpm (r/min)", "i_alpha_a (A)",
                       "i_q_a (A)", "load_nm (N·m)"]
    assert len(rows) == 1 + 501 and all(len(r) == 6 for r in rows)
    np.testing.assert_allclose([float(v) for v in (r[0] for r in rows[1:])], s["t_s"],
                               rtol=0, atol=1e-10)
    back = P.read_csv(path)
    assert list(back) == ["t_s", "speed_rpm", "speed_ref_rpm", "i_alpha_a", "i_q_a", "load_nm"]
    for key, value in s.items():
        np.testing.assert_allclose(back[key], value, rtol=1e-9, atol=1e-12)
    assert P.unit_of("speed_rad_s") == "rad/s" and P.unit_of("foo") == "-"
