# Ref: issue 5 item 8 (the `foc-servo host` commands); host/servo.py
"""``foc-servo host --port PORT|sim [--baud B] COMMAND ...``: a drive from the command line.

Commands: ``get NAME...``, ``set NAME=VALUE...``, ``dump``, ``load FILE``, ``save FILE``,
``watch NAME...``, ``scope``, ``clear-faults``, ``tune``. Each takes ``--json``: the figures then
follow as one JSON object on the last line of stdout. ``--port sim`` talks to the simulated
gateware (:meth:`~foc_servo.host.servo.Servo.drive_sim`: the whole controller and the motor;
``--sim-level registers``: :meth:`~foc_servo.host.servo.Servo.sim`, register level).

Wiring into ``foc-servo`` (host/cli.py, ``build_parser``)::

    from .host_cli import add_host_parser
    add_host_parser(sub)
"""

import argparse
import math
import sys
import time

from .cli import emit, int_at_least, positive_int as _positive_int

__all__ = ["add_host_parser", "cmd_host", "main"]

_nonneg_int = int_at_least(0)


def _positive_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, not {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text!r}")
    return value


def _plain(value):
    from .servo import _plain as plain
    return plain(value)


def _show(name, value):
    """``value unit`` as text."""
    from .registers import REGISTERS
    reg = REGISTERS[name]
    if isinstance(value, dict):
        on = [k for k, v in value.items() if v]
        return "{" + ", ".join(on) + "}"
    value = _plain(value)
    if isinstance(value, float):
        value = f"{value:.9g}"
    unit = f" {reg.unit}" if reg.unit and reg.kind == "number" else ""
    return f"{value}{unit}"


def _parse_assignment(text):
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise SystemExit(f"foc-servo host set: expected NAME=VALUE, not {text!r}")
    return name.strip(), value.strip()


def _cli_value(servo, name, text):
    """A command-line value for register ``name``: flags as ``a|b`` names or an integer,
    enums by name, numbers as numbers."""
    reg = servo.register(name)
    if reg.kind == "flags":
        if text.lstrip("-").isdigit():
            return int(text, 0)
        return [f for f in text.replace(",", "|").split("|") if f]
    if reg.kind == "enum" and text.lstrip("-").isdigit():
        return int(text)
    if reg.kind == "number" and reg.fmt.frac == 0 and reg.scale == "1":
        try:
            return int(text, 0)
        except ValueError:
            pass
    return text


def _emit(figures, lines, as_json):
    emit(figures, lines, as_json, default=_json_default, sort_keys=False)


def _json_default(value):
    plain = _plain(value)
    if plain is not value:
        return plain
    if hasattr(value, "tolist"):
        return value.tolist()
    return float(value)


# --- commands ----------------------------------------------------------------------------------

def _get(servo, args):
    values = servo.get_many(args.names)
    _emit({n: _plain(v) for n, v in values.items()},
          [f"{n} = {_show(n, v)}" for n, v in values.items()], args.json)


def _set(servo, args):
    pairs = [_parse_assignment(t) for t in args.assignments]
    values = {n: _cli_value(servo, n, v) for n, v in pairs}
    frames = servo.set_many(values)
    back = servo.get_many(values)
    _emit({"written": {n: _plain(v) for n, v in back.items()}, "frames": len(frames)},
          [f"{n} = {_show(n, v)}" for n, v in back.items()], args.json)


def _dump(servo, args):
    from .registers import REGISTERS
    values = servo.dump()
    lines = [f"{n:<20} {REGISTERS[n].access:<6} {_show(n, v)}" for n, v in values.items()]
    _emit({n: _plain(v) for n, v in values.items()}, lines, args.json)


def _save(servo, args):
    values = servo.save(args.file)
    _emit({"file": args.file, "registers": len(values)},
          [f"saved {len(values)} registers to {args.file}"], args.json)


def _load(servo, args):
    values = servo.load(args.file)
    _emit({"file": args.file, "registers": len(values)},
          [f"loaded {len(values)} registers from {args.file}"], args.json)


def _watch(servo, args):
    for n in args.names:
        servo.register(n)
    series = {n: [] for n in args.names}
    times = []
    start = time.monotonic()
    print("t_s " + " ".join(args.names))
    k = 0
    try:
        while args.count is None or k < args.count:
            if k:
                time.sleep(max(0.0, start + k * args.interval - time.monotonic()))
            values = servo.get_many(args.names)
            t = time.monotonic() - start
            times.append(round(t, 6))
            for n, v in values.items():
                series[n].append(_plain(v))
            print(f"{t:.3f} " + " ".join(_show(n, v) for n, v in values.items()), flush=True)
            k += 1
    except KeyboardInterrupt:
        pass
    _emit({"t_s": times, **series}, [], args.json)


