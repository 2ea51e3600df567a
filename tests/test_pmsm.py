# Ref: issue 6 item 1 (plant validation against analytic results) and item 7 (fault models);
#      Yaskawa SGMSH-15A table (sim/motor.py); hdl/encoder.py (quadrature, HALL_CODES, Z index)
"""The plant (sim/pmsm.py) against analytic results, an independent RK4 model and the encoder
decoder's golden model. Each test states its tolerance."""

import cmath
import math
import time

import numpy as np
import pytest

from foc_servo.hdl.encoder import HALL_CODES, hall_centres, quadrature_phase
from foc_servo.sim.models.encoder import QuadratureDecoderModel, hall_code
from foc_servo.sim.motor import DEFAULT_MOTOR
from foc_servo.sim.pmsm import (GATE_DTYPE, SENSOR_DTYPE, DcLink, Plant, Sensors,
                                ShootThroughError, quadrature_levels)

CLK = 50e6
M = DEFAULT_MOTOR
# Datasheet values (SGMSH-15A table), independent of the derivations in sim/motor.py.
KT_ARMS = 0.561         # N·m/A rms
J_SHEET = 2.47e-4       # kg·m²
TAU_E = 7.7e-3          # s, inductive time constant
LEG = [cmath.exp(2j * math.pi * k / 3) for k in range(3)]


def clocks(t_s):
    return int(round(t_s * CLK))


def pwm_period_events(c0, period, duties, dead):
    """Gate events of one centre-aligned PWM period from clock c0 (every leg low at c0): per
    phase low off, high on ``dead`` later, high off, low on ``dead`` later (12 edges)."""
    edges = []
    for k, d in enumerate(duties):
        d = min(max(d, 0.0), 1.0)
        r = c0 + int(round((1 - d) * period / 2))
        f = c0 + int(round((1 + d) * period / 2))
        if f - r <= dead:
            continue
        edges += [(r, k, 0), (r + dead, k, 1), (f, k, 2), (f + dead, k, 3)]
    edges.sort()
    gh, gl, out = 0, 7, []
    for c, k, kind in edges:
        if kind == 0:
            gl &= ~(1 << k)
        elif kind == 1:
            gh |= 1 << k
        elif kind == 2:
            gh &= ~(1 << k)
        else:
            gl |= 1 << k
        if out and out[-1][0] == c:
            out[-1] = (c, gh, gl)
        else:
            out.append((c, gh, gl))
    return np.array(out, dtype=GATE_DTYPE)


def q_axis_duties(theta_e, m, phi=math.pi / 2):
    """Duties putting a voltage vector of modulation m (of U_dc/2) at θ_e + φ (default: on the
    q axis)."""
    return [0.5 + 0.5 * m * math.cos(theta_e + phi - 2 * math.pi * k / 3) for k in range(3)]


def park_q(i_abc, theta_e):
    """i_q from phase currents (the test's own Clarke + Park)."""
    i_al = (2 * i_abc[0] - i_abc[1] - i_abc[2]) / 3
    i_be = (i_abc[1] - i_abc[2]) / math.sqrt(3)
    return -math.sin(theta_e) * i_al + math.cos(theta_e) * i_be


# --- analytic electrical tests ------------------------------------------------------------------

def test_locked_rotor_rl_step_matches_exponential():
    """Tolerance 0.1 % (brief); measured ~1e-13. The time constant is the datasheet's 7.7 ms."""
    udc = 10.0
    for gates, phase in (((0b001, 0b110), 0), ((0b010, 0b101), 1)):
        p = Plant(udc_v=udc, rotor="held")
        p.advance(0, None, gates)
        u_ph = 2.0 / 3.0 * udc               # star voltage of the driven phase
        for t in (0.2e-3, 1e-3, TAU_E, 3 * TAU_E):
            p.advance(clocks(t))
            i = p.i_abc
            expect = u_ph / M.r_ohm * (1 - math.exp(-t / TAU_E))
            assert i[phase] == pytest.approx(expect, rel=1e-3)
            others = [i[k] for k in range(3) if k != phase]
            assert others == pytest.approx([-expect / 2] * 2, rel=1e-3)
        assert p.omega_m == 0.0 and p.theta_m == 0.0


