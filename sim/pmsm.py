# Ref: issue 6 item 1 (plant: PMSM + two-level inverter + pin-level sensors) and item 7 (faults:
#      phase-to-phase short, DC link without brake resistor); SPEC.md §1 (T_e = 3/2·P·ψ_F·i_q);
#      hdl/encoder.py (quadrature phase, HALL_CODES, Z index); hdl/adc.py (AD7380-4 codes);
#      sim/motor.py (the default motor, Yaskawa SGMSH-15A); docs/PLANT.md (equations, validation)
"""The plant: a surface PMSM behind a two-level inverter, its DC link and its sensors, at pin level.

Time at the API is the controller's **system clock** (an int; ``clk_hz`` given): the closed loop
hands the plant the gate edges the gateware produced, and asks it for the encoder and Hall edges
and the ADC codes, once per chunk (about a PWM period), never once per clock.

Model (docs/PLANT.md has the derivations)
-----------------------------------------
*Motor* (star, neutral floating, sinusoidal EMF, ``L_d = L_q = L``, star-equivalent ``R``, ``L``,
amplitude-invariant αβ/dq, complex notation ``i = i_α + j·i_β``)::

    L·di/dt = v − R·i − e,     e = j·ω_e·ψ·e^{jθ_e}   (e_a = −ω_e·ψ·sin θ_e, …)
    T_e = 1.5·P·ψ·i_q,   J·dω_m/dt = T_e − T_load(t) − b·ω_m,   θ_e = P·θ_m

*Inverter*: leg x drives its terminal to ``+U_dc/2`` (high switch on) or ``−U_dc/2`` (low switch
on), measured from the DC-bus midpoint. With both switches off (dead time, or gates off) the
freewheeling diodes decide: leg current ``j_x > 0`` (out of the leg into the motor) flows through
the low diode (``−U_dc/2``), ``j_x < 0`` through the high one (``+U_dc/2``); at ``j_x = 0`` the
leg is open (its current stays 0) until the voltage the motor puts on the open terminal leaves
``[−U_dc/2, +U_dc/2]``, when the diode on that side starts to conduct (uncontrolled
rectification). Switches and diodes are ideal (no drop). Both switches of a leg on
(shoot-through) raises :class:`ShootThroughError`.

*Faults*: :meth:`Plant.short` ties two motor terminals through ``r_ohm`` (and the fault path's
wiring inductance ``l_h``); the currents the sensors see are the inverter's leg currents (motor
phase current plus the short's). :class:`DcLink` replaces the stiff bus by a capacitor fed from a
rectified source through ``r_source_ohm``; the rectifier only delivers current, so regeneration
charges the capacitor (no brake resistor).

Solver
------
State ``x`` = the motor currents ``(i_α, i_β)`` and, with a short, its current ``i_s``. Energy
``W = ½·xᵀMx`` (``M = diag(1.5L, 1.5L, L_s)``), losses ``xᵀR̃x`` (``R̃ = diag(1.5R, 1.5R, r)``),
leg currents ``j = Gᵀx``::

    M·dx/dt = −R̃·x − ẽ(t) + G·v,        ẽ = 1.5·(e_α, e_β, 0)

Open legs add the constraints ``g_xᵀx = 0`` (their unknown voltages are the Lagrange
multipliers), so the state moves in the null space ``x = N·y``; the generalised eigenvectors of
``(NᵀR̃N, NᵀMN)`` decouple it into scalar modes ``ż_k = −μ_k·z_k + β_k + Re(γ_k·e^{jθ_e(t)})``.
Between two events (gate edge, diode turn-off or turn-on) the leg voltages and U_dc are constant
and, over a sub-step of at most ``max_step_s`` (default 2 µs), so is ω_m (held at the speed
predicted for the sub-step's middle): each mode then has the **exact closed-form** solution
``z(t) = a·e^{−μt} + c + Re(d·e^{jω_e·t})``, and so do the integrals the energy accounts and the
mechanics need (∫z, ∫z_k·z_l, ∫e^{jθ}·z). Without a short and with no leg open (every PWM state,
dead time included) the two modes are one complex exponential, evaluated directly. Diode current
zero crossings and diode turn-on are located inside the sub-step by a bracketing root finder
(to 1e-7 A / 1e-6 V) and the sub-step ends there.

Error bound: the electrical solution is exact for the piecewise-constant (ω_m, U_dc) it is given.
The approximations are (1) ω_m held over a sub-step ``h`` at the value predicted for its middle
(from the last sub-step's acceleration): the EMF phase is off by at most
``P·(|α|/8 + |Δα|/2)·h²`` (Δα: the change of the acceleration between sub-steps) and its
magnitude by a zero-mean ramp of at most ``ψ·P·|α|·h/2``; at the motor's peak acceleration
(14.7 N·m / J = 60 000 rad/s²) and ``h`` = 2 µs that is 1.2·10⁻⁷ rad and 16 mV (0.005 % of
310 V), a current deviation of at most ``ψ·P·|α|·h²/(8L)`` = 3.3 µA inside a sub-step that
cancels to O(h³) at its end; (2) the mechanics, ``ω ← ω + h·(T̄_e − T_L(t + h/2) − b·ω̄)/J``,
``θ ← θ + h·ω̄`` with the exact mean torque ``T̄_e`` of the sub-step (second order in h);
(3) U_dc of a :class:`DcLink` held over a sub-step (it moves by ``|i_dc|·h/C``, 0.04 V at 20 A
and 1 mF). Measured against an RK4 model (tests/test_pmsm.py): 5 µA on 60 A, 3·10⁻⁵ rad/s on
163 rad/s, 7·10⁻⁸ rad after 3 ms of PWM acceleration (modulation 0.5); energy balance residual
5·10⁻⁸ of the energy converted.

Cost: 0.6 s of CPU in :meth:`Plant.advance` and 0.3 s in :meth:`Plant.sensor_events` per 100 ms
of motor time at 10 kHz PWM with 12 gate edges per period (docs/PLANT.md, "Performance").

Sensors
-------
:meth:`Plant.sensor_events` predicts the encoder (A/B/Z, ×4 quadrature, A leads B for positive
rotation: :func:`~foc_servo.hdl.encoder.quadrature_phase` counts up) and Hall edges (codes
:data:`~foc_servo.hdl.encoder.HALL_CODES`, sector ``floor((θ_e − hall_offset)/60°)``) up to a
clock from θ, ω and the present acceleration. It remembers what it emitted: an edge comes when the
predicted trajectory crosses the next boundary from the last *emitted* count, and a reversal needs
``hysteresis_counts`` beyond the boundary, so prediction errors at chunk boundaries make no
back-and-forth edges. :meth:`Plant.adc_codes` gives the AD7380-4's four codes (ia, ib, udc, aux).
"""

import cmath
import dataclasses
import math
import numbers
from typing import NamedTuple

import numpy as np

from ..hdl.encoder import HALL_CODES
from .motor import DEFAULT_MOTOR, MotorParams

__all__ = ["Plant", "Sensors", "DcLink", "PlantEnergy", "SensorSchedule", "ShootThroughError",
           "GATE_DTYPE", "SENSOR_DTYPE", "quadrature_levels"]

#: Gate events: the levels (bit 0 = phase a) that take effect from ``clock`` on.
GATE_DTYPE = np.dtype([("clock", "<i8"), ("gate_h", "u1"), ("gate_l", "u1")])
#: Sensor pin levels after an edge (``hall``: bit 0 = H_a).
SENSOR_DTYPE = np.dtype([("clock", "<i8"), ("a", "u1"), ("b", "u1"), ("z", "u1"),
                         ("hall", "u1")])

_TWO_PI = 2.0 * math.pi
_SQRT3 = math.sqrt(3.0)
#: e^{j·2πk/3}: the direction of phase k in the αβ plane.
_LEG = (1.0 + 0.0j, complex(-0.5, _SQRT3 / 2), complex(-0.5, -_SQRT3 / 2))
#: Quadrature state n mod 4 → (A, B): 00, 10, 11, 01 (the inverse of hdl.encoder.quadrature_phase).
_QUAD_A = np.array([0, 1, 1, 0], dtype=np.uint8)
_QUAD_B = np.array([0, 0, 1, 1], dtype=np.uint8)
_HALL = np.array(HALL_CODES, dtype=np.uint8)
#: A leg whose |current| is below this is open (A); root finder tolerances (A, V).
_EPS_I = 1e-6
_FTOL_I = 1e-7
_FTOL_V = 1e-6


def quadrature_levels(count):
    """Encoder (A, B) levels of a ×4 count (int or int array): n mod 4 = 0, 1, 2, 3 → (0, 0),
    (1, 0), (1, 1), (0, 1), so that counting up is A leading B."""
    q = np.asarray(count) % 4
    a, b = _QUAD_A[q], _QUAD_B[q]
    return (int(a), int(b)) if np.ndim(q) == 0 else (a, b)