def _scope(servo, args):
    import numpy as np
    from .servo import SCOPE_SOURCES
    channels = [c.strip() for c in args.channels.split(",") if c.strip()]
    step = None
    if args.step:
        step = {n: _cli_value(servo, n, v) for n, v in map(_parse_assignment, args.step)}
    cap = servo.scope_capture(channels, pretrigger=args.pretrigger, decimation=args.decimation,
                              trigger=args.trigger, step=step, timeout_s=args.capture_timeout)
    names = [c for c in cap if c != "t_s"]
    lines = [f"captured {len(cap['t_s'])} samples of {', '.join(names)} "
             f"(dt {args.decimation / servo.scales.pwm_hz:g} s, trigger at t = 0)"]
    if args.csv:
        header = "t_s," + ",".join(f"{n}_{SCOPE_SOURCES[n][2].replace('/', '_per_')}"
                                   for n in names)
        np.savetxt(args.csv, np.column_stack([cap["t_s"]] + [cap[n] for n in names]),
                   delimiter=",", header=header, comments="", fmt="%.9g")
        lines.append(f"wrote {args.csv}")
    if args.png:
        _plot(cap, names, args.png)
        lines.append(f"wrote {args.png}")
    fig = {n: {"min": float(np.min(cap[n])), "max": float(np.max(cap[n])),
               "mean": float(np.mean(cap[n])), "unit": SCOPE_SOURCES[n][2]} for n in names}
    for n in names:
        f = fig[n]
        lines.append(f"  {n:<10} min {f['min']:.6g} max {f['max']:.6g} mean {f['mean']:.6g} "
                     f"{f['unit']}")
    _emit({"samples": len(cap["t_s"]), "channels": fig, "csv": args.csv, "png": args.png},
          lines, args.json)


def _plot(cap, names, path):
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    from .servo import SCOPE_SOURCES
    units = sorted({SCOPE_SOURCES[n][2] for n in names})
    fig, axes = plt.subplots(len(units), 1, sharex=True, squeeze=False,
                             figsize=(8, 2.5 * len(units)))
    for ax, unit in zip(axes[:, 0], units):
        for n in names:
            if SCOPE_SOURCES[n][2] == unit:
                ax.plot(cap["t_s"] * 1e3, cap[n], label=n)
        ax.axvline(0, color="grey", lw=0.5)
        ax.set_ylabel(unit)
        ax.legend(loc="best")
        ax.grid(True, lw=0.3)
    axes[-1, 0].set_xlabel("t (ms), trigger at 0")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _clear_faults(servo, args):
    f = servo.clear_faults()
    lines = [f"trip {'on' if f['trip'] else 'off'}"] + [
        f"{k:<8} {', '.join(f[k]) or '-'}" for k in ("present", "first", "seen")]
    _emit(f, lines, args.json)


def _tune(servo, args):
    from ..sim.motor import MotorParams
    from .registers import REGISTERS
    try:
        motor = MotorParams.from_file(args.motor)
    except (OSError, ValueError, TypeError) as e:
        raise SystemExit(f"foc-servo host tune: {e}") from None
    result = servo.tune(motor, current_bandwidth_hz=args.current_bw_hz, speed_a=args.speed_a,
                        dry_run=args.dry_run)
    regs = result.registers
    values = {n: REGISTERS[n].from_raw(r, servo.scales) for n, r in regs.items()}
    cur, spd = result.current, result.speed
    lines = [f"current loop: K_p {cur.kp_v_per_a:.6g} V/A, K_i {cur.ki_v_per_as:.6g} V/(A·s), "
             f"ω_c {cur.omega_c_rad_s:.6g} rad/s",
             f"speed loop:   K_p {spd.kp_a_per_rad_s:.6g} A/(rad/s), "
             f"K_i {spd.ki_a_per_rad:.6g} A/rad"]
    lines += [f"{n:<12} = {values[n]:.9g} pu (raw {regs[n]})" for n in regs]
    lines.append("dry run: nothing written" if args.dry_run else "written")
    _emit({"registers": values, "raw": regs, "written": not args.dry_run,
           "current_kp_v_per_a": cur.kp_v_per_a, "current_ki_v_per_as": cur.ki_v_per_as,
           "speed_kp_a_per_rad_s": spd.kp_a_per_rad_s, "speed_ki_a_per_rad": spd.ki_a_per_rad},
          lines, args.json)


# --- parser ------------------------------------------------------------------------------------

