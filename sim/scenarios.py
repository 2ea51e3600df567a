# Ref: issue 6 items 2, 5, 6, 7; paper §4 (step 0 → 1667 r/min, Fig. 8; ramp 0.45 r/min per
#      sample to 500 r/min, Fig. 9; 10 kHz switching and sampling)
"""Closed-loop scenarios on :class:`~foc_servo.sim.closed_loop.CoSim`: the paper's experiments,
the load step, reversal, low and high speed, the current step and the fault scenarios.

Every scenario configures the drive **through the host link**, as a user does: the host library
(:class:`~foc_servo.host.servo.Servo`) writes the gains from :func:`~foc_servo.host.tuning.tune`
(technical optimum for the current loops, symmetric optimum for the speed loop), the encoder and
protection set-up, the current limit and the reference profile, in physical units; then it
commands the reference and the simulation records the plant (true speed, currents) once per
current-loop sample. Each returns a :class:`Result`: time series (numpy arrays), metrics and run
information (engine, motor time, wall time, clocks per second).

Commissioning shortcut (documented in docs/SIMULATION.md): the rotor starts one encoder count
before the Z index, so the first move aligns the encoder exactly (a real drive aligns once, at
commissioning); until then θ_e comes from the Hall sensors.
"""

import dataclasses
import math
import time

import numpy as np

from . import metrics as M
from .closed_loop import CoSim
from .engines.base import IN_BITS
from ..hdl.regmap import MT_EDGES_PER_LINE, Mode, mt_k_for
from .motor import DEFAULT_MOTOR

__all__ = ["Result", "SCENARIOS", "FAULTS", "step", "ramp", "load", "reversal", "lowspeed",
           "highspeed", "current_step", "fault"]


@dataclasses.dataclass
class Result:
    """What a scenario returns.

    Attributes
    ----------
    name : str
    series : dict of numpy arrays
        ``t_s``, ``speed_rpm`` (the plant's true speed), ``speed_ref_rpm``, ``i_alpha_a``,
        ``i_d_a``, ``i_q_a``, ``udc_v``, … (one row per current-loop sample).
    metrics : dict
        The scenario's figures (keys of the issue's ``--json`` interface).
    info : dict
        ``engine``, ``motor_time_s``, ``wall_s``, ``clocks``, ``clk_per_s``, …
    cosim : CoSim
        The co-simulation (for the VCD, more reads over the link, …).
    """
    name: str
    series: dict
    metrics: dict
    info: dict
    cosim: object = dataclasses.field(repr=False, default=None)


def _positive(name, value, unit):
    if (not isinstance(value, (int, float)) or isinstance(value, bool)
            or not math.isfinite(value) or value <= 0):
        raise ValueError(f"{name} must be a positive number of {unit}, not {value!r}")
    return float(value)


def _finite(name, value, unit, lo, hi):
    if (not isinstance(value, (int, float)) or isinstance(value, bool)
            or not math.isfinite(value) or not lo <= value <= hi):
        raise ValueError(f"{name} must be a number of {unit} from {lo:g} to {hi:g}, "
                         f"not {value!r}")
    return float(value)


def current_limit_a(motor):
    """The speed loop's i_q limit for ``motor``: the current of its peak torque, A."""
    return motor.t_peak_nm / motor.kt_nm_per_a


