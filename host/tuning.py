# Ref: paper eq. (7)–(9) (Tustin PI); SPEC.md §1–2; issue 5 item 8 (`foc-servo host tune`),
#      issue 6 items 4–5 (gains from the motor by one documented rule; t_min); docs/TUNING.md
"""PI gains from the motor parameters: one documented rule, physical and raw register values.

Current loop (PI_d = PI_q), **technical (modulus) optimum** with pole-zero cancellation. The plant
seen by a current PI is ``1/(R + s·L)`` behind the PWM and computation delay, modelled as a first-
order lag ``T_σ = delay_periods · T`` (``T = 1/pwm_hz``; the current is sampled at the period
centre and the new duties take effect at the next period boundary, T/2 later, and act on average
for another T/2: ``delay_periods = 1`` by default; 1.5 for drives that update one full period
after the sample)::

    K_p = ω_c · L          (V/A)         zero of the PI on the plant pole: T_i = K_p/K_i = L/R
    K_i = ω_c · R          (V/(A·s))     open loop L(s) = ω_c/s · e^(−s·T_σ)
    ω_c = 1/(2·T_σ)        when not given (technical optimum: ζ = 1/√2, 4.3 % overshoot,
                           phase margin 90° − ω_c·T_σ = 61.4° with the delay taken as a delay)

(the closed loop's −3 dB bandwidth is then ≈ 1.95·ω_c; √2·ω_c with the delay taken as a lag).
A given ``ω_c`` must keep the phase margin ``90° − ω_c·T_σ`` at least 30°.

Speed loop, **symmetric optimum** on the plant ``K_t/(J·s)`` (``K_t = 1.5·P·ψ``, N·m per A of
i_q; viscous friction neglected) with the closed current loop taken as the first-order lag
``2·T_σ`` plus the speed measurement and sampling delay ``T_ω`` (default one speed-loop period
``T_n = speed_div · T``: M/T averaging over the period, T_n/2, and the hold of the i_q reference,
T_n/2)::

    T_σn = 2·T_σ + T_ω
    K_p  = J / (a · K_t · T_σn)     (A per rad/s)
    T_i  = a² · T_σn,   K_i = K_p / T_i      (A per rad)
    ω_c  = 1/(a · T_σn),  phase margin = arcsin((a² − 1)/(a² + 1))   (a = 2: 36.9°, a = 3: 53.1°)

``a = 3`` by default (2 is the classic choice, with a 3.4 × larger speed ``kx``). A speed-loop
bandwidth (crossover) ω_c may be given instead of ``a``: then ``a = 1/(ω_c·T_σn)``, i.e.
``K_p = J·ω_c/K_t`` and ``K_i = J·ω_c³·T_σn/K_t``; the same range of ``a`` applies (ω_c below
``1/T_σn``), and the phase margin falls as ω_c approaches it (30° at ``1/(√3·T_σn)``).
``J`` is the rotor inertia plus ``j_load_kgm2``. The speed PI has no reference filter: a small
(unsaturated) step overshoots by about 43 % at ``a = 2`` and 25 % at ``a = 3``; large steps are
current-limited and the PI's anti-windup decides.

**Normalisation** to the gateware's PI (hdl/pi.py: ``O = K_p,n·E + I``,
``I += K_x,n·(E[n] + E[n−1])``, E and O in Q formats of their full scales)::

    K_p,n = K_p · E_FS / O_FS,   K_x,n = K_i · T_s / 2 · E_FS / O_FS

current loop: ``E_FS = I_FS`` (A), ``O_FS = (2/3)·U_rated`` (V, a modulation index of 1.0 after
the DC-bus compensation), ``T_s = T``; speed loop: ``E_FS = N_FS·2π/60`` (rad/s), ``O_FS = I_FS``,
``T_s = speed_div · T``. Raw register values are ``round(K·2**frac)`` (half away from zero) in the
register's format; a gain outside the format's range, or one the format's resolution cannot hold
within 5 %, raises :exc:`ValueError` with the fix.

**Delay compensation** (the ``theta_lead`` register, hdl/top.py): the inverse Park turns by the
angle the rotor covers in ``t_lead``; the register holds that angle at the full-scale speed,
``360°·(N_FS/60)·P·t_lead`` (:func:`lead_angle`). ``t_lead`` defaults to ``delay_periods · T``
(the mean delay of the new duties, as T_σ above).

**Dead-time compensation** (``dtc_clocks``, ``dtc_band``, hdl/deadtime_comp.py): each phase's
high time gets ``+sign(i_x)·max(t_dead·clk_hz, 1)`` clocks, the volt-seconds the gates' dead time
costs, linear in ``i_x`` below a band (:func:`dead_time_comp`). The band is half the largest
phase-current ripple of centred SVPWM, ``I_band = U_dc·T/(24·L)`` (the peak-to-peak ripple is at
most ``U_dc·T/(12·L)``, near a modulation index of 0.5): below it the ripple crosses zero
inside the dead time and the loss shrinks.
"""

