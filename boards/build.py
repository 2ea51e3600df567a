# Ref: issue 7 items 1–2 (board builds, utilisation and Fmax beside paper Table 1);
# Lattice TN1251 (iCE40 sysCLOCK PLL: F_PFD 10–133 MHz, F_VCO 533–1066 MHz, F_OUT 16–275 MHz);
# Lattice TN1263 (ECP5 sysCLOCK PLL: F_PFD 3.125–400 MHz, F_VCO 400–800 MHz) and Project Trellis
# ecppll; Xilinx DS189 (Spartan-7 -1 MMCM: F_PFD 10–450 MHz, F_VCO 600–1200 MHz); Xilinx DS162
# (Spartan-6 -3 PLL: F_PFD 19–500 MHz, F_VCO 400–1080 MHz).
"""Build the controller for a board: a bitstream (open toolchain) or a vendor build tree.

::

    board oscillator ─ PLL (SB_PLL40_PAD / EHXPLLL / MMCME2_BASE / PLL_BASE) ─ sync clock
    PLL lock, reset button ─ power-on timer ─ ResetSynchronizer ─ sync reset
    Board.motor pins, USB-UART, LEDs ─ lib.io buffers ─ Top(clk_hz = the PLL's actual output)

Flows (:func:`build`):

* ``bitstream`` (iCEBreaker, ULX3S): the Amaranth build plan is written to ``out_dir/NAME`` and
  its commands (``build_foc_servo.json``) run here one by one with YoWASP yosys / nextpnr /
  icepack or ecppack (``$YOSYS``, ``$NEXTPNR_ICE40``, … override them, as in Amaranth). yosys
  writes ``stat -json`` after synthesis (utilisation); nextpnr writes its ``--report`` JSON (Fmax
  per clock, device utilisation). A tool failure, e.g. a design that does not fit, is reported
  in the result (``fits`` false, ``error`` = the tool's ``ERROR`` lines), not raised. On the
  iCE40 the plan's RTLIL leaves out the power-up value of the block-RAM read registers loaded
  on every clock (:func:`~.area.ram_read_init_free`: yosys would emulate it in logic) and
  ``synth_ice40`` runs with :data:`ICE40_SYNTH_OPTS`.
* ``vendor`` (Arty S7 → Vivado, Atlys → ISE): the complete build tree and a zip of it, plus a
  yosys ``synth_xilinx`` estimate run on the tree's own Verilog (so the PLL and I/O primitive
  instances are checked against yosys' cell library too). The tree's Verilog is Verilog-2001,
  without the gateware's simulation-only ``Assert``/``Print``, its larger ROMs marked for block
  RAM (:func:`synthesis_verilog`). The LUT figure is Vivado's "Slice LUTs": logic LUTs and the
  LUTs of distributed RAMs and shift registers (:func:`~.area.xilinx_luts`).

The power-on timer holds the reset for 15 µs after the PLL locks: iCE40 block RAMs read as zero
for ~3 µs after configuration (the reason Amaranth's own iCE40 clock domain has the same delay),
harmless elsewhere.
"""

import json
import math
import numbers
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from json import dumps as _json_dumps   # build()'s ``json`` flag shadows the module there
from pathlib import Path

from amaranth.hdl import ClockDomain, ClockSignal, Const, Elaboratable, Instance, Module, Signal
from amaranth.lib import io
from amaranth.lib.cdc import FFSynchronizer, ResetSynchronizer

from ..hdl.fixed import check_choice
from ..hdl.top import CURRENT_LOOPS, Top
from . import area, ice40_cells
from .area import STRIP_CHECKS
from .platforms import MOTOR_PORTS, get_board

__all__ = ["PAPER", "CLOCK_RANGE_HZ", "MUL_WIDTH", "ICE40_SYNTH_OPTS", "PllConfig", "pll_config",
           "BoardTop", "synthesis_verilog", "prepare", "build", "report_lines"]

#: The paper's chip (Table 1: Xilinx Spartan-IIE at 33.333 MHz).
PAPER = {"lut4": 5077, "ff": 3326, "bram_bits": 64 * 1024, "clock_mhz": 33.333}

#: The system clocks a build accepts, Hz (the iCE40 PLL's output starts at 16 MHz).
CLOCK_RANGE_HZ = (20e6, 200e6)

#: Design name: the file stem of every generated file.
NAME = "foc_servo"

#: Reset hold after PLL lock, s (module docstring).
POR_DELAY_S = 15e-6

#: ``Top(mul_width=…)`` per FPGA family: the signed operand width of its hard multiplier where
#: products are split for the clock (ECP5 ``MULT18X18D`` 18 × 18 at 100 MHz; Spartan-6
#: ``DSP48A1`` 18 × 18: 18); ``None``: products not split, the synthesiser maps them whole (iCE40:
#: onto the 16 × 16 ``SB_MAC16`` better than a 16-bit split can, ``hdl/dsp.py``, docs/AREA.md
#: §7.4; Spartan-7 at 50 MHz: onto cascaded ``DSP48E1``, −≈ 90 LUT6 and −2 DSP48E1 against 18,
#: AREA.md "Session 11: Spartan-7"). Bit- and cycle-identical whatever the width.
MUL_WIDTH = {"ice40": None, "ecp5": 18, "xc7": None, "xc6s": 18}

#: ``Top(uv_arm_chain=…)`` per FPGA family: the protection's under-voltage arming compare on a
#: carry chain of its own on the ECP5 (its 17-input AND behind the shared chain was a 100 MHz
#: critical path, docs/AREA.md §7.53, §7.58); two chains elsewhere (the iCE40's cells, §7.30).
#: The same verdicts either way.
UV_ARM_CHAIN = {"ice40": False, "ecp5": True, "xc7": False, "xc6s": False}

#: ``Top(trip_register=…)`` per FPGA family: the protection's OR of its causes in a flip-flop of
#: its own (ECP5: the trip and the gates start at one flip-flop, 100 MHz, docs/AREA.md §7.34;
#: the Spartans as before: the other form is +1 LUT6 on the Arty S7); the OR of the
#: ``present`` flip-flops on the iCE40 (those flip-flops pack with their LUTs: −8 logic cells on
#: the iCEBreaker, §7.70). The same trip either way.
TRIP_REGISTER = {"ice40": False, "ecp5": True, "xc7": True, "xc6s": True}