def setup(cosim, *, current_limit=None, slew_rpm_per_s=None, accel_ff=True, speed_a=3.0,
          current_bandwidth_hz=None, ref_delay_runs=3.25, int_hold=True, tune_kw=None,
          slew_frac=0.92, ff_iq_a=None, move_rpm=None, uq_limit=0.999):
    """Configure the simulated drive over its host link for the speed and current modes.

    Writes: ``u_rated`` (the DC bus), the encoder (lines, pole pairs, Z offset, Hall offset) and
    the M/T scale ``mt_k`` for those lines and the build's counted edges per line, the
    speed loop's current limit, the PI gains (:meth:`~foc_servo.host.servo.Servo.tune`), the
    protection limits (over-current 1.25 × the current limit, over-voltage 1.3 × U_dc,
    over-speed 1.2 × the motor's maximum) and the reference profile: ``speed_slew`` (r/min per
    speed-loop update) from ``slew_rpm_per_s``, default ``slew_frac`` = 92 % of the
    current-limited acceleration α_max, and the acceleration feed-forward
    ``speed_ff_iq = J·α/K_t`` (``ff_iq_a`` overrides it, A), the PI's reference delayed by
    ``ref_delay_runs`` (3.25 runs: the speed lags the profile by the current's latency and
    voltage-limited rise, ≈ 0.4 ms from standstill at U_dc = 310 V, the M/T average adds
    ≈ 0.1 ms; a delay a little short of that lets the PI's share top the current up to the limit
    during the acceleration) and its integrator held until the delayed reference has arrived
    (``int_hold``).

    ``uq_limit`` is the q-axis current PI's output limit ``±pi_q_lim`` in its per-unit of
    (2/3)·U_dc (the register's reset is the linear-modulation circle √3/2 = 0.866): 0.999 lets
    the q voltage reach the hexagon, over-modulating (the SVPWM keeps the vector's angle and puts
    it on the hexagon's edge) while the current is voltage-limited — the start and the end of a
    current-limited acceleration — so the current rises and falls ≈ 5 % faster on average over
    the rotor angle. In steady state below the base speed the loop stays linear. The d axis keeps
    the linear limit.

    ``move_rpm`` (the speed change the scenario is about to command, r/min) turns on whole-run
    planning, as a motion planner does: the slew is lowered to ``|Δ|/n`` for the smallest whole
    number ``n`` of speed-loop runs, so the last step (which lands, and so carries no
    feed-forward) is always a full one, and the response no longer depends on where in a run
    the move happens to end. The step, reversal and load scenarios pass it.

    The defaults are the best measured (docs/SIMULATION.md, "Closed-loop performance"): the PI's
    room above the feed-forward (8 % of the current limit) covers the current loop's deficit at
    the limit. Returns the host library's Servo.
    """
    servo = cosim.servo()
    motor, plant = cosim.motor, cosim.plant
    i_max = current_limit_a(motor) if current_limit is None else current_limit
    i_fs = cosim.scales.i_fs_a
    if i_max >= i_fs:
        raise ValueError(f"current_limit must be below I_FS = {i_fs:g} A, not {i_max:g} A")
    servo.set_many({
        "u_rated": plant.udc_v,
        "enc_lines": motor.encoder_lines,
        "enc_pole_pairs": motor.pole_pairs,
        "enc_z_offset": plant.z_offset_register(),
        "enc_hall_offset": plant.hall_offset_register() * 360.0 / 65536,
        "mt_k": mt_k_for(cosim.scales, lines=motor.encoder_lines,
                         edges_per_line=MT_EDGES_PER_LINE[cosim.top.mt_edges]),
    })
    if (not isinstance(uq_limit, (int, float)) or isinstance(uq_limit, bool)
            or not 0 < uq_limit < 1):
        raise ValueError(f"uq_limit must be a number of (2/3)·U_dc above 0 and below 1, "
                         f"not {uq_limit!r}")
    servo.set_many({"pi_speed_lim_lo": -i_max, "pi_speed_lim_hi": i_max})
    servo.tune(motor, current_bandwidth_hz=current_bandwidth_hz, speed_a=speed_a,
               **(tune_kw or {}))
    servo.set_many({"pi_q_lim_lo": -uq_limit, "pi_q_lim_hi": uq_limit})
    servo.set_many({
        "prot_oc_limit": min(1.25 * i_max, 0.999 * i_fs),
        "prot_ov_limit": 1.3 * plant.udc_v,
        "prot_os_limit": 1.2 * motor.n_max_rpm,
    })
    t_max = i_max * motor.kt_nm_per_a
    alpha_max = t_max / motor.j_kgm2                    # rad/s² (mechanical)
    if slew_rpm_per_s is None:
        slew_rpm_per_s = slew_frac * alpha_max * 60 / (2 * math.pi)
    f_speed = cosim.scales.pwm_hz / max(servo.get("speed_div"), 1)
    if slew_rpm_per_s and move_rpm:
        # Whole-run planning: the move takes a whole number n of speed-loop runs, the slew a
        # hair above |Δ|/n so that the n-th step is the one that lands (it carries no
        # feed-forward, as every landing step): the feed-forward then always stops one run
        # before the profile ends, whatever the move.
        runs = max(math.ceil(abs(move_rpm) * f_speed / slew_rpm_per_s - 1e-9), 1)
        slew_rpm_per_s = abs(move_rpm) * f_speed / runs * (1 + 1e-6)
    if slew_rpm_per_s:
        alpha = slew_rpm_per_s * 2 * math.pi / 60
        servo.set_many({"speed_slew": slew_rpm_per_s / f_speed,
                        "speed_ff_iq": (0.0 if not accel_ff else ff_iq_a if ff_iq_a is not None
                                        else motor.j_kgm2 * alpha / motor.kt_nm_per_a),
                        "speed_ref_delay": ref_delay_runs, "speed_int_hold": int_hold})
    return servo


