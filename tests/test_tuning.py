# Ref: host/tuning.py (technical / symmetric optimum, normalisation); docs/TUNING.md
"""The tuning rule against independent math: discrete closed-loop simulations of the current
loop (R-L plant, exact zero-order hold with the PWM's half-period delay) and of the cascade
(current loop, inertia, back-EMF, M/T period-average speed), plus normalisation round trips and
validation messages."""

import math

import numpy as np
import pytest

from foc_servo.hdl.fixed import UQ
from foc_servo.hdl.regmap import Scales
from foc_servo.host.registers import REGISTERS
from foc_servo.host.tuning import (CURRENT_KX_FORMAT, SPEED_KX_FORMAT, current_gains,
                                   dead_time_comp, feedforward_registers, lead_angle,
                                   physical_from_registers, speed_gains, t_min_s, to_raw, tune)
from foc_servo.sim.motor import SGMSH_15A

#: Other motors the rule must serve too: 10× inertia, small fast motor, slow big motor.
MOTORS = [
    SGMSH_15A,
    SGMSH_15A.replace(j_kgm2=10 * SGMSH_15A.j_kgm2),
    SGMSH_15A.replace(r_ohm=2.5, l_d_h=4e-3, l_q_h=4e-3, j_kgm2=3e-5),
    SGMSH_15A.replace(r_ohm=0.05, l_d_h=1e-3, l_q_h=1e-3, j_kgm2=5e-3),
]


def _plant(motor, t_s):
    """Exact discretisation of ``L di/dt = v − R i`` sampled at the PWM period centre, the
    voltage computed from sample k acting from T/2 after it for one period:
    ``i[k+1] = α·i[k] + b1·v[k−1] + b2·v[k]``."""
    e_h = math.exp(-t_s / 2 * motor.r_ohm / motor.l_q_h)
    return e_h * e_h, (1 - e_h) * e_h / motor.r_ohm, (1 - e_h) / motor.r_ohm


def current_step(motor, g, n=600):
    alpha, b1, b2 = _plant(motor, g.t_s)
    kx = g.ki_v_per_as * g.t_s / 2
    i = v_prev = integ = e_prev = 0.0
    out = np.empty(n)
    for k in range(n):
        e = 1.0 - i
        integ += kx * (e + e_prev)
        e_prev = e
        v = g.kp_v_per_a * e + integ
        out[k] = i
        i = alpha * i + b1 * v_prev + b2 * v
        v_prev = v
    return out


def current_freq(motor, g, w):
    """Open and closed current loop at ``z = exp(jωT)``."""
    alpha, b1, b2 = _plant(motor, g.t_s)
    z = np.exp(1j * w * g.t_s)
    loop = (b1 / z + b2) / (z - alpha) * (g.kp_v_per_a
                                          + g.ki_v_per_as * g.t_s / 2 * (z + 1) / (z - 1))
    return loop, loop / (1 + loop)


@pytest.mark.parametrize("motor", MOTORS)
@pytest.mark.parametrize("pwm_hz", [5e3, 10e3, 20e3])
def test_current_loop_technical_optimum_in_discrete_simulation(motor, pwm_hz):
    g = current_gains(motor, pwm_hz=pwm_hz)
    assert g.omega_c_rad_s == pytest.approx(pwm_hz / 2)          # ω_c = 1/(2·T_σ), T_σ = T
    assert g.kp_v_per_a == pytest.approx(g.omega_c_rad_s * motor.l_q_h)
    assert g.ki_v_per_as == pytest.approx(g.omega_c_rad_s * motor.r_ohm)
    # Step: the technical optimum promises 4.3 % overshoot; no steady-state error.
    y = current_step(motor, g)
    assert 0.03 < y.max() - 1 < 0.06
    assert abs(y[-1] - 1) < 1e-6
    # Frequency response: crossover at ω_c, phase margin 90° − ω_c·T_σ, −3 dB at ≈ 1.95·ω_c.
    w = g.omega_c_rad_s * np.logspace(-1, 1.2, 20001)
    loop, closed = current_freq(motor, g, w)
    k = np.argmin(abs(abs(loop) - 1))
    assert w[k] == pytest.approx(g.omega_c_rad_s, rel=0.05)
    assert 180 + math.degrees(np.angle(loop[k])) == pytest.approx(g.phase_margin_deg, abs=3)
    assert g.phase_margin_deg == pytest.approx(90 - math.degrees(0.5))
    bw = w[np.argmax(abs(closed) < 1 / math.sqrt(2))]
    assert 1.8 < bw / g.omega_c_rad_s < 2.1


