# Ref: issue 6 item 5 (`foc-servo sim step|ramp|load|reversal|lowspeed|fault ...`)
"""``foc-servo sim``: closed-loop scenarios on the simulated drive, in physical units.

Each sub-command runs a scenario of :mod:`foc_servo.sim.scenarios`, prints its figures (``--json``:
one JSON object on the last line), and on request writes the plot (``--plot``), the time series
(``--csv``) and a value-change dump of the pins and the analog quantities (``--vcd``).
"""

import argparse
import math

from .cli import emit

__all__ = ["add_sim_parser"]


def _number(unit, lo=-math.inf, hi=math.inf, *, lo_open=False):
    """argparse type: a finite number of ``unit`` within [lo, hi] (lo excluded if ``lo_open``)."""
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number of {unit}, not {text!r}") from None
        bad_lo = value <= lo if lo_open else value < lo
        if not math.isfinite(value) or bad_lo or value > hi:
            rng = f"{'above' if lo_open else 'at least'} {lo:g}"
            if hi != math.inf:
                rng += f" and at most {hi:g}"
            raise argparse.ArgumentTypeError(f"must be a number of {unit} {rng}, not {text}")
        return value
    return parse


def _common(p):
    p.add_argument("--engine", choices=["compiled", "pysim"], default="compiled",
                   help="compiled (Verilator, fast) or pysim (Amaranth's simulator, the "
                        "reference; slow) (default: %(default)s)")
    p.add_argument("--current-loop", choices=["pipelined", "engine"], default="pipelined",
                   help="current-loop gateware: pipelined (CurrentLoop, 46-48 clocks) or engine "
                        "(EngineCurrentLoop, same results, 134-232 clocks, a third of the area) "
                        "(default: %(default)s)")
    p.add_argument("--speed-loop", choices=["sequential", "engine"], default="sequential",
                   help="speed-loop gateware: sequential (SpeedLoop) or engine (a run of the "
                        "loop engine, the iCEBreaker's; needs --current-loop engine and the "
                        "block-RAM register staging, which it selects) (default: %(default)s)")
    p.add_argument("--regs-staging", choices=["ff", "bram"], default=None,
                   help="register-file staging (Top regs_staging; default: ff, bram with "
                        "--speed-loop engine)")
    p.add_argument("--pwm-khz", type=_number("kHz", 1, 100), default=10.0,
                   help="PWM (switching and current-loop sampling) frequency, kHz "
                        "(default: %(default)s)")
    p.add_argument("--clk-mhz", type=_number("MHz", 1, 500), default=50.0,
                   help="system clock, MHz (default: %(default)s; 33.333 also supported)")
    p.add_argument("--motor", metavar="FILE",
                   help="motor parameter file (TOML or JSON, see docs/PLANT.md; default: the "
                        "Yaskawa SGMSH-15A)")
    p.add_argument("--udc", type=_number("V", 0, lo_open=True), default=310.0,
                   help="DC-bus voltage, V (default: %(default)s)")
    p.add_argument("--current-bw-hz", type=_number("Hz", 0, lo_open=True), default=None,
                   help="current-loop crossover, Hz (default: the technical optimum)")
    p.add_argument("--speed-a", type=_number("", 1, lo_open=True), default=3.0,
                   help="symmetric-optimum a of the speed loop (default: %(default)s)")
    p.add_argument("--duration-ms", type=_number("ms", 0, lo_open=True), default=None,
                   help="motor time to simulate, ms (default: per scenario)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: %(default)s)")
    p.add_argument("--plot", metavar="FILE.png", help="write a figure like the paper's Fig. 8/9")
    p.add_argument("--csv", metavar="FILE.csv", help="write the time series")
    p.add_argument("--vcd", metavar="FILE.vcd", help="write pins and analog values (GTKWave)")
    p.add_argument("--quiet", action="store_true", help="no progress bar on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the figures as one JSON object on the last line")