def _info(cosim, name, wall_s, **extra):
    clocks = cosim.now
    info = {"scenario": name, "engine": cosim.engine.kind, "motor_time_s": clocks / cosim.clk_hz,
            "clocks": clocks, "wall_s": wall_s,
            # The simulation proper (not the Verilog conversion or a model build).
            "clk_per_s": clocks / max(cosim.wall_s, 1e-9),
            "engine_s": cosim.engine_s, "plant_s": cosim.plant_s, "sim_wall_s": cosim.wall_s,
            "build_s": getattr(cosim.engine, "build_s", 0.0) or 0.0, "clk_hz": cosim.clk_hz,
            "pwm_hz": cosim.scales.pwm_hz, "current_loop": cosim.top.current_loop}
    info.update(extra)
    return info


def _ref_series(t, changes):
    """The reference at times ``t`` from [(t_change, value)] (a step function)."""
    ref = np.zeros(len(t))
    for tc, v in changes:
        ref[t >= tc] = v
    return ref


def _start_angle(motor, sensors_z_count=0, direction=1):
    """Rotor angle half an encoder count before the Z index in the direction of motion, so the
    first move aligns the encoder (the commissioning shortcut of the module docstring)."""
    cpr = 4 * motor.encoder_lines
    return 2 * math.pi * (sensors_z_count - 0.5 * (1 if direction >= 0 else -1)) / cpr


def _cosim(name, *, engine, motor, pwm_hz, clk_hz, direction=1, **kw):
    kw.setdefault("theta_m0", _start_angle(motor, direction=direction))
    return CoSim(engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz, **kw)


def _run(cosim, seconds, label, progress):
    cosim.run_for(seconds, progress=f"sim {label}" if progress else None)


def _speed_run(name, targets, *, duration_s, engine, motor, pwm_hz, clk_hz, progress, setup_kw,
               start_rpm=0.0, **kw):
    """Speed mode: reference ``start_rpm``, then ``targets`` = [(t_s, r/min)] written over the
    link at those times; run to ``duration_s``. Returns (cosim, servo, series, [(t, ref)])."""
    direction = 1 if (targets[0][1] if targets else start_rpm) >= start_rpm else -1
    cosim = _cosim(name, engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                   direction=direction, progress=progress, **kw)
    servo = setup(cosim, **(setup_kw or {}))
    servo.set_many({"speed_ref": start_rpm, "mode": Mode.SPEED})
    t_zero = cosim.t_s
    changes = [(t_zero, start_rpm)]
    for t_s, rpm in targets:
        _run(cosim, max(t_zero + t_s - cosim.t_s, 0.0), name, progress)
        servo.set("speed_ref", rpm)
        changes.append((cosim.t_s, rpm))
    _run(cosim, max(t_zero + duration_s - cosim.t_s, 0.0), name, progress)
    series = cosim.series()
    series["speed_ref_rpm"] = _ref_series(series["t_s"], changes)
    return cosim, servo, series, changes


def _t_max(motor, setup_kw):
    i_max = (setup_kw or {}).get("current_limit") or current_limit_a(motor)
    return i_max * motor.kt_nm_per_a