def add_host_parser(subparsers):
    """Add the ``host`` sub-command (and its commands) to an argparse ``subparsers``; returns
    its parser. Its handler is :func:`cmd_host` (``set_defaults(func=cmd_host)``)."""
    p = subparsers.add_parser(
        "host", help="talk to a drive over its serial link (or --port sim: the simulator)",
        description="Read and write a drive's registers in physical units "
                    "(docs/REGISTERS.md).")
    p.add_argument("--port", required=True,
                   help="serial port (e.g. /dev/ttyUSB0), or 'sim' for the simulated gateware")
    p.add_argument("--baud", type=_positive_int, default=115200,
                   help="baud rate (default: %(default)s)")
    p.add_argument("--sim-level", choices=["drive", "registers"], default="drive",
                   help="with --port sim: 'drive' (default) is the whole controller gateware "
                        "driving the simulated motor (compiled engine, built once); 'registers' "
                        "is only the host link, register file and trace buffer (Amaranth's "
                        "simulator)")
    p.add_argument("--sim-uart", action="store_true",
                   help="with --port sim --sim-level registers: simulate the UARTs too (slower)")
    p.add_argument("--timeout", type=_positive_float, default=None,
                   help="reply timeout, s (default: 0.5, 120 with --port sim)")
    p.set_defaults(func=cmd_host)
    json_opt = argparse.ArgumentParser(add_help=False)
    json_opt.add_argument("--json", action="store_true",
                          help="print the figures as one JSON object on the last line")
    sub = p.add_subparsers(dest="host_command", required=True, metavar="COMMAND")

    c = sub.add_parser("get", parents=[json_opt], help="read registers (in units)")
    c.add_argument("names", nargs="+", metavar="NAME")
    c.set_defaults(host_func=_get)

    c = sub.add_parser("set", parents=[json_opt],
                       help="write registers: NAME=VALUE (units; enums by name; flags a|b)")
    c.add_argument("assignments", nargs="+", metavar="NAME=VALUE")
    c.set_defaults(host_func=_set)

    c = sub.add_parser("dump", parents=[json_opt], help="read every readable register")
    c.set_defaults(host_func=_dump)

    c = sub.add_parser("load", parents=[json_opt],
                       help="restore a parameter file (.toml/.json): all checked, then written")
    c.add_argument("file")
    c.set_defaults(host_func=_load)

    c = sub.add_parser("save", parents=[json_opt],
                       help="save the rw registers to a parameter file (.toml/.json)")
    c.add_argument("file")
    c.set_defaults(host_func=_save)

    c = sub.add_parser("watch", parents=[json_opt], help="print registers periodically")
    c.add_argument("names", nargs="+", metavar="NAME")
    c.add_argument("--interval", type=_positive_float, default=0.5,
                   help="seconds between reads (default: %(default)s)")
    c.add_argument("--count", type=_positive_int, default=None,
                   help="number of reads (default: until Ctrl-C)")
    c.set_defaults(host_func=_watch)

    c = sub.add_parser("scope", parents=[json_opt],
                       help="triggered capture of up to 4 signals to CSV and PNG")
    c.add_argument("--channels", required=True,
                   help="comma-separated sources: speed, speed_ref, i_d, i_q, i_d_ref, i_q_ref, "
                        "i_alpha, i_beta, u_d, u_q, u_alpha, u_beta, theta, u_dc")
    c.add_argument("--pretrigger", type=_nonneg_int, default=0,
                   help="samples before the trigger (default: %(default)s)")
    c.add_argument("--decimation", type=_positive_int, default=1,
                   help="one sample every n loop ticks (default: %(default)s)")
    c.add_argument("--trigger", choices=["host", "step"], default="host",
                   help="host: trigger at once; step: on a reference step (default: "
                        "%(default)s)")
    c.add_argument("--step", action="append", metavar="NAME=VALUE",
                   help="with --trigger step: write this reference once armed (repeatable)")
    c.add_argument("--capture-timeout", type=_positive_float, default=30.0,
                   help="seconds to wait for the capture (default: %(default)s)")
    c.add_argument("--png", help="plot to this PNG file")
    c.add_argument("--csv", help="samples to this CSV file")
    c.set_defaults(host_func=_scope)

    c = sub.add_parser("clear-faults", parents=[json_opt],
                       help="release the trip latch; print the faults")
    c.set_defaults(host_func=_clear_faults)

    c = sub.add_parser("tune", parents=[json_opt],
                       help="current and speed PI gains from a motor file, written as registers")
    c.add_argument("--motor", required=True, help="motor file (.toml or .json, docs/TUNING.md)")
    c.add_argument("--current-bw-hz", type=_positive_float, default=None,
                   help="current-loop crossover, Hz (default: technical optimum)")
    c.add_argument("--speed-a", type=_positive_float, default=3.0,
                   help="symmetric-optimum a of the speed loop (default: %(default)s)")
    c.add_argument("--dry-run", action="store_true", help="print the gains, write nothing")
    c.set_defaults(host_func=_tune)
    return p


def cmd_host(args):
    """Handler of ``foc-servo host``: connect, run the command, close. Library and link errors
    end the program with a one-line message."""
    from .protocol import LinkError
    from .servo import Servo, ServoError
    what = f"foc-servo host {args.host_command}"
    try:
        if args.port == "sim":
            kw = {} if args.timeout is None else {"timeout_s": args.timeout}
            if args.sim_level == "drive":
                servo = Servo.drive_sim(**kw)
            else:
                servo = Servo.sim(uart=args.sim_uart, **kw)
        else:
            servo = Servo.open(args.port, args.baud, timeout_s=args.timeout or 0.5)
        with servo:
            return args.host_func(servo, args)
    except (ServoError, LinkError) as e:
        raise SystemExit(f"{what}: {e}") from None


def main(argv=None):
    """``foc-servo``-like entry with only the ``host`` command (``main(["host", ...])``)."""
    parser = argparse.ArgumentParser(prog="foc-servo")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_host_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