class ShootThroughError(RuntimeError):
    """Both switches of an inverter leg were on: the gateware must never do this."""


def _is_real(value):
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _check_real(owner, name, value, lo, hi, unit, *, lo_open=False, hi_open=False):
    """A finite real in the range; TypeError for a wrong type, ValueError outside the range."""
    rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if not _is_real(value):
        raise TypeError(f"{owner} {name} must be a number in {rng} {unit}, not {value!r}".replace(
            "  ", " "))
    v = float(value)
    if (not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo)
            or (hi_open and v == hi)):
        raise ValueError(f"{owner} {name} {value!r} {unit} is outside the allowed range "
                         f"{rng} {unit}".replace("  ", " ").rstrip())
    return v


def _check_int(owner, name, value, lo, hi, unit=""):
    if not isinstance(value, numbers.Integral) or isinstance(value, bool):
        raise TypeError(f"{owner} {name} must be an integer from {lo} to {hi} {unit}, "
                        f"not {value!r}".replace("  ", " "))
    if not lo <= value <= hi:
        raise ValueError(f"{owner} {name} {value!r} {unit} is outside the allowed range "
                         f"{lo} … {hi}".replace("  ", " "))
    return int(value)


@dataclasses.dataclass(frozen=True)
class DcLink:
    """A DC-link capacitor fed from a diode-rectified source, without a brake resistor.

    The source delivers ``(u_source_v − u_c)/r_source_ohm`` while that is positive and nothing
    otherwise, so energy returned by the motor (regenerative braking) charges the capacitor.

    Parameters
    ----------
    c_f : float
        Capacitance, F, (0, 1].
    r_source_ohm : float
        Source resistance (rectifier, line, inrush), Ω, (0, 1000].
    u_source_v : float
        Source (rectified peak) voltage, V, (0, 2000].
    """
    c_f: float = 1e-3
    r_source_ohm: float = 0.5
    u_source_v: float = 310.0

    def __post_init__(self):
        object.__setattr__(self, "c_f", _check_real("DcLink", "c_f", self.c_f, 0.0, 1.0, "F",
                                                    lo_open=True))
        object.__setattr__(self, "r_source_ohm", _check_real(
            "DcLink", "r_source_ohm", self.r_source_ohm, 0.0, 1000.0, "Ω", lo_open=True))
        object.__setattr__(self, "u_source_v", _check_real(
            "DcLink", "u_source_v", self.u_source_v, 0.0, 2000.0, "V", lo_open=True))


@dataclasses.dataclass(frozen=True)
class Sensors:
    """Pin-level sensor models: incremental encoder, Hall switches, ADC.

    Parameters
    ----------
    lines : int or None
        Encoder lines per turn (×4: ``cpr = 4·lines`` counts); ``None``: the motor's
        ``encoder_lines``. 1 … 2²⁰.
    z_count : int
        The ×4 count (0 … cpr − 1, from θ_m = 0) during which Z is high, once per turn. The
        decoder's angle is right when its ``enc_z_offset`` is ``pole_pairs·z_count mod cpr``
        (:meth:`Plant.z_offset_register`).
    hall_offset_rad : float
        Electrical angle of the Hall pattern: sector ``k`` (code ``HALL_CODES[k]``) for
        ``θ_e − hall_offset_rad ∈ [60°·k, 60°·(k + 1))``; the decoder's ``enc_hall_offset`` is this
        angle (:meth:`Plant.hall_offset_register`). [−2π, 2π] rad.
    hysteresis_counts : float
        Reversal hysteresis of the encoder and Hall edges, in encoder counts, [0, 1).
    min_edge_clk : int
        Least spacing of two edges of the encoder (or of the Hall) schedule, clocks (catch-up edges
        after a prediction error are spaced by it, so the decoder's glitch filter passes them).
        1 … 1000.
    enc_a_broken : None, 0 or 1
        A broken line on encoder A: held at that level.
    hall_floating : None, 0 or 1
        Hall connector off: all three lines at that level (1: pull-ups, code 111).
    i_fs_a : float
        ADC current full scale: the current of code 32768, A, (0, 10000].
    u_lsb_v : float
        ADC U_dc scale, V per LSB, (0, 10].
    noise_lsb : float
        Standard deviation of the Gaussian ADC noise, LSB, [0, 1000].
    adc_offset_lsb : tuple of 4 ints
        Offsets added to the codes (ia, ib, udc, aux), LSB, each −32768 … 32767.
    aux_v : float
        Voltage on the unused channel D, in the U_dc scale, V.
    """
    lines: int = None
    z_count: int = 0
    hall_offset_rad: float = 0.0
    hysteresis_counts: float = 0.25
    min_edge_clk: int = 8
    enc_a_broken: int = None
    hall_floating: int = None
    i_fs_a: float = 40.0
    u_lsb_v: float = 12.5e-3
    noise_lsb: float = 1.0
    adc_offset_lsb: tuple = (0, 0, 0, 0)
    aux_v: float = 0.0

    def __post_init__(self):
        if self.lines is not None:
            _check_int("Sensors", "lines", self.lines, 1, 1 << 20, "lines")
        _check_int("Sensors", "z_count", self.z_count, 0, (1 << 22) - 1, "counts")
        if self.lines is not None and self.z_count >= 4 * self.lines:
            raise ValueError(f"Sensors z_count {self.z_count} counts is outside the allowed "
                             f"range 0 … {4 * self.lines - 1} (4·lines − 1)")
        _check_real("Sensors", "hall_offset_rad", self.hall_offset_rad, -_TWO_PI, _TWO_PI, "rad")
        _check_real("Sensors", "hysteresis_counts", self.hysteresis_counts, 0.0, 1.0, "counts",
                    hi_open=True)
        _check_int("Sensors", "min_edge_clk", self.min_edge_clk, 1, 1000, "clocks")
        for name in ("enc_a_broken", "hall_floating"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, numbers.Integral)
                                      or isinstance(value, bool) or value not in (0, 1)):
                raise TypeError(f"Sensors {name} must be None, 0 or 1, not {value!r}")
        _check_real("Sensors", "i_fs_a", self.i_fs_a, 0.0, 10000.0, "A", lo_open=True)
        _check_real("Sensors", "u_lsb_v", self.u_lsb_v, 0.0, 10.0, "V", lo_open=True)
        _check_real("Sensors", "noise_lsb", self.noise_lsb, 0.0, 1000.0, "LSB")
        _check_real("Sensors", "aux_v", self.aux_v, -1e4, 1e4, "V")
        off = self.adc_offset_lsb
        if (not isinstance(off, (tuple, list)) or len(off) != 4
                or any(not isinstance(o, numbers.Integral) or isinstance(o, bool)
                       or not -32768 <= o <= 32767 for o in off)):
            raise TypeError(f"Sensors adc_offset_lsb must be 4 integers from -32768 to 32767 "
                            f"LSB, not {off!r}")
        object.__setattr__(self, "adc_offset_lsb", tuple(int(o) for o in off))


@dataclasses.dataclass(frozen=True)
class PlantEnergy:
    """Energy accounts since the plant was made, J (a snapshot: :attr:`Plant.energy`).

    Balance (:attr:`residual_j`, zero up to the solver error)::

        e_in = e_load + e_friction + e_copper + e_fault + Δw_mag + Δw_kin

    Attributes
    ----------
    e_in_j : float
        Electrical energy from the DC bus into the inverter, ∫U_dc·i_dc dt.
    e_load_j : float
        Mechanical energy into the load, ∫T_load·ω dt (with ``rotor="held"``, all the shaft work
        ∫(T_e − b·ω)·ω dt).
    e_friction_j : float
        Viscous friction, ∫b·ω² dt.
    e_copper_j : float
        Motor copper loss, ∫R·(i_a² + i_b² + i_c²) dt.
    e_fault_j : float
        Loss in the short's resistance.
    w_mag_j, w_mag0_j : float
        Stored magnetic energy now and at the start (motor ``0.75·L·|i_αβ|²`` + the short's).
    w_kin_j, w_kin0_j : float
        Kinetic energy ``½·J·ω²`` now and at the start.
    e_source_j, e_source_loss_j, e_bus_j, w_cap_j, w_cap0_j : float
        :class:`DcLink` accounts: energy from the source, its loss in ``r_source_ohm``, energy
        drawn from the capacitor node ∫u_c·i_dc dt (≈ ``e_in_j``), capacitor energy now and at the
        start; all 0 with a stiff bus.
    """
    e_in_j: float
    e_load_j: float
    e_friction_j: float
    e_copper_j: float
    e_fault_j: float
    w_mag_j: float
    w_mag0_j: float
    w_kin_j: float
    w_kin0_j: float
    e_source_j: float
    e_source_loss_j: float
    e_bus_j: float
    w_cap_j: float
    w_cap0_j: float

    @property
    def residual_j(self):
        """``e_in − (e_load + e_friction + e_copper + e_fault + Δw_mag + Δw_kin)``."""
        return self.e_in_j - (self.e_load_j + self.e_friction_j + self.e_copper_j
                              + self.e_fault_j + self.w_mag_j - self.w_mag0_j
                              + self.w_kin_j - self.w_kin0_j)

    @property
    def dc_residual_j(self):
        """DC link: ``e_source − e_source_loss − e_bus − Δw_cap``."""
        return (self.e_source_j - self.e_source_loss_j - self.e_bus_j
                - (self.w_cap_j - self.w_cap0_j))