def step(*, speed_rpm=1667.0, duration_s=0.1, engine="compiled", motor=DEFAULT_MOTOR,
         pwm_hz=10e3, clk_hz=50e6, t_step_s=2e-3, window_s=10e-3, setup_kw=None,
         progress=False, **kw):
    """Speed step 0 → ``speed_rpm`` at ``t_step_s`` (the paper's Fig. 8: 1667 r/min).

    Metrics (:func:`~foc_servo.sim.metrics.step_metrics`, of the plant's true speed): ``settle_s``
    (into ±0.5 % of the target, from the reference write), ``t_min_s`` (J·Δω/(T_max − T_load), T_max
    from the speed loop's current limit), ``settle_ratio``, ``overshoot_pct``, ``ss_err_pct`` (mean
    error over the last ``window_s``, % of the target), ``ss_peak_pct``, ``rise_s``.
    """
    speed_rpm = _finite("speed_rpm", speed_rpm, "r/min", -motor.n_max_rpm, motor.n_max_rpm)
    duration_s = _positive("duration_s", duration_s, "s")
    if speed_rpm == 0:
        raise ValueError("speed_rpm must not be 0 for a step")
    if not t_step_s + 3 * window_s <= duration_s:
        raise ValueError(f"duration_s must leave room for the step and the steady-state window "
                         f"(≥ {t_step_s + 3 * window_s:g} s), not {duration_s!r}")
    t0 = time.perf_counter()
    setup_kw = dict({"move_rpm": speed_rpm}, **(setup_kw or {}))
    cosim, _, s, changes = _speed_run("step", [(t_step_s, speed_rpm)], duration_s=duration_s,
                                      engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                                      progress=progress, setup_kw=setup_kw, **kw)
    load = kw.get("load_nm", 0.0)
    sm = M.step_metrics(s["t_s"], s["speed_rpm"], y0=0.0, y1=speed_rpm, t0=changes[-1][0],
                        window_s=window_s, j_kgm2=motor.j_kgm2, t_max_nm=_t_max(motor, setup_kw),
                        t_load_nm=0.0 if callable(load) else abs(load))
    return Result("step", s, sm.as_dict(), _info(
        cosim, "step", time.perf_counter() - t0,
        title=f"Speed step 0 → {speed_rpm:g} r/min ({motor.name}, {pwm_hz / 1e3:g} kHz)"), cosim)


def ramp(*, speed_rpm=500.0, rate_rpm_per_sample=0.45, duration_s=None, engine="compiled",
         motor=DEFAULT_MOTOR, pwm_hz=10e3, clk_hz=50e6, window_s=10e-3, setup_kw=None,
         progress=False, **kw):
    """Speed ramp 0 → ``speed_rpm`` at ``rate_rpm_per_sample`` r/min per current-loop sample (the
    paper's Fig. 9: 0.45 r/min per sample to 500 r/min at 10 kHz), made by the gateware's
    reference profile (``speed_slew``) with the acceleration feed-forward.

    Metrics (:func:`~foc_servo.sim.metrics.ramp_metrics`): ``track_err_pct`` (largest |ref − n|
    during the ramp, % of ``speed_rpm``, no start-up allowance), ``ss_err_pct`` (mean error over
    the last ``window_s``, % of ``speed_rpm``), ``ss_peak_pct``; and, labelled as such,
    ``track_err_after_10ms_pct`` (the same with a 10 ms start-up allowance).
    """
    speed_rpm = _finite("speed_rpm", speed_rpm, "r/min", -motor.n_max_rpm, motor.n_max_rpm)
    rate = _positive("rate_rpm_per_sample", rate_rpm_per_sample, "r/min per sample")
    ramp_s = abs(speed_rpm) / (rate * pwm_hz)
    t_step = 2e-3
    if duration_s is None:
        duration_s = t_step + ramp_s + 3 * window_s
    duration_s = _positive("duration_s", duration_s, "s")
    if duration_s < t_step + ramp_s + window_s:
        raise ValueError(f"duration_s must cover the ramp ({ramp_s * 1e3:.1f} ms) and the "
                         f"steady-state window: at least {t_step + ramp_s + window_s:g} s, "
                         f"not {duration_s!r}")
    # The PI's reference delay of a small-current ramp: the closed current loop and the M/T
    # average, ≈ 2.5 runs (a full-current step adds the voltage-limited current rise: setup()).
    setup_kw = dict({"ref_delay_runs": 2.5}, **(setup_kw or {}), slew_rpm_per_s=rate * pwm_hz)
    t0 = time.perf_counter()
    cosim, _, s, changes = _speed_run("ramp", [(t_step, speed_rpm)], duration_s=duration_s,
                                      engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                                      progress=progress, setup_kw=setup_kw, **kw)
    # The reference as the gateware makes it: from the write, rate per sample to the target.
    t_ref = changes[-1][0]
    sign = 1.0 if speed_rpm > 0 else -1.0
    ref = np.clip((s["t_s"] - t_ref) * rate * pwm_hz, 0.0, abs(speed_rpm)) * sign
    s["speed_ref_rpm"] = ref
    rm = M.ramp_metrics(s["t_s"], s["speed_rpm"], ref, window_s=window_s,
                        full_scale=abs(speed_rpm))
    met = rm.as_dict()
    # Also, stated as such, the tracking error after a 10 ms start-up allowance (the M/T block
    # has no measurement until the rotor has passed two counted edges: half a line with the
    # default ×4 counting, two lines with mt_edges="a_rising").
    allow = 10e-3
    met["track_err_after_10ms_pct"] = (M.ramp_tracking_error(
        s["t_s"], s["speed_rpm"], ref, t_start=rm.t_start_s, t_end=rm.t_end_s,
        full_scale=abs(speed_rpm), allowance_s=allow)
        if rm.t_end_s - rm.t_start_s > allow else None)
    return Result("ramp", s, met, _info(
        cosim, "ramp", time.perf_counter() - t0,
        title=f"Speed ramp {rate:g} r/min per sample to {speed_rpm:g} r/min"), cosim)