def test_current_bandwidth_given_and_limited():
    g = current_gains(SGMSH_15A, pwm_hz=10e3, bandwidth_rad_s=2000.0)
    assert g.kp_v_per_a == pytest.approx(2000 * SGMSH_15A.l_q_h)
    y = current_step(SGMSH_15A, g, n=2000)
    assert y.max() < 1.005                          # lower bandwidth: more margin, no overshoot
    # Time constant 1/ω_c: 63 % at ≈ 5 samples of 100 µs (within one sample).
    assert 4 <= np.argmax(y > 1 - math.exp(-1)) <= 7
    with pytest.raises(ValueError, match=r"^current bandwidth 20000 rad/s is above 10472 rad/s, "
                                         r"the most a delay of 100 µs allows with 30° phase "
                                         r"margin; lower it or raise pwm_hz$"):
        current_gains(SGMSH_15A, pwm_hz=10e3, bandwidth_rad_s=20e3)


def cascade(motor, cur, spd, step_rad_s, periods, sub=40):
    """Speed step on the cascade: continuous R-L-EMF and inertia (Euler, ``sub`` steps a
    period), voltage applied from T/2 after each sample, speed from the angle over the last
    period (M/T), speed PI every ``spd.t_s``, both PIs Tustin."""
    t = cur.t_s
    dt = t / sub
    div = round(spd.t_s / t)
    r, ll, kt = motor.r_ohm, motor.l_q_h, motor.kt_nm_per_a
    emf = motor.pole_pairs * motor.psi_wb
    kxc, kxs = cur.ki_v_per_as * t / 2, spd.ki_a_per_rad * spd.t_s / 2
    i = w = th = th_prev = ic = ec_prev = is_ = es_prev = iq_ref = v_now = 0.0
    out = np.empty(periods)
    for k in range(periods):
        w_meas = (th - th_prev) / t
        th_prev = th
        if k % div == 0:
            es = step_rad_s - w_meas
            is_ += kxs * (es + es_prev)
            es_prev = es
            iq_ref = spd.kp_a_per_rad_s * es + is_
        ec = iq_ref - i
        ic += kxc * (ec + ec_prev)
        ec_prev = ec
        v = cur.kp_v_per_a * ec + ic
        out[k] = w_meas
        for s in range(sub):
            if s == sub // 2:
                v_now = v
            i += (v_now - emf * w - r * i) / ll * dt
            w += kt * i / spd.j_kgm2 * dt
            th += w * dt
    return out


def so_overshoot(a):
    """Small-step overshoot of the continuous symmetric-optimum loop (no reference filter),
    from its own simulation in normalised time (J = K_t = T_σn = 1)."""
    kp, ti, dt = 1 / a, a * a, 1e-3
    w = integ = iq = peak = 0.0
    for _ in range(int(6 * a * a / dt)):
        e = 1 - w
        integ += kp / ti * e * dt
        iq += (kp * e + integ - iq) * dt
        w += iq * dt
        peak = max(peak, w)
    return peak - 1


@pytest.mark.parametrize("motor", MOTORS[:3])
@pytest.mark.parametrize("a, speed_div", [(2.0, 1), (3.0, 1), (4.0, 1), (3.0, 4)])
def test_speed_loop_symmetric_optimum_in_cascade_simulation(motor, a, speed_div):
    cur = current_gains(motor, pwm_hz=10e3)
    spd = speed_gains(motor, cur, a=a, speed_div=speed_div)
    assert spd.t_sigma_n_s == pytest.approx(2 * cur.t_sigma_s + speed_div * cur.t_s)
    assert spd.kp_a_per_rad_s == pytest.approx(
        motor.j_kgm2 / (a * 1.5 * motor.pole_pairs * motor.psi_wb * spd.t_sigma_n_s))
    assert spd.ki_a_per_rad == pytest.approx(spd.kp_a_per_rad_s / (a * a * spd.t_sigma_n_s))
    assert spd.phase_margin_deg == pytest.approx(
        math.degrees(math.atan(a) - math.atan(1 / a)))
    periods = int(40 * a * a * spd.t_sigma_n_s / cur.t_s)
    y = cascade(motor, cur, spd, 1.0, periods)
    # The sampled loop's delays are a little shorter than the rule's lag model, so it
    # overshoots a little less than the continuous prediction, never more.
    predicted = so_overshoot(a)
    assert 0.6 * predicted < y.max() - 1 < predicted + 0.02
    assert abs(y[-1] - 1) < 1e-3