#: ``Top(scope_down_counts=…)`` per FPGA family: the scope's pre-trigger fill and post-trigger
#: count as down-counters on the iCE40 (no compare of a fill count with the pre-trigger count,
#: no ``~pre + 1`` adder: −23 logic cells on the iCEBreaker); a fill count and its compare
#: elsewhere (the Spartan-7's carry chains are cheap: the down-counters cost it +22 LUT6;
#: docs/AREA.md §7.70). The same captures either way.
SCOPE_DOWN_COUNTS = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(timer_clamp=…)`` per FPGA family: the dead-time compensation's clamp in the PWM
#: timer's shadow and active registers on the iCE40 (their flip-flops pack with their LUTs: the
#: timer 242 → 209 logic cells on the iCEBreaker, docs/AREA.md §7.72); in the compensation
#: elsewhere (the netlists of before). The same levels either way.
TIMER_CLAMP = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(gates_dead_n=…)`` per FPGA family: the gates' turn-on compare operand
#: ``~(max(dead_time, 1) − 1)`` held by the register file's flip-flops (the iCE40: no decrement
#: and zero test in front of the three compares, −15 logic cells on the iCEBreaker, docs/AREA.md
#: §7.79); computed in :class:`~foc_servo.hdl.gates.Gates` from ``dead_time`` elsewhere (the
#: netlists of before). The same gate outputs either way.
GATES_DEAD_N = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(timer_sample_split=…)`` per FPGA family: the PWM timer's ADC strobe as two
#: equalities selected after them on the iCE40 (the timer −8 logic cells alone, docs/AREA.md
#: §7.79); one equality behind a multiplexer of the two positions elsewhere (the Arty S7: the
#: split form is +18 LUT6). The same strobes either way.
TIMER_SAMPLE_SPLIT = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(timer_one_adder=…)`` per FPGA family: the PWM timer's triangle counter on one adder on
#: the iCE40 (the timer −24 logic cells alone, docs/AREA.md §7.79) and the Spartan-7 (−3
#: LUT6); the ECP5 keeps the netlist of its session-16 builds (with the one adder and the
#: gates' wrapping counts the ULX3S made 100.57 / 102.17 / 96.78 MHz on seeds 1 / 2 / 3: seed
#: 3 missed, docs/AREA.md §7.80), the Spartan-6 the netlist of before. The same outputs.
TIMER_ONE_ADDER = {"ice40": True, "ecp5": False, "xc7": True, "xc6s": False}

#: ``Top(gates_wrap=…)`` per FPGA family: the gates' off counts without saturation on the iCE40
#: and the Spartan-7 (the Arty S7 6 597 against 6 618 LUT6 the other way, docs/AREA.md §7.80);
#: saturating on the ECP5 (its session-16 netlist, as :data:`TIMER_ONE_ADDER`) and the
#: Spartan-6. The same gate outputs.
GATES_WRAP = {"ice40": True, "ecp5": False, "xc7": True, "xc6s": False}

#: ``Top(adc_marker=…)`` per FPGA family: the ADC's read frame counted by a marker bit in its
#: first channel's shift register on the iCE40 (no bit counter: the top's ADC module 104 → 93
#: logic cells, docs/AREA.md §7.86); the other families keep their netlists. The same pins and
#: codes.
ADC_MARKER = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(gates_prev_pwm=…)`` per FPGA family: the gates' "wanted state unchanged" from the
#: previous clock's ``pwm`` levels and ``run`` on the iCE40 (4 flip-flops for 6, each of the
#: 6 alone in its logic cell: −2 cells alone, docs/AREA.md §7.86); the other families keep
#: their netlists. The same gate outputs.
GATES_PREV_PWM = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(dtc_one_count=…)`` per family: the dead-time compensation's sequence on one count on
#: the iCE40 (−5 cells alone) and the Spartan-7 (the Arty S7 6 597 against 6 616 LUT6); the
#: ECP5 keeps the netlist of its 100 MHz build (with it, seed 2 missed 100 MHz on a path in
#: the current loop's PI: placement, docs/AREA.md §7.79), the Spartan-6 the netlist of before
#: (not measured). The same corrections either way.
DTC_ONE_COUNT = {"ice40": True, "ecp5": False, "xc7": True, "xc6s": False}

#: ``Top(link_read_hold=…)`` per FPGA family: the host link's frame-buffer read address from
#: registered flags on the ECP5 (the state decode in front of its distributed-RAM read was a
#: 100 MHz critical path, docs/AREA.md §7.62); chosen from the state elsewhere (iCE40: +31
#: logic cells on the iCEBreaker the other way). The same replies and accesses either way.
LINK_READ_HOLD = {"ice40": False, "ecp5": True, "xc7": False, "xc6s": False}

#: ``Top(prot_limits=…)`` per FPGA family (where the board stages its registers in block RAM,
#: which the form needs): the protection's limits in a limit RAM mirrored from the register
#: file's staging RAM and one comparator stepping through the sampled causes on the iCE40
#: (no limit flip-flops, one carry chain for six: docs/AREA.md §7.77; a sampled cause reaches
#: the gates 1 … 7 clocks later, the pins as before); the limit ports and a comparator per
#: cause elsewhere (the netlists of before). ``"ram"`` takes 2 block RAMs (30 of the UP5K's
#: 30 with the rest of the top); ``"ram16"`` 1, for +39 logic cells (6 479 against 6 440).
PROT_LIMITS = {"ice40": "ram", "ecp5": "ports", "xc7": "ports", "xc6s": "ports"}
#: ``Top(enc_fold_reload=…)`` per FPGA family: the encoder's glitch-filter counters with the
#: reload select in their decrement's LUTs on the iCE40 (one LUT and carry per bit: −36 logic
#: cells for the encoder alone, docs/AREA.md §7.76); ``rem − 1`` and a select elsewhere (the
#: netlists of before; the other form costs the Spartan-7 ≈ 60 LUT6). The same outputs.
ENC_FOLD_RELOAD = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}
#: ``Top(enc_plausibility_complement=…)`` per FPGA family: the encoder/Hall check's differences
#: as ``~d = (boundary + offset) + ~θ`` and ``d_prev − d`` on the iCE40 (no operand select in
#: front of a carry: −12 logic cells for the encoder alone, docs/AREA.md §7.84); ``θ − …`` and
#: ``d − d_prev`` elsewhere (the netlists of before). The same outputs.
ENC_PLAUSIBILITY_COMPLEMENT = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(mt_chunk_multipliers=…)`` per FPGA family: M/T's product ``k·|ΔM|`` on one SB_MAC16
#: per 16-bit chunk of ``k`` on the iCE40 (no 3-way chunk select in front of one multiplier,
#: the carry's flip-flops with their LUTs: 7 of the UP5K's 8 SB_MAC16, −33 logic cells for
#: M/T alone, docs/AREA.md §7.76); one multiplier elsewhere (the netlists of before). The same
#: speeds either way.
MT_CHUNK_MULTIPLIERS = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``Top(mt_k_export=…)`` per FPGA family: ``mt_k`` from the register file's export port into
#: the SB_MAC16s' input registers on the iCE40 (its 48 flip-flops out of the register file,
#: docs/AREA.md §7.76; needs the block-RAM staging and one multiplier per chunk); the
#: register file's flip-flops elsewhere. The same speeds either way.
MT_K_EXPORT = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}
#: ``Top(mt_engine=…)`` per FPGA family (only with the engine's current loop and the block-RAM
#: staging): M/T speed's multiply and divide as the loop engine's run ``mt`` (M/T keeps its
#: window logic; its SB_MAC16s, 60-bit division register and result logic go; the TC span 27
#: bits, the result ≈ 75 clocks later; docs/AREA.md §7.64, §7.82): on the iCE40 (the
#: iCEBreaker: −200 logic cells, 3 SB_MAC16 fewer; the combined program 394 of the ROM's 512
#: words with the NOP folding, §7.81); M/T's own arithmetic elsewhere (the netlists of before).
MT_ENGINE = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}
#: ``Top(ram_loop_count=…)`` per FPGA family (only with ``regs_staging="bram"``):
#: ``st_current_loops`` counted in the register file's staging RAM on the iCE40 (−32 logic
#: cells on the iCEBreaker, docs/AREA.md §7.78); the loop's own counter elsewhere (the Arty S7
#: +23 LUT6 the other way). The same values either way.
RAM_LOOP_COUNT = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}
#: ``Top(link_compact=…)`` per FPGA family: the host link's iCE40 forms (its reply's zero test
#: on the selected byte, the COBS code byte counted in place, …: fewer logic cells on the
#: iCEBreaker, docs/AREA.md §7.75); elsewhere the form of before (the ECP5's 100 MHz paths run
#: through the link, §7.62). The same replies and accesses in the same clocks either way.
LINK_COMPACT = {"ice40": True, "ecp5": False, "xc7": False, "xc6s": False}