def test_open_circuit_back_emf_amplitude_and_frequency():
    """Gates off, speed held: currents stay exactly 0; the line-to-line terminal voltage is a
    sine of amplitude √2·K_t,rms/√3·ω_m (= √3·ω_e·ψ) and frequency P·n/60, within 0.1 %."""
    w = 3000 * 2 * math.pi / 60
    p = Plant(omega_m0=w, rotor="held", theta_m0=0.1)
    step = clocks(5e-6)
    t, v_ab = [], []
    for k in range(1, 4001):                                # 20 ms: 4 electrical periods
        p.advance(k * step)
        assert p.i_abc == (0.0, 0.0, 0.0)
        v = p.terminal_v()
        e = p.back_emf_abc()
        assert v[0] - v[1] == pytest.approx(e[0] - e[1], abs=1e-9)
        t.append(p.t_s)
        v_ab.append(v[0] - v[1])
    t, v_ab = np.array(t), np.array(v_ab)
    # Frequency from the rising zero crossings (linear interpolation).
    k = np.nonzero((v_ab[:-1] < 0) & (v_ab[1:] >= 0))[0]
    tz = t[k] - v_ab[k] * (t[k + 1] - t[k]) / (v_ab[k + 1] - v_ab[k])
    f = (len(tz) - 1) / (tz[-1] - tz[0])
    assert f == pytest.approx(M.pole_pairs * 3000 / 60, rel=1e-3)
    # Amplitude: least-squares sine at that frequency.
    basis = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)])
    coef, *_ = np.linalg.lstsq(basis, v_ab, rcond=None)
    amp = math.hypot(*coef)
    assert amp == pytest.approx(math.sqrt(2) * KT_ARMS / math.sqrt(3) * w, rel=1e-3)
    assert amp == pytest.approx(math.sqrt(3) * M.pole_pairs * w * M.psi_wb, rel=1e-3)


def test_energy_balance_pwm_with_load_and_dead_time():
    """30 ms of PWM (10 kHz, 12 edges per period, 1 µs dead time) with a 2 N·m load: electrical
    energy in = mechanical out + copper loss + Δ(magnetic + kinetic), within 0.5 % (brief); the
    test asks 1e-5."""
    period, dead = 5000, 50
    p = Plant(load_nm=2.0)
    p.advance(0, None, (0, 7))
    edges = 0
    for k in range(300):
        ev = pwm_period_events(k * period, period, q_axis_duties(p.theta_e, 0.3), dead)
        edges += len(ev)
        p.advance((k + 1) * period, ev)
    assert edges == 300 * 12
    e = p.energy
    assert e.e_in_j > 10.0 and e.e_copper_j > 0.5 and e.e_load_j > 1.0 and e.w_kin_j > 1.0
    assert abs(e.residual_j) <= 1e-5 * e.e_in_j
    assert abs(e.residual_j) <= 5e-3 * e.e_in_j
    assert p.speed_rpm > 500


def _rk4_reference(gate_list, period, n_periods, udc, load_nm, h_clk):
    """Independent model: RK4 on (i_α, i_β, ω, θ) with the leg voltages ±U_dc/2 of the gates
    (every leg driven by a switch), step h_clk clocks; returns the state at the end."""
    r, l, psi, pp, j = M.r_ohm, M.l_q_h, M.psi_wb, M.pole_pairs, M.j_kgm2
    h = h_clk / CLK

    def f(s, v):
        ia, ib, w, th = s
        we = pp * w
        ea, eb = -we * psi * math.sin(pp * th), we * psi * math.cos(pp * th)
        iq = -math.sin(pp * th) * ia + math.cos(pp * th) * ib
        return ((v.real - r * ia - ea) / l, (v.imag - r * ib - eb) / l,
                (1.5 * pp * psi * iq - load_nm) / j, w)

    s = (0.0, 0.0, 0.0, 0.0)
    level = (0, 7)
    events = {int(c): (int(gh), int(gl)) for ev in gate_list for c, gh, gl in ev}
    for c in range(0, n_periods * period, h_clk):
        if c in events:
            level = events[c]
        gh, gl = level
        v = sum((1 if (gh >> k) & 1 else -1) * udc / 3 * LEG[k] for k in range(3))
        k1 = f(s, v)
        k2 = f(tuple(a + 0.5 * h * b for a, b in zip(s, k1)), v)
        k3 = f(tuple(a + 0.5 * h * b for a, b in zip(s, k2)), v)
        k4 = f(tuple(a + h * b for a, b in zip(s, k3)), v)
        s = tuple(a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
                  for a, b1, b2, b3, b4 in zip(s, k1, k2, k3, k4))
    return s


def test_pwm_run_against_independent_rk4_model():
    """Free rotor, load 1 N·m, 3 ms of PWM without dead time (edges on multiples of 10 clocks):
    currents within 1 mA, speed within 1e-4 rad/s, angle within 1e-6 rad of an RK4 model with
    200 ns steps."""
    period, n = 5000, 30
    p = Plant(load_nm=1.0, theta_m0=0.0)
    p.advance(0, None, (0, 7))
    gate_list = []
    for k in range(n):
        duties = [round(d * 250) / 250 for d in q_axis_duties(p.theta_e, 0.5)]
        ev = pwm_period_events(k * period, period, duties, 0)
        assert np.all(ev["clock"] % 10 == 0)
        gate_list.append(ev)
        p.advance((k + 1) * period, ev)
    ia, ib, w, th = _rk4_reference(gate_list, period, n, 310.0, 1.0, 10)
    assert p.i_alpha_beta == pytest.approx((ia, ib), abs=1e-3)
    assert abs(p.i_alpha_beta[1]) > 5.0
    assert p.omega_m == pytest.approx(w, abs=1e-4)
    assert p.theta_m == pytest.approx(th, abs=1e-6)