class SensorSchedule(NamedTuple):
    """:meth:`Plant.sensor_events`: ``edges`` (SENSOR_DTYPE array, the pin levels after each
    edge, clocks increasing, only clocks where a level changes) and ``levels`` (a SENSOR_DTYPE
    record: the levels at ``clock = now``)."""
    edges: np.ndarray
    levels: np.void


# --- closed-form pieces --------------------------------------------------------------------------

def _phi(s, h):
    """∫₀ʰ e^{s·t} dt = (e^{s·h} − 1)/s (complex or real s; h for s → 0)."""
    x = s * h
    if abs(x) < 1e-4:
        return h * (1.0 + x * (0.5 + x * (1.0 / 6.0 + x / 24.0)))
    if isinstance(x, complex):
        return (cmath.exp(x) - 1.0) / s
    return math.expm1(x) / s


def _root(f, fa, fb, h, ftol):
    """The crossing of f in (0, h], given f(0) = fa < 0 ≤ fb = f(h): Illinois regula falsi with a
    bisection every fourth step. Returns a t with 0 ≤ f(t) ≤ ftol, or the end of a bracket of
    1e-15 s whose right end has f ≥ 0 (the event has happened at the returned time)."""
    a, b = 0.0, h
    fa_w, fb_w = fa, fb                  # Illinois-weighted end values
    side = 0
    for it in range(200):
        if fb <= ftol or b - a <= 1e-15:
            break
        c = (a * fb_w - b * fa_w) / (fb_w - fa_w)
        if it % 4 == 3 or not a < c < b:
            c = 0.5 * (a + b)
        fc = f(c)
        if fc >= 0.0:
            b, fb, fb_w = c, fc, fc
            if side == 1:
                fa_w *= 0.5
            side = 1
        else:
            a, fa, fa_w = c, fc, fc
            if side == -1:
                fb_w *= 0.5
            side = -1
    return b


class _Topology:
    """The constrained circuit for one set of open legs (and the short, if any): modes, the
    maps from modes to currents, and the open legs' implied voltages."""

    def __init__(self, open_mask, r_ohm, l_h, short):
        n = 2 if short is None else 3
        self.open = open_mask
        g = np.zeros((n, 3))
        for x in range(3):
            g[0, x], g[1, x] = _LEG[x].real, _LEG[x].imag
        m_mat = np.diag([1.5 * l_h, 1.5 * l_h] + ([] if short is None else [short[3]]))
        r_mat = np.diag([1.5 * r_ohm, 1.5 * r_ohm] + ([] if short is None else [short[2]]))
        if short is not None:
            g[2, short[0]] += 1.0
            g[2, short[1]] -= 1.0
        go = g[:, [x for x in range(3) if open_mask[x]]]
        if go.shape[1]:
            u, s, vt = np.linalg.svd(go.T)
            rank = int((s > 1e-12 * s.max()).sum())
            null = vt[rank:].T
        else:
            null = np.eye(n)
        m = null.shape[1]
        self.m = m
        if m:
            k = null.T @ m_mat @ null
            rr = null.T @ r_mat @ null
            chol = np.linalg.cholesky(k)
            ci = np.linalg.inv(chol)
            mu, w = np.linalg.eigh(ci @ rr @ ci.T)
            v = ci.T @ w                                    # Vᵀ·K·V = I, Vᵀ·Rr·V = diag(μ)
            x_of_z = null @ v                               # x = X·z
            z_of_x = v.T @ k @ null.T                       # z = Z·x (x in the null space)
        else:
            mu = np.zeros(0)
            x_of_z = np.zeros((n, 0))
            z_of_x = np.zeros((0, n))
        self.mu = [float(u_) for u_ in mu]
        self.xz = [[float(c) for c in row] for row in x_of_z]          # n × m
        self.zx = [[float(c) for c in row] for row in z_of_x]          # m × n
        self.jz = [[float(c) for c in row] for row in (g.T @ x_of_z)]   # 3 × m: leg currents
        self.bz = [[float(c) for c in row] for row in (x_of_z.T @ g)]   # m × 3: β = B·v
        ge = np.zeros(n, dtype=complex)
        ge[0], ge[1] = 1j, 1.0
        self.gamma = [complex(c) for c in (x_of_z.T @ ge)]             # γ_k per −1.5·ω_e·ψ
        # Copper (motor) and fault losses as quadratic forms of z.
        cu = (x_of_z[:2].T @ x_of_z[:2]) * 1.5 * r_ohm
        fault = (x_of_z[2:].T @ x_of_z[2:]) * (short[2] if short is not None else 0.0)
        self.cu = [[float(c) for c in row] for row in cu]
        self.fault = [[float(c) for c in row] for row in fault]
        # Implied voltages of the open legs: v_o = P·(−R̃x − ẽ + G_d·v_d).
        if go.shape[1]:
            mi = np.linalg.inv(m_mat)
            self.p_open = -np.linalg.pinv(go.T @ mi @ go) @ go.T @ mi
        else:
            self.p_open = np.zeros((0, n))
        self.g = g
        self.r_mat = r_mat
        self.n = n

    def implied(self, x, e_ab, v):
        """Voltages of the open legs (in leg order), for state x, EMF e_αβ (complex) and leg
        voltages v (open legs' entries ignored)."""
        vd = np.array([0.0 if self.open[k] else v[k] for k in range(3)])
        f = -self.r_mat @ np.asarray(x, dtype=float) + self.g @ vd
        f[0] -= 1.5 * e_ab.real
        f[1] -= 1.5 * e_ab.imag
        return self.p_open @ f


class _ModalSeg:
    """Closed-form solution of the modes over a sub-step (constant ω_e, voltages)."""

    __slots__ = ("we", "th0", "a", "c", "d", "mu")

    def __init__(self, topo, z0, beta, gam, we, th0):
        self.we, self.th0 = we, th0
        self.mu = topo.mu
        rot = cmath.exp(1j * th0)
        self.a, self.c, self.d = [], [], []
        for k, mu in enumerate(topo.mu):
            c = beta[k] / mu
            d = gam[k] * rot / complex(mu, we)
            self.a.append(z0[k] - c - d.real)
            self.c.append(c)
            self.d.append(d)

    def z(self, t):
        w = cmath.exp(1j * self.we * t)
        return [a * math.exp(-mu * t) + c + (d * w).real
                for a, c, d, mu in zip(self.a, self.c, self.d, self.mu)]

    def integrals(self, h):
        """(∫z_k, ∫z_k·z_l matrix, ∫e^{jθ}·z_k) over [0, h]."""
        we, mus = self.we, self.mu
        jw = 1j * we
        m = len(mus)
        f_jw = _phi(jw, h)
        f_2jw = _phi(2 * jw, h)
        iz, ie = [], []
        for k in range(m):
            a, c, d, mu = self.a[k], self.c[k], self.d[k], mus[k]
            iz.append(a * _phi(-mu, h) + c * h + (d * f_jw).real)
            ie.append(cmath.exp(1j * self.th0) * (a * _phi(jw - mu, h) + c * f_jw
                                                   + 0.5 * d * f_2jw + 0.5 * d.conjugate() * h))
        izz = [[0.0] * m for _ in range(m)]
        for k in range(m):
            for l in range(k, m):
                ak, ck, dk, mk = self.a[k], self.c[k], self.d[k], mus[k]
                al, cl, dl, ml = self.a[l], self.c[l], self.d[l], mus[l]
                v = (ak * al * _phi(-mk - ml, h) + ak * cl * _phi(-mk, h)
                     + ck * al * _phi(-ml, h) + ck * cl * h
                     + (ak * dl * _phi(jw - mk, h)).real + (al * dk * _phi(jw - ml, h)).real
                     + (ck * dl * f_jw).real + (cl * dk * f_jw).real
                     + 0.5 * (dk * dl * f_2jw).real + 0.5 * (dk * dl.conjugate()).real * h)
                izz[k][l] = izz[l][k] = v
        return iz, izz, ie