def add_sim_parser(sub):
    p = sub.add_parser("sim", help="closed-loop simulation of the drive and motor (step, ramp, "
                                   "load, reversal, lowspeed, highspeed, current, fault)")
    ssub = p.add_subparsers(dest="scenario", required=True, metavar="SCENARIO")

    s = ssub.add_parser("step", help="speed step 0 → SPEED (the paper's Fig. 8)")
    s.add_argument("--speed", type=_number("r/min", -6000, 6000), default=1667.0,
                   help="target speed, r/min (default: %(default)s)")
    _common(s)

    s = ssub.add_parser("ramp", help="speed ramp (the paper's Fig. 9: 0.45 r/min per sample to "
                                     "500 r/min)")
    s.add_argument("--speed", type=_number("r/min", -6000, 6000), default=500.0,
                   help="final speed, r/min (default: %(default)s)")
    s.add_argument("--rate", type=_number("r/min per sample", 0, lo_open=True), default=0.45,
                   help="reference slope, r/min per current-loop sample (default: %(default)s)")
    _common(s)

    s = ssub.add_parser("load", help="load-torque step at constant speed")
    s.add_argument("--speed", type=_number("r/min", -6000, 6000), default=1000.0,
                   help="speed, r/min (default: %(default)s)")
    s.add_argument("--torque", type=_number("N·m"), default=None,
                   help="load step, N·m (default: the motor's rated torque)")
    _common(s)

    s = ssub.add_parser("reversal", help="speed reversal +SPEED → −SPEED")
    s.add_argument("--speed", type=_number("r/min", 0, 6000, lo_open=True), default=1000.0,
                   help="speed magnitude, r/min (default: %(default)s)")
    _common(s)

    s = ssub.add_parser("lowspeed", help="very low speed (0.2 r/min by default): ripple")
    s.add_argument("--speed", type=_number("r/min", -100, 100), default=0.2,
                   help="speed, r/min (default: %(default)s)")
    _common(s)

    s = ssub.add_parser("highspeed", help="step to the motor's maximum speed")
    s.add_argument("--speed", type=_number("r/min", -6000, 6000), default=None,
                   help="speed, r/min (default: the motor's maximum, 5000)")
    _common(s)

    s = ssub.add_parser("current", help="q-axis current step in current (torque) mode")
    s.add_argument("--iq", type=_number("A"), default=10.0,
                   help="i_q step, A (default: %(default)s)")
    _common(s)

    from ..sim.scenarios import FAULTS
    s = ssub.add_parser("fault", help="fault scenario: detection, gates off, cause readable, "
                                      "registers kept")
    s.add_argument("kind", choices=list(FAULTS), help="; ".join(
        f"{k}: {v}" for k, v in FAULTS.items()))
    _common(s)
    p.set_defaults(func=cmd_sim)


def _scenario_kwargs(args):
    from ..sim.motor import DEFAULT_MOTOR, MotorParams
    motor = DEFAULT_MOTOR if args.motor is None else MotorParams.from_file(args.motor)
    kw = dict(engine=args.engine, motor=motor, pwm_hz=args.pwm_khz * 1e3,
              clk_hz=args.clk_mhz * 1e6, udc_v=args.udc, seed=args.seed,
              progress=not args.quiet,
              setup_kw={"speed_a": args.speed_a, "current_bandwidth_hz": args.current_bw_hz})
    if args.duration_ms is not None:
        kw["duration_s"] = args.duration_ms / 1e3
    if args.current_loop != "pipelined":
        # Passed only when not the default: the default top's compiled-model source key
        # (sim/engines/compiled.py, over the Top kwargs) stays the one already cached.
        kw["current_loop"] = args.current_loop
    # (Likewise passed only when not the default.)
    if args.speed_loop != "sequential":
        kw["speed_loop"] = args.speed_loop
    staging = args.regs_staging or ("bram" if args.speed_loop == "engine" else "ff")
    if staging != "ff":
        kw["regs_staging"] = staging
    if args.vcd:
        kw["record_pins"] = True
    return kw


def _lines(res):
    info, met = res.info, res.metrics
    lines = [f"{res.name}: {info['motor_time_s'] * 1e3:.1f} ms of motor time on the "
             f"{info['engine']} engine ({info['current_loop']} current loop) in "
             f"{info['wall_s']:.1f} s wall (simulating "
             f"{info['sim_wall_s']:.1f} s: engine {info['engine_s']:.1f} s, plant "
             f"{info['plant_s']:.1f} s; {info['clk_per_s'] / 1e6:.3f} M clocks/s)"]
    for k, v in met.items():
        if isinstance(v, float):
            lines.append(f"  {k:<24} {v:.6g}")
        elif v is None or isinstance(v, (int, str, bool)):
            lines.append(f"  {k:<24} {v}")
    return lines


def cmd_sim(args):
    from ..sim import scenarios
    kw = _scenario_kwargs(args)
    name = args.scenario
    if name == "fault":
        res = scenarios.fault(args.kind, **kw)
    elif name == "current":
        res = scenarios.current_step(iq_a=args.iq, **kw)
    elif name == "ramp":
        res = scenarios.ramp(speed_rpm=args.speed, rate_rpm_per_sample=args.rate, **kw)
    elif name == "load":
        res = scenarios.load(speed_rpm=args.speed, torque_nm=args.torque, **kw)
    elif name == "highspeed":
        res = scenarios.highspeed(speed_rpm=args.speed, **kw)
    else:
        res = getattr(scenarios, name)(speed_rpm=args.speed, **kw)
    lines = _lines(res)
    if args.plot:
        from ..sim.plots import plot_response
        path = plot_response(res.series, args.plot, title=res.info.get("title", name),
                             metrics=res.metrics)
        lines.append(f"wrote {path}")
    if args.csv:
        from ..sim.plots import write_csv
        path = write_csv(res.series, args.csv)
        lines.append(f"wrote {path}")
    if args.vcd:
        n = res.cosim.write_vcd(args.vcd)
        lines.append(f"wrote {args.vcd} ({n} value changes)")
    fig = dict(res.metrics)
    for key in ("engine", "current_loop", "motor_time_s", "wall_s", "clk_per_s", "clocks", "engine_s",
                "plant_s", "sim_wall_s", "build_s"):
        fig[key] = res.info[key]
    emit(fig, lines, args.json)
