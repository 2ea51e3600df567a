"""The ``foc-servo`` command.

Every sub-command that reports figures takes ``--json`` and then prints them as one JSON object on
the last line of its output (the keys the issues name are a public interface). Progress goes to
stderr, so stdout stays clean for pipes.
"""

import argparse
import json
import sys
import time
from pathlib import Path

__all__ = ["main"]


def int_at_least(minimum):
    """argparse type: an integer of at least ``minimum``, with a message naming both."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, not {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, not {value}")
        return value
    return parse


positive_int = int_at_least(1)


def emit(figures, human_lines, as_json, *, default=float, sort_keys=True):
    """Print the human-readable lines, then (``--json``) the figures as one JSON object on the
    last line: the rule every figure-reporting command follows."""
    for line in human_lines:
        print(line)
    if as_json:
        print(json.dumps(figures, sort_keys=sort_keys, default=default))


def cmd_verilog(args):
    from amaranth.back import verilog

    from ..boards.area import ports
    from ..hdl.catalog import BLOCKS
    names = args.block or list(BLOCKS)
    unknown = [n for n in names if n not in BLOCKS]
    if unknown:
        raise SystemExit(f"foc-servo verilog: unknown block {unknown[0]!r}; "
                         f"choose from {', '.join(BLOCKS)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        path = out / f"{name}.v"
        block = BLOCKS[name]()
        path.write_text(verilog.convert(block, name=name, ports=ports(block)))
        print(f"wrote {path}")


def _fmt_area(area):
    lines = [f"{'block':<10} {'iCE40 LUT4':>10} {'FF':>6} {'carry':>6} {'DSP':>4}   "
             f"{'xc7 LUT':>8} {'FF':>6} {'CARRY4':>6} {'DSP':>4}"]
    for name, fig in area.items():
        i, x = fig["ice40"], fig["xc7"]
        lines.append(f"{name:<10} {i['lut4']:>10} {i['ff']:>6} {i['carry']:>6} {i['dsp']:>4}   "
                     f"{x['lut']:>8} {x['ff']:>6} {x['carry4']:>6} {x['dsp']:>4}")
    return lines


def _arith_lines(fig):
    d = fig["details"]
    return [
        "arithmetic blocks against their golden models:",
        f"  CORDIC   {d['cordic']['vectors']:>7} rotations: max error {fig['cordic_max_err_lsb']:.3f}"
        f" LSB, RMS {fig['cordic_rms_err_lsb']:.3f} LSB, latency {fig['cordic_latency_clk']} clk, "
        f"throughput {fig['cordic_throughput_per_clk']:.3f} /clk, "
        f"{fig['cordic_mismatches']} mismatches",
        f"  PI       {d['pi']['vectors']:>7} samples:   {fig['pi_mismatches']} mismatches",
        f"  Clarke   {d['clarke']['vectors']:>7} vectors:   {fig['clarke_mismatches']} mismatches",
        f"  divider  {d['divider']['vectors']:>7} divisions: {fig['divider_mismatches']} mismatches, "
        f"{fig['divider_clk']} clk per division",
        f"  Amaranth simulator on the CORDIC alone: {fig['pysim_clk_per_s']:.0f} clk/s",
    ]


def _io_lines(fig):
    from ..sim.verify.mt_speed import table_text
    mt = fig["details"]["mt_speed"]
    lines = [
        "motor-side blocks:",
        f"  M/T speed gateware vs model: {fig['mt_mismatches']} mismatches over {mt['vectors']} "
        f"outputs",
        *("  " + line for line in table_text(mt)),
        f"  M/T worst 10…10000 r/min {fig['mt_err_pct_10_10000']:.4f} %, 0.2…10 r/min "
        f"{fig['mt_err_pct_0p2_10']:.4f} %; lowest resolvable at 1 MHz / 16-bit TC: "
        f"{fig['mt_min_rpm_1mhz_16bit']:g} r/min",
        f"  electrical angle drift after {fig['angle_drift_counts_per_phase']} counts forward, back "
        f"and random walk: {fig['angle_drift_counts']} counts",
        f"  glitch filter: {fig['glitch_short_counted']} short pulses counted, "
        f"{fig['glitch_long_missed']} long pulses missed",
        f"  SVPWM {fig['svpwm_commands']} commands: {fig['svpwm_mismatches']} mismatches, "
        f"volt-seconds error {fig['volt_seconds_err_counts']:.3f} counts, overmodulation angle "
        f"error {fig['overmod_angle_err_deg']:.4f}°",
        f"  dead time: {fig['deadtime_violations']} violations",
        f"  fault → gates off: max {fig['fault_latency_clk_max']} clk "
        f"({', '.join(f'{k} {v}' for k, v in fig['fault_latency_clk'].items())})",
        f"  protection {fig['protect_mismatches']} mismatches, ADC {fig['adc_mismatches']} "
        f"mismatches",
    ]
    return lines


def cmd_bench(args):
    from ..sim.bench import bench_arith, bench_control, bench_io
    start = time.perf_counter()
    suites = ["arith", "io", "control", "link"] if args.suite == "all" else [args.suite]
    fig, lines = {}, []
    for suite in suites:
        if suite == "arith":
            part = bench_arith(count=args.count or 100_000, seed=args.seed,
                               area=not args.no_area, progress=not args.quiet)
            lines += _arith_lines(part)
        elif suite == "control":
            part = bench_control(count=args.count or 2_000, seed=args.seed,
                                 area=not args.no_area, progress=not args.quiet)
            st = part["foc_latency_stages"]
            lines += [
                "controller:",
                f"  current loop: compute latency {part['foc_latency_clk']} clk "
                f"({' + '.join(f'{k} {v}' for k, v in st.items())}), checked on every sample "
                f"({part['foc_latency_errors']} deviations); {part['foc_mismatches']} mismatches "
                f"over {part['details']['foc']['vectors']} samples",
                f"  register file {part['regs_mismatches']} mismatches, speed loop/modes/scope "
                f"{part['servo_mismatches']} mismatches",
            ]
        elif suite == "link":
            from ..sim.verify import link
            part = link.run(rw=1000, malformed=10_000, seed=args.seed, progress=not args.quiet)
            lines += ["host link (simulated gateware):",
                      *("  " + line for line in link.summary(part).splitlines())]
            public = ("rw_mismatches", "malformed_frames", "malformed_writes", "hangs")
            part = {k if k in public else f"link_{k}": v for k, v in part.items()}
        else:
            part = bench_io(count=args.count or 10_000, seed=args.seed,
                            drift_counts=args.drift_counts, area=not args.no_area,
                            progress=not args.quiet)
            lines += _io_lines(part)
        for key in ("area", "details", "vectors"):
            if key in part:
                fig.setdefault(key, {}).update(part.pop(key))
        fig.update(part)
    if "area" in fig:
        lines += ["area from yosys (synthesis, no place-and-route):", *_fmt_area(fig["area"])]
    fig["wall_s"] = time.perf_counter() - start
    lines.append(f"wall time {fig['wall_s']:.1f} s")
    emit(fig, lines, args.json)


def cmd_prove(args):
    from ..boards.prove import PROOFS, prove, summary, table
    unknown = [n for n in args.names if n not in PROOFS]
    if unknown:
        raise SystemExit(f"foc-servo prove: unknown proof {unknown[0]!r}; "
                         f"choose from {', '.join(PROOFS)}")
    start = time.perf_counter()
    results = prove(args.names or None, broken=args.broken, cover=args.cover,
                    progress=not args.quiet, timeout_s=args.timeout)
    doc = summary(results, broken=args.broken)
    doc["wall_s"] = time.perf_counter() - start
    emit(doc, table(results, suffix="_broken" if args.broken else "").splitlines(), args.json)
    want = "failed" if args.broken else "proven"
    return 0 if all(r["status"] == want for r in results.values()) else 1


def cmd_build(args):
    from ..boards.build import build
    build(args.board, out_dir=args.out, clk_hz=args.clk_mhz * 1e6 if args.clk_mhz else None,
          current_loop=args.current_loop, seed=args.seed, progress=not args.quiet,
          json=args.json)


def cmd_fmax(args):
    from ..boards.fmax import fmax_block, fmax_catalog
    blocks = fmax_catalog()
    names = args.block or [n for n in blocks if n != "top"]
    unknown = [n for n in names if n not in blocks]
    if unknown:
        raise SystemExit(f"foc-servo fmax: unknown block {unknown[0]!r}; "
                         f"choose from {', '.join(blocks)}")
    results, lines = {}, []
    for name in names:
        keep = Path(args.out) / name if args.out else None
        r = results[name] = fmax_block(name, family=args.family, freq_mhz=args.freq_mhz,
                                       seed=args.seed, keep_dir=keep, progress=not args.quiet)
        cp = r["critical_path"] or {}
        lines.append(f"{name:<10} {r['fmax_mhz'] or 0:7.2f} MHz  ({r['wall_s']:.0f} s)  "
                     f"{cp.get('from')} → {cp.get('to')}: {cp.get('delay_ns')} ns, "
                     f"{cp.get('logic_levels')} levels")
    doc = results[names[0]] if len(names) == 1 else {"blocks": results}
    emit(doc, lines, args.json)


def build_parser():
    parser = argparse.ArgumentParser(
        prog="foc-servo",
        description="FPGA vector-controlled PMSM speed servo: gateware generator, simulation, "
                    "benchmarks.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("verilog", help="write the Verilog of each block to build/verilog/")
    p.add_argument("--out", default="build/verilog", help="output folder (default: %(default)s)")
    p.add_argument("--block", action="append", help="only this block (repeatable)")
    p.set_defaults(func=cmd_verilog)

    from .codegen import add_arguments as regs_arguments, cmd_regs
    p = sub.add_parser("regs", help="regenerate docs/REGISTERS.md and include/foc_servo_regs.h "
                                    "from the register map (--check: fail if they are stale)")
    regs_arguments(p)
    p.set_defaults(func=cmd_regs)

    from .host_cli import add_host_parser
    add_host_parser(sub)

    from .sim_cli import add_sim_parser
    add_sim_parser(sub)

    from ..boards.platforms import BOARDS
    p = sub.add_parser("build", help="build the controller for a board: a bitstream (iCEBreaker, "
                                     "ULX3S) or a vendor build tree (Arty S7, Atlys), with "
                                     "utilisation and Fmax beside the paper's Table 1")
    p.add_argument("--board", required=True, choices=list(BOARDS), help="the board")
    p.add_argument("--out", default="build", help="output folder (default: %(default)s)")
    p.add_argument("--clk-mhz", type=float, default=None,
                   help="system clock, MHz (default: the board's, 50; 33.333 on the iCEBreaker; "
                        "the PLL's nearest is used)")
    from ..hdl.top import CURRENT_LOOPS
    p.add_argument("--current-loop", choices=CURRENT_LOOPS, default=None,
                   help="current-loop gateware: pipelined (CurrentLoop) or engine "
                        "(EngineCurrentLoop, fewer LUTs and multipliers) (default: the board's: "
                        "engine on the iCEBreaker, pipelined elsewhere)")
    p.add_argument("--seed", type=int, default=None,
                   help="nextpnr placement seed (iCEBreaker, ULX3S; default: nextpnr's, 1)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the figures as one JSON object on the last line")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("fmax", help="Fmax of one block alone on the ECP5-85F or the iCE40 UP5K "
                                    "(yosys + nextpnr, ports registered): Fmax, critical path "
                                    "and utilisation")
    p.add_argument("--block", action="append",
                   help="catalogue block, uart_rx / uart_tx, foc_engine or foc_engine_speed "
                        "(repeatable; default: "
                        "every block but the top)")
    from ..boards.fmax import FAMILIES
    p.add_argument("--family", choices=list(FAMILIES), default="ecp5",
                   help="ecp5 (ECP5-85F, synth_ecp5) or ice40 (UP5K, synth_ice40 -dsp; the "
                        "utilisation's ICESTORM_LC must fit 5 280) (default: %(default)s)")
    p.add_argument("--freq-mhz", type=float, default=None,
                   help="clock constraint for nextpnr, MHz (default: 100 on the ECP5, 33.333 on "
                        "the iCE40)")
    p.add_argument("--seed", type=int, default=1, help="nextpnr seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="keep netlists, logs and reports in OUT/BLOCK")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the figures as one JSON object on the last line (one block: its "
                        "figures, fmax_mhz and critical_path.from/to; several: under 'blocks')")
    p.set_defaults(func=cmd_fmax)

    p = sub.add_parser("prove", help="SymbiYosys safety proofs (k-induction, yices): dead time, "
                                     "fault → gates off, PI limits, host-link writes")
    p.add_argument("names", nargs="*", metavar="NAME", help="proofs to run (default: all)")
    p.add_argument("--broken", action="store_true",
                   help="run the deliberately broken variants (each must fail)")
    p.add_argument("--cover", action="store_true", help="also run the cover statements")
    p.add_argument("--timeout", type=float, default=600, help="per proof, s (default: 600)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the figures as one JSON object on the last line")
    p.set_defaults(func=cmd_prove)

    p = sub.add_parser("bench", help="measure accuracy, simulator speed and area")
    p.add_argument("suite", nargs="?", default="all",
                   choices=["all", "arith", "io", "control", "link"],
                   help="which figures: arith (foundation blocks), io (motor-side blocks), control "
                        "(current loop latency, register file, speed loop; area incl. the top), link "
                        "(host link: 1 000 writes + read-backs through pyserial, 10 000 malformed "
                        "frames), all (default: %(default)s)")
    p.add_argument("--count", type=positive_int, default=None,
                   help="random vectors per block (default: 100 000 for arith, 10 000 for io, "
                        "2 000 current-loop samples for control)")
    p.add_argument("--drift-counts", type=positive_int, default=1_000_000,
                   help="encoder counts per phase of the angle-drift run (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default: %(default)s)")
    p.add_argument("--no-area", action="store_true", help="skip the yosys area figures")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the figures as one JSON object on the last line")
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv=None):
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
