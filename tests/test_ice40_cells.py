# Ref: issue 7 (the iCEBreaker fit), boards/ice40_cells.py
import json
import re
import subprocess

from amaranth.back import rtlil
from amaranth.hdl import Cat, Module, Signal, unsigned
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from foc_servo.boards.area import STRIP_CHECKS, ports
from foc_servo.boards.fmax import _tool
from foc_servo.boards.ice40_cells import _instances, _sources, logic_cells, report_lines


def _cell(kind, src="", **conn):
    dirs = {"O": "output", "Q": "output", "CO": "output"}
    return {"type": kind, "attributes": {"src": src},
            "port_directions": {p: dirs.get(p, "input") for p in conn},
            "connections": {p: [b] for p, b in conn.items()}}


def test_packing_rules_on_a_hand_made_netlist():
    """Each rule once: a LUT feeding only a flip-flop shares its cell; a LUT feeding a
    flip-flop and more does not; a flip-flop loaded from another flip-flop or a port has a cell
    of its own; an adder bit's carry joins its LUT; a comparator's carry (no sum LUT) is alone
    and, its carry-out read by logic, needs a feed-out cell; a LUT2 on a lone carry's operand
    moves into the carry's cell."""
    cells = {
        # 10 = LUT → only FF 20 (one cell)
        "top.a.l1": _cell("SB_LUT4", "x/hdl/alpha.py:1", I0=1, I1=2, I2="0", I3="0", O=10),
        "top.a.f1": _cell("SB_DFF", "x/hdl/alpha.py:2", D=10, Q=20),
        # LUT 11 → FF 21 and LUT 12: two cells for the LUTs, one for the flip-flop
        "top.a.l2": _cell("SB_LUT4", "x/hdl/alpha.py:3", I0=1, I1=2, I2=3, I3="0", O=11),
        "top.a.f2": _cell("SB_DFF", "x/hdl/alpha.py:4", D=11, Q=21),
        "top.a.l3": _cell("SB_LUT4", "", I0=11, I1=1, I2="0", I3="0", O=12),
        # FF → FF (a pipeline copy): alone
        "top.b.f3": _cell("SB_DFFE", "x/hdl/beta.py:1", D=20, E=1, Q=22),
        # adder bit: carry with CI 30, operands 4, 5; its sum LUT reads I1 = 4, I2 = 5, I3 = 30
        "top.b.c1": _cell("SB_CARRY", "x/hdl/beta.py:2", CI=30, I0=4, I1=5, CO=31),
        "top.b.s1": _cell("SB_LUT4", "", I0="0", I1=4, I2=5, I3=30, O=13),
        "top.b.c0": _cell("SB_CARRY", "x/hdl/beta.py:3", CI="0", I0=6, I1=7, CO=30),
        # comparator bit: operand 8 from a LUT2 (I2, I3), carry-out 31 read by a LUT's I0
        "top.b.l4": _cell("SB_LUT4", "", I0="0", I1="0", I2=1, I3=2, O=8),
        "top.b.c2": _cell("SB_CARRY", "x/hdl/beta.py:4", CI=31, I0=8, I1=9, CO=32),
        "top.b.l5": _cell("SB_LUT4", "", I0=32, I1=1, I2="0", I3="0", O=14),
    }
    netlist = {"modules": {"top": {"attributes": {"top": "1"}, "cells": cells}}}
    est = logic_cells(netlist)
    t = est["total"]
    assert (t["lut4"], t["ff"], t["carry"]) == (6, 3, 3)
    assert t["ff_alone"] == 2                       # f2 (shared LUT output), f3 (from a FF)
    assert t["carry_alone"] == 2                    # c0 (constant carry-in), c2 (no sum LUT)
    assert t["lut_merged"] == 1                     # l4 into c2's cell
    # feed-out: c2's carry-out read by l5; feed-in: none (c1's and c2's carry-ins are carries')
    assert t["chain"] == 1
    assert t["cells"] == 6 - 1 + 2 + 2 + 1
    # LUTs without src count where their instance's cells come from (top.a: alpha, top.b: beta)
    assert est["by_source"]["alpha"]["lut4"] == 3 and est["by_source"]["beta"]["lut4"] == 3
    assert list(est["by_source"]) == ["beta", "alpha"]      # most cells first
    lines = report_lines(est)
    assert lines[-1].split()[:2] == ["total", str(t["cells"])]