def test_speed_overshoot_prediction_values():
    # The values docs/TUNING.md quotes.
    assert so_overshoot(2.0) == pytest.approx(0.434, abs=0.005)
    assert so_overshoot(3.0) == pytest.approx(0.249, abs=0.005)


def test_tune_catalogue_motor_registers():
    t = tune(SGMSH_15A)
    scales = Scales()
    u_base = 2 / 3 * 310.0
    kp_n = t.current.kp_v_per_a * scales.i_fs_a / u_base
    assert t.normalized["pi_q_kp"] == pytest.approx(kp_n)
    assert t.normalized["pi_d_kx"] == pytest.approx(
        t.current.ki_v_per_as * 1e-4 / 2 * scales.i_fs_a / u_base)
    n_fs = scales.n_fs_rpm * 2 * math.pi / 60
    assert t.normalized["pi_speed_kp"] == pytest.approx(
        t.speed.kp_a_per_rad_s * n_fs / scales.i_fs_a)
    assert t.normalized["pi_speed_kx"] == pytest.approx(
        t.speed.ki_a_per_rad * 1e-4 / 2 * n_fs / scales.i_fs_a)
    assert set(t.registers) == {"pi_d_kp", "pi_d_kx", "pi_q_kp", "pi_q_kx", "pi_speed_kp",
                                "pi_speed_kx"}
    for name, raw in t.registers.items():
        fmt = REGISTERS[name].fmt
        assert fmt.min_raw <= raw <= fmt.max_raw
        assert abs(fmt.from_raw(raw) - t.normalized[name]) <= fmt.lsb / 2


@pytest.mark.parametrize("speed_div", [1, 3])
def test_physical_raw_round_trip(speed_div):
    scales = Scales(i_fs_a=40.0, pwm_hz=16e3)
    t = tune(SGMSH_15A, scales=scales, u_rated_v=300.0, speed_div=speed_div)
    back = physical_from_registers(t.registers, scales=scales, u_rated_v=300.0,
                                   speed_div=speed_div)
    phys = {"pi_q_kp": t.current.kp_v_per_a, "pi_q_kx": t.current.ki_v_per_as,
            "pi_speed_kp": t.speed.kp_a_per_rad_s, "pi_speed_kx": t.speed.ki_a_per_rad}
    for name, value in phys.items():
        fmt = REGISTERS[name].fmt
        # Within half an LSB of the register, expressed physically.
        assert abs(back[name] - value) <= fmt.lsb / 2 * value / t.normalized[name] * 1.000001
    # Raw → physical → raw is the identity.
    t2 = tune(SGMSH_15A, scales=scales, u_rated_v=300.0, speed_div=speed_div,
              current_kp_v_per_a=back["pi_q_kp"], current_ki_v_per_as=back["pi_q_kx"],
              speed_kp_a_per_rad_s=back["pi_speed_kp"], speed_ki_a_per_rad=back["pi_speed_kx"])
    assert t2.registers == t.registers


def test_tune_overrides_each_gain():
    t = tune(SGMSH_15A, current_kp_v_per_a=5.0, speed_ki_a_per_rad=100.0)
    assert t.current.kp_v_per_a == 5.0
    assert t.current.ki_v_per_as == tune(SGMSH_15A).current.ki_v_per_as
    assert t.speed.ki_a_per_rad == 100.0
    assert t.speed.kp_a_per_rad_s != 100.0