def test_dead_time_diode_freewheels_then_opens():
    """a high, b and c low builds i_a > 0; then a's high switch off: the low diode clamps a to
    −U/2. (1) b, c low: free decay i0·e^{−t/τ}; (2) b, c high: driven to 0 along −2U/(3R) + …,
    then the leg opens and i_a stays 0 (no reverse current). Tolerance 1e-6 relative / 1 µA."""
    udc = 20.0
    tau = M.l_q_h / M.r_ohm
    for bc_high in (False, True):
        p = Plant(udc_v=udc, rotor="held")
        p.advance(0, None, (0b001, 0b110))
        p.advance(clocks(5e-3))
        i0 = p.i_abc[0]
        c0 = p.now
        p.advance(c0, None, (0b110, 0) if bc_high else (0, 0b110))
        assert p.terminal_v()[0] == -udc / 2
        i_inf = -2 * udc / (3 * M.r_ohm) if bc_high else 0.0
        t_zero = tau * math.log((i0 - i_inf) / -i_inf) if bc_high else math.inf
        for t in (0.1e-3, 1e-3, 2.5e-3, 2.99e-3, 3.02e-3, 6e-3):
            p.advance(c0 + clocks(t))
            expect = i_inf + (i0 - i_inf) * math.exp(-t / tau) if t < t_zero else 0.0
            assert p.i_abc[0] == pytest.approx(expect, rel=1e-6, abs=1e-6)
            if t > t_zero:
                assert p.i_abc == (0.0, 0.0, 0.0)
                assert -udc / 2 < p.terminal_v()[0] <= udc / 2      # open, within the bus
        assert abs(p.energy.residual_j) < 1e-9


def test_one_open_leg_against_scalar_rk4():
    """a high, b low, c off with no current (leg c open): i_a = −i_b, i_c = 0 exactly, and
    L·di/dt = U/2 − R·i − (e_a − e_b)/2 at a held 2000 r/min: within 1e-6 A of an RK4 solution
    (50 ns steps) after 0.5 ms."""
    w = 2000 * 2 * math.pi / 60
    p = Plant(udc_v=310.0, rotor="held", omega_m0=w, theta_m0=0.3)
    p.advance(0, None, (0b001, 0b010))
    p.advance(clocks(0.5e-3))
    r, l, psi, pp = M.r_ohm, M.l_q_h, M.psi_wb, M.pole_pairs
    i, h = 0.0, 50e-9

    def f(t, i):
        th = pp * (0.3 + w * t)
        e_ab = -pp * w * psi * (math.sin(th) - math.sin(th - 2 * math.pi / 3))
        return (155.0 - r * i - e_ab / 2) / l

    t = 0.0
    for _ in range(10000):
        k1 = f(t, i)
        k2 = f(t + h / 2, i + h / 2 * k1)
        k3 = f(t + h / 2, i + h / 2 * k2)
        k4 = f(t + h, i + h * k3)
        i += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    ia, ib, ic = p.i_abc
    assert ic == pytest.approx(0.0, abs=1e-12)
    assert ia == pytest.approx(-ib, abs=1e-12)
    assert ia == pytest.approx(i, abs=1e-6)
    assert ia > 1.0
    assert abs(p.energy.residual_j) < 1e-9


def test_gates_off_rectification_starts_when_line_emf_reaches_the_bus():
    """Gates off, held speed with a line-to-line EMF peak (183 V) above U_dc (100 V): no current
    until max|e_xy| first reaches U_dc (within 1 µs), then the diodes rectify: energy flows into
    the bus (e_in < 0) and the balance holds (1e-9 of the energy converted)."""
    w = 400.0
    p = Plant(udc_v=100.0, omega_m0=w, rotor="held", theta_m0=0.0)
    pp, psi = M.pole_pairs, M.psi_wb
    t = np.arange(0, 1e-3, 1e-9)
    th = pp * w * t
    e = [-pp * w * psi * np.sin(th - 2 * np.pi * k / 3) for k in range(3)]
    ll = np.max(np.abs([e[0] - e[1], e[1] - e[2], e[2] - e[0]]), axis=0)
    t_on = t[np.argmax(ll >= 100.0)]
    step = clocks(0.2e-6)
    first = None
    for k in range(1, 2000):
        p.advance(k * step)
        if first is None and max(map(abs, p.i_abc)) > 0.0:
            first = p.t_s
    assert first == pytest.approx(t_on, abs=1e-6)
    en = p.energy
    assert en.e_in_j < -1e-3
    assert abs(en.residual_j) < 1e-9 * max(1.0, -en.e_load_j)
    assert en.e_load_j < 0        # the dynamometer drives the rotor


# --- mechanics ------------------------------------------------------------------------------------

def test_free_acceleration_follows_torque_over_inertia():
    """Constant voltage vector on the q axis from standstill, free rotor: ω(t) = ∫T/J dt with
    T = K_t,rms/√2 · i_q (datasheet K_t and J; i_q from the phase currents by the test's own
    Park transform), trapezoid over 2 µs samples; within 0.1 %."""
    p = Plant(udc_v=20.0, theta_m0=-math.pi / 2 / M.pole_pairs)   # q axis along phase a
    p.advance(0, None, (0b001, 0b110))
    step = clocks(2e-6)
    torque = [0.0]
    for k in range(1, 1001):
        p.advance(k * step)
        torque.append(KT_ARMS / math.sqrt(2) * park_q(p.i_abc, p.theta_e))
        assert p.torque_nm == pytest.approx(torque[-1], rel=1e-3, abs=1e-9)
    omega = np.trapezoid(torque, dx=2e-6) / J_SHEET
    assert p.omega_m == pytest.approx(omega, rel=1e-3)
    assert p.omega_m > 10.0