#: ``synth_ice40`` options of the iCE40 boards: ``-dsp`` (``SB_MAC16`` multipliers: without
#: them the multipliers swamp the UP5K's LUTs) and ``-dffe_min_ce_use 4``: a clock enable that
#: fewer than 4 flip-flops share becomes a multiplexer in the LUT in front of each instead of
#: an ``SB_DFFE`` pin, so a flip-flop loaded from another flip-flop, a block RAM or a port under
#: a rare enable shares its logic cell with that LUT instead of taking one alone (iCEBreaker:
#: −63 logic cells; 2: −49, 8: +10; docs/AREA.md "Session 12: the iCE40 flow"). A mapping
#: choice of yosys, the logic unchanged.
ICE40_SYNTH_OPTS = "-dsp -dffe_min_ce_use 4"


# --- PLL settings ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class PllConfig:
    """The PLL settings chosen for a board clock.

    Attributes
    ----------
    primitive : str
        The PLL primitive instantiated.
    f_in_hz, f_pfd_hz, f_vco_hz, f_out_hz : float
        Reference, phase-detector, VCO and output frequencies, Hz (``f_out_hz`` is the actual
        system clock passed to :class:`~foc_servo.hdl.top.Top`).
    f_req_hz : float
        The frequency asked for, Hz.
    divs : dict
        The primitive's divider parameters (names as in the primitive).
    """
    primitive: str
    f_in_hz: float
    f_req_hz: float
    f_pfd_hz: float
    f_vco_hz: float
    f_out_hz: float
    divs: dict

    def describe(self):
        divs = " ".join(f"{k} {v}" for k, v in self.divs.items())
        return (f"{self.f_in_hz / 1e6:g} MHz → {self.primitive} {divs} (PFD "
                f"{self.f_pfd_hz / 1e6:.4g} MHz, VCO {self.f_vco_hz / 1e6:.4g} MHz) → "
                f"{self.f_out_hz / 1e6:.6g} MHz")


# Per family: (primitive, input-divider range, multiplier range, output-divider values,
# PFD range Hz, VCO range Hz, preferred VCO Hz for ties, output range Hz).
_PLL_LIMITS = {
    # iCE40: f_out = f_in / (DIVR+1) · (DIVF+1) / 2^DIVQ, SIMPLE feedback.
    "ice40": ("SB_PLL40_PAD", range(0 + 1, 15 + 2), range(0 + 1, 127 + 2),
              [2 ** q for q in range(1, 7)], (10e6, 133e6), (533e6, 1066e6), 800e6,
              (16e6, 275e6)),
    # ECP5: f_out = f_in / CLKI_DIV · CLKFB_DIV (CLKOP feedback), VCO = f_out · CLKOP_DIV.
    "ecp5": ("EHXPLLL", range(1, 129), range(1, 129), list(range(1, 129)),
             (3.125e6, 400e6), (400e6, 800e6), 600e6, (3.125e6, 400e6)),
    # Spartan-7 -1 MMCM: VCO = f_in / DIVCLK_DIVIDE · CLKFBOUT_MULT_F, f_out = VCO / CLKOUT0.
    "xc7": ("MMCME2_BASE", range(1, 107), range(2, 65), list(range(1, 129)),
            (10e6, 450e6), (600e6, 1200e6), 1000e6, (4.69e6, 464e6)),
    # Spartan-6 -3 PLL: VCO = f_in / DIVCLK_DIVIDE · CLKFBOUT_MULT, f_out = VCO / CLKOUT0.
    "xc6s": ("PLL_BASE", range(1, 53), range(1, 65), list(range(1, 129)),
             (19e6, 500e6), (400e6, 1080e6), 600e6, (3.125e6, 400e6)),
}


def _is_hz(value):
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and math.isfinite(value))


def pll_config(family, f_in_hz, f_out_hz):
    """The PLL settings nearest to ``f_out_hz`` from a ``f_in_hz`` reference.

    Exhaustive search over the integer dividers within the family's PFD, VCO and output ranges;
    least frequency error first, then the VCO nearest the family's preferred one (600 MHz on the
    ECP5, as Project Trellis' ecppll), then the smallest input divider.

    Raises
    ------
    ValueError
        If ``family`` is unknown or no setting reaches ``f_out_hz`` within 2 %.
    """
    if family not in _PLL_LIMITS:
        raise ValueError(f"PLL family must be one of {', '.join(_PLL_LIMITS)}, not {family!r}")
    prim, in_divs, mults, out_divs, pfd_r, vco_r, vco_pref, out_r = _PLL_LIMITS[family]
    best = None
    for d in in_divs:
        pfd = f_in_hz / d
        if not pfd_r[0] <= pfd <= pfd_r[1]:
            continue
        for mul in mults:
            for o in out_divs:
                if family == "ecp5":
                    out = pfd * mul
                    vco = out * o
                else:
                    vco = pfd * mul
                    out = vco / o
                if not (vco_r[0] <= vco <= vco_r[1] and out_r[0] <= out <= out_r[1]):
                    continue
                key = (round(abs(out - f_out_hz), 3), abs(vco - vco_pref), d)
                if best is None or key < best[0]:
                    best = (key, d, mul, o, pfd, vco, out)
    if best is None or abs(best[6] - f_out_hz) > 0.02 * f_out_hz:
        raise ValueError(f"No {prim} setting gives {f_out_hz / 1e6:g} MHz from "
                         f"{f_in_hz / 1e6:g} MHz within 2 %")
    _, d, mul, o, pfd, vco, out = best
    if family == "ice40":
        divs = {"DIVR": d - 1, "DIVF": mul - 1, "DIVQ": o.bit_length() - 1}
    elif family == "ecp5":
        divs = {"CLKI_DIV": d, "CLKFB_DIV": mul, "CLKOP_DIV": o}
    else:
        divs = {"DIVCLK_DIVIDE": d, ("CLKFBOUT_MULT_F" if family == "xc7" else "CLKFBOUT_MULT"):
                mul, ("CLKOUT0_DIVIDE_F" if family == "xc7" else "CLKOUT0_DIVIDE"): o}
    return PllConfig(primitive=prim, f_in_hz=float(f_in_hz), f_req_hz=float(f_out_hz),
                     f_pfd_hz=pfd, f_vco_hz=vco, f_out_hz=out, divs=divs)


def _ice40_filter_range(f_pfd_hz):
    # TN1251 / icepll: loop-filter setting by PFD frequency band.
    for limit, value in ((17e6, 1), (26e6, 2), (44e6, 3), (66e6, 4), (101e6, 5)):
        if f_pfd_hz < limit:
            return value
    return 6