def test_tune_gain_that_does_not_fit_names_gain_range_and_fix():
    # 10× the rotor inertia at a 500 Hz speed loop needs a speed kx of 91 (UQ4.20 holds < 16).
    with pytest.raises(ValueError, match=r"^pi_speed_kx 90\.9\d* does not fit UQ\(24, 20\) "
                                         r"\(representable 0 … 15\.999999\): with N_FS = 12000 "
                                         r"r/min and I_FS = 40 A; lower the speed ω_c 3142 rad/s "
                                         r"\(500 Hz\), use another full scale \(gain ∝ "
                                         r"N_FS/I_FS\), or a format with more integer bits$"):
        tune(MOTORS[1], speed_bandwidth_rad_s=2 * math.pi * 500)
    # ... and fits with a format with more integer bits.
    t = tune(MOTORS[1], speed_bandwidth_rad_s=2 * math.pi * 500, speed_kx_format=UQ(24, 16))
    assert t.registers["pi_speed_kx"] == round(t.normalized["pi_speed_kx"] * 2 ** 16)
    # The classic a = 2 (speed kx 1.36) fits the register map's UQ4.20; the old UQ0.24 did not.
    assert tune(SGMSH_15A, a=2.0).normalized["pi_speed_kx"] == pytest.approx(1.36, abs=0.005)
    with pytest.raises(ValueError, match=r"^pi_speed_kx 1\.358\d* does not fit UQ\(24, 24\) "):
        tune(SGMSH_15A, a=2.0, speed_kx_format=UQ(24, 24))
    with pytest.raises(ValueError, match=r"^pi_d_kx 0\.0152\d* is below the resolution of "
                                         r"UQ\(16, 5\) \(steps of 0\.0312: error above 5%\): with "
                                         r"I_FS = 40 A and u_rated = 310 V; use another I_FS or "
                                         r"u_rated, or a format with more fraction bits$"):
        tune(SGMSH_15A, current_kx_format=UQ(16, 5))


def _significant_bits(raw):
    return int(raw).bit_length()


def test_speed_formats_hold_50_to_500_hz_for_the_default_motor():
    """Decision record (docs/TUNING.md): at 10 kHz and the default scales, the speed PI's
    gains for crossovers of 50 … 500 Hz fit the register formats with at least 8 significant
    bits; UQ(24, 20) is the finest kx format that holds 500 Hz (UQ(24, 21) and the former
    UQ(24, 24) do not)."""
    assert SPEED_KX_FORMAT == UQ(24, 20) and Scales().i_fs_a == 40.0
    kx = {}
    for f_hz in (50, 100, 200, 300, 400, 500):
        t = tune(SGMSH_15A, speed_bandwidth_rad_s=2 * math.pi * f_hz)
        assert t.speed.omega_c_rad_s == pytest.approx(2 * math.pi * f_hz)
        for name, raw in t.registers.items():
            assert _significant_bits(raw) >= 8, (f_hz, name, raw)
        kx[f_hz] = t.normalized["pi_speed_kx"]
    assert kx[50] == pytest.approx(0.0091, rel=0.01) and kx[500] == pytest.approx(9.10, rel=0.01)
    # K_i ∝ ω_c³ at a fixed T_σn (a = 1/(ω_c·T_σn)).
    assert kx[500] / kx[50] == pytest.approx(1000)
    with pytest.raises(ValueError, match=r"^pi_speed_kx 9\.09\d* does not fit UQ\(24, 21\) "):
        tune(SGMSH_15A, speed_bandwidth_rad_s=2 * math.pi * 500, speed_kx_format=UQ(24, 21))
    with pytest.raises(ValueError, match=r"^pi_speed_kx 1\.\d* does not fit UQ\(24, 24\) "):
        tune(SGMSH_15A, speed_bandwidth_rad_s=2 * math.pi * 300, speed_kx_format=UQ(24, 24))