def test_load_and_friction_decelerate_as_analytic():
    """Gates off (no current below the diode threshold): constant load → ω0 − T_L·t/J exactly;
    viscous friction → ω0·e^{−b·t/J}. Tolerance 1e-9 relative."""
    p = Plant(omega_m0=100.0, load_nm=0.5)
    p.advance(clocks(10e-3))
    assert p.omega_m == pytest.approx(100.0 - 0.5 * 10e-3 / M.j_kgm2, rel=1e-9)
    assert p.theta_m == pytest.approx(100.0 * 10e-3 - 0.25 * 1e-4 / M.j_kgm2, rel=1e-9)
    b = 2e-3
    p = Plant(M.replace(b_nms=b), omega_m0=100.0)
    p.advance(clocks(50e-3))
    assert p.omega_m == pytest.approx(100.0 * math.exp(-b * 50e-3 / M.j_kgm2), rel=1e-6)
    e = p.energy
    assert e.e_friction_j == pytest.approx(e.w_kin0_j - e.w_kin_j, rel=1e-6)


def test_load_torque_callable_of_time():
    """A load torque that is a function of time: a step at 5 ms; ω within 1e-9 relative."""
    p = Plant(omega_m0=50.0, load_nm=lambda t: 0.0 if t < 5e-3 else 1.0)
    p.advance(clocks(10e-3))
    assert p.omega_m == pytest.approx(50.0 - 1.0 * 5e-3 / M.j_kgm2, rel=1e-9)


# --- DC link --------------------------------------------------------------------------------------

def test_dc_link_charges_through_the_source_resistance():
    """Capacitor at 200 V, source 310 V through 0.5 Ω, 1 mF, no load: u(t) = 310 − 110·e^{−t/RC}
    within 1e-9 relative; the DC-link energy accounts balance."""
    p = Plant(udc_v=200.0, dc_link=DcLink(c_f=1e-3, r_source_ohm=0.5, u_source_v=310.0))
    for t in (0.1e-3, 0.5e-3, 2e-3):
        p.advance(clocks(t))
        assert p.udc_v == pytest.approx(310.0 - 110.0 * math.exp(-t / 0.5e-3), rel=1e-9)
    assert abs(p.energy.dc_residual_j) < 1e-9 * p.energy.e_source_j


def test_regenerative_braking_overcharges_the_dc_link():
    """3000 r/min, 6 ms of a PWM voltage vector for i_q ≈ −10 A (85.5 V at θ_e + 69°): the
    rectifier cannot take the energy back, so U_dc rises above the source; DC-link balance within
    1e-9 of the energy, motor balance within 1e-5, and ∫u_c·i_dc = e_in within 1e-4."""
    period, dead = 5000, 50
    dc = DcLink(c_f=1e-3, r_source_ohm=0.5, u_source_v=310.0)
    p = Plant(dc_link=dc, omega_m0=3000 * 2 * math.pi / 60)
    p.advance(0, None, (0, 7))
    for k in range(60):
        m = 85.5 / (p.udc_v / 2)
        duties = q_axis_duties(p.theta_e, m, math.radians(69.2))
        p.advance((k + 1) * period, pwm_period_events(k * period, period, duties, dead))
    e = p.energy
    assert p.udc_v > 320.0
    assert p.speed_rpm < 2200.0
    assert e.e_in_j < -4.0
    assert abs(e.dc_residual_j) < 1e-9 * abs(e.e_in_j) + 1e-9
    assert abs(e.residual_j) < 1e-5 * abs(e.e_in_j)
    assert e.e_bus_j == pytest.approx(e.e_in_j, rel=1e-4)
    assert 0.5 * dc.c_f * p.udc_v ** 2 > 0.5 * dc.c_f * 310.0 ** 2 + 3.0


# --- faults ---------------------------------------------------------------------------------------