class _Track:
    """Emitted state of one sensor's edge schedule (encoder count or Hall sector)."""

    def __init__(self, step, off, hyst, gap, theta0):
        self.step, self.off, self.hyst, self.gap = step, off, hyst, gap
        self.idx = math.floor((theta0 - off) / step)
        self.dir = 0
        self.last = -(1 << 40)
        self.sched = None           # (clocks, idx, dir) emitted by the last call, clocks > base

    def rebase(self, now):
        """Keep the emitted edges up to ``now`` (the state at now); forget the rest."""
        if self.sched is not None:
            clocks, idx, dirs = self.sched
            k = int(np.searchsorted(clocks, now, side="right"))
            if k:
                self.idx, self.dir, self.last = int(idx[k - 1]), int(dirs[k - 1]), \
                    int(clocks[k - 1])
            self.sched = None

    def predict(self, th0, w, acc, horizon):
        """Edge times (s from now), indices and directions for θ(t) = th0 + w·t + acc·t²/2,
        t ∈ [0, horizon]."""
        step, off, hyst = self.step, self.off, self.hyst
        idx, d = self.idx, self.dir
        times, idxs, dirs = [], [], []

        def emit(t, new, s):
            times.append(t)
            idxs.append(new)
            dirs.append(np.full(len(new), s, dtype=np.int64))

        # Catch up with the angle now if it is beyond the thresholds (a prediction error).
        if th0 >= (idx + 1) * step + off + (hyst if d < 0 else 0.0):
            k = math.floor((th0 - off) / step)
            emit(np.zeros(k - idx), np.arange(idx + 1, k + 1), 1)
            idx, d = k, 1
        elif th0 < idx * step + off - (hyst if d > 0 else 0.0):
            k = math.floor((th0 - off) / step)
            emit(np.zeros(idx - k), np.arange(idx - 1, k - 1, -1), -1)
            idx, d = k, -1
        # Monotone pieces of the trajectory (split at the turning point).
        pieces = [(0.0, horizon)]
        if acc != 0.0 and 0.0 < -w / acc < horizon:
            pieces = [(0.0, -w / acc), (-w / acc, horizon)]
        for ta, tb in pieces:
            th_a = th0 + w * ta + 0.5 * acc * ta * ta
            th_b = th0 + w * tb + 0.5 * acc * tb * tb
            wa = w + acc * ta
            if th_b > th_a:
                s = 1
                thr1 = (idx + 1) * step + off + (hyst if d < 0 else 0.0)
                if th_b < thr1:
                    continue
                k = math.floor((th_b - off) / step)
                new = np.arange(idx + 1, k + 1)
                thr = new * step + off
            elif th_b < th_a:
                s = -1
                thr1 = idx * step + off - (hyst if d > 0 else 0.0)
                if th_b >= thr1:
                    continue
                k = math.floor((th_b - off) / step)
                new = np.arange(idx - 1, k - 1, -1)
                thr = (new + 1) * step + off
            else:
                continue
            thr[0] = thr1
            delta = thr - th_a
            if acc == 0.0:
                tau = delta / wa
            else:
                # Stable root of acc·τ²/2 + wa·τ − delta = 0 on the branch moving with s.
                disc = np.sqrt(np.maximum(wa * wa + 2.0 * acc * delta, 0.0))
                den = wa + s * disc
                with np.errstate(divide="ignore", invalid="ignore"):
                    tau = np.where(den != 0.0, 2.0 * delta / den, 0.0)
            emit(ta + np.clip(tau, 0.0, tb - ta), new, s)
            idx, d = k, s
        if not times:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return (np.concatenate(times), np.concatenate(idxs).astype(np.int64),
                np.concatenate(dirs))

    def schedule(self, now, until, clk_hz, th0, w, acc):
        """Clocks (in (now, until]), indices and directions of the edges from ``now``."""
        self.rebase(now)
        t, idx, dirs = self.predict(th0, w, acc, (until - now) / clk_hz)
        if not len(t):
            return t.astype(np.int64), idx, dirs
        clocks = now + np.maximum(np.ceil(t * clk_hz - 1e-6).astype(np.int64), 1)
        # Least spacing `gap`, also from the last emitted edge: c'_k = max_j≤k (c_j + (k−j)·gap).
        k = np.arange(len(clocks), dtype=np.int64)
        first = max(int(clocks[0]), self.last + self.gap)
        clocks[0] = first
        clocks = np.maximum.accumulate(clocks - k * self.gap) + k * self.gap
        keep = clocks <= until
        clocks, idx, dirs = clocks[keep], idx[keep], dirs[keep]
        self.sched = (clocks, idx, dirs)
        return clocks, idx, dirs


# --- the plant -----------------------------------------------------------------------------------