def _pll_instance(family, pll, clk_in, clk_out, locked):
    """The PLL primitive: ``clk_in`` (a pad for the iCE40) → ``clk_out``, ``locked``."""
    d = pll.divs
    if family == "ice40":
        return Instance(
            "SB_PLL40_PAD",
            p_FEEDBACK_PATH="SIMPLE", p_PLLOUT_SELECT="GENCLK",
            p_DIVR=d["DIVR"], p_DIVF=d["DIVF"], p_DIVQ=d["DIVQ"],
            p_FILTER_RANGE=_ice40_filter_range(pll.f_pfd_hz),
            i_PACKAGEPIN=clk_in, i_RESETB=Const(1), i_BYPASS=Const(0),
            o_PLLOUTGLOBAL=clk_out, o_LOCK=locked)
    if family == "ecp5":
        return Instance(
            "EHXPLLL",
            a_FREQUENCY_PIN_CLKI=f"{pll.f_in_hz / 1e6:g}",
            a_FREQUENCY_PIN_CLKOP=f"{pll.f_out_hz / 1e6:.6g}",
            a_ICP_CURRENT="12", a_LPF_RESISTOR="8", a_MFG_ENABLE_FILTEROPAMP="1",
            a_MFG_GMCREF_SEL="2",
            p_PLLRST_ENA="DISABLED", p_INTFB_WAKE="DISABLED", p_STDBY_ENABLE="DISABLED",
            p_DPHASE_SOURCE="DISABLED", p_OUTDIVIDER_MUXA="DIVA",
            p_CLKI_DIV=d["CLKI_DIV"], p_CLKFB_DIV=d["CLKFB_DIV"],
            p_CLKOP_ENABLE="ENABLED", p_CLKOP_DIV=d["CLKOP_DIV"],
            # ecppll: CPHASE = half an output period in VCO cycles (its 180° convention).
            p_CLKOP_CPHASE=d["CLKOP_DIV"] // 2, p_CLKOP_FPHASE=0,
            p_FEEDBK_PATH="CLKOP",
            i_CLKI=clk_in, i_CLKFB=clk_out, i_RST=Const(0), i_STDBY=Const(0),
            i_PHASESEL0=Const(0), i_PHASESEL1=Const(0), i_PHASEDIR=Const(1),
            i_PHASESTEP=Const(1), i_PHASELOADREG=Const(1), i_PLLWAKESYNC=Const(0),
            i_ENCLKOP=Const(0),
            o_CLKOP=clk_out, o_LOCK=locked)
    period_ns = 1e9 / pll.f_in_hz
    if family == "xc7":
        return Instance(
            "MMCME2_BASE",
            p_BANDWIDTH="OPTIMIZED", p_STARTUP_WAIT="FALSE",
            p_CLKIN1_PERIOD=round(period_ns, 3), p_REF_JITTER1=0.01,
            p_DIVCLK_DIVIDE=d["DIVCLK_DIVIDE"], p_CLKFBOUT_MULT_F=float(d["CLKFBOUT_MULT_F"]),
            p_CLKFBOUT_PHASE=0.0,
            p_CLKOUT0_DIVIDE_F=float(d["CLKOUT0_DIVIDE_F"]), p_CLKOUT0_PHASE=0.0,
            p_CLKOUT0_DUTY_CYCLE=0.5,
            i_CLKIN1=clk_in, i_CLKFBIN=clk_out["fb"], o_CLKFBOUT=clk_out["fb"],
            i_RST=Const(0), i_PWRDWN=Const(0),
            o_CLKOUT0=clk_out["out"], o_LOCKED=locked)
    return Instance(
        "PLL_BASE",
        p_BANDWIDTH="OPTIMIZED", p_CLK_FEEDBACK="CLKFBOUT", p_COMPENSATION="INTERNAL",
        p_CLKIN_PERIOD=round(period_ns, 3), p_REF_JITTER=0.01,
        p_DIVCLK_DIVIDE=d["DIVCLK_DIVIDE"], p_CLKFBOUT_MULT=d["CLKFBOUT_MULT"],
        p_CLKFBOUT_PHASE=0.0,
        p_CLKOUT0_DIVIDE=d["CLKOUT0_DIVIDE"], p_CLKOUT0_PHASE=0.0, p_CLKOUT0_DUTY_CYCLE=0.5,
        i_CLKIN=clk_in, i_CLKFBIN=clk_out["fb"], o_CLKFBOUT=clk_out["fb"], i_RST=Const(0),
        o_CLKOUT0=clk_out["out"], o_LOCKED=locked)


# --- the board top -------------------------------------------------------------------------------