def test_phase_to_phase_short_current_and_trip_behaviour():
    """Short a–b (0.05 Ω, 1 µH) while a is high and b low: the short current is
    U/r·(1 − e^{−t·r/L}) (1e-6 relative), the motor currents are those of a plant without the
    short (1e-9 A), the leg currents carry both, the comparator trips; after gates off the
    energy still balances (1e-9 of the fault loss)."""
    w = 200.0
    ref = Plant(rotor="held", omega_m0=w)
    p = Plant(rotor="held", omega_m0=w)
    for q in (ref, p):
        q.advance(0, None, (0b001, 0b110))
        q.advance(5000)
    p.short("ab", r_ohm=0.05, l_h=1e-6)
    assert not p.oc_level(40.0)
    for k in (1, 20, 300):
        p.advance(5000 + k)
        ref.advance(5000 + k)
        t = k / CLK
        assert p.i_short_a == pytest.approx(310.0 / 0.05 * (1 - math.exp(-t * 0.05 / 1e-6)),
                                            rel=1e-6)
        assert p.i_abc == pytest.approx(ref.i_abc, abs=1e-9)
        legs = p.i_leg_abc
        assert legs[0] == pytest.approx(p.i_abc[0] + p.i_short_a, abs=1e-9)
        assert legs[1] == pytest.approx(p.i_abc[1] - p.i_short_a, abs=1e-9)
    assert p.oc_level(40.0)
    assert p.adc_codes(noise=False)[:2] == (32767, -32768)
    p.advance(p.now, None, (0, 0))
    p.advance(p.now + clocks(2e-3))
    e = p.energy
    assert e.e_fault_j > 0.1
    assert abs(e.residual_j) < 1e-9 * e.e_fault_j
    # After the trip the short current decays through the diodes; then the EMF drives a loop
    # current through the short only (legs open).
    assert p.i_leg_abc == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert abs(p.i_short_a) > 1.0


def test_shoot_through_raises_with_clock_and_phase():
    p = Plant()
    ev = np.array([(100, 0b010, 0b101), (200, 0b010, 0b111)], dtype=GATE_DTYPE)
    with pytest.raises(ShootThroughError, match=r"^both switches of phase b are on from clock "
                                                r"200 \(gate_h 010, gate_l 111\): shoot-through$"):
        p.advance(300, ev)
    assert p.now == 200
    with pytest.raises(ShootThroughError, match=r"^both switches of phase a are on from clock 0 "):
        Plant().advance(10, None, (0b101, 0b011))


# --- sensors --------------------------------------------------------------------------------------

def _collect(p, until, chunk=5000):
    """Sensor edges from now to ``until`` in chunks, advancing the plant: (levels, edges)."""
    levels, out = None, []
    while p.now < until:
        end = min(until, p.now + chunk)
        sch = p.sensor_events(end)
        if levels is None:
            levels = sch.levels
        out.append(sch.edges)
        p.advance(end)
    return levels, np.concatenate(out)


@pytest.mark.parametrize("direction", [1, -1])
def test_encoder_counts_four_per_line_per_turn_with_one_index(direction):
    """Held ±3000 r/min for two turns (started half a count off a boundary): 4·lines quadrature
    steps per turn, all in the direction of rotation (+1 = A leads B), one Z pulse per turn,
    one count wide, at z_count. Exact."""
    lines, z_count = 5000, 123
    step = 2 * math.pi / (4 * lines)
    w = direction * 3000 * 2 * math.pi / 60
    p = Plant(rotor="held", omega_m0=w, theta_m0=0.5 * step,
              sensors=Sensors(z_count=z_count, lines=lines))
    levels, ev = _collect(p, clocks(2 * 60 / 3000))
    q = quadrature_phase(np.r_[levels["a"], ev["a"]].astype(int),
                         np.r_[levels["b"], ev["b"]].astype(int))
    dq = np.diff(q) % 4
    steps = np.count_nonzero(dq == (1 if direction > 0 else 3))
    assert steps == 2 * 4 * lines
    assert np.count_nonzero(dq == 2) == 0
    assert np.count_nonzero(dq == (3 if direction > 0 else 1)) == 0
    z = np.r_[levels["z"], ev["z"]].astype(int)
    rises = np.nonzero(np.diff(z) == 1)[0] + 1
    falls = np.nonzero(np.diff(z) == -1)[0] + 1
    assert len(rises) == 2 and len(falls) == 2
    # One count wide: Z rises with the step into count z_count and falls with the next step
    # (row j of the levels changes with dq[j − 1]).
    for r in rises:
        f = falls[falls > r][0]
        assert dq[r - 1] != 0 and dq[f - 1] != 0
        assert np.count_nonzero(dq[r - 1:f - 1]) == 1
    assert np.diff(ev["clock"]).min() >= 1


def test_encoder_edges_decode_to_the_true_angle():
    """The emitted A/B/Z fed to the decoder's golden model (z_offset from
    Plant.z_offset_register): after the index, its electrical position equals
    P·floor(θ_m/step) mod cpr at every chunk end (exact); decoded θ within one count."""
    z_count = 777
    p = Plant(rotor="held", omega_m0=-2000 * 2 * math.pi / 60, theta_m0=1.0,
              sensors=Sensors(z_count=z_count))
    zo = p.z_offset_register()
    assert zo == (M.pole_pairs * z_count) % 20000
    dec = QuadratureDecoderModel(lines=5000, pole_pairs=M.pole_pairs, z_offset=zo)
    step = 2 * math.pi / 20000
    first = True
    for k in range(1, 401):
        sch = p.sensor_events(k * 5000)
        if first:
            lv = sch.levels
            dec.tick(int(lv["a"]), int(lv["b"]), int(lv["z"]), z_offset=zo)
            first = False
        for r in sch.edges:
            dec.tick(int(r["a"]), int(r["b"]), int(r["z"]), z_offset=zo)
        p.advance(k * 5000)
        if dec.aligned:
            assert dec.e == (M.pole_pairs * math.floor(p.theta_m / step)) % 20000
            err = (dec.theta - p.theta_e / (2 * math.pi) * 65536 + 32768) % 65536 - 32768
            assert -4 * 65536 / 20000 - 1 <= err <= 1
    assert dec.aligned