def load(*, speed_rpm=1000.0, torque_nm=None, duration_s=0.06, t_load_s=0.025,
         engine="compiled", motor=DEFAULT_MOTOR, pwm_hz=10e3, clk_hz=50e6, setup_kw=None,
         progress=False, **kw):
    """Load-torque step (default the motor's rated torque) at ``speed_rpm``.

    Metrics (:func:`~foc_servo.sim.metrics.load_step`): ``dip_rpm``, ``dip_pct``, ``t_dip_s``
    (after the step), ``recovery_s`` (back into ±0.5 %), and the steady-state errors before the
    step (``ss_err_pct``) and at the end (``ss_err_after_pct``).
    """
    speed_rpm = _finite("speed_rpm", speed_rpm, "r/min", -motor.n_max_rpm, motor.n_max_rpm)
    torque = motor.t_rated_nm if torque_nm is None else _finite(
        "torque_nm", torque_nm, "N·m", -motor.t_peak_nm, motor.t_peak_nm)
    if not 0 < t_load_s < duration_s:
        raise ValueError(f"t_load_s must lie within the run (0 … {duration_s:g} s), "
                         f"not {t_load_s!r}")
    t0 = time.perf_counter()
    t_abs = {}

    def load_nm(t):
        return torque if "t" in t_abs and t >= t_abs["t"] else 0.0

    cosim = _cosim("load", engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                   direction=1 if speed_rpm >= 0 else -1, load_nm=load_nm, progress=progress,
                   **kw)
    servo = setup(cosim, **dict({"move_rpm": speed_rpm}, **(setup_kw or {})))
    servo.set_many({"speed_ref": speed_rpm, "mode": Mode.SPEED})
    t_ref = cosim.t_s
    t_abs["t"] = t_ref + t_load_s
    _run(cosim, t_ref + duration_s - cosim.t_s, "load", progress)
    s = cosim.series()
    s["speed_ref_rpm"] = _ref_series(s["t_s"], [(t_ref, speed_rpm)])
    before = s["t_s"] < t_abs["t"]
    ls = M.load_step(s["t_s"], s["speed_rpm"], t_step=t_abs["t"], ref=speed_rpm)
    ss_b = M.steady_state_error(s["t_s"][before], s["speed_rpm"][before], speed_rpm,
                                window_s=min(5e-3, 0.5 * t_load_s))
    ss_a = M.steady_state_error(s["t_s"], s["speed_rpm"], speed_rpm, window_s=5e-3)
    met = {"dip_rpm": ls.dip_rpm, "dip_pct": ls.dip_pct, "t_dip_s": ls.t_dip_s,
           "recovery_s": ls.recovery_s, "torque_nm": torque, "ss_err_pct": ss_b.mean_pct,
           "ss_err_after_pct": ss_a.mean_pct}
    return Result("load", s, met, _info(
        cosim, "load", time.perf_counter() - t0,
        title=f"Load step {torque:g} N·m at {speed_rpm:g} r/min"), cosim)