class Plant:
    """Surface PMSM + two-level inverter + DC link + encoder, Hall and ADC, in system clocks.

    Parameters
    ----------
    motor : MotorParams
        The motor (default :data:`~foc_servo.sim.motor.DEFAULT_MOTOR`, Yaskawa SGMSH-15A). It
        must be a surface PMSM (``l_d_h == l_q_h``).
    clk_hz : float
        System clock, Hz, [1e5, 1e10]: the unit of every clock at the API.
    udc_v : float
        DC-bus voltage, V, (0, 2000]: a stiff source, or the capacitor's initial voltage with
        ``dc_link``.
    dc_link : DcLink or None
        A capacitor fed by a rectifier (no brake resistor) instead of a stiff bus.
    load_nm : float or callable
        Load torque (opposing positive rotation when positive; an active load), N·m, or a
        function ``load_nm(t_s)`` of the plant's time in seconds.
    sensors : Sensors or None
        Sensor models; ``None``: ``Sensors()``.
    theta_m0 : float
        Initial mechanical angle, rad (θ_e = P·θ_m; the encoder counts from θ_m = 0).
    omega_m0 : float
        Initial mechanical speed, rad/s, within ±10·n_max.
    seed : int
        Seed of the ADC noise.
    rotor : str
        ``"free"``: J, b and the load move it; ``"held"``: the speed stays ``omega_m0`` whatever
        the torque (a stiff dynamometer; ``omega_m0 = 0`` locks the rotor).
    max_step_s : float
        Longest sub-step over which ω_m and U_dc are held, s, [1e-8, 1e-4] (module docstring).

    Attributes
    ----------
    now : int
        The clock the state refers to.
    """

    def __init__(self, motor=DEFAULT_MOTOR, *, clk_hz=50e6, udc_v=310.0, dc_link=None,
                 load_nm=0.0, sensors=None, theta_m0=0.0, omega_m0=0.0, seed=0, rotor="free",
                 max_step_s=2e-6):
        if not isinstance(motor, MotorParams):
            raise TypeError(f"Plant motor must be a MotorParams, not {motor!r}")
        if motor.l_d_h != motor.l_q_h:
            raise ValueError(f"Plant models a surface PMSM: motor l_d_h {motor.l_d_h!r} H must "
                             f"equal l_q_h {motor.l_q_h!r} H")
        self._clk_hz = _check_real("Plant", "clk_hz", clk_hz, 1e5, 1e10, "Hz")
        udc = _check_real("Plant", "udc_v", udc_v, 0.0, 2000.0, "V", lo_open=True)
        if dc_link is not None and not isinstance(dc_link, DcLink):
            raise TypeError(f"Plant dc_link must be None or a DcLink, not {dc_link!r}")
        if callable(load_nm):
            self._load = load_nm
            self._load_const = None
        else:
            self._load_const = _check_real("Plant", "load_nm", load_nm, -1e5, 1e5, "N·m")
            self._load = None
        if sensors is None:
            sensors = Sensors()
        if not isinstance(sensors, Sensors):
            raise TypeError(f"Plant sensors must be a Sensors or None, not {sensors!r}")
        theta_m0 = _check_real("Plant", "theta_m0", theta_m0, -1e9, 1e9, "rad")
        w_max = 10.0 * motor.n_max_rpm * _TWO_PI / 60.0
        omega_m0 = _check_real("Plant", "omega_m0", omega_m0, -w_max, w_max, "rad/s")
        self._seed = _check_int("Plant", "seed", seed, 0, (1 << 63) - 1)
        if rotor not in ("free", "held"):
            raise ValueError(f"Plant rotor must be 'free' or 'held', not {rotor!r}")
        self._max_step = _check_real("Plant", "max_step_s", max_step_s, 1e-8, 1e-4, "s")

        self._motor = motor
        self._held = rotor == "held"
        self._r, self._l = motor.r_ohm, motor.l_q_h
        self._psi, self._p, self._j, self._b = (motor.psi_wb, motor.pole_pairs, motor.j_kgm2,
                                                motor.b_nms)
        lines = motor.encoder_lines if sensors.lines is None else sensors.lines
        if sensors.z_count >= 4 * lines:
            raise ValueError(f"Sensors z_count {sensors.z_count} counts is outside the allowed "
                             f"range 0 … {4 * lines - 1} (4·lines − 1)")
        self._sensors = sensors
        self._lines = lines
        self._cpr = 4 * lines
        self._dc = dc_link
        self._rng = np.random.default_rng(self._seed)

        # State.
        self._now = 0
        self._t = 0.0                       # seconds, = now / clk_hz at the end of advance()
        self._x = [0.0, 0.0]                # i_α, i_β (, i_s)
        self._theta = theta_m0              # mechanical angle, rad, unwrapped
        self._omega = omega_m0
        self._alpha = 0.0                   # acceleration of the last sub-step, rad/s²
        self._u = udc
        self._gates = (0, 0)
        self._short = None                  # (p, q, r_ohm, l_h)
        self._topos = {}
        # Energy accounts.
        self._e = dict(e_in=0.0, e_load=0.0, e_fric=0.0, e_cu=0.0, e_fault=0.0, e_src=0.0,
                       e_src_loss=0.0, e_bus=0.0)
        self._w_kin0 = 0.5 * self._j * omega_m0 ** 2
        self._w_cap0 = 0.0 if dc_link is None else 0.5 * dc_link.c_f * udc ** 2
        # Sensor schedules (mechanical angle tracks).
        step = _TWO_PI / self._cpr
        hyst = sensors.hysteresis_counts * step
        self._enc = _Track(step, 0.0, hyst, sensors.min_edge_clk, theta_m0)
        self._hall = _Track(math.pi / 3 / self._p, sensors.hall_offset_rad / self._p, hyst,
                            sensors.min_edge_clk, theta_m0)

    # --- read-only parameters and state ----------------------------------------------------------

    motor = property(lambda self: self._motor)
    sensors = property(lambda self: self._sensors)
    clk_hz = property(lambda self: self._clk_hz)
    dc_link = property(lambda self: self._dc)
    gates = property(lambda self: self._gates, doc="(gate_h, gate_l) in force now.")
    now = property(lambda self: self._now, doc="The clock the state refers to (0 at the start).")

    @property
    def t_s(self):
        """Plant time, s (``now / clk_hz``)."""
        return self.now / self._clk_hz

    @property
    def i_alpha_beta(self):
        """Motor currents (i_α, i_β), A (amplitude-invariant)."""
        return self._x[0], self._x[1]

    @property
    def i_abc(self):
        """Motor phase currents (i_a, i_b, i_c), A (positive into the motor)."""
        i = complex(self._x[0], self._x[1])
        return tuple((i * leg.conjugate()).real for leg in _LEG)

    @property
    def i_leg_abc(self):
        """Inverter output (leg) currents, A: the motor's plus a short's; what the ADC and the
        over-current comparator see."""
        return tuple(self._leg_currents(self._x))

    @property
    def i_dq(self):
        """(i_d, i_q), A, in the rotor frame at θ_e."""
        i = complex(self._x[0], self._x[1]) * cmath.exp(-1j * self._p * self._theta)
        return i.real, i.imag

    @property
    def i_short_a(self):
        """Current in the short (from its first to its second phase), A; 0 without one."""
        return self._x[2] if len(self._x) > 2 else 0.0

    @property
    def theta_m(self):
        """Mechanical angle, rad, unwrapped (continuous: counts whole turns)."""
        return self._theta

    @property
    def theta_e(self):
        """Electrical angle P·θ_m, rad, in [0, 2π)."""
        return (self._p * self._theta) % _TWO_PI

    @property
    def omega_m(self):
        """Mechanical speed, rad/s."""
        return self._omega

    @property
    def speed_rpm(self):
        return self._omega * 60.0 / _TWO_PI

    @property
    def alpha_m(self):
        """Mechanical acceleration (of the last sub-step), rad/s²."""
        return self._alpha

    @property
    def udc_v(self):
        """DC-bus voltage now, V."""
        return self._u

    @property
    def torque_nm(self):
        """Electromagnetic torque now, 1.5·P·ψ·i_q, N·m."""
        return 1.5 * self._p * self._psi * self.i_dq[1]

    @property
    def energy(self):
        """The energy accounts (:class:`PlantEnergy`)."""
        e = self._e
        return PlantEnergy(
            e_in_j=e["e_in"], e_load_j=e["e_load"], e_friction_j=e["e_fric"],
            e_copper_j=e["e_cu"], e_fault_j=e["e_fault"], w_mag_j=self._w_mag(), w_mag0_j=0.0,
            w_kin_j=0.5 * self._j * self._omega ** 2, w_kin0_j=self._w_kin0,
            e_source_j=e["e_src"], e_source_loss_j=e["e_src_loss"], e_bus_j=e["e_bus"],
            w_cap_j=0.0 if self._dc is None else 0.5 * self._dc.c_f * self._u ** 2,
            w_cap0_j=self._w_cap0)

    def _w_mag(self):
        x = self._x
        w = 0.75 * self._l * (x[0] * x[0] + x[1] * x[1])
        if self._short is not None:
            w += 0.5 * self._short[3] * x[2] * x[2]
        return w

    def back_emf_abc(self):
        """Phase back-EMFs (e_a, e_b, e_c) now, V: ``e_x = −ω_e·ψ·sin(θ_e − 2πk/3)``."""
        we, th = self._p * self._omega, self._p * self._theta
        return tuple(-we * self._psi * math.sin(th - _TWO_PI * k / 3) for k in range(3))

    def terminal_v(self):
        """Motor terminal voltages (v_a, v_b, v_c) now, V, from the DC-bus midpoint: ±U_dc/2 on
        a conducting leg, the voltage the motor puts on an open one. With every leg open the
        common mode is undefined; the voltages are then returned with zero mean (without a short:
        the phase EMFs, star point at the midpoint)."""
        sw = self._switch_states()
        states = self._resolve(sw, self._x, self._omega)
        v = [s * 0.5 * self._u for s in states]
        open_mask = tuple(s == 0 for s in states)
        if any(open_mask):
            topo = self._topology(open_mask)
            e = self._emf_ab(self._p * self._omega, self._p * self._theta)
            vo = topo.implied(self._x, e, v)
            for k, x in enumerate([x for x in range(3) if open_mask[x]]):
                v[x] = float(vo[k])
        return tuple(v)

    def z_offset_register(self):
        """The decoder's ``enc_z_offset`` for this encoder: ``pole_pairs·z_count mod cpr``."""
        return (self._p * self._sensors.z_count) % self._cpr

    def hall_offset_register(self):
        """The decoder's ``enc_hall_offset`` (BinaryAngle(16) raw) for this Hall placement."""
        return round(self._sensors.hall_offset_rad / _TWO_PI * 65536) % 65536

    # --- faults ----------------------------------------------------------------------------------

    def short(self, phases="ab", r_ohm=0.05, l_h=1e-6):
        """A phase-to-phase short at the motor terminals from now on.

        Parameters
        ----------
        phases : str
            Two distinct phase letters, ``"ab"``, ``"bc"`` or ``"ca"`` (either order).
        r_ohm : float
            Resistance of the short, Ω, (0, 1000].
        l_h : float
            Inductance of the fault path (wiring), H, [1e-9, 1e-3].
        """
        if (not isinstance(phases, str) or len(phases) != 2 or set(phases) - set("abc")
                or phases[0] == phases[1]):
            raise ValueError(f"Plant short phases must be two distinct letters of 'abc', "
                             f"not {phases!r}")
        if self._short is not None:
            raise ValueError("Plant short: there is already a short")
        r = _check_real("Plant short", "r_ohm", r_ohm, 0.0, 1000.0, "Ω", lo_open=True)
        lh = _check_real("Plant short", "l_h", l_h, 1e-9, 1e-3, "H")
        self._short = ("abc".index(phases[0]), "abc".index(phases[1]), r, lh)
        self._x = self._x[:2] + [0.0]
        self._topos = {}

    def sensor_fault(self, *, enc_a_broken=None, hall_floating=None):
        """A sensor wiring fault from now on: the encoder's A line held at 0 or 1, or the three
        Hall lines floating at 0 or 1 (``None``: that sensor intact). The pin changes at the next
        :meth:`sensor_events` (a level event at ``now + 1``)."""
        self._sensors = dataclasses.replace(self._sensors, enc_a_broken=enc_a_broken,
                                            hall_floating=hall_floating)

    # --- sensors ---------------------------------------------------------------------------------

    def adc_codes(self, noise=True):
        """The AD7380-4's codes (ia, ib, udc, aux) now: ``round(x/fs·32768 + noise) + offset``,
        saturated to 16-bit two's complement; currents are the leg currents of phases a and b at
        ``Sensors.i_fs_a``, U_dc and aux at ``Sensors.u_lsb_v`` per LSB."""
        s = self._sensors
        j = self._leg_currents(self._x)
        k_i = 32768.0 / s.i_fs_a
        x = np.array([j[0] * k_i, j[1] * k_i, self._u / s.u_lsb_v, s.aux_v / s.u_lsb_v])
        if noise and s.noise_lsb > 0.0:
            x = x + self._rng.normal(0.0, s.noise_lsb, 4)
        codes = np.round(np.clip(x, -1e9, 1e9)).astype(np.int64) + np.array(s.adc_offset_lsb)
        return tuple(int(c) for c in np.clip(codes, -32768, 32767))

    def oc_level(self, threshold_a):
        """The fast over-current comparator: whether any leg current's magnitude exceeds
        ``threshold_a`` (A) now."""
        thr = _check_real("Plant oc_level", "threshold_a", threshold_a, 0.0, 1e6, "A")
        return any(abs(j) > thr for j in self._leg_currents(self._x))

    def _pins(self, enc_idx, hall_idx):
        """Pin levels (a, b, z, hall) for count and sector index arrays."""
        s = self._sensors
        q = enc_idx % 4
        a, b = _QUAD_A[q], _QUAD_B[q]
        z = ((enc_idx % self._cpr) == s.z_count).astype(np.uint8)
        hall = _HALL[hall_idx % 6]
        if s.enc_a_broken is not None:
            a = np.full_like(a, s.enc_a_broken)
        if s.hall_floating is not None:
            hall = np.full_like(hall, 7 * s.hall_floating)
        return a, b, z, hall

    def sensor_events(self, until):
        """Encoder and Hall edges predicted from now to clock ``until``.

        The trajectory ``θ_m(t) = θ_m + ω_m·t + α·t²/2`` (α the present acceleration) is cut into
        encoder counts (``2π/cpr``) and Hall sectors (``π/(3P)``, at ``hall_offset_rad/P``); an
        edge's clock is the first clock edge at or after the crossing (``ceil``). What was emitted
        is remembered: the next edge is the next boundary from the last emitted count, a reversal
        needs ``hysteresis_counts`` beyond the boundary, and edges of one sensor are at least
        ``min_edge_clk`` apart (a prediction error is caught up by spaced edges from ``now + 1``).
        Edges emitted by an earlier call for clocks after ``now`` are forgotten (the new call
        supersedes them), so a caller that stopped early can simply ask again.

        Returns
        -------
        SensorSchedule
            ``(edges, levels)``: edges in (now, until], levels at now.
        """
        until = self._check_until(until)
        th, w = self._theta, self._omega
        acc = 0.0 if self._held else self._accel_now()
        ce, ie, _ = self._enc.schedule(self.now, until, self._clk_hz, th, w, acc)
        ch, ih, _ = self._hall.schedule(self.now, until, self._clk_hz, th, w, acc)
        # Levels at now: the state before the new edges (after rebase).
        e0, h0 = self._enc.idx, self._hall.idx
        a0, b0, z0, hl0 = self._pins(np.array([e0]), np.array([h0]))
        levels = np.zeros((), dtype=SENSOR_DTYPE)
        levels["clock"], levels["a"], levels["b"], levels["z"], levels["hall"] = \
            self.now, a0[0], b0[0], z0[0], hl0[0]
        levels = levels[()]
        n_e, n_h = len(ce), len(ch)
        if n_e + n_h == 0:
            return SensorSchedule(np.zeros(0, dtype=SENSOR_DTYPE), levels)
        clocks = np.concatenate([ce, ch])
        order = np.argsort(clocks, kind="stable")
        clocks = clocks[order]
        is_enc = np.concatenate([np.ones(n_e, bool), np.zeros(n_h, bool)])[order]
        vals = np.concatenate([ie, ih])[order]
        pos = np.arange(len(clocks))
        # Forward fill each sensor's index (initial: the index at now).
        last_e = np.maximum.accumulate(np.where(is_enc, pos, -1))
        last_h = np.maximum.accumulate(np.where(~is_enc, pos, -1))
        enc_idx = np.where(last_e >= 0, vals[np.maximum(last_e, 0)], e0)
        hall_idx = np.where(last_h >= 0, vals[np.maximum(last_h, 0)], h0)
        # One row per clock (the last), and only where a level changes.
        last_of_clock = np.ones(len(clocks), dtype=bool)
        last_of_clock[:-1] = clocks[1:] != clocks[:-1]
        clocks, enc_idx, hall_idx = (clocks[last_of_clock], enc_idx[last_of_clock],
                                     hall_idx[last_of_clock])
        a, b, z, hall = self._pins(enc_idx, hall_idx)
        word = a | (b << 1) | (z << 2) | (hall << 3)
        prev = np.empty_like(word)
        prev[0] = a0[0] | (b0[0] << 1) | (z0[0] << 2) | (hl0[0] << 3)
        prev[1:] = word[:-1]
        changed = word != prev
        rows = np.zeros(int(changed.sum()), dtype=SENSOR_DTYPE)
        rows["clock"], rows["a"], rows["b"], rows["z"], rows["hall"] = (
            clocks[changed], a[changed], b[changed], z[changed], hall[changed])
        return SensorSchedule(rows, levels)

    def sensor_levels(self):
        """The pin levels now as last emitted (a SENSOR_DTYPE record)."""
        self._enc.rebase(self.now)
        self._hall.rebase(self.now)
        a, b, z, hall = self._pins(np.array([self._enc.idx]), np.array([self._hall.idx]))
        rec = np.zeros((), dtype=SENSOR_DTYPE)
        rec["clock"], rec["a"], rec["b"], rec["z"], rec["hall"] = self.now, a[0], b[0], z[0], \
            hall[0]
        return rec[()]

    # --- integration ------------------------------------------------------------------------------

    def _check_until(self, until):
        if not isinstance(until, numbers.Integral) or isinstance(until, bool):
            raise TypeError(f"Plant clock must be an integer, not {until!r}")
        until = int(until)
        if until < self.now:
            raise ValueError(f"Plant clock {until} is before now ({self.now})")
        return until

    def _check_gates(self, gh, gl, clock):
        if not (isinstance(gh, numbers.Integral) and isinstance(gl, numbers.Integral)
                and 0 <= gh <= 7 and 0 <= gl <= 7):
            raise ValueError(f"Plant gate levels must be 3-bit integers (0 … 7), not "
                             f"({gh!r}, {gl!r})")
        both = int(gh) & int(gl)
        if both:
            phase = "abc"[(both & -both).bit_length() - 1]
            raise ShootThroughError(f"both switches of phase {phase} are on from clock {clock} "
                                    f"(gate_h {int(gh):03b}, gate_l {int(gl):03b}): shoot-through")
        return int(gh), int(gl)

    def advance(self, until, gate_events=None, gates_before=None):
        """Integrate from ``now`` to clock ``until``.

        Parameters
        ----------
        until : int
            Clock to reach (≥ now).
        gate_events : numpy structured array or None
            Fields ``clock``, ``gate_h``, ``gate_l`` (3 bits each, bit 0 = phase a): the gate
            levels that take effect from that clock on, clocks non-decreasing in [now, until].
        gates_before : (int, int) or None
            ``(gate_h, gate_l)`` before the first event; ``None``: the levels in force.

        Raises
        ------
        ShootThroughError
            Both switches of a leg on (the state is left at that clock).
        """
        until = self._check_until(until)
        if gates_before is not None:
            try:
                gh, gl = gates_before
            except (TypeError, ValueError):
                raise TypeError(f"Plant gates_before must be a pair (gate_h, gate_l), "
                                f"not {gates_before!r}") from None
            self._gates = self._check_gates(gh, gl, self.now)
        if gate_events is not None and len(gate_events):
            try:
                clocks = np.asarray(gate_events["clock"], dtype=np.int64)
                ghs = np.asarray(gate_events["gate_h"], dtype=np.int64)
                gls = np.asarray(gate_events["gate_l"], dtype=np.int64)
            except (ValueError, KeyError, IndexError, TypeError):
                raise TypeError("Plant gate_events must be a structured array with fields "
                                "clock, gate_h, gate_l") from None
            if np.any(np.diff(clocks) < 0):
                raise ValueError("Plant gate_events clocks must be non-decreasing")
            if clocks[0] < self.now or clocks[-1] > until:
                raise ValueError(f"Plant gate_events clocks must be in [now, until] = "
                                 f"[{self.now}, {until}], not {clocks[0]} … {clocks[-1]}")
            for c, gh, gl in zip(clocks.tolist(), ghs.tolist(), gls.tolist()):
                if (gh, gl) == self._gates:       # only the events that change the gates matter
                    continue
                if c > self.now:
                    self._run(c)
                self._gates = self._check_gates(gh, gl, c)
        self._run(until)

    def _run(self, until):
        if until == self.now:
            return
        t_end = until / self._clk_hz
        remaining = t_end - self._t
        zero_steps = 0
        gh, gl = self._gates
        if (gh | gl) == 7 and self._short is None:
            self._run_driven(remaining)
            remaining = 0.0
        while remaining > 1e-15:
            if (gh | gl) == 0 and self._short is None and self._x[0] == self._x[1] == 0.0:
                h = self._idle_step(remaining)
                if h:
                    remaining -= h
                    continue
            h = self._step(min(remaining, self._max_step), zero_steps >= 4)
            zero_steps = zero_steps + 1 if h <= 1e-14 else 0
            remaining -= h
        self._t = t_end
        self._now = until

    def _run_driven(self, span):
        """:meth:`_step` specialised (locals, equal sub-steps) for the common case: every leg
        driven by a switch, no short; the same closed form as :meth:`_fast`."""
        n = max(1, math.ceil(span / self._max_step - 1e-9))
        h = span / n
        r, l, psi, p, jm, b = self._r, self._l, self._psi, self._p, self._j, self._b
        lam = r / l
        el = math.exp(-lam * h)
        f_l = -math.expm1(-lam * h) / lam
        f_2l = -math.expm1(-2.0 * lam * h) / (2.0 * lam)
        gh, gl = self._gates
        sw = [1 if (gh >> k) & 1 else -1 for k in range(3)]
        held, dc = self._held, self._dc
        load, load_c = self._load, self._load_const
        k_t = 1.5 * p * psi
        e = self._e
        e_in = e_cu = e_load = e_fric = 0.0
        i0 = complex(self._x[0], self._x[1])
        w, acc, theta, t = self._omega, self._alpha, self._theta, self._t
        u = self._u
        vsum = sw[0] * _LEG[0] + sw[1] * _LEG[1] + sw[2] * _LEG[2]
        v = (1.0 / 3.0) * u * vsum
        c = v / r
        cc = c.conjugate()
        c2 = c.real * c.real + c.imag * c.imag
        jp = 1j * p
        for _ in range(n):
            w_bar = w if held else w + 0.5 * acc * h
            we = p * w_bar
            rot = cmath.exp(jp * theta)
            s_ = complex(lam, we)
            d = -1j * we * psi * rot / (l * s_)
            a = i0 - c - d
            wh = we * h
            ww = cmath.exp(1j * wh)
            if -1e-4 < wh < 1e-4:
                f_w = h * (1.0 + 1j * wh * (0.5 + 1j * wh / 6.0))
            else:
                f_w = (ww - 1.0) / (1j * we)
            f_sb = (1.0 - el * ww.conjugate()) / s_
            i1 = a * el + c + d * ww
            int_i = a * f_l + c * h + d * f_w
            # ∫|i|² = |a|²·f_2l + (|c|² + |d|²)·h + 2·Re(a·(c̄·f_l + d̄·f_sb) + c̄·d·f_w)
            int_i2 = ((a.real * a.real + a.imag * a.imag) * f_2l
                      + (c2 + d.real * d.real + d.imag * d.imag) * h
                      + 2.0 * (a * (cc * f_l + d.conjugate() * f_sb) + cc * d * f_w).real)
            int_iq = (rot.conjugate() * (a * f_sb + c * f_w.conjugate() + d * h)).imag
            de_in = 1.5 * (v.real * int_i.real + v.imag * int_i.imag)
            e_in += de_in
            e_cu += 1.5 * r * int_i2
            te_mean = k_t * int_iq / h
            if held:
                e_load += h * (te_mean - b * w_bar) * w_bar
                e_fric += h * b * w_bar * w_bar
            else:
                t_load = load_c if load is None else float(load(t + 0.5 * h))
                acc = (te_mean - t_load - b * w_bar) / jm
                w_avg = w + 0.5 * acc * h
                e_load += h * t_load * w_avg
                e_fric += h * b * w_bar * w_avg
                w += acc * h
            theta += w_bar * h
            t += h
            i0 = i1
            if dc is not None:
                self._t = t - h
                self._dc_step(h, de_in / u)
                u = self._u
                v = (1.0 / 3.0) * u * vsum
                c = v / r
                cc = c.conjugate()
                c2 = c.real * c.real + c.imag * c.imag
        self._x = [i0.real, i0.imag]
        self._omega, self._alpha, self._theta, self._t = w, (0.0 if held else acc), theta, t
        e["e_in"] += e_in
        e["e_cu"] += e_cu
        e["e_load"] += e_load
        e["e_fric"] += e_fric

    def _idle_step(self, span):
        """All gates off, no current, no short: while the line-to-line EMF stays below U_dc no
        diode can conduct, so only the mechanics move; steps up to 50 µs. Returns the time
        advanced (0 when the EMF could reach the bus, and the general step must run)."""
        h = min(span, 50e-6)
        w, acc = self._omega, (0.0 if self._held else self._alpha)
        w_max = abs(w) + abs(acc) * h
        if _SQRT3 * self._p * w_max * self._psi >= 0.999 * self._u:
            return 0.0
        e = self._e
        if self._held:
            w_bar = w
            e["e_load"] += h * (-self._b * w) * w
            e["e_fric"] += h * self._b * w * w
        else:
            t_load = self._load_at(self._t + 0.5 * h)
            # Exact for constant torque: a = −(T_L + b·w̄)/J with w̄ the mean speed.
            w_bar = w + 0.5 * acc * h
            acc = (-t_load - self._b * w_bar) / self._j
            w_bar = w + 0.5 * acc * h
            e["e_load"] += h * t_load * w_bar
            e["e_fric"] += h * self._b * w_bar * w_bar
            self._omega = w + acc * h
            self._alpha = acc
        self._theta += w_bar * h
        if self._dc is not None:
            self._dc_step(h, 0.0)
        self._t += h
        return h

    def _switch_states(self):
        gh, gl = self._gates
        return [1 if (gh >> k) & 1 else (-1 if (gl >> k) & 1 else 0) for k in range(3)]

    def _topology(self, open_mask):
        topo = self._topos.get(open_mask)
        if topo is None:
            topo = self._topos[open_mask] = _Topology(open_mask, self._r, self._l, self._short)
        return topo

    def _leg_currents(self, x):
        i = complex(x[0], x[1])
        j = [(i * leg.conjugate()).real for leg in _LEG]
        if self._short is not None:
            j[self._short[0]] += x[2]
            j[self._short[1]] -= x[2]
        return j

    def _emf_ab(self, we, th_e):
        return 1j * we * self._psi * cmath.exp(1j * th_e)

    def _load_at(self, t):
        return self._load_const if self._load is None else float(self._load(t))

    def _accel_now(self):
        if self._held:
            return 0.0
        te = self.torque_nm
        return (te - self._load_at(self._t) - self._b * self._omega) / self._j

    def _resolve(self, sw, x, w_m):
        """Leg voltage signs (+1, −1, or 0 = open) for switch states ``sw`` at state x: switches,
        then diodes by the sign of the leg current, then diode turn-on where an open terminal's
        voltage leaves the bus."""
        states = list(sw)
        if all(sw):
            return states
        j = self._leg_currents(x)
        for k in range(3):
            if not sw[k]:
                states[k] = -1 if j[k] > _EPS_I else (1 if j[k] < -_EPS_I else 0)
        half = 0.5 * self._u
        e = self._emf_ab(self._p * w_m, self._p * self._theta)
        for _ in range(4):
            open_mask = tuple(s == 0 for s in states)
            if not any(open_mask):
                break
            topo = self._topology(open_mask)
            vo = topo.implied(x, e, [s * half for s in states])
            legs = [k for k in range(3) if open_mask[k]]
            if len(legs) == 3:
                hi, lo = int(np.argmax(vo)), int(np.argmin(vo))
                if vo[hi] - vo[lo] > 2.0 * half:
                    states[legs[hi]], states[legs[lo]] = 1, -1
                    continue
                break
            viol = [max(v - half, -half - v) for v in vo]
            k = int(np.argmax(viol))
            if viol[k] > 0.0:
                states[legs[k]] = 1 if vo[k] > half else -1
                continue
            break
        return states

    def _step(self, h, ignore_events=False):
        """One sub-step of at most h seconds; returns the time advanced."""
        p, psi = self._p, self._psi
        w_m = self._omega
        w_bar = w_m if self._held else w_m + 0.5 * self._alpha * h
        we = p * w_bar
        th0 = p * self._theta
        half = 0.5 * self._u
        sw = self._switch_states()
        short = self._short
        if short is None and sw[0] and sw[1] and sw[2]:
            states, fast = sw, True
        else:
            states = self._resolve(sw, self._x, w_bar)
            fast = short is None and all(states)
        if fast:
            res = self._fast(h, states, sw, we, th0, half, ignore_events)
        else:
            res = self._modal(h, states, sw, we, th0, half, ignore_events)
        h, x1, e_in, e_cu, e_fault, i_q_int = res
        self._x = x1
        if h <= 0.0:                    # an event at the start: only the leg states change
            return 0.0
        # Mechanics.
        te_mean = 1.5 * p * psi * i_q_int / h
        e = self._e
        if self._held:
            e["e_load"] += h * (te_mean - self._b * w_bar) * w_bar
            e["e_fric"] += h * self._b * w_bar * w_bar
            self._alpha = 0.0
        else:
            t_load = self._load_at(self._t + 0.5 * h)
            acc = (te_mean - t_load - self._b * w_bar) / self._j
            w_avg = w_m + 0.5 * acc * h
            e["e_load"] += h * t_load * w_avg
            e["e_fric"] += h * self._b * w_bar * w_avg
            self._omega = w_m + acc * h
            self._alpha = acc
        self._theta += w_bar * h
        e["e_in"] += e_in
        e["e_cu"] += e_cu
        e["e_fault"] += e_fault
        if self._dc is not None:
            self._dc_step(h, e_in / self._u)
        self._t += h
        return h

    def _fast(self, h, states, sw, we, th0, half, ignore_events):
        """All legs conducting, no short: i(t) = A·e^{−λt} + C + D·e^{jω_e t} (complex)."""
        r, l = self._r, self._l
        lam = r / l
        v = (2.0 / 3.0) * half * sum(s * leg for s, leg in zip(states, _LEG))
        i0 = complex(self._x[0], self._x[1])
        e0 = 1j * we * self._psi * cmath.exp(1j * th0)
        s_ = complex(lam, we)
        c = v / r
        d = -e0 / (l * s_)
        a = i0 - c - d
        diodes = [k for k in range(3) if not sw[k]]

        def at(t):
            return a * math.exp(-lam * t) + c + d * cmath.exp(1j * we * t)

        i1 = at(h)
        if diodes and not ignore_events:
            # A diode conducts while −s·j > 0; its current crossing zero ends the sub-step.
            t_ev = h
            for k in diodes:
                cond1 = -states[k] * (i1 * _LEG[k].conjugate()).real
                if cond1 <= 0.0:
                    sk, leg = states[k], _LEG[k].conjugate()
                    cond0 = -sk * (i0 * leg).real

                    def f(t, sk=sk, leg=leg):
                        return sk * (at(t) * leg).real     # ≥ 0 once crossed

                    t_k = _root(f, -cond0, -cond1, h, _FTOL_I) if cond0 > 0.0 else 0.0
                    t_ev = min(t_ev, t_k)
            if t_ev < h:
                h = t_ev
                i1 = at(h)
        el = math.exp(-lam * h)
        w = cmath.exp(1j * we * h)
        f_l = -math.expm1(-lam * h) / lam
        f_w = _phi(1j * we, h)
        f_sb = (1.0 - el * w.conjugate()) / s_           # ∫e^{−(λ + jω)t}
        int_i = a * f_l + c * h + d * f_w
        int_i2 = ((a * a.conjugate()).real * (-math.expm1(-2.0 * lam * h)) / (2.0 * lam)
                  + (abs(c) ** 2 + abs(d) ** 2) * h
                  + 2.0 * (a * c.conjugate()).real * f_l
                  + 2.0 * (a * d.conjugate() * f_sb).real
                  + 2.0 * (c * d.conjugate() * f_w.conjugate()).real)
        int_iq = (cmath.exp(-1j * th0) * (a * f_sb + c * f_w.conjugate() + d * h)).imag
        e_in = 1.5 * (v.conjugate() * int_i).real
        e_cu = 1.5 * r * int_i2
        return h, [i1.real, i1.imag], e_in, e_cu, 0.0, int_iq

    def _modal(self, h, states, sw, we, th0, half, ignore_events):
        """General case (open legs, short): decoupled modes, closed form each."""
        open_mask = tuple(s == 0 for s in states)
        topo = self._topology(open_mask)
        x0 = self._x
        n, m = topo.n, topo.m
        z0 = [sum(topo.zx[k][i] * x0[i] for i in range(n)) for k in range(m)]
        v = [s * half for s in states]
        beta = [sum(topo.bz[k][x] * v[x] for x in range(3) if not open_mask[x])
                for k in range(m)]
        gam = [-1.5 * we * self._psi * g for g in topo.gamma]
        seg = _ModalSeg(topo, z0, beta, gam, we, th0)

        def x_at(z):
            return [sum(topo.xz[i][k] * z[k] for k in range(m)) for i in range(n)]

        def legs_at(z):
            return [sum(topo.jz[x][k] * z[k] for k in range(m)) for x in range(3)]

        z1 = seg.z(h)
        if not ignore_events:
            t_ev = h
            j0, j1 = legs_at(z0), legs_at(z1)
            # Diode currents crossing zero.
            for k in range(3):
                if sw[k] or not states[k]:
                    continue
                sk = states[k]
                if -sk * j1[k] <= 0.0:
                    def f(t, sk=sk, k=k):
                        return sk * legs_at(seg.z(t))[k]
                    c0 = -sk * j0[k]
                    t_ev = min(t_ev, _root(f, -c0, -(-sk * j1[k]), h, _FTOL_I)
                               if c0 > 0.0 else 0.0)
            # Open legs: diode turn-on (implied voltage leaving the bus).
            if any(open_mask):
                legs = [k for k in range(3) if open_mask[k]]

                def onset(t):
                    e = self._emf_ab(we, th0 + we * t)
                    vo = topo.implied(x_at(seg.z(t)), e, v)
                    if len(legs) == 3:
                        return float(vo.max() - vo.min()) - 2.0 * half
                    return max(max(u - half, -half - u) for u in vo)

                g1 = onset(h)
                if g1 > 0.0:
                    g0 = onset(0.0)
                    t_ev = min(t_ev, _root(onset, g0, g1, h, _FTOL_V) if g0 < 0.0 else 0.0)
            if t_ev < h:
                h = t_ev
                z1 = seg.z(h)
        x1 = x_at(z1)
        if h <= 0.0:
            return 0.0, x1, 0.0, 0.0, 0.0, 0.0
        iz, izz, ie = seg.integrals(h)
        e_in = sum(beta[k] * iz[k] for k in range(m))
        e_cu = sum(topo.cu[k][l_] * izz[k][l_] for k in range(m) for l_ in range(m))
        e_fault = sum(topo.fault[k][l_] * izz[k][l_] for k in range(m) for l_ in range(m))
        int_iq = sum((ie[k] * complex(topo.xz[1][k], topo.xz[0][k])).real for k in range(m)) \
            if m else 0.0
        return h, x1, e_in, e_cu, e_fault, int_iq

    def _dc_step(self, h, q):
        """DC link over h with the inverter drawing the charge q (a constant current q/h): exact
        for that current, the rectifier conducting while u_c < u_source."""
        dc = self._dc
        cap, rs, us = dc.c_f, dc.r_source_ohm, dc.u_source_v
        tau = rs * cap
        i = q / h
        u, left = self._u, h
        e = self._e
        for _ in range(3):                       # at most two region changes
            if left <= 0.0:
                break
            if u < us or (u == us and i > 0.0):
                # Conducting: C·du/dt = (us − u)/rs − i → u(s) = u_inf + a·e^{−s/τ}.
                u_inf = us - rs * i
                a = u - u_inf
                dt = left
                if u_inf > us and a < 0.0:       # rising through us: the rectifier stops
                    dt = min(left, max(tau * math.log(a / (us - u_inf)), 0.0))
                ex = math.exp(-dt / tau)
                int_exp = tau * -math.expm1(-dt / tau)
                # i_src = (us − u)/rs = i − (a/rs)·e^{−s/τ}
                e["e_src"] += us * (i * dt - a * int_exp / rs)
                e["e_src_loss"] += rs * (i * i * dt - 2.0 * i * a * int_exp / rs
                                         + (a / rs) ** 2 * 0.5 * tau * -math.expm1(-2 * dt / tau))
                e["e_bus"] += i * (u_inf * dt + a * int_exp)
                u = us if dt < left else u_inf + a * ex
            else:
                # Rectifier off: C·du/dt = −i.
                dt = left
                if i > 0.0:
                    dt = min(left, (u - us) * cap / i)
                e["e_bus"] += i * (u * dt - 0.5 * i * dt * dt / cap)
                u = us if dt < left else u - i * dt / cap
            left -= dt
        if not u > 0.0:
            raise RuntimeError(f"Plant DC link voltage collapsed to {u:.3g} V at "
                               f"t = {self._t:.6g} s")
        self._u = u