@pytest.mark.parametrize("direction", [1, -1])
def test_hall_sequence_and_sector_angles(direction):
    """Held ±1500 r/min, Hall offset 20°: codes run through HALL_CODES (5, 1, 3, 2, 6, 4)
    forward and the reverse backward; between edges the code is hall_code(θ_e − offset) of the
    decoder's golden model; each edge is within one clock of a 60° boundary; the decoder's
    sector centre + Plant.hall_offset_register() is within 30° of θ_e."""
    off = math.radians(20)
    w = direction * 1500 * 2 * math.pi / 60
    p = Plant(rotor="held", omega_m0=w, theta_m0=0.2, sensors=Sensors(hall_offset_rad=off))
    levels, ev = _collect(p, clocks(20e-3))
    h = np.r_[levels["hall"], ev["hall"]]
    c = np.r_[0, ev["clock"]]
    change = np.r_[True, h[1:] != h[:-1]]
    codes, when = h[change], c[change]
    assert len(codes) > 10
    order = list(HALL_CODES) if direction > 0 else list(HALL_CODES)[::-1]
    k0 = order.index(int(codes[0]))
    assert codes.tolist() == [order[(k0 + i) % 6] for i in range(len(codes))]
    pp = M.pole_pairs
    centres = hall_centres()
    raw_off = p.hall_offset_register()
    for i in range(1, len(codes) - 1):
        mid = 0.5 * (when[i] + when[i + 1]) / CLK
        th_e = pp * (0.2 + w * mid)
        raw = int(math.floor((th_e - off) / (2 * math.pi) * 65536)) % 65536
        assert codes[i] == hall_code(raw)
        # Edge at a boundary: (θ_e − off) at the edge clock is a multiple of 60° (1 clock).
        th_edge = pp * (0.2 + w * when[i] / CLK) - off
        dist = (th_edge / (math.pi / 3) + 0.5) % 1.0 - 0.5
        assert abs(dist) * (math.pi / 3) <= abs(pp * w) / CLK + 1e-9
        decoded = (centres[HALL_CODES.index(int(codes[i]))] + raw_off) % 65536
        diff = ((decoded - th_e / (2 * math.pi) * 65536) + 32768) % 65536 - 32768
        assert abs(diff) <= 65536 / 12 + 1


def test_sensor_schedule_tracks_a_pwm_run_without_back_and_forth():
    """PWM acceleration (the acceleration changes inside every chunk, so the prediction is
    off): every quadrature step is forward, edges of the encoder are ≥ min_edge_clk apart, and
    the emitted count stays within one count of floor(θ_m/step)."""
    period = 5000
    p = Plant()
    p.advance(0, None, (0, 7))
    step = 2 * math.pi / 20000
    levels, out = None, []
    for k in range(200):
        sch = p.sensor_events((k + 1) * period)
        if levels is None:
            levels = sch.levels
        out.append(sch.edges)
        p.advance((k + 1) * period, pwm_period_events(k * period, period,
                                                      q_axis_duties(p.theta_e, 0.3), 50))
        lv = p.sensor_levels()
        n = math.floor(p.theta_m / step)
        assert (int(lv["a"]), int(lv["b"])) in {quadrature_levels(n + d) for d in (-1, 0, 1)}
    ev = np.concatenate(out)
    q = quadrature_phase(np.r_[levels["a"], ev["a"]].astype(int),
                         np.r_[levels["b"], ev["b"]].astype(int))
    dq = np.diff(q) % 4
    assert np.count_nonzero(dq == 3) == 0 and np.count_nonzero(dq == 2) == 0
    assert np.count_nonzero(dq == 1) > 1000
    enc = ev[np.r_[True, (ev["a"][1:] != ev["a"][:-1]) | (ev["b"][1:] != ev["b"][:-1])]]
    assert np.diff(enc["clock"]).min() >= 8


def test_sensor_catch_up_edges_are_spaced_by_min_edge_clk():
    """A load step the prediction cannot see (rotor at rest when the chunk is predicted, a
    −20 N·m load from 10 µs on): the edges missed are emitted from now + 1 on, min_edge_clk
    apart, and the count catches up exactly."""
    p = Plant(load_nm=lambda t: 0.0 if t < 10e-6 else -20.0, sensors=Sensors(min_edge_clk=12))
    sch = p.sensor_events(50000)
    assert len(sch.edges) == 0
    p.advance(50000)
    n = math.floor(p.theta_m / (2 * math.pi / 20000))
    assert n >= 50
    p.advance(50000, None, None)
    sch = p.sensor_events(50001 + 12 * n)
    enc = sch.edges
    assert enc["clock"][0] == 50001
    assert np.all(np.diff(enc["clock"][:n]) == 12)
    q = quadrature_phase(enc["a"].astype(int), enc["b"].astype(int))
    assert q[n - 1] == n % 4