import dataclasses
import math
import numbers

from ..hdl.fixed import QFormat
from ..hdl.regmap import Scales
from .registers import REGISTERS

__all__ = ["CurrentGains", "SpeedGains", "Tuning", "current_gains", "speed_gains",
           "current_norm", "speed_norm", "to_raw", "from_raw", "tune", "physical_from_registers",
           "t_min_s", "lead_angle", "dead_time_comp", "feedforward_registers", "LEAD_FORMAT",
           "DECOUPLE_FORMAT", "DTC_CLOCKS_FORMAT", "DTC_BAND_FORMAT", "DEFAULT_DEAD_TIME_S",
           "CURRENT_KP_FORMAT", "CURRENT_KX_FORMAT", "SPEED_KP_FORMAT", "SPEED_KX_FORMAT",
           "MAX_QUANT_ERROR"]

#: Register formats of the gains, from the register map (hdl/regmap.py).
CURRENT_KP_FORMAT = REGISTERS["pi_q_kp"].fmt
CURRENT_KX_FORMAT = REGISTERS["pi_q_kx"].fmt
SPEED_KP_FORMAT = REGISTERS["pi_speed_kp"].fmt
SPEED_KX_FORMAT = REGISTERS["pi_speed_kx"].fmt
LEAD_FORMAT = REGISTERS["theta_lead"].fmt
DECOUPLE_FORMAT = REGISTERS["decouple_l"].fmt
DTC_CLOCKS_FORMAT = REGISTERS["dtc_clocks"].fmt
DTC_BAND_FORMAT = REGISTERS["dtc_band"].fmt
#: The gate dead time :func:`feedforward_registers` assumes: the ``dead_time`` register's reset
#: value (``Top(dead_time_s=None)``).
DEFAULT_DEAD_TIME_S = 1e-6

#: Largest relative rounding error of a raw gain accepted by :func:`to_raw`.
MAX_QUANT_ERROR = 0.05

_RPM = 2.0 * math.pi / 60.0