class BoardTop(Elaboratable):
    """:class:`~foc_servo.hdl.top.Top` on a board: PLL, reset, pin buffers (module docstring).

    Parameters
    ----------
    board : str or Board
        A :data:`~.platforms.BOARDS` name.
    clk_hz : float or None
        System clock asked for, Hz, within :data:`CLOCK_RANGE_HZ`; ``None``: the board's
        :attr:`~.platforms.Board.clk_hz` (50 MHz; 33.333 MHz on the iCEBreaker). The PLL
        gives the nearest it can (:attr:`pll`); Top runs at that actual frequency, with the
        family's multiplier width (:data:`MUL_WIDTH`), the board's scope RAM
        (:attr:`~.platforms.Board.scope_ram`: one SPRAM on the UP5K) and register-file staging
        (:attr:`~.platforms.Board.regs_staging`: block RAM on the UP5K and the Arty S7).
    current_loop : str or None
        ``Top(current_loop=...)``, one of :data:`~foc_servo.hdl.top.CURRENT_LOOPS`:
        ``"pipelined"`` (:class:`~foc_servo.hdl.foc.CurrentLoop`) or ``"engine"``
        (:class:`~foc_servo.hdl.foc_engine.EngineCurrentLoop`); ``None`` (default): the board's
        :attr:`~.platforms.Board.current_loop` (``"engine"`` on the iCEBreaker, else
        ``"pipelined"``).

    Attributes
    ----------
    board : Board
    pll : PllConfig
    top : Top
    clk_hz : float
        The actual system clock, Hz.
    current_loop : str

    Raises
    ------
    TypeError
        ``clk_hz`` not a number, ``current_loop`` not a string (or ``board`` not a name).
    ValueError
        ``clk_hz`` out of range, ``current_loop`` not one of the values, or an unknown board.
    """

    def __init__(self, board, *, clk_hz=None, current_loop=None):
        self._board = get_board(board)
        current_loop = _current_loop(self._board, current_loop)
        if clk_hz is None:
            clk_hz = self._board.clk_hz
        if not _is_hz(clk_hz):
            raise TypeError(f"Build clk_hz must be a number of Hz or None, not {clk_hz!r}")
        lo, hi = CLOCK_RANGE_HZ
        if not lo <= clk_hz <= hi:
            raise ValueError(f"Build clk_hz must be from {lo / 1e6:g} MHz to {hi / 1e6:g} MHz, "
                             f"not {clk_hz!r} Hz")
        _, f_in = self._board.clock
        self._pll = pll_config(self._board.family, f_in, clk_hz)
        # The board's speed loop on the engine only where the engine runs the current loop
        # with its configuration RAM (Top's condition), else the SpeedLoop.
        speed_loop = (self._board.speed_loop
                      if (current_loop, self._board.regs_staging) == ("engine", "bram")
                      else "sequential")
        mt_engine = (MT_ENGINE[self._board.family]
                     and (current_loop, self._board.regs_staging) == ("engine", "bram"))
        self._top = Top(clk_hz=self._pll.f_out_hz, mul_width=MUL_WIDTH[self._board.family],
                        current_loop=current_loop, scope_ram=self._board.scope_ram,
                        regs_staging=self._board.regs_staging, speed_loop=speed_loop,
                        uv_arm_chain=UV_ARM_CHAIN[self._board.family],
                        trip_register=TRIP_REGISTER[self._board.family],
                        scope_down_counts=SCOPE_DOWN_COUNTS[self._board.family],
                        timer_clamp=TIMER_CLAMP[self._board.family],
                        prot_limits=(PROT_LIMITS[self._board.family]
                                     if self._board.regs_staging == "bram" else "ports"),
                        enc_fold_reload=ENC_FOLD_RELOAD[self._board.family],
                        enc_plausibility_complement=ENC_PLAUSIBILITY_COMPLEMENT[
                            self._board.family],
                        mt_chunk_multipliers=(MT_CHUNK_MULTIPLIERS[self._board.family]
                                              and not mt_engine),
                        mt_engine=mt_engine,
                        mt_k_export=MT_K_EXPORT[self._board.family],
                        ram_loop_count=RAM_LOOP_COUNT[self._board.family],
                        link_compact=LINK_COMPACT[self._board.family],
                        gates_dead_n=GATES_DEAD_N[self._board.family],
                        timer_sample_split=TIMER_SAMPLE_SPLIT[self._board.family],
                        timer_one_adder=TIMER_ONE_ADDER[self._board.family],
                        gates_wrap=GATES_WRAP[self._board.family],
                        adc_marker=ADC_MARKER[self._board.family],
                        gates_prev_pwm=GATES_PREV_PWM[self._board.family],
                        dtc_one_count=DTC_ONE_COUNT[self._board.family],
                        link_read_hold=LINK_READ_HOLD[self._board.family])

    board = property(lambda self: self._board)
    pll = property(lambda self: self._pll)
    top = property(lambda self: self._top)
    clk_hz = property(lambda self: self._pll.f_out_hz)
    current_loop = property(lambda self: self._top.current_loop)

    def elaborate(self, platform):
        m = Module()
        board, pll, family = self._board, self._pll, self._board.family
        clk_name, _ = board.clock

        # --- clock: oscillator → PLL → global buffer ----------------------------------------
        clk = Signal()
        locked = Signal()
        clk_port = platform.request(clk_name, dir="-")
        if family == "ice40":
            # SB_PLL40_PAD takes the pad itself (the iCEBreaker's 12 MHz input is a PLL pad).
            m.submodules.pll = _pll_instance(family, pll, clk_port.io, clk, locked)
        else:
            m.submodules.clk_buf = clk_buf = io.Buffer("i", clk_port)
            if family == "ecp5":
                m.submodules.pll = _pll_instance(family, pll, clk_buf.i, clk, locked)
            else:
                fb, raw = Signal(), Signal()
                m.submodules.pll = _pll_instance(family, pll, clk_buf.i,
                                                 {"fb": fb, "out": raw}, locked)
                m.submodules.bufg = Instance("BUFG", i_I=raw, o_O=clk)
        # No constraint on the PLL output: nextpnr, Vivado and ISE all derive it from the
        # oscillator's (which the platform writes) through the PLL's own settings, so the
        # Fmax report's constraint is the tools' reading of these dividers.
        m.domains.sync = ClockDomain("sync")
        m.d.comb += ClockSignal("sync").eq(clk)

        # --- reset: PLL unlocked or reset button, then POR_DELAY_S after lock ---------------
        m.domains.por = ClockDomain("por", reset_less=True, local=True)
        m.d.comb += ClockSignal("por").eq(clk)
        locked_s = Signal()
        m.submodules.lock_sync = FFSynchronizer(locked, locked_s, o_domain="por")
        delay = math.ceil(POR_DELAY_S * pll.f_out_hz)
        timer = Signal(range(delay + 1))
        ready = Signal()
        with m.If(~locked_s):
            m.d.por += [timer.eq(0), ready.eq(0)]
        with m.Elif(timer == delay):
            m.d.por += ready.eq(1)
        with m.Else():
            m.d.por += timer.eq(timer + 1)
        arst = ~ready
        if board.reset is not None:
            m.submodules.rst_buf = rst_buf = io.Buffer("i", platform.request(board.reset,
                                                                             dir="-"))
            arst = arst | rst_buf.i
        m.submodules.reset_sync = ResetSynchronizer(arst, domain="sync")

        # --- the controller and its pins ----------------------------------------------------
        m.submodules.top = top = self._top
        motor = platform.request("motor", 0, dir="-")
        for name, (_, direction) in MOTOR_PORTS.items():
            m.submodules[f"{name}_buf"] = buf = io.Buffer(direction, getattr(motor, name))
            if direction == "o":
                m.d.comb += buf.o.eq(getattr(top, name))
            else:
                m.d.comb += getattr(top, name).eq(buf.i)
        uart = platform.request("uart", 0, dir="-")
        m.submodules.uart_rx_buf = rx = io.Buffer("i", uart.rx)
        m.submodules.uart_tx_buf = tx = io.Buffer("o", uart.tx)
        m.d.comb += [top.uart_rx.eq(rx.i), tx.o.eq(top.uart_tx)]
        for bit in range(len(top.led)):
            m.submodules[f"led{bit}_buf"] = led = io.Buffer("o", platform.request("led", bit,
                                                                                 dir="-"))
            m.d.comb += led.o.eq(top.led[bit])
        return m


# --- flows ----------------------------------------------------------------------------------------

class _Stages:
    """Progress on stderr: one line per stage with its wall time; while a tool runs, an
    elapsed-time line updated in place on a terminal (every 30 s otherwise)."""

    def __init__(self, board, enabled, stream=None):
        self.board, self.enabled = board, enabled
        self.stream = stream or sys.stderr
        self.times = {}

    def _write(self, text):
        if self.enabled:
            self.stream.write(text)
            self.stream.flush()

    def run(self, label, func):
        start = time.perf_counter()
        tty = self.enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self._write(f"[{self.board}] {label} …" + ("" if tty else "\n"))
        done = threading.Event()
        if not self.enabled:
            done.set()

        def tick():
            while not done.wait(1.0 if tty else 30.0):
                elapsed = time.perf_counter() - start
                self._write(f"\r[{self.board}] {label} … {elapsed:4.0f} s" if tty else
                            f"[{self.board}] {label} … {elapsed:.0f} s\n")
        ticker = threading.Thread(target=tick, daemon=True)
        ticker.start()
        try:
            return func()
        finally:
            done.set()
            ticker.join()
            elapsed = time.perf_counter() - start
            self.times[label] = round(elapsed, 1)
            self._write(f"\r[{self.board}] {label}: {elapsed:.1f} s\n" if tty else
                        f"[{self.board}] {label}: {elapsed:.1f} s\n")


def _overrides(board, name, seed=None):
    stat = f"tee -q -o {name}.stat.json stat -json"
    # --timing-allow-fail: a design that places and routes but misses its clock still gets a
    # bitstream and its Fmax (reported as timing_met false) instead of a bare failure.
    pnr = f"--report {name}.report.json --timing-allow-fail"
    if seed is not None:
        pnr += f" --seed {seed}"
    # The gateware's Assert / Print cells out before synthesis (STRIP_CHECKS; as the vendor
    # flows' synthesis_verilog does).
    if board.family == "ice40":
        return {"script_after_read": STRIP_CHECKS, "synth_opts": ICE40_SYNTH_OPTS,
                "script_after_synth": stat, "nextpnr_opts": pnr}
    if board.family == "ecp5":
        return {"script_after_read": STRIP_CHECKS, "script_after_synth": stat,
                "nextpnr_opts": pnr}
    return {}