def test_sensor_events_asked_again_supersede_the_unused_ones():
    """Edges emitted for clocks after now are forgotten when asked again (a caller that stopped
    early): the levels at the stop are those of the first schedule at that clock."""
    w = 3000 * 2 * math.pi / 60
    p = Plant(rotor="held", omega_m0=w)
    first = p.sensor_events(10000)
    p.advance(4321)
    again = p.sensor_events(10000)
    before = first.edges[first.edges["clock"] <= 4321][-1]
    for f in ("a", "b", "z", "hall"):
        assert again.levels[f] == before[f]
    assert again.levels["clock"] == 4321
    assert np.all(again.edges["clock"] > 4321)
    np.testing.assert_array_equal(again.edges, first.edges[first.edges["clock"] > 4321])


def test_sensor_faults_broken_a_line_and_floating_hall():
    w = 1000 * 2 * math.pi / 60
    p = Plant(rotor="held", omega_m0=w, sensors=Sensors(enc_a_broken=1, hall_floating=1))
    levels, ev = _collect(p, clocks(5e-3))
    assert levels["a"] == 1 and np.all(ev["a"] == 1)
    assert np.count_nonzero(np.diff(ev["b"].astype(int))) > 100
    assert levels["hall"] == 7 and np.all(ev["hall"] == 7)
    p = Plant(rotor="held", omega_m0=w, sensors=Sensors(enc_a_broken=0, hall_floating=0))
    levels, ev = _collect(p, clocks(1e-3))
    assert np.all(ev["a"] == 0) and np.all(ev["hall"] == 0)
    assert ev.dtype == SENSOR_DTYPE


def test_adc_codes_quantisation_noise_offset_and_saturation():
    """Noiseless codes are round(x/fs·32768) (exact); noise has σ within 5 % and a mean within
    0.1 LSB over 4000 draws, is seeded; offsets add; currents beyond full scale and U_dc beyond
    32767 LSB saturate."""
    udc = 10.0
    p = Plant(udc_v=udc, rotor="held", sensors=Sensors(i_fs_a=40.0, u_lsb_v=12.5e-3))
    p.advance(0, None, (0b001, 0b110))
    p.advance(clocks(2e-3))
    ia, ib, _ = p.i_abc
    codes = p.adc_codes(noise=False)
    assert codes == (round(ia / 40 * 32768), round(ib / 40 * 32768), round(udc / 12.5e-3), 0)
    draws = np.array([p.adc_codes() for _ in range(4000)])
    assert np.std(draws[:, 0]) == pytest.approx(1.0, rel=0.05)
    assert np.mean(draws[:, 0]) == pytest.approx(ia / 40 * 32768, abs=0.1)
    q = Plant(udc_v=udc, rotor="held", seed=7)
    r = Plant(udc_v=udc, rotor="held", seed=7)
    assert [q.adc_codes() for _ in range(5)] == [r.adc_codes() for _ in range(5)]
    s = Plant(udc_v=310.0, sensors=Sensors(adc_offset_lsb=(3, -2, 10, 5), noise_lsb=0.0))
    assert s.adc_codes() == (3, -2, 24800 + 10, 5)
    hi = Plant(udc_v=500.0, sensors=Sensors(noise_lsb=0.0))
    assert hi.adc_codes()[2] == 32767
    big = Plant(udc_v=310.0, rotor="held", sensors=Sensors(i_fs_a=1.0, noise_lsb=0.0))
    big.advance(0, None, (0b001, 0b110))
    big.advance(clocks(1e-3))
    assert big.adc_codes()[:2] == (32767, -32768)
    assert big.oc_level(1.0) and not big.oc_level(1e4)


# --- parameters and API ---------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, exc, message", [
    (dict(udc_v=-1.0), ValueError,
     r"^Plant udc_v -1\.0 V is outside the allowed range \(0, 2000\] V$"),
    (dict(udc_v="310"), TypeError, r"^Plant udc_v must be a number in \(0, 2000\] V, not '310'$"),
    (dict(clk_hz=0), ValueError, r"^Plant clk_hz 0 Hz is outside the allowed range "
                                 r"\[100000, 1e\+10\] Hz$"),
    (dict(omega_m0=1e5), ValueError, r"^Plant omega_m0 100000\.0 rad/s is outside the allowed "
                                     r"range \[-5235\.99, 5235\.99\] rad/s$"),
    (dict(rotor="locked"), ValueError, r"^Plant rotor must be 'free' or 'held', not 'locked'$"),
    (dict(max_step_s=1e-3), ValueError, r"^Plant max_step_s 0\.001 s is outside the allowed "
                                        r"range \[1e-08, 0\.0001\] s$"),
    (dict(sensors=3), TypeError, r"^Plant sensors must be a Sensors or None, not 3$"),
    (dict(dc_link=310.0), TypeError, r"^Plant dc_link must be None or a DcLink, not 310\.0$"),
    (dict(seed=-1), ValueError, r"^Plant seed -1 is outside the allowed range 0 … "),
    (dict(motor=M.replace(l_d_h=1e-3)), ValueError,
     r"^Plant models a surface PMSM: motor l_d_h 0\.001 H must equal l_q_h 0\.00242"),
    (dict(sensors=Sensors(z_count=20000)), ValueError,
     r"^Sensors z_count 20000 counts is outside the allowed range 0 … 19999 \(4·lines − 1\)$"),
])
def test_plant_parameter_errors(kwargs, exc, message):
    motor = kwargs.pop("motor", M)
    with pytest.raises(exc, match=message):
        Plant(motor, **kwargs)