@pytest.mark.parametrize("f_hz", [50, 177, 300])
def test_speed_bandwidth_is_the_open_loop_crossover(f_hz):
    # Independent: |L(jω)| of the rule's model (PI · K_t/(J·s) · 1/(1 + s·T_σn)) is 1 at ω_c,
    # and the gains are the symmetric optimum with a = 1/(ω_c·T_σn).
    m = SGMSH_15A
    cur = current_gains(m, pwm_hz=10e3)
    wc = 2 * math.pi * f_hz
    spd = speed_gains(m, cur, bandwidth_rad_s=wc, a=7.0)      # a is ignored
    s = 1j * wc
    loop = ((spd.kp_a_per_rad_s + spd.ki_a_per_rad / s) * m.kt_nm_per_a / (m.j_kgm2 * s)
            / (1 + s * spd.t_sigma_n_s))
    assert abs(loop) == pytest.approx(1.0, rel=1e-9)
    same = speed_gains(m, cur, a=1 / (wc * spd.t_sigma_n_s))
    assert (spd.kp_a_per_rad_s, spd.ki_a_per_rad) == pytest.approx(
        (same.kp_a_per_rad_s, same.ki_a_per_rad), rel=1e-12)
    assert 180 + math.degrees(np.angle(loop)) == pytest.approx(spd.phase_margin_deg, abs=1e-6)
    with pytest.raises(ValueError, match=r"^speed bandwidth 3769\.91 rad/s is outside 167 … 3333 "
                                         r"rad/s \(exclusive\), the symmetric optimum's range for "
                                         r"T_σn = 300 µs \(a = 1/\(ω_c·T_σn\) from 1 to 20\); "
                                         r"change it, or pwm_hz / speed_div$"):
        speed_gains(m, cur, bandwidth_rad_s=2 * math.pi * 600)


def test_lead_angle_register():
    # 1 PWM period at 10 kHz, N_FS = 12000 r/min, 4 pole pairs: 800 Hz electrical · 100 µs.
    deg, raw = lead_angle(SGMSH_15A)
    assert deg == pytest.approx(28.8) and raw == round(0.08 * 2**16) == 5243
    assert REGISTERS["theta_lead"].from_raw(raw, Scales()) == pytest.approx(28.8, abs=0.006)
    deg2, raw2 = lead_angle(SGMSH_15A, t_lead_s=150e-6, scales=Scales(n_fs_rpm=6000))
    assert deg2 == pytest.approx(21.6) and raw2 == round(0.06 * 2**16)
    assert lead_angle(SGMSH_15A, t_lead_s=0) == (0.0, 0)
    with pytest.raises(ValueError, match=r"^t_lead 2000 µs is 576° at N_FS = 12000 r/min \(800 Hz "
                                         r"electrical\), beyond the theta_lead register's "
                                         r"359\.9945°; at most 1249\.98 µs$"):
        lead_angle(SGMSH_15A, t_lead_s=2e-3)


def test_dead_time_compensation_registers():
    m = SGMSH_15A
    # 1 µs at 50 MHz = 50 clocks; I_band = 310 V · 100 µs / (24 · 2.42 mH) = 0.534 A, i.e.
    # 8.7 × 50 current LSBs (40 A / 32768): 2**3 (0.49 A).
    regs = dead_time_comp(m)
    assert regs == {"dtc_clocks": 50, "dtc_band": 3}
    band_a = 310 * 1e-4 / (24 * m.l_q_h)
    assert band_a == pytest.approx(0.534, abs=1e-3)
    assert 50 * 2**3 * 40 / 32768 / band_a == pytest.approx(1, abs=math.sqrt(2) - 1)
    # The physical value of dtc_clocks is the dead time.
    assert REGISTERS["dtc_clocks"].from_raw(50, Scales()) == pytest.approx(1e-6)
    # Other clocks, dead times and bands; 0 s acts as 1 clock (as the gates); off.
    assert dead_time_comp(m, scales=Scales(clk_hz=33.333e6)) == {"dtc_clocks": 33,
                                                                  "dtc_band": 4}
    assert dead_time_comp(m, dead_time_s=0) == {"dtc_clocks": 1, "dtc_band": 9}
    assert dead_time_comp(m, band_a=1e4)["dtc_band"] == 15
    assert dead_time_comp(m, band_a=1e-4)["dtc_band"] == 0
    assert dead_time_comp(m, dead_time_s=None) == {"dtc_clocks": 0, "dtc_band": 4}
    # In the feed-forward that Servo.tune writes, and through tune().
    ff = feedforward_registers(m, scales=Scales())
    assert ff["dtc_clocks"] == 50 and ff["dtc_band"] == 3 and ff["theta_lead"] == 5243
    assert tune(m, dead_time_s=2e-6).feedforward["dtc_clocks"] == 100
    assert tune(m, dead_time_s=None).feedforward["dtc_clocks"] == 0
    for name, raw in ff.items():
        REGISTERS[name].to_words(raw)                       # each fits its register
    with pytest.raises(ValueError, match=r"^dead_time_s 6 µs is 300 clocks at 5e\+07 Hz, "
                                         r"beyond the dtc_clocks register's 255$"):
        dead_time_comp(m, dead_time_s=6e-6)
    with pytest.raises(ValueError, match=r"^dead_time_s must be a finite number at least 0 s, "
                                         r"not -1e-06$"):
        feedforward_registers(m, dead_time_s=-1e-6)
    with pytest.raises(ValueError, match=r"^band_a must be a finite number above 0 A, not 0$"):
        dead_time_comp(m, band_a=0)