def synthesis_verilog(rtlil_text, *, name=NAME, xilinx_roms=False):
    """Verilog-2001 of an RTLIL design for vendor synthesis (Vivado, ISE).

    Amaranth's ``emit_verilog`` steps (``proc -nomux -norom``, ``memory_collect``, internal
    attributes stripped, ``write_verilog -norename``) with the simulation-only cells removed
    first (``chformal -remove; delete t:$print``). The gateware's ``Assert``/``Print``
    statements (dead-time and PI invariants, checked in every simulation) otherwise come out as
    SystemVerilog ``assert`` and ``$write`` in a ``.v`` file, which Verilog-2001 readers reject
    (yosys' own ``read_verilog``: "Can't resolve task name `\\assert'"). Amaranth's bundled
    yosys has no ``chformal``: this runs the full one (``$YOSYS`` or YoWASP).

    With ``xilinx_roms`` (the vendor flows) the read-only memories worth a block RAM carry
    ``(* rom_style = "block" *)`` (:func:`~.area.mark_xilinx_roms`): Vivado / XST and the yosys
    estimate made on this Verilog then build them alike.

    Raises
    ------
    RuntimeError
        If yosys fails (the message carries its output).
    """
    attrs = ("-remove generator -remove top -remove src -remove amaranth.hierarchy "
             "-remove amaranth.decoding")
    if xilinx_roms:
        rtlil_text = area.mark_xilinx_roms(rtlil_text)
    script = (f"read_rtlil {name}.il; proc -nomux -norom; memory_collect; {STRIP_CHECKS}; "
              f"attrmap {attrs}; attrmap -modattr {attrs}; "
              f"write_verilog -norename {name}.v")
    with tempfile.TemporaryDirectory(prefix="foc-servo-verilog-") as tmp:
        work = Path(tmp)                        # YoWASP tools see only their working directory
        (work / f"{name}.il").write_text(rtlil_text)
        proc = subprocess.run(_tool("yosys") + ["-q", "-p", script], cwd=work,
                              capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"yosys could not write the Verilog of {name}:\n"
                               f"{(proc.stderr or proc.stdout)[-2000:]}")
        return (work / f"{name}.v").read_text()


def _current_loop(board, current_loop):
    """``current_loop`` checked, or the board's default for ``None``."""
    if current_loop is None:
        return board.current_loop
    check_choice("Build", "current_loop", current_loop, CURRENT_LOOPS)
    return current_loop


def prepare(board, *, out_dir="build", clk_hz=None, current_loop=None, seed=None):
    """Write ``board``'s build plan (sources, constraints, scripts) to ``out_dir/NAME``.

    Nothing is run: for a vendor board this is the Vivado / ISE tree, also archived as
    ``out_dir/NAME/foc_servo.zip``. ``clk_hz`` and ``current_loop`` as in :class:`BoardTop`
    (checked before anything is written); ``seed`` as in :func:`build`.

    Returns
    -------
    dict
        ``board`` (Board), ``top`` (BoardTop), ``dir`` (Path), ``files`` (names written),
        ``zip`` (Path or None), ``commands`` (argv lists of the build script).
    """
    _check_seed(seed)
    top = BoardTop(board, clk_hz=clk_hz, current_loop=current_loop)
    board = top.board
    root = Path(out_dir) / board.name
    root.mkdir(parents=True, exist_ok=True)
    if board.flow == "vendor":
        # Amaranth's own .v is replaced (below): skip its conversion, keep the RTLIL.
        platform = board.platform(file_templates={"{{name}}.il": "{{emit_rtlil()}}",
                                                  "{{name}}.v": "/* replaced */"})
        plan = platform.prepare(top, name=NAME)
        plan.files[f"{NAME}.v"] = synthesis_verilog(plan.files.pop(f"{NAME}.il"),
                                                    xilinx_roms=True)
    else:
        plan = board.platform().prepare(top, name=NAME, **_overrides(board, NAME, seed))
        if board.family == "ice40":
            # The RAM read registers' power-up value, emulated in logic, dropped (AREA.md
            # "Session 12: the iCE40 flow"; :func:`~.area.ram_read_init_free`).
            plan.files[f"{NAME}.il"] = area.ram_read_init_free(plan.files[f"{NAME}.il"])
    plan.extract(root)
    zip_path = None
    if board.flow == "vendor":
        zip_path = root / f"{NAME}.zip"
        plan.archive(zip_path)
    commands = json.loads((root / f"build_{NAME}.json").read_text())["commands"]
    return {"board": board, "top": top, "dir": root, "files": sorted(plan.files),
            "zip": zip_path, "commands": commands}


def _tool(name):
    """The command line that runs tool ``name``: ``$NAME`` (as Amaranth's scripts read it),
    else the YoWASP build, else ``name`` on the PATH."""
    var = name.upper().replace("-", "_").replace("+", "X")
    if os.environ.get(var):
        return shlex.split(os.environ[var])
    if name == "yosys":
        return area._yosys_command()
    for candidate in (f"yowasp-{name}", name):
        found = shutil.which(candidate)
        sibling = Path(sys.executable).parent / candidate
        if found or sibling.exists():
            return [found or str(sibling)]
    raise FileNotFoundError(f"{name} not found: install yowasp-{name} (pip install "
                            f"\"foc-servo[tools]\") or set ${var}")


def _run(argv, cwd, log_path):
    """Run one build command in ``cwd`` (YoWASP tools see only it), output to ``log_path``."""
    with open(log_path, "w") as log:
        return subprocess.run(_tool(argv[0]) + list(argv[1:]), cwd=cwd, stdout=log,
                              stderr=subprocess.STDOUT).returncode


def _error_lines(*paths):
    lines = []
    for path in paths:
        if path.exists():
            lines += [ln.strip() for ln in path.read_text(errors="replace").splitlines()
                      if ln.lstrip().startswith("ERROR")]
    return list(dict.fromkeys(lines))          # unique, in order


def _figures(family, cells):
    """Utilisation from yosys ``num_cells_by_type``: lut, ff, dsp, bram_bits and the detail."""
    def total(*prefixes):
        return sum(n for cell, n in cells.items() if cell.startswith(prefixes))
    if family == "ice40":
        s = area.summarise("ice40", cells)
        return {"lut": s["lut4"], "lut_kind": "LUT4", "ff": s["ff"], "dsp": s["dsp"],
                "bram_bits": 4096 * s["bram"], "carry": s["carry"], "bram_blocks": s["bram"],
                "spram_blocks": total("SB_SPRAM256KA")}
    if family == "ecp5":
        ebr = total("DP16KD", "PDPW16KD")
        # A CCU2C (2-bit adder slice) holds two LUT4s: count them as nextpnr's TRELLIS_COMB.
        return {"lut": total("LUT4") + 2 * total("CCU2C"), "lut_kind": "LUT4",
                "ff": total("TRELLIS_FF"), "dsp": total("MULT18X18D"),
                "bram_bits": 18_432 * ebr, "carry": total("CCU2C"), "bram_blocks": ebr,
                "alu54": total("ALU54B"), "lutram_bits": 64 * total("TRELLIS_DPR16X4")}
    # Xilinx: ``lut`` as Vivado's / ISE's "Slice LUTs", logic and memory (area.xilinx_luts).
    if family == "xc7":
        s = area.summarise("xc7", cells)
        return {"lut": s["lut"], "lut_kind": "LUT6", "ff": s["ff"], "dsp": s["dsp"],
                "bram_bits": 18_432 * s["bram"], "carry": s["carry4"], "bram_blocks": s["bram"],
                "lut_logic": s["lut_logic"], "lut_memory": s["lut_memory"], "srl": s["srl"],
                "muxf": s["muxf"], "inv": total("INV"),
                "lutram_cells": total("RAM") - total("RAMB")}
    # Spartan-6
    bram = total("RAMB16BWER") + total("RAMB8BWER") / 2
    luts = area.xilinx_luts(cells)
    return {"lut": luts["lut"], "lut_kind": "LUT6", "ff": total("FD"), "dsp": total("DSP48A1"),
            "bram_bits": int(18_432 * bram), "carry": total("CARRY4"), "bram_blocks": bram,
            "lut_logic": luts["lut_logic"], "lut_memory": luts["lut_memory"],
            "srl": total("SRL"), "muxf": total("MUXF"), "inv": total("INV"),
            "lutram_cells": total("RAM") - total("RAMB")}