@pytest.mark.parametrize("make, exc, message", [
    (lambda: Sensors(lines=100, z_count=400), ValueError,
     r"^Sensors z_count 400 counts is outside the allowed range 0 … 399 \(4·lines − 1\)$"),
    (lambda: Sensors(enc_a_broken=2), TypeError,
     r"^Sensors enc_a_broken must be None, 0 or 1, not 2$"),
    (lambda: Sensors(hysteresis_counts=1.0), ValueError,
     r"^Sensors hysteresis_counts 1\.0 counts is outside the allowed range \[0, 1\) counts$"),
    (lambda: Sensors(i_fs_a=0.0), ValueError,
     r"^Sensors i_fs_a 0\.0 A is outside the allowed range \(0, 10000\] A$"),
    (lambda: Sensors(adc_offset_lsb=(1, 2, 3)), TypeError,
     r"^Sensors adc_offset_lsb must be 4 integers from -32768 to 32767 LSB, not \(1, 2, 3\)$"),
    (lambda: Sensors(min_edge_clk=0), ValueError,
     r"^Sensors min_edge_clk 0 clocks is outside the allowed range 1 … 1000$"),
    (lambda: DcLink(c_f=0.0), ValueError,
     r"^DcLink c_f 0\.0 F is outside the allowed range \(0, 1\] F$"),
    (lambda: Plant().short("aa"), ValueError,
     r"^Plant short phases must be two distinct letters of 'abc', not 'aa'$"),
    (lambda: Plant().short("bc", r_ohm=0.0), ValueError,
     r"^Plant short r_ohm 0\.0 Ω is outside the allowed range \(0, 1000\] Ω$"),
    (lambda: Plant().advance(-1), ValueError, r"^Plant clock -1 is before now \(0\)$"),
    (lambda: Plant().advance(1.5), TypeError, r"^Plant clock must be an integer, not 1\.5$"),
    (lambda: Plant().advance(10, np.array([(11, 0, 0)], dtype=GATE_DTYPE)), ValueError,
     r"^Plant gate_events clocks must be in \[now, until\] = \[0, 10\], not 11 … 11$"),
    (lambda: Plant().advance(10, None, (8, 0)), ValueError,
     r"^Plant gate levels must be 3-bit integers \(0 … 7\), not \(8, 0\)$"),
    (lambda: Plant().oc_level(-1.0), ValueError,
     r"^Plant oc_level threshold_a -1\.0 A is outside the allowed range \[0, 1e\+06\] A$"),
])
def test_other_parameter_errors(make, exc, message):
    with pytest.raises(exc, match=message):
        make()


def test_state_properties_are_consistent():
    """i_dq is the Park transform of i_abc at θ_e, speed_rpm of ω, torque of i_q (exact)."""
    p = Plant(udc_v=50.0, theta_m0=0.4, omega_m0=30.0)
    p.advance(0, None, (0b011, 0b100))
    p.advance(clocks(1e-3))
    th = p.theta_e
    assert 0.0 <= th < 2 * math.pi
    assert th == pytest.approx((M.pole_pairs * p.theta_m) % (2 * math.pi), abs=1e-12)
    assert p.i_dq[1] == pytest.approx(park_q(p.i_abc, th), abs=1e-9)
    assert sum(p.i_abc) == pytest.approx(0.0, abs=1e-12)
    assert p.speed_rpm == pytest.approx(p.omega_m * 60 / (2 * math.pi))
    assert p.torque_nm == pytest.approx(1.5 * M.pole_pairs * M.psi_wb * p.i_dq[1])
    assert p.now == clocks(1e-3) and p.t_s == pytest.approx(1e-3)
    assert p.gates == (0b011, 0b100)


@pytest.mark.slow
def test_python_cost_per_100ms_at_10khz():
    """100 ms of motor time at 10 kHz PWM, 12 gate edges and one sensor_events call per period:
    at most 2 s of CPU (brief: ≤ ~2 s of Python per 100 ms)."""
    period = 5000
    p = Plant(load_nm=1.0)
    p.advance(0, None, (0, 7))
    evs = [None] * 1000
    cpu = 0.0
    for k in range(1000):
        evs = pwm_period_events(k * period, period, q_axis_duties(p.theta_e, 0.5), 50)
        t0 = time.process_time()
        p.sensor_events((k + 1) * period)
        p.advance((k + 1) * period, evs)
        cpu += time.process_time() - t0
    print(f"plant CPU per 100 ms of motor time: {cpu:.2f} s")
    assert cpu <= 2.0