def reversal(*, speed_rpm=1000.0, duration_s=0.06, t_rev_s=0.02, engine="compiled",
             motor=DEFAULT_MOTOR, pwm_hz=10e3, clk_hz=50e6, window_s=10e-3, setup_kw=None,
             progress=False, **kw):
    """Speed reversal +``speed_rpm`` → −``speed_rpm`` at ``t_rev_s``.

    Metrics: of the reversal step (``settle_s``, ``t_min_s``, ``settle_ratio``,
    ``overshoot_pct``, ``ss_err_pct``, …) as for :func:`step`.
    """
    speed_rpm = _finite("speed_rpm", speed_rpm, "r/min", 0, motor.n_max_rpm)
    if speed_rpm == 0:
        raise ValueError("speed_rpm must be above 0 for a reversal")
    t0 = time.perf_counter()
    setup_kw = dict({"move_rpm": 2 * speed_rpm}, **(setup_kw or {}))
    cosim, _, s, changes = _speed_run(
        "reversal", [(0.0, speed_rpm), (t_rev_s, -speed_rpm)], duration_s=duration_s,
        engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz, progress=progress,
        setup_kw=setup_kw, **kw)
    sm = M.step_metrics(s["t_s"], s["speed_rpm"], y0=speed_rpm, y1=-speed_rpm,
                        t0=changes[-1][0], window_s=window_s, j_kgm2=motor.j_kgm2,
                        t_max_nm=_t_max(motor, setup_kw))
    return Result("reversal", s, sm.as_dict(), _info(
        cosim, "reversal", time.perf_counter() - t0,
        title=f"Speed reversal ±{speed_rpm:g} r/min"), cosim)


def lowspeed(*, speed_rpm=0.2, duration_s=0.5, engine="compiled", motor=DEFAULT_MOTOR,
             pwm_hz=10e3, clk_hz=50e6, window_s=None, setup_kw=None, progress=False, **kw):
    """Very low speed (0.2 r/min by default; the issue also asks 1 r/min): the speed ripple.

    Metrics: ``ripple_pkpk_rpm``, ``ripple_rms_rpm`` and ``mean_rpm`` of the plant's true speed
    over the last half of the run (:func:`~foc_servo.sim.metrics.speed_ripple`), the ripple also
    in % of the reference (``ripple_pkpk_pct``, ``ripple_rms_pct``), ``ss_err_pct`` (mean error,
    % of the reference), and what the speed measurement can see: ``mt_edges_per_s`` (the M/T
    block's counted edges per second: four per encoder line with the default ``mt_edges="x4"``,
    one with ``"a_rising"``) and ``mt_edges_in_window``.
    """
    speed_rpm = _finite("speed_rpm", speed_rpm, "r/min", -100, 100)
    if speed_rpm == 0:
        raise ValueError("speed_rpm must not be 0")
    duration_s = _positive("duration_s", duration_s, "s")
    window_s = 0.5 * duration_s if window_s is None else window_s
    t0 = time.perf_counter()
    cosim, _, s, _ = _speed_run("lowspeed", [(0.0, speed_rpm)], duration_s=duration_s,
                                engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                                progress=progress, setup_kw=setup_kw, **kw)
    rp = M.speed_ripple(s["t_s"], s["speed_rpm"], window_s=window_s)
    ss = M.steady_state_error(s["t_s"], s["speed_rpm"], speed_rpm, window_s=window_s)
    # What the M/T block can know: it counts the build's edges (MT_EDGES_PER_LINE per line), so
    # at this speed it gets a new measurement every 1/edges_per_s s at best.
    edges_per_s = (abs(speed_rpm) / 60.0 * motor.encoder_lines
                   * MT_EDGES_PER_LINE[cosim.top.mt_edges])
    met = {"speed_rpm": speed_rpm, "ripple_pkpk_rpm": rp.pkpk, "ripple_rms_rpm": rp.rms,
           "ripple_pkpk_pct": 100.0 * rp.pkpk / abs(speed_rpm),
           "ripple_rms_pct": 100.0 * rp.rms / abs(speed_rpm),
           "mean_rpm": rp.mean, "ss_err_pct": ss.mean_pct, "window_s": window_s,
           "mt_edges_per_s": edges_per_s,
           "mt_edges_in_window": edges_per_s * window_s}
    return Result("lowspeed", s, met, _info(
        cosim, "lowspeed", time.perf_counter() - t0,
        title=f"Low speed {speed_rpm:g} r/min"), cosim)