def _positive(name, value, unit, *, allow_zero=False):
    if (not isinstance(value, numbers.Real) or isinstance(value, bool)
            or not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero)):
        bound = "at least 0" if allow_zero else "above 0"
        unit = f" {unit}" if unit else ""
        raise ValueError(f"{name} must be a finite number {bound}{unit}, not {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class CurrentGains:
    """Current PI gains (PI_d = PI_q) in physical units.

    Attributes
    ----------
    kp_v_per_a : float
        Proportional gain, V per A (phase amplitude, dq).
    ki_v_per_as : float
        Integral gain, V per A·s.
    omega_c_rad_s : float
        Open-loop crossover ω_c, rad/s.
    t_sigma_s : float
        Delay T_σ of PWM and computation, s.
    t_s : float
        Sample period (the PWM period), s.
    """
    kp_v_per_a: float
    ki_v_per_as: float
    omega_c_rad_s: float
    t_sigma_s: float
    t_s: float

    @property
    def phase_margin_deg(self):
        """``90° − ω_c·T_σ`` (the delay as a pure delay)."""
        return 90.0 - math.degrees(self.omega_c_rad_s * self.t_sigma_s)


@dataclasses.dataclass(frozen=True)
class SpeedGains:
    """Speed PI gains in physical units.

    Attributes
    ----------
    kp_a_per_rad_s : float
        Proportional gain, A of i_q per rad/s (mechanical).
    ki_a_per_rad : float
        Integral gain, A per rad (A per rad/s per s).
    a : float
        Symmetric-optimum parameter.
    t_sigma_n_s : float
        Equivalent small time constant T_σn of the inner loop and measurement, s.
    omega_c_rad_s : float
        Open-loop crossover ``1/(a·T_σn)``, rad/s.
    t_s : float
        Speed-loop sample period, s.
    j_kgm2 : float
        Total inertia the gains were computed for, kg·m².
    kt_nm_per_a : float
        Torque constant used, N·m per A of i_q.
    """
    kp_a_per_rad_s: float
    ki_a_per_rad: float
    a: float
    t_sigma_n_s: float
    omega_c_rad_s: float
    t_s: float
    j_kgm2: float
    kt_nm_per_a: float

    @property
    def phase_margin_deg(self):
        """``arcsin((a² − 1)/(a² + 1))`` of the symmetric optimum."""
        return math.degrees(math.asin((self.a ** 2 - 1) / (self.a ** 2 + 1)))


def current_gains(motor, *, pwm_hz, bandwidth_rad_s=None, delay_periods=1.0):
    """Technical-optimum current PI gains (module docstring: formulas).

    Parameters
    ----------
    motor : MotorParams
    pwm_hz : float
        PWM frequency = current-loop rate, Hz.
    bandwidth_rad_s : float, optional
        Open-loop crossover ω_c; default ``1/(2·T_σ)``.
    delay_periods : float
        T_σ in PWM periods, (0, 10].

    Raises
    ------
    ValueError
        For a non-positive rate or bandwidth, or a bandwidth whose phase margin
        ``90° − ω_c·T_σ`` is below 30°.
    """
    pwm_hz = _positive("pwm_hz", pwm_hz, "Hz")
    delay_periods = _positive("delay_periods", delay_periods, "periods")
    if delay_periods > 10:
        raise ValueError(f"delay_periods must be at most 10 periods, not {delay_periods!r}")
    t_s = 1.0 / pwm_hz
    t_sigma = delay_periods * t_s
    if bandwidth_rad_s is None:
        wc = 1.0 / (2.0 * t_sigma)
    else:
        wc = _positive("current bandwidth", bandwidth_rad_s, "rad/s")
        wc_max = math.pi / 3.0 / t_sigma
        if wc > wc_max:
            raise ValueError(f"current bandwidth {wc:g} rad/s is above {wc_max:.0f} rad/s, the "
                             f"most a delay of {t_sigma * 1e6:.4g} µs allows with 30° phase "
                             f"margin; lower it or raise pwm_hz")
    return CurrentGains(kp_v_per_a=wc * motor.l_q_h, ki_v_per_as=wc * motor.r_ohm,
                        omega_c_rad_s=wc, t_sigma_s=t_sigma, t_s=t_s)


def speed_gains(motor, current, *, speed_div=1, a=3.0, j_load_kgm2=0.0, speed_delay_s=None,
                bandwidth_rad_s=None):
    """Symmetric-optimum speed PI gains (module docstring: formulas).

    Parameters
    ----------
    motor : MotorParams
    current : CurrentGains
        The inner loop (its ``t_sigma_s`` and ``t_s``).
    speed_div : int
        Speed loop every ``speed_div`` PWM periods, 1 … 255.
    a : float
        Symmetric-optimum parameter, (1, 20]; default 3 (53° phase margin; 2 is the classic
        choice, 37°, and needs a 3.4 × larger speed ``kx``).
    j_load_kgm2 : float
        Load inertia added to the rotor's, kg·m².
    speed_delay_s : float, optional
        T_ω; default one speed-loop period.
    bandwidth_rad_s : float, optional
        Speed-loop crossover ω_c instead of ``a`` (which is then ignored):
        ``a = 1/(ω_c·T_σn)``, from ``1/(20·T_σn)`` up to (not including) ``1/T_σn``.

    Raises
    ------
    ValueError
        For an ``a`` or a bandwidth out of range, or a bad ``speed_div``, inertia or delay.
    """
    if not isinstance(speed_div, numbers.Integral) or isinstance(speed_div, bool) \
            or not 1 <= speed_div <= 255:
        raise ValueError(f"speed_div must be an integer from 1 to 255 periods, not {speed_div!r}")
    j = motor.j_kgm2 + _positive("j_load_kgm2", j_load_kgm2, "kg·m²", allow_zero=True)
    t_n = speed_div * current.t_s
    t_w = t_n if speed_delay_s is None else _positive("speed_delay_s", speed_delay_s, "s",
                                                      allow_zero=True)
    t_sn = 2.0 * current.t_sigma_s + t_w
    if bandwidth_rad_s is not None:
        wc = _positive("speed bandwidth", bandwidth_rad_s, "rad/s")
        a = 1.0 / (wc * t_sn)
        if not 1.0 < a <= 20.0:
            raise ValueError(
                f"speed bandwidth {wc:g} rad/s is outside {1 / (20 * t_sn):.0f} … "
                f"{1 / t_sn:.0f} rad/s (exclusive), the symmetric optimum's range for "
                f"T_σn = {t_sn * 1e6:.4g} µs (a = 1/(ω_c·T_σn) from 1 to 20); change it, or "
                f"pwm_hz / speed_div")
    a = _positive("symmetric optimum a", a, "")
    if not 1.0 < a <= 20.0:
        raise ValueError(f"symmetric optimum a must be above 1 and at most 20, not {a!r}")
    kt = motor.kt_nm_per_a
    kp = j / (a * kt * t_sn)
    ki = kp / (a * a * t_sn)
    return SpeedGains(kp_a_per_rad_s=kp, ki_a_per_rad=ki, a=a, t_sigma_n_s=t_sn,
                      omega_c_rad_s=1.0 / (a * t_sn), t_s=t_n, j_kgm2=j, kt_nm_per_a=kt)


def current_norm(scales, u_rated_v):
    """``E_FS / O_FS`` of the current PIs: ``I_FS / ((2/3)·U_rated)``, A/V."""
    u_rated_v = _positive("u_rated_v", u_rated_v, "V")
    return scales.i_fs_a / (2.0 / 3.0 * u_rated_v)


def speed_norm(scales):
    """``E_FS / O_FS`` of the speed PI: ``(N_FS·2π/60) / I_FS``, rad/s per A."""
    return scales.n_fs_rpm * _RPM / scales.i_fs_a


def to_raw(name, value, fmt, *, hint=""):
    """Raw register value of gain ``name`` (``round(value·2**frac)``, half away from zero).

    Raises
    ------
    ValueError
        If ``value`` is outside ``fmt``'s range, or rounds with a relative error above
        :data:`MAX_QUANT_ERROR` (naming the gain, the value, the representable range, and
        ``hint``, the fix).
    """
    if not isinstance(fmt, QFormat):
        raise TypeError(f"{name} format must be a QFormat, not {fmt!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, not {value!r}")
    fix = f": {hint}" if hint else ""
    if value < fmt.min or value > fmt.max:
        raise ValueError(f"{name} {value:.6g} does not fit {fmt!r} (representable "
                         f"{fmt.min:g} … {fmt.max:.8g}){fix}")
    raw = fmt.to_raw(value, name=name)
    if value != 0 and abs(fmt.from_raw(raw) - value) > MAX_QUANT_ERROR * abs(value):
        raise ValueError(f"{name} {value:.6g} is below the resolution of {fmt!r} (steps of "
                         f"{fmt.lsb:.3g}: error above {MAX_QUANT_ERROR:.0%}){fix}")
    return raw


def from_raw(raw, fmt):
    """The normalised gain of a raw register value."""
    return fmt.from_raw(raw)


@dataclasses.dataclass(frozen=True)
class Tuning:
    """Result of :func:`tune`.

    Attributes
    ----------
    current : CurrentGains
    speed : SpeedGains
    normalized : dict
        Register name → normalised gain (float, before rounding).
    registers : dict
        Register name → raw value (``pi_d_kp``, ``pi_d_kx``, ``pi_q_kp``, ``pi_q_kx``,
        ``pi_speed_kp``, ``pi_speed_kx``), ready to write.
    feedforward : dict
        Register name → raw value of the current loop's feed-forward
        (:func:`feedforward_registers`: ``decouple_enable``, ``decouple_l``, ``decouple_psi``,
        ``theta_lead``, ``dtc_clocks``, ``dtc_band``); empty when :func:`tune` was called with
        ``feedforward=False``.
    """
    current: CurrentGains
    speed: SpeedGains
    normalized: dict
    registers: dict
    feedforward: dict = dataclasses.field(default_factory=dict)


def tune(motor, *, scales=None, u_rated_v=310.0, speed_div=1, current_bandwidth_rad_s=None,
         delay_periods=1.0, a=3.0, j_load_kgm2=0.0, speed_delay_s=None,
         speed_bandwidth_rad_s=None,
         current_kp_v_per_a=None, current_ki_v_per_as=None,
         speed_kp_a_per_rad_s=None, speed_ki_a_per_rad=None,
         current_kp_format=CURRENT_KP_FORMAT, current_kx_format=CURRENT_KX_FORMAT,
         speed_kp_format=SPEED_KP_FORMAT, speed_kx_format=SPEED_KX_FORMAT, feedforward=True,
         dead_time_s=DEFAULT_DEAD_TIME_S):
    """Current and speed PI gains for ``motor``, physical and as raw register values, and the
    current loop's feed-forward (d–q decoupling and delay compensation,
    :func:`feedforward_registers`).

    Parameters
    ----------
    motor : MotorParams
    scales : Scales
        The drive's scales (``pwm_hz``, ``i_fs_a``, ``n_fs_rpm``); default ``Scales()``.
    u_rated_v : float
        The ``u_rated`` of the DC-bus compensation, V (a modulation index of 1.0 is
        ``(2/3)·u_rated_v``).
    speed_div, current_bandwidth_rad_s, delay_periods, a, j_load_kgm2, speed_delay_s
        See :func:`current_gains` and :func:`speed_gains`.
    speed_bandwidth_rad_s : float, optional
        Speed-loop crossover instead of ``a`` (:func:`speed_gains`'s ``bandwidth_rad_s``).
    current_kp_v_per_a, current_ki_v_per_as, speed_kp_a_per_rad_s, speed_ki_a_per_rad : float
        Overrides of the rule's gains (each independently).
    current_kp_format, current_kx_format, speed_kp_format, speed_kx_format : QFormat
        Register formats.
    feedforward : bool
        Also compute the feed-forward registers (``Tuning.feedforward``), with ``t_lead`` =
        ``delay_periods`` PWM periods.
    dead_time_s : float or None
        The drive's gate dead time (its ``dead_time`` register), s, for the dead-time
        compensation; default 1 µs, the register's reset value; ``None``: compensation off.

    Raises
    ------
    ValueError
        From the rule's checks, or when a gain does not fit its register format: the message
        names the gain, its value, the format's range (or resolution) and the fixes (lower
        bandwidth, other full scales, another format).
    """
    scales = Scales() if scales is None else scales
    if not isinstance(scales, Scales):
        raise TypeError(f"scales must be a Scales, not {scales!r}")
    cur = current_gains(motor, pwm_hz=scales.pwm_hz, bandwidth_rad_s=current_bandwidth_rad_s,
                        delay_periods=delay_periods)
    if current_kp_v_per_a is not None or current_ki_v_per_as is not None:
        kp = cur.kp_v_per_a if current_kp_v_per_a is None else \
            _positive("current kp", current_kp_v_per_a, "V/A", allow_zero=True)
        ki = cur.ki_v_per_as if current_ki_v_per_as is None else \
            _positive("current ki", current_ki_v_per_as, "V/(A·s)", allow_zero=True)
        cur = dataclasses.replace(cur, kp_v_per_a=kp, ki_v_per_as=ki,
                                  omega_c_rad_s=kp / motor.l_q_h)
    spd = speed_gains(motor, cur, speed_div=speed_div, a=a, j_load_kgm2=j_load_kgm2,
                      speed_delay_s=speed_delay_s, bandwidth_rad_s=speed_bandwidth_rad_s)
    if speed_kp_a_per_rad_s is not None or speed_ki_a_per_rad is not None:
        kp = spd.kp_a_per_rad_s if speed_kp_a_per_rad_s is None else \
            _positive("speed kp", speed_kp_a_per_rad_s, "A/(rad/s)", allow_zero=True)
        ki = spd.ki_a_per_rad if speed_ki_a_per_rad is None else \
            _positive("speed ki", speed_ki_a_per_rad, "A/rad", allow_zero=True)
        spd = dataclasses.replace(spd, kp_a_per_rad_s=kp, ki_a_per_rad=ki)

    cn = current_norm(scales, u_rated_v)
    sn = speed_norm(scales)
    normalized = {
        "pi_d_kp": cur.kp_v_per_a * cn,
        "pi_d_kx": cur.ki_v_per_as * cur.t_s / 2.0 * cn,
        "pi_speed_kp": spd.kp_a_per_rad_s * sn,
        "pi_speed_kx": spd.ki_a_per_rad * spd.t_s / 2.0 * sn,
    }
    normalized["pi_q_kp"] = normalized["pi_d_kp"]
    normalized["pi_q_kx"] = normalized["pi_d_kx"]
    cur_hint = (f"with I_FS = {scales.i_fs_a:g} A and u_rated = {u_rated_v:g} V; ",
                "use another I_FS or u_rated, or a format with ")
    spd_hint = (f"with N_FS = {scales.n_fs_rpm:g} r/min and I_FS = {scales.i_fs_a:g} A; ",
                "use another full scale (gain ∝ N_FS/I_FS), or a format with ")
    # A gain too large for its format comes from too high a bandwidth: that knob first.
    cur_bw = (f"lower the current ω_c {cur.omega_c_rad_s:.0f} rad/s "
              f"({cur.omega_c_rad_s / 2 / math.pi:.0f} Hz), ")
    spd_bw = (f"lower the speed ω_c {spd.omega_c_rad_s:.0f} rad/s "
              f"({spd.omega_c_rad_s / 2 / math.pi:.0f} Hz), ")
    fmts = {"pi_d_kp": (current_kp_format, cur_hint, cur_bw),
            "pi_q_kp": (current_kp_format, cur_hint, cur_bw),
            "pi_d_kx": (current_kx_format, cur_hint, cur_bw),
            "pi_q_kx": (current_kx_format, cur_hint, cur_bw),
            "pi_speed_kp": (speed_kp_format, spd_hint, spd_bw),
            "pi_speed_kx": (speed_kx_format, spd_hint, spd_bw)}
    registers = {}
    for name in ("pi_d_kp", "pi_d_kx", "pi_q_kp", "pi_q_kx", "pi_speed_kp", "pi_speed_kx"):
        fmt, (scale_text, fix), bw = fmts[name]
        value = normalized[name]
        if value > fmt.max:
            hint = scale_text + bw + fix + "more integer bits"
        else:
            hint = scale_text + fix + "more fraction bits"
        registers[name] = to_raw(name, value, fmt, hint=hint)
    ff = (feedforward_registers(motor, scales=scales, u_rated_v=u_rated_v,
                                t_lead_s=delay_periods / scales.pwm_hz, dead_time_s=dead_time_s)
          if feedforward else {})
    return Tuning(current=cur, speed=spd, normalized=normalized, registers=registers,
                  feedforward=ff)


def physical_from_registers(registers, *, scales=None, u_rated_v=310.0, speed_div=1,
                            current_kp_format=CURRENT_KP_FORMAT,
                            current_kx_format=CURRENT_KX_FORMAT,
                            speed_kp_format=SPEED_KP_FORMAT, speed_kx_format=SPEED_KX_FORMAT):
    """Physical gains of raw register values (the inverse of :func:`tune`'s normalisation).

    Parameters
    ----------
    registers : dict
        Register name → raw value; any of ``pi_d_kp``, ``pi_d_kx``, ``pi_q_kp``, ``pi_q_kx``
        (V/A, V/(A·s)) and ``pi_speed_kp``, ``pi_speed_kx`` (A/(rad/s), A/rad).
    scales, u_rated_v, speed_div, *_format
        As for :func:`tune`.

    Returns
    -------
    dict
        Register name → physical gain.
    """
    scales = Scales() if scales is None else scales
    t = 1.0 / scales.pwm_hz
    cn = current_norm(scales, u_rated_v)
    sn = speed_norm(scales)
    conv = {
        "pi_d_kp": (current_kp_format, 1.0 / cn), "pi_q_kp": (current_kp_format, 1.0 / cn),
        "pi_d_kx": (current_kx_format, 2.0 / (t * cn)),
        "pi_q_kx": (current_kx_format, 2.0 / (t * cn)),
        "pi_speed_kp": (speed_kp_format, 1.0 / sn),
        "pi_speed_kx": (speed_kx_format, 2.0 / (speed_div * t * sn)),
    }
    out = {}
    for name, raw in registers.items():
        if name not in conv:
            raise ValueError(f"{name!r} is not a PI gain register; choose from "
                             f"{', '.join(conv)}")
        fmt, k = conv[name]
        out[name] = fmt.from_raw(raw) * k
    return out


def t_min_s(j_kgm2, delta_speed_rpm, t_max_nm, t_load_nm=0.0):
    """Physical floor of a current-limited speed step: ``t_min = J·Δω / (T_max − T_load)``, s.

    Parameters
    ----------
    j_kgm2 : float
        Total inertia, kg·m².
    delta_speed_rpm : float
        Speed change, r/min (its magnitude is used).
    t_max_nm : float
        Largest torque the speed loop may command (``K_t`` × its current limit), N·m.
    t_load_nm : float
        Load torque opposing the step, N·m; must be below ``t_max_nm``.
    """
    j = _positive("j_kgm2", j_kgm2, "kg·m²")
    if not isinstance(delta_speed_rpm, numbers.Real) or not math.isfinite(delta_speed_rpm):
        raise ValueError(f"delta_speed_rpm must be a finite number of r/min, "
                         f"not {delta_speed_rpm!r}")
    t_max = _positive("t_max_nm", t_max_nm, "N·m")
    if (not isinstance(t_load_nm, numbers.Real) or not math.isfinite(t_load_nm)
            or t_load_nm >= t_max):
        raise ValueError(f"t_load_nm {t_load_nm!r} N·m must be below t_max_nm {t_max:g} N·m")
    return j * abs(delta_speed_rpm) * _RPM / (t_max - t_load_nm)


def lead_angle(motor, *, scales=None, t_lead_s=None, delay_periods=1.0):
    """The ``theta_lead`` register for a delay ``t_lead``: the electrical angle turned in
    ``t_lead`` at the full-scale speed, ``360°·(N_FS/60)·P·t_lead``.

    Parameters
    ----------
    motor : MotorParams
        Its ``pole_pairs``.
    scales : Scales
        ``n_fs_rpm`` and ``pwm_hz``; default ``Scales()``.
    t_lead_s : float, optional
        The delay to compensate, s; default ``delay_periods / pwm_hz``.
    delay_periods : float
        ``t_lead`` in PWM periods when ``t_lead_s`` is not given (1: the duties of a centred
        sample act from T/2 to 3T/2 after it, mean T).

    Returns
    -------
    (float, int)
        The advance at full-scale speed in degrees, and the raw register value.

    Raises
    ------
    ValueError
        For a negative delay, or an advance of a turn or more (the register holds less than
        360°): naming ``t_lead``, the angle and the largest ``t_lead`` that fits.
    """
    scales = Scales() if scales is None else scales
    if not isinstance(scales, Scales):
        raise TypeError(f"scales must be a Scales, not {scales!r}")
    if t_lead_s is None:
        t_lead_s = _positive("delay_periods", delay_periods, "periods", allow_zero=True) \
            / scales.pwm_hz
    t_lead_s = _positive("t_lead_s", t_lead_s, "s", allow_zero=True)
    f_e_fs = scales.n_fs_rpm / 60.0 * motor.pole_pairs          # electrical Hz at N_FS
    turns = f_e_fs * t_lead_s
    if turns * (1 << LEAD_FORMAT.frac) > LEAD_FORMAT.max_raw + 0.5:
        raise ValueError(f"t_lead {t_lead_s * 1e6:.6g} µs is {360 * turns:.6g}° at N_FS = "
                         f"{scales.n_fs_rpm:g} r/min ({f_e_fs:g} Hz electrical), beyond the "
                         f"theta_lead register's {360 * LEAD_FORMAT.max:.4f}°; at most "
                         f"{LEAD_FORMAT.max / f_e_fs * 1e6:.6g} µs")
    raw = to_raw("theta_lead", turns, LEAD_FORMAT) if turns else 0
    return 360.0 * turns, raw


def dead_time_comp(motor, *, scales=None, u_rated_v=310.0, dead_time_s=DEFAULT_DEAD_TIME_S,
                   band_a=None):
    """The dead-time compensation registers (hdl/deadtime_comp.py)::

        dtc_clocks = max(round(t_dead · clk_hz), 1)       the effective dead time of the gates
        dtc_band   = round(log2(I_band / (dtc_clocks · I_FS/32768)))   in 0 … 15
        I_band     = U_dc·T / (24·L)                      half the largest SVPWM ripple

    so the trapezoid gives the full correction beyond ``≈ I_band`` (rounded to a power of two:
    within a factor √2).

    Parameters
    ----------
    motor : MotorParams
        Its ``l_q_h`` (for the ripple).
    scales : Scales
        ``clk_hz``, ``pwm_hz``, ``i_fs_a``; default ``Scales()``.
    u_rated_v : float
        DC-bus voltage for the ripple, V.
    dead_time_s : float or None
        The drive's gate dead time (the ``dead_time`` register), s; default 1 µs, the register's
        reset value. ``None``: compensation off (``dtc_clocks`` 0).
    band_a : float or None
        ``I_band``, A, instead of the ripple estimate.

    Returns
    -------
    dict
        ``dtc_clocks``, ``dtc_band`` (raw).

    Raises
    ------
    ValueError
        A dead time of more than 255 clocks (naming it, in µs and clocks), or a band that is not
        a positive number of A.
    """
    scales = Scales() if scales is None else scales
    if not isinstance(scales, Scales):
        raise TypeError(f"scales must be a Scales, not {scales!r}")
    if dead_time_s is None:
        return {"dtc_clocks": 0, "dtc_band": REGISTERS["dtc_band"].reset}
    dead_time_s = _positive("dead_time_s", dead_time_s, "s", allow_zero=True)
    clocks = max(round(dead_time_s * scales.clk_hz), 1)
    if clocks > DTC_CLOCKS_FORMAT.max_raw:
        raise ValueError(f"dead_time_s {dead_time_s * 1e6:g} µs is {clocks} clocks at "
                         f"{scales.clk_hz:g} Hz, beyond the dtc_clocks register's "
                         f"{DTC_CLOCKS_FORMAT.max_raw}")
    if band_a is None:
        band_a = (_positive("u_rated_v", u_rated_v, "V") / scales.pwm_hz
                  / (24.0 * _positive("motor l_q_h", motor.l_q_h, "H")))
    band_a = _positive("band_a", band_a, "A")
    lsb_a = scales.i_fs_a / 32768.0
    band = round(math.log2(band_a / (clocks * lsb_a)))
    return {"dtc_clocks": clocks,
            "dtc_band": min(max(band, DTC_BAND_FORMAT.min_raw), DTC_BAND_FORMAT.max_raw)}


def feedforward_registers(motor, *, scales=None, u_rated_v=310.0, t_lead_s=None,
                          dead_time_s=DEFAULT_DEAD_TIME_S):
    """The current loop's feed-forward registers for ``motor`` (hdl/foc.py, hdl/top.py)::

        decouple_l   = ω_e(N_FS)·L_q·I_FS / ((2/3)·U_rated)     (u_d −= ω_e·L·i_q,
        decouple_psi = ω_e(N_FS)·ψ_F / ((2/3)·U_rated)            u_q += ω_e·L·i_d + ω_e·ψ_F)
        theta_lead   = :func:`lead_angle` (the PWM delay)
        dtc_clocks, dtc_band = :func:`dead_time_comp` (the gates' dead time ``dead_time_s``,
                       default 1 µs: the drive's ``dead_time`` register must hold the same)

    with ``ω_e(N_FS) = 2π·N_FS/60·P``. Without the decoupling, the PIs must build the back-EMF
    and the cross-coupling ω_e·L·i_q in their integrators: at 1667 r/min and 30 A that is 46 V
    on q and 51 V on d for this package's default motor, which an accelerating drive tracks
    only with a lag (an i_d error of several A). Without the dead-time compensation the dead
    time takes ``t_dead/T·U_dc`` (3.1 V at 1 µs, 10 kHz, 310 V) off each phase voltage, against
    the current: at standstill the pole-cancelling PI rejects that only with ``L/R``.

    Parameters
    ----------
    motor : MotorParams
    scales : Scales
        The drive's scales; default ``Scales()``.
    u_rated_v : float
        The ``u_rated`` register, V.
    t_lead_s : float or None
        Delay for :func:`lead_angle`; default one PWM period.
    dead_time_s : float or None
        The drive's gate dead time, s (:func:`dead_time_comp`); ``None``: compensation off.

    Returns
    -------
    dict
        Register name → raw value: ``decouple_enable`` (1), ``decouple_l``, ``decouple_psi``,
        ``theta_lead``, ``dtc_clocks``, ``dtc_band``.

    Raises
    ------
    ValueError
        When a term does not fit its register (naming it, its value and the range).
    """
    scales = Scales() if scales is None else scales
    if not isinstance(scales, Scales):
        raise TypeError(f"scales must be a Scales, not {scales!r}")
    u_base = 2.0 / 3.0 * _positive("u_rated_v", u_rated_v, "V")
    w_fs = scales.n_fs_rpm * _RPM * motor.pole_pairs
    hint = (f"with N_FS = {scales.n_fs_rpm:g} r/min, I_FS = {scales.i_fs_a:g} A and u_rated = "
            f"{u_rated_v:g} V; use a lower N_FS or a higher u_rated")
    _, lead = lead_angle(motor, scales=scales, t_lead_s=t_lead_s)
    return {"decouple_enable": 1,
            "decouple_l": to_raw("decouple_l", w_fs * motor.l_q_h * scales.i_fs_a / u_base,
                                 DECOUPLE_FORMAT, hint=hint),
            "decouple_psi": to_raw("decouple_psi", w_fs * motor.psi_wb / u_base,
                                   DECOUPLE_FORMAT, hint=hint),
            "theta_lead": lead,
            **dead_time_comp(motor, scales=scales, u_rated_v=u_rated_v,
                             dead_time_s=dead_time_s)}