def _estimate(board, root, stages):
    """yosys ``synth_xilinx`` on the vendor tree's Verilog (PLL and I/O primitives included)."""
    family = "xc7" if board.family == "xc7" else "xc6s"
    script = (f"read_verilog {NAME}.v; synth_xilinx -family {family} -flatten -noiopad "
              f"-noclkbuf -top {NAME}; tee -q -o estimate/{NAME}.stat.json stat -json")
    (root / "estimate").mkdir(exist_ok=True)
    log = root / "estimate" / f"{NAME}.yosys.log"
    code = stages.run(f"yosys synth_xilinx -family {family} (estimate)", lambda: subprocess.run(
        _tool("yosys") + ["-q", "-l", f"estimate/{NAME}.yosys.log", "-p", script],
        cwd=root, capture_output=True, text=True).returncode)
    stat = root / "estimate" / f"{NAME}.stat.json"
    if code != 0 or not stat.exists():
        return None, _error_lines(log) or [f"yosys exited with {code}"], [log]
    cells = json.loads(stat.read_text())["design"]["num_cells_by_type"]
    return _figures(board.family, cells), [], [log, stat]


def _nextpnr_report(root):
    """Fmax and utilisation from nextpnr's ``--report`` JSON (None if it was not written)."""
    path = root / f"{NAME}.report.json"
    if not path.exists():
        return None
    rep = json.loads(path.read_text())
    fmax = {clk: v for clk, v in rep.get("fmax", {}).items()}
    critical = None
    for cp in rep.get("critical_paths", [])[:1]:
        steps = cp.get("path", [])
        cells = [s["from"]["cell"] for s in steps] + [s["to"]["cell"] for s in steps[-1:]]
        critical = {"from": cells[0] if cells else None, "to": cells[-1] if cells else None,
                    "logic_levels": sum(1 for s in steps if s.get("type") == "logic"),
                    "delay_ns": round(sum(s.get("delay", 0.0) for s in steps), 3)}
    return {"fmax": fmax, "utilization": rep.get("utilization", {}), "critical_path": critical}


def _nextpnr_log_utilisation(root):
    """Device utilisation lines of the nextpnr log (``CELL: used/ available``), if any."""
    path = root / f"{NAME}.tim"
    util = {}
    if path.exists():
        for m in re.finditer(r"Info:\s+(\w+):\s+(\d+)/\s*(\d+)\s+\d+%", path.read_text()):
            util[m.group(1)] = {"used": int(m.group(2)), "available": int(m.group(3))}
    return util


def _run_bitstream(board, prep, stages):
    root = prep["dir"]
    result = {"fits": None, "fmax_mhz": None, "error": None, "fmax": {}, "pnr_utilisation": {}}
    logs = []
    for argv in prep["commands"]:
        tool = argv[0]
        log = root / f"{NAME}.{tool}.out"
        logs.append(log)
        code = stages.run(tool, lambda argv=argv, log=log: _run(argv, root, log))
        if tool == "yosys" and (root / f"{NAME}.stat.json").exists():
            cells = json.loads((root / f"{NAME}.stat.json").read_text())["design"]
            result.update(_figures(board.family, cells["num_cells_by_type"]))
            netlist = root / f"{NAME}.json"
            if board.family == "ice40" and netlist.exists():
                result["logic_cells"] = ice40_cells.logic_cells(json.loads(netlist.read_text()))
        if code != 0:
            errors = _error_lines(root / f"{NAME}.tim", root / f"{NAME}.rpt", log)
            result["error"] = f"{tool} failed (exit {code}): " + (
                " | ".join(errors) if errors else log.read_text()[-500:])
            if tool.startswith("nextpnr"):
                result["fits"] = False
                util = result["pnr_utilisation"] = _nextpnr_log_utilisation(root)
                rep = _nextpnr_report(root)
                if rep and rep["fmax"]:         # routed, then failed (e.g. a timing check)
                    result["fmax"] = rep["fmax"]
                    result["fmax_mhz"] = round(min(v["achieved"] for v in rep["fmax"].values()),
                                               2)
                    result["timing_met"] = all(v["achieved"] >= v["constraint"]
                                               for v in rep["fmax"].values())
                over = [f"needs {v['used']} of {v['available']} {k}" for k, v in util.items()
                        if v["used"] > v["available"]]
                if over:
                    result["error"] = f"does not fit the {board.title}: " + ", ".join(over) \
                        + "; " + result["error"]
            break
        if tool.startswith("nextpnr"):
            rep = _nextpnr_report(root)
            if rep:
                result["pnr_utilisation"] = rep["utilization"]
                result["fmax"] = rep["fmax"]
                result["critical_path"] = rep["critical_path"]
                achieved = [v["achieved"] for v in rep["fmax"].values()]
                result["fmax_mhz"] = round(min(achieved), 2) if achieved else None
                result["timing_met"] = all(v["achieved"] >= v["constraint"]
                                           for v in rep["fmax"].values())
            result["fits"] = True
    return result, logs


def _check_seed(seed):
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
        raise TypeError(f"Build seed must be None or a non-negative integer, not {seed!r}")