class _Mix(wiring.Component):
    """A counter, a register loaded from a shared bus, a copy of it, a comparator."""
    def __init__(self):
        super().__init__({"bus": In(16), "load": In(4), "a": In(16), "b": In(16),
                          "lt": Out(1), "count": Out(16), "copy": Out(64)})

    def elaborate(self, platform):
        m = Module()
        regs = [Signal(unsigned(16), name=f"r{k}") for k in range(4)]
        for k, r in enumerate(regs):
            with m.If(self.load[k]):
                m.d.sync += r.eq(self.bus)
        m.d.sync += [self.count.eq(self.count + 1), self.lt.eq(self.a < self.b),
                     self.copy.eq(Cat(*regs))]
        return m


def test_cells_without_a_source_go_to_their_instance():
    """A LUT without ``src`` named after a RAM's read data (``...speed_loop.rf.0.0_RDATA...``)
    belongs to the instance its name starts with (the hierarchy from ``hdlname``), whose cells
    vote servo, not to the pseudo-instance ``rf.0`` that one ``fixed`` carry shares its name
    with (the session-11/12 tables' moving ``fixed`` row; docs/AREA.md "Session 12")."""
    cells = {"top.servo.speed_loop.rf.0.0_RDATA_SB_LUT4_O": _cell("SB_LUT4"),
             "top.servo.speed_loop.rf.0.0_RDATA_SB_CARRY_CO": _cell("SB_CARRY",
                                                                   "hdl/fixed.py:10"),
             "top.servo.speed_loop.acc_SB_DFF_Q": _cell("SB_DFF", "hdl/servo.py:100"),
             "top.servo.speed_loop.b_SB_DFF_Q": _cell("SB_DFF", "hdl/servo.py:101")}
    module = {"cells": cells,
              "netnames": {"x": {"attributes": {"hdlname": "top servo speed_loop acc"}}}}
    assert _instances(module) == {"top", "top.servo", "top.servo.speed_loop"}
    lut = "top.servo.speed_loop.rf.0.0_RDATA_SB_LUT4_O"
    assert _sources(cells, _instances(module))[lut] == "servo"
    assert _sources(cells)[lut] == "fixed"         # by the name up to its last dot


def test_estimate_agrees_with_nextpnr(tmp_path):
    """The estimate against nextpnr-ice40's own packer (``--pack-only``) on a small design that
    has each kind of cell: within 2 % (nextpnr also packs its constant drivers)."""
    block = _Mix()
    (tmp_path / "mix.il").write_text(rtlil.convert(block, name="mix", ports=ports(block)))
    subprocess.run(_tool("yosys") + ["-q", "-p", f"read_rtlil mix.il; {STRIP_CHECKS}; "
                                     "synth_ice40 -dsp -top mix -json mix.json"],
                   cwd=tmp_path, check=True)
    proc = subprocess.run(_tool("nextpnr-ice40") + ["--up5k", "--package", "sg48", "--json",
                                                    "mix.json", "--pack-only",
                                                    "--pcf-allow-unconstrained"],
                          cwd=tmp_path, capture_output=True, text=True, check=True)
    used = int(re.search(r"ICESTORM_LC:\s+(\d+)/", proc.stdout + proc.stderr).group(1))
    est = logic_cells(json.loads((tmp_path / "mix.json").read_text()))["total"]
    assert est["ff_alone"] >= 128           # the bus registers and their copy
    assert est["carry_alone"] >= 16         # the comparator
    assert abs(est["cells"] - used) <= max(2, 0.02 * used), (est, used)