def highspeed(*, speed_rpm=None, duration_s=0.1, **kw):
    """Step 0 → the motor's maximum speed (5000 r/min for the default motor); as :func:`step`."""
    motor = kw.get("motor", DEFAULT_MOTOR)
    speed_rpm = motor.n_max_rpm if speed_rpm is None else speed_rpm
    res = step(speed_rpm=speed_rpm, duration_s=duration_s, **kw)
    res.name = "highspeed"
    res.info["scenario"] = "highspeed"
    return res


def current_step(*, iq_a=10.0, duration_s=0.01, t_step_s=1e-3, engine="compiled",
                 motor=DEFAULT_MOTOR, pwm_hz=10e3, clk_hz=50e6, setup_kw=None, progress=False,
                 **kw):
    """Step of the q-axis current reference in current (torque) mode, rotor held (a stiff
    dynamometer at standstill: the electrical response alone) at a Hall sector centre (θ_e from
    the Hall sensors is exact there).

    Metrics of the plant's true i_q: ``settle_s`` (±2 %, the noise of a 1-LSB ADC is about
    0.1 % of I_FS), ``overshoot_pct``, ``rise_s``, ``ss_err_pct``.
    """
    i_fs = kw.get("i_fs_a", 40.0)
    iq = _finite("iq_a", iq_a, "A", -0.99 * i_fs, 0.99 * i_fs)
    if iq == 0:
        raise ValueError("iq_a must not be 0")
    t0 = time.perf_counter()
    # Held at standstill the encoder never meets its Z index: θ_e comes from the Hall sensors,
    # exact at a sector centre (θ_e = 30°, the plant's Hall offset is 0).
    kw.setdefault("theta_m0", math.pi / 6 / motor.pole_pairs)
    cosim = _cosim("current", engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                   rotor="held", progress=progress, **kw)
    servo = setup(cosim, **(setup_kw or {}))
    servo.set_many({"i_d_ref": 0.0, "i_q_ref": 0.0, "mode": Mode.CURRENT})
    _run(cosim, t_step_s, "current", progress)
    servo.set("i_q_ref", iq)
    t_ref = cosim.t_s
    _run(cosim, t_ref + duration_s - cosim.t_s, "current", progress)
    s = cosim.series()
    s["speed_ref_rpm"] = np.zeros(len(s["t_s"]))
    s["i_q_ref_a"] = _ref_series(s["t_s"], [(t_ref, iq)])
    sm = M.step_metrics(s["t_s"], s["i_q_a"], y0=0.0, y1=iq, t0=t_ref, band=0.02,
                        window_s=min(2e-3, 0.3 * duration_s))
    return Result("current", s, sm.as_dict(), _info(
        cosim, "current", time.perf_counter() - t0,
        title=f"Current step i_q 0 → {iq:g} A (rotor held)"), cosim)


#: Fault scenarios (``foc-servo sim fault KIND``): kind → what happens.
FAULTS = {
    "encoder_a": "encoder A line broken (held at its level) at 1000 r/min (encoder/Hall "
                 "plausibility check)",
    "short": "phase-to-phase short a–b at 1000 r/min (over-current)",
    "regen": "regenerative stop from 3000 r/min, no brake resistor (DC-bus over-voltage)",
    "gate_driver": "gate-driver fault pin asserted at 1000 r/min",
}
#: The fault bit each scenario must latch first (``st_fault_first``).
FAULT_CAUSES = {
    "encoder_a": ("encoder_hall",),
    "short": ("overcurrent_a", "overcurrent_b", "overcurrent_c", "overcurrent_comparator"),
    "regen": ("overvoltage",),
    "gate_driver": ("external",),
}


def _rw_raw(servo):
    """Raw values of every read-write register (``{name: raw}``)."""
    from ..host.registers import REGISTERS
    names = [n for n, r in REGISTERS.items() if r.access == "rw"]
    return servo._read_raw(names)