def test_default_formats_come_from_the_register_map():
    assert CURRENT_KX_FORMAT == REGISTERS["pi_q_kx"].fmt == REGISTERS["pi_d_kx"].fmt
    assert SPEED_KX_FORMAT == REGISTERS["pi_speed_kx"].fmt


@pytest.mark.parametrize("call, message", [
    (lambda: current_gains(SGMSH_15A, pwm_hz=0), r"pwm_hz must be a finite number above 0 Hz, "
                                                 r"not 0"),
    (lambda: current_gains(SGMSH_15A, pwm_hz=1e4, delay_periods=11),
     r"delay_periods must be at most 10 periods, not 11\.0"),
    (lambda: current_gains(SGMSH_15A, pwm_hz=1e4, bandwidth_rad_s=-5),
     r"current bandwidth must be a finite number above 0 rad/s, not -5"),
    (lambda: tune(SGMSH_15A, a=1.0), r"symmetric optimum a must be above 1 and at most 20, "
                                     r"not 1\.0"),
    (lambda: tune(SGMSH_15A, speed_div=0), r"speed_div must be an integer from 1 to 255 "
                                           r"periods, not 0"),
    (lambda: tune(SGMSH_15A, j_load_kgm2=-1e-3), r"j_load_kgm2 must be a finite number at "
                                                 r"least 0 kg·m², not -0\.001"),
    (lambda: tune(SGMSH_15A, u_rated_v=0), r"u_rated_v must be a finite number above 0 V, "
                                           r"not 0"),
    (lambda: tune(SGMSH_15A, speed_kp_a_per_rad_s=math.nan),
     r"speed kp must be a finite number at least 0 A/\(rad/s\), not nan"),
    (lambda: to_raw("x", 1.0, "UQ(16, 8)"), r"x format must be a QFormat, not 'UQ\(16, 8\)'"),
    (lambda: physical_from_registers({"mode": 1}), r"'mode' is not a PI gain register; choose "
                                                   r"from pi_d_kp, .*"),
    (lambda: t_min_s(1e-3, 1000, 5.0, 5.0), r"t_load_nm 5\.0 N·m must be below t_max_nm 5 N·m"),
    (lambda: t_min_s(0, 1000, 5.0), r"j_kgm2 must be a finite number above 0 kg·m², not 0"),
])
def test_tuning_validation_messages(call, message):
    with pytest.raises((ValueError, TypeError), match=rf"^{message}$"):
        call()


def test_t_min_current_limited_step():
    m = SGMSH_15A
    # 0 → 1667 r/min at the catalogue's peak torque: J·Δω/T = 2.47e-4 · 174.6 / 14.7.
    t = t_min_s(m.j_kgm2, 1667, m.t_peak_nm)
    assert t == pytest.approx(2.47e-4 * 1667 * 2 * math.pi / 60 / 14.7, rel=1e-12)
    assert 2.9e-3 < t < 3.0e-3                     # the paper's "< 1 ms" needs ~3× the torque
    # A load torque slows it; the sign of the step does not matter.
    assert t_min_s(m.j_kgm2, -1667, m.t_peak_nm, 4.9) == pytest.approx(t * 14.7 / 9.8)
    # Integrating J·dω/dt = T_max − T_load numerically reaches Δω at t_min.
    dt, w, steps = 1e-7, 0.0, 0
    while w < 1667 * 2 * math.pi / 60:
        w += (m.t_peak_nm - 4.9) / m.j_kgm2 * dt
        steps += 1
    assert steps * dt == pytest.approx(t_min_s(m.j_kgm2, 1667, m.t_peak_nm, 4.9), rel=1e-4)