def build(board, *, out_dir="build", clk_hz=None, current_loop=None, seed=None, progress=False,
          json=False):
    """Build the controller for ``board`` and print its utilisation beside paper Table 1.

    Parameters
    ----------
    board : str
        A :data:`~.platforms.BOARDS` name: ``icebreaker``, ``ulx3s`` (bitstream here),
        ``arty_s7``, ``atlys`` (Vivado / ISE tree + yosys estimate).
    out_dir : str or Path
        Everything goes to ``out_dir/board``.
    clk_hz : float or None
        System clock asked for, Hz (``None``: the board's, 50 MHz; 33.333 MHz on the
        iCEBreaker); the PLL's nearest is used and reported.
    current_loop : str or None
        The current-loop gateware, ``"pipelined"`` or ``"engine"``; ``None`` (default): the
        board's choice (``"engine"`` on the iCEBreaker; :class:`BoardTop`).
    seed : int or None
        nextpnr's placement seed (``--seed``; ``None``: nextpnr's default, 1). The whole top's
        Fmax moves by ±4 MHz from seed to seed on the ECP5. Ignored by the vendor flows.
    progress : bool
        Stage lines on stderr while the tools run.
    json : bool
        Print the result as one JSON object on the last line of stdout (after the human
        lines), as every ``foc-servo`` figure-reporting command does.

    Returns
    -------
    dict
        JSON-ready: ``board``, ``title``, ``flow``, ``lut`` (and ``lut_kind``), ``ff``,
        ``bram_bits``, ``dsp``, ``fmax_mhz`` (``None`` without place-and-route or when it
        failed; the slowest clock, MHz), ``timing_met`` (that Fmax against the clock, or
        ``None``), ``clock_mhz`` (actual), ``clock_requested_mhz``, ``current_loop`` (the
        ``Top(current_loop=...)`` built), ``seed`` (nextpnr's, as given), ``scope_ram`` (its
        trace-buffer RAM), ``regs_staging`` (its register-file staging), ``pll`` (text), ``paper``
        (Table 1), ``fits`` (bool, or ``None`` when not known), ``error`` (the failing tool's
        ``ERROR`` lines or ``None``), ``wall_s``, ``stages`` (wall time per stage, s),
        ``artifacts`` (name → path), ``utilisation`` (all figures, including the
        place-and-route tool's own ``used``/``available`` table where it ran).

    Raises
    ------
    TypeError, ValueError
        A bad board name, ``clk_hz`` or ``current_loop`` (before anything is written).
    """
    start = time.perf_counter()
    board = get_board(board)
    current_loop = _current_loop(board, current_loop)
    stages = _Stages(board.name, progress)
    prep = stages.run("elaborate + write build plan",
                      lambda: prepare(board, out_dir=out_dir, clk_hz=clk_hz,
                                      current_loop=current_loop, seed=seed))
    root, top = prep["dir"], prep["top"]
    artifacts = {"dir": root}
    if board.flow == "vendor":
        figures, errors, logs = _estimate(board, root, stages)
        artifacts.update(zip=prep["zip"], script=root / f"build_{NAME}.sh",
                         estimate_log=logs[0])
        res = {"fmax_mhz": None, "fmax": {}, "pnr_utilisation": {},
               "error": " | ".join(errors) if errors else None, **(figures or {})}
        if figures:
            res["fits"] = all(figures[k] <= board.capacity[k] for k in board.capacity)
        else:
            res["fits"] = None
    else:
        res, logs = _run_bitstream(board, prep, stages)
        bit = root / (f"{NAME}.bin" if board.family == "ice40" else f"{NAME}.bit")
        artifacts.update(bitstream=bit if bit.exists() else None,
                         yosys_log=root / f"{NAME}.rpt", nextpnr_log=root / f"{NAME}.tim")
        rep = root / f"{NAME}.report.json"
        if rep.exists():
            artifacts["nextpnr_report"] = rep
    util_keys = [k for k in res if k not in ("fits", "fmax_mhz", "error", "fmax", "timing_met")]
    result = {
        "board": board.name, "title": board.title, "flow": board.flow,
        "lut": res.get("lut"), "lut_kind": res.get("lut_kind"), "ff": res.get("ff"),
        "bram_bits": res.get("bram_bits"), "dsp": res.get("dsp"),
        "fmax_mhz": res["fmax_mhz"], "fmax": res["fmax"], "timing_met": res.get("timing_met"),
        "clock_mhz": round(top.clk_hz / 1e6, 6),
        "clock_requested_mhz": round(top.pll.f_req_hz / 1e6, 6), "seed": seed,
        "current_loop": top.current_loop, "speed_loop": top.top.speed_loop,
        "scope_ram": top.top.scope_ram, "regs_staging": top.top.regs_staging,
        "pll": top.pll.describe(), "pll_divs": top.pll.divs,
        "paper": dict(PAPER), "fits": res["fits"], "error": res["error"],
        "utilisation": {k: res[k] for k in util_keys},
        "wall_s": round(time.perf_counter() - start, 1), "stages": stages.times,
        "artifacts": {k: (str(v) if v is not None else None) for k, v in artifacts.items()},
    }
    (root / "report.json").write_text(_json_dumps(result, indent=1, sort_keys=True))
    from ..host.cli import emit        # the CLI's one printing rule (lazy: cli imports boards)
    emit(result, report_lines(result), json)
    return result


def report_lines(result):
    """Human-readable summary of a :func:`build` result, beside paper Table 1."""
    p = result["paper"]

    def fmt(value, unit=""):
        return "—" if value is None else f"{value:,}{unit}".replace(",", " ")
    kbit = None if result["bram_bits"] is None else round(result["bram_bits"] / 1024, 1)
    if result["fmax_mhz"] is not None:
        met = "met" if result["timing_met"] else "NOT met"
        fmax = (f"{result['fmax_mhz']:.1f} MHz (nextpnr; the {result['clock_mhz']:g} MHz clock: "
                f"{met})")
    elif result["flow"] == "vendor":
        fmax = "— (no place-and-route here: run the Vivado/ISE tree)"
    else:
        fmax = "— (place-and-route did not finish)"
    source = "yosys estimate" if result["flow"] == "vendor" else "yosys"
    lines = [
        f"{result['board']}: {result['title']}",
        f"  clock     {result['pll']} (asked {result['clock_requested_mhz']:g} MHz)",
        f"  gateware  Top(current_loop={result.get('current_loop', 'pipelined')!r}, "
        f"scope_ram={result.get('scope_ram', 'bram')!r}, "
        f"regs_staging={result.get('regs_staging', 'ff')!r}, "
        f"speed_loop={result.get('speed_loop', 'sequential')!r})",
        f"  {'':<10}{'this build (' + source + ')':>28}   {'paper Table 1':>14}",
        f"  {result['lut_kind'] or 'LUT':<10}{fmt(result['lut']):>28}   {fmt(p['lut4']):>14}",
        f"  {'FF':<10}{fmt(result['ff']):>28}   {fmt(p['ff']):>14}",
        f"  {'RAM':<10}{fmt(kbit, ' Kbit'):>28}   {fmt(p['bram_bits'] // 1024, ' Kbit'):>14}",
        f"  {'DSP':<10}{fmt(result['dsp']):>28}   {'—':>14}",
        f"  {'clock':<10}{result['clock_mhz']:>24.6g} MHz   {p['clock_mhz']:>10g} MHz",
        f"  Fmax      {fmax}",
    ]
    u = result["utilisation"]
    if u.get("lut_memory") is not None:         # Xilinx: what the LUT figure holds
        lines.insert(5, f"  {'':<10}= {fmt(u['lut_logic'])} logic + {fmt(u['lut_memory'])} "
                        f"distributed RAM / SRL (+ {fmt(u.get('inv'))} INV, ≤ 1 LUT each)")
    cp = result["utilisation"].get("critical_path")
    if cp:
        lines.append(f"  critical  {cp['delay_ns']:.2f} ns, {cp['logic_levels']} logic levels: "
                     f"{cp['from']} → {cp['to']}")
    util = result["utilisation"].get("pnr_utilisation") or {}
    busy = {k: v for k, v in util.items() if v.get("used")}
    if busy:
        lines.append("  place-and-route: " + ", ".join(
            f"{k} {v['used']}/{v['available']}" for k, v in sorted(busy.items())))
    lc = result["utilisation"].get("logic_cells")
    if lc:
        lines.append(f"  logic cells, estimated from the netlist by nextpnr's packing rules: "
                     f"{lc['total']['cells']:,}".replace(",", " "))
        lines += ice40_cells.report_lines(lc, limit=8)
    fits = {True: "yes", False: "NO", None: "unknown"}[result["fits"]]
    lines.append(f"  fits      {fits}" + (f" — {result['error']}" if result["error"] else ""))
    lines.append(f"  wall time {result['wall_s']:.1f} s ("
                 + ", ".join(f"{k} {v:.1f} s" for k, v in result["stages"].items()) + ")")
    for key, path in result["artifacts"].items():
        if path:
            lines.append(f"  {key:<15}{path}")
    return lines