def fault(kind, *, duration_s=None, engine="compiled", motor=DEFAULT_MOTOR, pwm_hz=10e3,
          clk_hz=50e6, udc_v=310.0, setup_kw=None, progress=False, **kw):
    """A fault at speed (:data:`FAULTS`): detected, gates off, the cause readable over the host
    link, the registers unchanged.

    Metrics: ``detected`` (tripped with the expected cause first), ``cause`` (the fault bits of
    ``st_fault_first``), ``detect_latency_s`` (from the fault's onset — the break, the short, the
    fault pin, or U_dc crossing the over-voltage limit at the plant — to the trip),
    ``gates_off_latency_clk`` (from the trip to all six gates off), ``registers_lost`` (read-write
    registers whose value changed), ``peak_current_a``, ``peak_udc_v``.
    """
    if kind not in FAULTS:
        raise ValueError(f"fault kind must be one of {', '.join(FAULTS)}, not {kind!r}")
    speed = 3000.0 if kind == "regen" else 1000.0
    i_max = current_limit_a(motor)
    plant_kw = {}
    if kind == "regen":
        from .pmsm import DcLink
        plant_kw["dc_link"] = DcLink(c_f=330e-6, r_source_ohm=0.5, u_source_v=udc_v)
    if kind == "short":
        plant_kw["oc_threshold_a"] = 1.5 * i_max
    t0 = time.perf_counter()
    cosim = _cosim(kind, engine=engine, motor=motor, pwm_hz=pwm_hz, clk_hz=clk_hz,
                   udc_v=udc_v, progress=progress, **plant_kw, **kw)
    servo = setup(cosim, **(setup_kw or {}))
    ov_limit = 380.0
    servo.set("prot_ov_limit", ov_limit)
    servo.set_many({"speed_ref": speed, "mode": Mode.SPEED})
    t_spin = 2.5 * speed / (motor.t_peak_nm / motor.j_kgm2 * 60 / (2 * math.pi)) + 5e-3
    _run(cosim, t_spin, kind, progress)
    if kind == "regen":
        servo.set("speed_ref", 0.0)             # the command: part of the registers kept
    before = _rw_raw(servo)
    onset = cosim.now + 1
    if kind == "encoder_a":
        # The line stays at the level it had (a broken wire held by its pull resistor): no
        # illegal transition at the break, only the plausibility check can see it.
        level = (cosim.engine.pins_in >> IN_BITS["enc_a"]) & 1
        cosim.plant.sensor_fault(enc_a_broken=level)
    elif kind == "short":
        cosim.plant.short("ab", r_ohm=0.05)
        cosim.max_chunk = 50                    # the comparator pin follows the plant closely
    elif kind == "gate_driver":
        cosim.set_pin("fault_n", 0, at=onset)
    if duration_s is None:
        duration_s = 40e-3 if kind in ("encoder_a", "regen") else 5e-3
    _run(cosim, duration_s, kind, progress)
    cosim.max_chunk = cosim.pwm_period
    s = cosim.series()
    if kind == "regen":
        over = np.flatnonzero(s["udc_v"] > ov_limit)
        onset_s = float(s["t_s"][over[0]]) if len(over) else None
    else:
        onset_s = onset / cosim.clk_hz
    status = servo.get_many(["st_trip", "st_fault_first", "st_fault_seen"])
    after = _rw_raw(servo)
    first = [k for k, v in status["st_fault_first"].items() if v]
    trip = cosim.trip_clock
    detected = bool(status["st_trip"]) and trip is not None and any(
        c in first for c in FAULT_CAUSES[kind])
    met = {
        "detected": detected,
        "cause": first,
        "detect_latency_s": (None if trip is None or onset_s is None
                             else trip / cosim.clk_hz - onset_s),
        "gates_off_latency_clk": (None if cosim.gates_off_clock is None or trip is None
                                  else cosim.gates_off_clock - trip),
        "registers_lost": sum(before[n] != after[n] for n in before),
        "peak_current_a": float(np.max(np.abs([s["i_a_a"], s["i_b_a"], s["i_c_a"]])))
        if len(s["t_s"]) else 0.0,
        "peak_udc_v": float(np.max(s["udc_v"])) if len(s["t_s"]) else udc_v,
    }
    s["speed_ref_rpm"] = np.full(len(s["t_s"]), speed)
    return Result(f"fault {kind}", s, met, _info(
        cosim, f"fault {kind}", time.perf_counter() - t0, title=f"Fault: {FAULTS[kind]}"), cosim)


#: Scenario name → function (the ``foc-servo sim`` sub-commands).
SCENARIOS = {"step": step, "ramp": ramp, "load": load, "reversal": reversal,
             "lowspeed": lowspeed, "highspeed": highspeed, "current": current_step,
             "fault": fault}
