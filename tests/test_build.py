# Ref: issue 7 items 1–2 (boards, pin maps, build flows); Digilent Pmod Interface Specification
# 1.2.0 (pins 5/11 GND, 6/12 VCC); Lattice TN1251 / icepll and Project Trellis ecppll (PLL).
"""Boards and build flows.

Quick (default run): the pin maps are complete, on real connector pins, free of clashes and as
documented in docs/BOARDS.md; the PLL settings agree with the vendors' own calculators (icepll,
ecppll, run here from YoWASP); parameter errors; the Vivado and ISE trees are complete (every
top-level port constrained to the documented pin, the sources the scripts name present,
Verilog-2001 without simulation-only statements, the zip identical to the tree).

Slow (``-m slow``): the real builds — iCEBreaker and ULX3S bitstreams with YoWASP, the yosys
``synth_xilinx`` estimates of the vendor trees — cross-checked between yosys and nextpnr.
"""

import difflib
import gc
import json
import os
import re
import subprocess
import warnings
import zipfile
from pathlib import Path

import pytest
from amaranth.back import rtlil, verilog
from amaranth.hdl import Assert, Module, Print, Shape, Signal, UnusedElaboratable
from amaranth.lib import wiring

from foc_servo.boards.build import (ADC_MARKER, CLOCK_RANGE_HZ, DTC_ONE_COUNT, ENC_FOLD_RELOAD,
                                    ENC_PLAUSIBILITY_COMPLEMENT, GATES_DEAD_N, GATES_PREV_PWM,
                                    GATES_WRAP, LINK_COMPACT, LINK_READ_HOLD, MT_CHUNK_MULTIPLIERS,
                                    MT_ENGINE, MT_K_EXPORT, MUL_WIDTH, NAME, PROT_LIMITS,
                                    RAM_LOOP_COUNT, SCOPE_DOWN_COUNTS, TIMER_CLAMP, TIMER_ONE_ADDER,
                                    TIMER_SAMPLE_SPLIT, TRIP_REGISTER, BoardTop, build, pll_config,
                                    prepare, synthesis_verilog, _tool)
from foc_servo.boards.platforms import BOARDS, MOTOR_PORTS, get_board, pin_map
from foc_servo.hdl.top import Top

DOCS = Path(__file__).resolve().parent.parent / "docs" / "BOARDS.md"


def _inspect(factory, facts):
    """``facts(factory())`` for an object only inspected, never elaborated: its unused
    sub-blocks are collected here, their UnusedElaboratable warnings silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        result = facts(factory())
        gc.collect()
    return result


# --- pin maps -------------------------------------------------------------------------------------

def _resource_pins(platform, name, number):
    """FPGA pins of a board resource (all subsignals), resolved through its connectors."""
    conns = {f"{c[0]}_{c[1]}": platform.connectors[c] for c in platform.connectors}
    pins = []

    def walk(node):
        for sub in node.ios:
            if hasattr(sub, "ios"):
                walk(sub)
            else:
                for pin in sub.names:
                    conn, _, conn_pin = pin.rpartition(":")
                    pins.append(conns[conn].mapping[conn_pin] if conn else pin)
    walk(platform.lookup(name, number))
    return pins


def test_top_pins_all_mapped():
    # Every Top pin is a motor pin, the UART or the LEDs: a new Top pin fails here until a
    # board maps it.
    members = _inspect(Top, lambda top: dict(top.signature.members))
    assert set(members) == set(MOTOR_PORTS) | {"uart_rx", "uart_tx", "led"}
    for name, (width, direction) in MOTOR_PORTS.items():
        member = members[name]
        assert Shape.cast(member.shape).width == width, name
        assert member.flow == (wiring.In if direction == "i" else wiring.Out), name


@pytest.mark.parametrize("name", list(BOARDS))
def test_pin_map_complete_on_connectors(name):
    board = get_board(name)
    platform = board.platform()
    rows = pin_map(board)
    # every bit of every motor pin exactly once, in its direction
    for port, (width, direction) in MOTOR_PORTS.items():
        bits = [r for r in rows if r["port"] == port]
        assert sorted(r["bit"] for r in bits) == list(range(width)), port
        assert all(r["dir"] == direction for r in bits), port
    assert len(rows) == sum(w for w, _ in MOTOR_PORTS.values()) == 20
    # on a real connector pin of the board, mapped to an FPGA pin
    for r in rows:
        conn = platform.connectors[r["conn"]]
        assert r["conn_pin"] in conn.mapping, r
        assert r["fpga_pin"] == conn.mapping[r["conn_pin"]] not in ("", "-"), r
        if r["conn"][0] == "pmod":
            # Pmod: I/O on pins 1–4 and 7–10; 5/11 are GND and 6/12 VCC
            assert int(r["conn_pin"]) in (1, 2, 3, 4, 7, 8, 9, 10), r
    # no FPGA pin twice, none shared with the clock, reset, UART or the status LEDs
    fpga = [r["fpga_pin"] for r in rows]
    assert len(set(fpga)) == len(fpga)
    others = _resource_pins(platform, board.clock[0], 0)
    others += _resource_pins(platform, "uart", 0)
    others += _resource_pins(platform, "led", 0) + _resource_pins(platform, "led", 1)
    if board.reset:
        others += _resource_pins(platform, board.reset, 0)
    assert not set(fpga) & set(others)
    # fail-safe pulls where the family has them (iCE40: pull-ups only)
    attrs = {r["port"]: r["attrs"] for r in rows}
    pulls = {"ice40": ({"PULLUP": 1}, None), "ecp5": ({"PULLMODE": "UP"}, {"PULLMODE": "DOWN"}),
             "xc7": ({"PULLUP": "TRUE"}, {"PULLDOWN": "TRUE"}),
             "xc6s": ({"PULLUP": "TRUE"}, {"PULLDOWN": "TRUE"})}[board.family]
    for port in ("oc_comp", "enc_a", "enc_b", "enc_z", "hall"):
        assert pulls[0].items() <= attrs[port].items(), port
    if pulls[1]:
        assert pulls[1].items() <= attrs["fault_n"].items()
    assert all(v in ("LVCMOS33", "SB_LVCMOS") for r in rows for k, v in r["attrs"].items()
               if k in ("IOSTANDARD", "IO_TYPE", "IO_STANDARD"))


def _doc_tables():
    """docs/BOARDS.md pin tables: board title → {signal: (connector pin, FPGA pin)}."""
    tables, title = {}, None
    for line in DOCS.read_text().splitlines():
        if line.startswith("### "):
            title = line[4:].strip()
        m = re.match(r"\| `([\w\[\]]+)` \| (in|out) \| ([\w+-]+) \| (\w+) \|", line)
        if m and title:
            tables.setdefault(title, {})[m.group(1)] = (m.group(3), m.group(4))
    return tables


@pytest.mark.parametrize("name", list(BOARDS))
def test_docs_pin_tables_match(name):
    board = get_board(name)
    documented = _doc_tables()[board.title]
    actual = {r["signal"]: (f"{r['connector'].upper()}-{r['conn_pin']}", r["fpga_pin"])
              for r in pin_map(board)}
    assert documented == actual


# --- PLL ------------------------------------------------------------------------------------------

def _yowasp(tool, *args, cwd=None):
    return subprocess.run(_tool(tool) + list(args), capture_output=True, text=True, cwd=cwd,
                          check=True).stdout


@pytest.mark.parametrize("f_mhz", [50, 33.333, 100])
def test_ice40_pll_matches_icepll(f_mhz):
    cfg = pll_config("ice40", 12e6, f_mhz * 1e6)
    out = _yowasp("icepll", "-i", "12", "-o", str(f_mhz))
    ref = {k: int(v) for k, v in re.findall(r"(DIVR|DIVF|DIVQ):\s+(\d+)", out)}
    achieved = float(re.search(r"F_PLLOUT:\s+([\d.]+) MHz \(achieved\)", out).group(1))
    assert cfg.divs == ref
    assert cfg.f_out_hz / 1e6 == pytest.approx(achieved, abs=1e-3)
    assert cfg.f_out_hz == 12e6 * (ref["DIVF"] + 1) / (ref["DIVR"] + 1) / 2 ** ref["DIVQ"]


def test_ecp5_pll_matches_ecppll(tmp_path):
    for f_mhz in (50, 33.333333, 100):
        cfg = pll_config("ecp5", 25e6, f_mhz * 1e6)
        out = _yowasp("ecppll", "-i", "25", "-o", str(f_mhz), "-f", "pll.v", cwd=tmp_path)
        ref = {"CLKI_DIV": int(re.search(r"Refclk divisor: (\d+)", out).group(1)),
               "CLKFB_DIV": int(re.search(r"Feedback divisor: (\d+)", out).group(1)),
               "CLKOP_DIV": int(re.search(r"clkout0 divisor: (\d+)", out).group(1))}
        assert cfg.divs == ref, f_mhz
        assert cfg.f_out_hz == pytest.approx(25e6 / ref["CLKI_DIV"] * ref["CLKFB_DIV"])


@pytest.mark.parametrize("family, f_in, limits", [
    # (PFD, VCO) ranges from the data sheets (module docstring of boards/build.py)
    ("xc7", 100e6, ((10e6, 450e6), (600e6, 1200e6))),
    ("xc6s", 100e6, ((19e6, 500e6), (400e6, 1080e6))),
])
def test_xilinx_pll_settings(family, f_in, limits):
    mult = "CLKFBOUT_MULT_F" if family == "xc7" else "CLKFBOUT_MULT"
    out = "CLKOUT0_DIVIDE_F" if family == "xc7" else "CLKOUT0_DIVIDE"
    for f in (50e6, 100e6 / 3, 33.333e6, 27e6, 125e6):
        cfg = pll_config(family, f_in, f)
        d = cfg.divs
        pfd = f_in / d["DIVCLK_DIVIDE"]
        vco = pfd * d[mult]
        assert limits[0][0] <= pfd <= limits[0][1] and limits[1][0] <= vco <= limits[1][1]
        assert cfg.f_out_hz == pytest.approx(vco / d[out])
        # 100 MHz · M / (D · O) reaches each of these exactly
        assert cfg.f_out_hz == pytest.approx(f, rel=2e-5), (family, f)


def test_pll_errors():
    with pytest.raises(ValueError, match=r"^PLL family must be one of ice40, ecp5, xc7, xc6s, "
                                         r"not 'gw1n'$"):
        pll_config("gw1n", 12e6, 50e6)
    with pytest.raises(ValueError, match=r"^No SB_PLL40_PAD setting gives 5 MHz from 12 MHz "
                                         r"within 2 %$"):
        pll_config("ice40", 12e6, 5e6)


# --- parameter errors -----------------------------------------------------------------------------

def test_board_top_errors(tmp_path):
    with pytest.raises(ValueError, match=r"^Board must be one of icebreaker, ulx3s, arty_s7, "
                                         r"atlys, not 'mimas_v2'$"):
        BoardTop("mimas_v2")
    with pytest.raises(TypeError, match=r"^Board must be a board name string, not 3$"):
        BoardTop(3)
    with pytest.raises(TypeError, match=r"^Build clk_hz must be a number of Hz or None, "
                                        r"not '50e6'$"):
        BoardTop("icebreaker", clk_hz="50e6")
    with pytest.raises(ValueError, match=r"^Build clk_hz must be from 20 MHz to 200 MHz, "
                                         r"not 5000000.0 Hz$"):
        BoardTop("ulx3s", clk_hz=5e6)
    # nothing is written before the parameters are checked
    with pytest.raises(ValueError, match=r"^Board must be one of"):
        build("nope", out_dir=tmp_path / "out")
    with pytest.raises(ValueError, match=r"^Build clk_hz must be from"):
        build("atlys", out_dir=tmp_path / "out", clk_hz=300e6)
    assert not (tmp_path / "out").exists()
    assert CLOCK_RANGE_HZ == (20e6, 200e6)


@pytest.mark.parametrize("name, clk_hz, actual", [
    ("icebreaker", None, 33.0e6), ("icebreaker", 50e6, 50.25e6), ("icebreaker", 33.333e6, 33.0e6),
    ("ulx3s", None, 50e6), ("ulx3s", 33.333e6, 25e6 * 4 / 3), ("arty_s7", None, 50e6),
    ("arty_s7", 33.333e6, 1e8 / 3), ("atlys", None, 50e6), ("atlys", 33.333e6, 1e8 / 3),
])
def test_top_runs_at_the_actual_pll_frequency(name, clk_hz, actual):
    clocks = _inspect(lambda: BoardTop(name, clk_hz=clk_hz),
                      lambda top: (top.clk_hz, top.top.clk_hz, top.pll.f_out_hz))
    assert clocks[0] == pytest.approx(actual)
    assert clocks[0] == clocks[1] == clocks[2]


@pytest.mark.parametrize("name, mul_width", [("icebreaker", None), ("ulx3s", 18),
                                             ("arty_s7", None), ("atlys", 18)])
def test_board_top_uses_the_family_multiplier_width(name, mul_width):
    """ECP5 (100 MHz), Spartan-6: 18-bit multiplier operands; iCE40, Spartan-7: products not
    split (hdl/dsp.py; fewer LUTs and DSPs, the same results and clocks)."""
    widths = _inspect(lambda: BoardTop(name, current_loop="pipelined"),
                      lambda top: (top.top.mul_width, top.top._loop.mul_width,
                                   top.top._servo.loop_params["mul_width"]))
    assert widths == (mul_width,) * 3
    assert MUL_WIDTH[get_board(name).family] == mul_width


#: The forms ``boards.build`` selects per FPGA family: the Top's parameter, its table, the value
#: on the iCEBreaker, ULX3S, Arty S7 and Atlys, and the facts that show it reached the block.
#: The host link's registered frame-buffer read address on the ECP5 only (its Fmax; the iCE40's
#: cells the other way, docs/AREA.md §7.62); the protection's OR of its causes in a flip-flop of
#: its own but on the iCE40 (the ECP5's Fmax; the iCE40's cells the other way, the Spartans'
#: LUT6 unchanged, §7.70); the scope's down-counters on the iCE40 only (its cells; the
#: Spartan-7's LUT6 the other way, §7.70); the dead-time compensation's clamp in the PWM timer
#: on the iCE40 only (its cells; the other netlists as before, §7.72); the current loop's pass
#: count in the register file's staging RAM on the iCE40 only (its cells; the Arty's LUT6 the
#: other way, §7.78).
#: on the iCE40 only (its cells; the other netlists as before, §7.72); the host link's compact
#: forms on the iCE40 only (its cells; the ECP5's 100 MHz paths, §7.75).
FAMILY_FORMS = [
    ("link_read_hold", LINK_READ_HOLD, (False, True, False, False),
     lambda top: (top.link_read_hold, top._link.core.read_hold)),
    ("link_compact", LINK_COMPACT, (True, False, False, False),
     lambda top: (top.link_compact, top._link.core.compact)),
    ("trip_register", TRIP_REGISTER, (False, True, True, True),
     lambda top: (top.trip_register, top._protect.trip_register)),
    ("scope_down_counts", SCOPE_DOWN_COUNTS, (True, False, False, False),
     lambda top: (top.scope_down_counts, top._scope.down_counts)),
    ("timer_clamp", TIMER_CLAMP, (True, False, False, False),
     lambda top: (top.timer_clamp, top._timer.signed_duty, not top._dtc.clamp)),
    ("prot_limits", PROT_LIMITS, ("ram", "ports", "ports", "ports"),
     lambda top: (top.prot_limits, top._protect.limits)),
    ("enc_fold_reload", ENC_FOLD_RELOAD, (True, False, False, False),
     lambda top: (top.enc_fold_reload, top._encoder.fold_reload,
                  top._encoder._filter.fold_reload)),
    ("enc_plausibility_complement", ENC_PLAUSIBILITY_COMPLEMENT, (True, False, False, False),
     lambda top: (top.enc_plausibility_complement, top._encoder.plausibility_complement,
                  top._encoder._plausibility.complement)),
    # (with mt_engine, the iCE40's, M/T has no multiplier: the chunk form stands for it)
    ("mt_chunk_multipliers", MT_CHUNK_MULTIPLIERS, (True, False, False, False),
     lambda top: (top.mt_chunk_multipliers or top.mt_engine,
                  top._mt.chunk_multipliers or top.mt_engine)),
    ("mt_engine", MT_ENGINE, (True, False, False, False),
     lambda top: (top.mt_engine, top._mt.arith == "engine",
                  getattr(top._loop, "mt_mode", False))),
    ("mt_k_export", MT_K_EXPORT, (True, False, False, False),
     lambda top: (top.mt_k_export, top._mt.k_steady or top.mt_engine, bool(top._mt_k_words))),
    # (st_current_loops a counter of the staging RAM: the iCE40's; the ULX3S stages in
    # flip-flops, so none there; the Arty S7's LUT6 the other way, §7.78)
    ("ram_loop_count", RAM_LOOP_COUNT, (True, False, False, False),
     lambda top: (top.ram_loop_count,
                  "st_current_loops" in top._regs.counters)),
    ("gates_dead_n", GATES_DEAD_N, (True, False, False, False),
     lambda top: (top.gates_dead_n, top._gates.dead_input == "dead_n",
                  "dead_time" in top._operands)),
    ("timer_sample_split", TIMER_SAMPLE_SPLIT, (True, False, False, False),
     lambda top: (top.timer_sample_split, top._timer.sample_split)),
    ("gates_wrap", GATES_WRAP, (True, False, True, False),
     lambda top: (top.gates_wrap, top._gates.wrap)),
    ("timer_one_adder", TIMER_ONE_ADDER, (True, False, True, False),
     lambda top: (top.timer_one_adder, top._timer.one_adder)),
    ("dtc_one_count", DTC_ONE_COUNT, (True, False, True, False),
     lambda top: (top.dtc_one_count, top._dtc.one_count)),
    ("adc_marker", ADC_MARKER, (True, False, False, False),
     lambda top: (top.adc_marker, top._adc.marker)),
    ("gates_prev_pwm", GATES_PREV_PWM, (True, False, False, False),
     lambda top: (top.gates_prev_pwm, top._gates.prev_pwm)),
]


@pytest.mark.parametrize("param, table, values, facts", FAMILY_FORMS,
                         ids=[form[0] for form in FAMILY_FORMS])
@pytest.mark.parametrize("index, name",
                         list(enumerate(("icebreaker", "ulx3s", "arty_s7", "atlys"))))
def test_board_top_family_forms(param, table, values, facts, index, name):
    """Each family-selected form is the board family's, in the Top and in its block."""
    found = _inspect(lambda: BoardTop(name), lambda top: facts(top.top))
    assert found == (values[index],) * len(found)
    assert table[get_board(name).family] is values[index]


@pytest.mark.parametrize("kwargs, loop", [({}, "pipelined"), ({"current_loop": "pipelined"},
                                                                "pipelined"),
                                          ({"current_loop": "engine"}, "engine")])
def test_board_top_builds_the_chosen_current_loop(kwargs, loop):
    """``current_loop`` reaches Top: its class, with the family's multiplier width where the
    loop takes one (the engine has its own 18-bit datapath)."""
    from foc_servo.hdl.foc import CurrentLoop
    from foc_servo.hdl.foc_engine import EngineCurrentLoop
    facts = _inspect(lambda: BoardTop("ulx3s", **kwargs),
                     lambda top: (top.current_loop, top.top.current_loop, type(top.top._loop),
                                  top.top.mul_width))
    assert facts == (loop, loop, {"pipelined": CurrentLoop, "engine": EngineCurrentLoop}[loop],
                     18)


@pytest.mark.parametrize("name, default", [("icebreaker", "engine"), ("ulx3s", "pipelined"),
                                           ("arty_s7", "pipelined"), ("atlys", "pipelined")])
def test_board_default_current_loop(name, default):
    """``current_loop=None`` (the CLI's default) takes the board's choice: the loop engine on the
    UP5K, whose 8 SB_MAC16 the pipelined loop alone would exceed; an explicit value wins."""
    assert get_board(name).current_loop == default
    assert BoardTop(name).current_loop == default
    assert BoardTop(name, current_loop=None).top.current_loop == default
    other = "pipelined" if default == "engine" else "engine"
    assert BoardTop(name, current_loop=other).current_loop == other


def test_build_current_loop_errors(tmp_path):
    with pytest.raises(ValueError, match=r"^Build current_loop must be one of 'pipelined', "
                                         r"'engine', not 'cordic'$"):
        BoardTop("ulx3s", current_loop="cordic")
    with pytest.raises(TypeError, match=r"^Build current_loop must be a string, one of "
                                        r"'pipelined', 'engine', not 1$"):
        BoardTop("icebreaker", current_loop=1)
    # checked before anything is written, also by prepare() and build()
    with pytest.raises(ValueError, match=r"^Build current_loop must be one of"):
        prepare("ulx3s", out_dir=tmp_path / "out", current_loop="Engine")
    with pytest.raises(ValueError, match=r"^Build current_loop must be one of"):
        build("ulx3s", out_dir=tmp_path / "out", current_loop="engine ")
    assert not (tmp_path / "out").exists()


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")
def test_build_reports_the_current_loop(tmp_path, monkeypatch, capsys):
    """``build(current_loop="engine")``: the engine is in the written design, and the result
    (report.json, the ``--json`` line, the printed report) names it; every other key stays.
    The tools are not run (``_run_bitstream`` stubbed: the real builds are the slow tests)."""
    import foc_servo.boards.build as build_mod
    fake = {"fits": True, "fmax_mhz": 61.5, "error": None, "timing_met": True,
            "fmax": {"sync": {"achieved": 61.5, "constraint": 50.0}}, "pnr_utilisation": {},
            "lut": 1, "lut_kind": "LUT4", "ff": 2, "dsp": 3, "bram_bits": 4}
    monkeypatch.setattr(build_mod, "_run_bitstream", lambda board, prep, stages: (dict(fake), []))
    keys = None
    for loop in ("pipelined", "engine"):
        r = build("ulx3s", out_dir=tmp_path / loop, current_loop=loop, json=True)
        out = capsys.readouterr().out.strip().splitlines()
        assert json.loads(out[-1])["current_loop"] == r["current_loop"] == loop
        assert (f"  gateware  Top(current_loop={loop!r}, scope_ram='bram', regs_staging='ff', "
                f"speed_loop='sequential')" in out)
        assert r["scope_ram"] == "bram" and r["regs_staging"] == "ff"
        assert r["speed_loop"] == "sequential"
        saved = json.loads((tmp_path / loop / "ulx3s" / "report.json").read_text())
        assert saved["current_loop"] == loop
        il = (tmp_path / loop / "ulx3s" / f"{NAME}.il").read_text()
        # the written design holds the chosen loop: the engine's datapath, or the pipeline's
        # CORDIC rotator
        engine = "module \\foc_servo.top.current_loop.engine\n" in il
        cordic = "module \\foc_servo.top.current_loop.cordic\n" in il
        assert (engine, cordic) == ((True, False) if loop == "engine" else (False, True))
        if keys is None:
            keys = set(r)
        assert set(r) == keys
    assert {"board", "title", "flow", "lut", "lut_kind", "ff", "bram_bits", "dsp", "fmax_mhz",
            "fmax", "timing_met", "clock_mhz", "clock_requested_mhz", "pll", "pll_divs", "paper",
            "fits", "error", "utilisation", "wall_s", "stages", "artifacts",
            "current_loop", "speed_loop", "scope_ram", "regs_staging", "seed"} == keys
    assert r["seed"] is None


def test_board_top_speed_loop_is_the_boards_with_the_engine_only():
    """The iCEBreaker runs the speed loop on the loop engine (``Board.speed_loop``), but only
    with the engine current loop (``--current-loop pipelined`` gives the SpeedLoop); the other
    boards keep the SpeedLoop, the Arty also with ``--current-loop engine``."""
    import gc
    import warnings

    from amaranth.hdl import UnusedElaboratable

    from foc_servo.boards.build import BoardTop
    from foc_servo.boards.platforms import get_board
    assert get_board("icebreaker").speed_loop == "engine"
    assert get_board("ulx3s").speed_loop == get_board("arty_s7").speed_loop == "sequential"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)
        got = {(b, loop): BoardTop(b, current_loop=loop).top.speed_loop
               for b, loop in (("icebreaker", None), ("icebreaker", "pipelined"),
                               ("arty_s7", "engine"), ("ulx3s", None))}
        gc.collect()
    assert got == {("icebreaker", None): "engine", ("icebreaker", "pipelined"): "sequential",
                   ("arty_s7", "engine"): "sequential", ("ulx3s", None): "sequential"}


# --- vendor build trees ---------------------------------------------------------------------------

def test_synthesis_verilog_drops_simulation_checks(tmp_path):
    # A design with the gateware's kind of invariant: Amaranth's Verilog carries it as a
    # SystemVerilog assert that a Verilog-2001 reader (yosys read_verilog without -sv)
    # rejects; synthesis_verilog's output reads, and keeps the logic.
    m = Module()
    a, b, o = Signal(name="a"), Signal(name="b"), Signal(name="o")
    m.d.comb += [o.eq(a ^ b), Assert(~(a & b), "a and b together"), Print("a", a)]
    text = rtlil.convert(m, name="chk", ports=[a, b, o])
    amaranth_v = verilog.convert(m, name="chk", ports=[a, b, o])
    clean = synthesis_verilog(text, name="chk")
    assert re.search(r"\bassert\b", amaranth_v) and not re.search(r"\bassert\b|\$write", clean)
    assert re.search(r"assign o = a \^ b;", clean)

    def reads(src):
        (tmp_path / "x.v").write_text(src)
        return subprocess.run(_tool("yosys") + ["-q", "-p", "read_verilog x.v; hierarchy -top chk"],
                              cwd=tmp_path, capture_output=True, text=True).returncode == 0
    assert not reads(amaranth_v)
    assert reads(clean)


class _Roms(wiring.Component):
    """Memories of every kind: only ``big`` (a ROM of > 64 words, one synchronous read port) is
    worth a block RAM on the Xilinx parts; ``small`` (64 words), ``comb`` (asynchronous read)
    and ``ram`` (a write port) are not marked, ``kept`` keeps its own ``rom_style``."""
    a: wiring.In(7)
    big: wiring.Out(16)
    small: wiring.Out(16)
    comb: wiring.Out(16)
    ram: wiring.Out(16)
    kept: wiring.Out(16)

    def elaborate(self, platform):
        import random

        from amaranth.lib.memory import Memory
        m = Module()
        rng = random.Random(5)
        for name, depth in (("big", 128), ("small", 64), ("comb", 128), ("ram", 128),
                            ("kept", 128)):
            init = [rng.getrandbits(16) for _ in range(depth)]
            attrs = {"rom_style": "logic"} if name == "kept" else {}
            m.submodules[name] = mem = Memory(shape=16, depth=depth, init=init, attrs=attrs)
            if name == "ram":
                w = mem.write_port()
                m.d.comb += [w.addr.eq(self.a), w.data.eq(self.a), w.en.eq(self.a[6])]
            r = mem.read_port(domain="comb" if name == "comb" else "sync")
            m.d.comb += [r.addr.eq(self.a), getattr(self, name).eq(r.data)]
        return m


def test_vendor_verilog_marks_the_roms_for_block_ram(tmp_path):
    """The vendor flows' Verilog carries ``rom_style = "block"`` on each ROM of more than 64
    words with a synchronous read (not on a small ROM, an asynchronous one or a RAM), so the
    yosys estimate on it and Vivado / XST agree; ``synth_area``'s xc7 target applies the same
    rule: the big ROM is a block RAM instead of ≈ 40 LUT6 and MUXF7s."""
    from foc_servo.boards.area import mark_xilinx_roms, ports, summarise, synth_area
    roms = _Roms()
    text = rtlil.convert(roms, name="roms", ports=ports(roms))
    marked = synthesis_verilog(text, name="roms", xilinx_roms=True)
    assert synthesis_verilog(text, name="roms").count("rom_style") == 1     # kept's own
    rom = r'\(\* rom_style = "(\w+)" \*\)\s*reg \[15:0\] \\?([a-z]+)'
    assert re.findall(rom, marked) == [("block", "big"), ("logic", "kept")]
    assert marked.count("rom_style") == 2
    assert mark_xilinx_roms(mark_xilinx_roms(text)) == mark_xilinx_roms(text)

    def estimate(verilog_text):
        (tmp_path / "roms.v").write_text(verilog_text)
        script = ("read_verilog roms.v; synth_xilinx -flatten -noiopad -noclkbuf -top roms; "
                  "tee -q -o stat.json stat -json")
        subprocess.run(_tool("yosys") + ["-q", "-p", script], cwd=tmp_path, check=True)
        return json.loads((tmp_path / "stat.json").read_text())["design"]["num_cells_by_type"]

    def bram(cells):
        return sum(n for k, n in cells.items() if k.startswith("RAMB"))
    cells, plain = estimate(marked), estimate(synthesis_verilog(text, name="roms"))
    r = synth_area(_Roms(), "xc7", name="roms")
    # the ROM in a RAMB18 (the RAM where yosys puts it, either way)
    assert bram(cells) == bram(r["cells"]) == bram(plain) + 1
    assert summarise("xc7", plain)["lut"] > summarise("xc7", cells)["lut"] + 30


def test_xilinx_luts_count_the_luts_of_memories():
    """``lut`` is Vivado's "Slice LUTs": logic LUTs and the LUTs of distributed RAMs and shift
    registers (RAM32M = a whole SLICEM's four); INV and block RAM are not LUTs."""
    from foc_servo.boards.area import summarise, xilinx_luts
    from foc_servo.boards.build import _figures
    cells = {"LUT2": 3, "LUT6": 2, "RAM32M": 2, "RAM64X1D": 1, "SRLC32E": 1, "RAMB18E1": 1,
             "INV": 5, "FDRE": 7, "MUXF7": 1}
    assert xilinx_luts(cells) == {"lut": 16, "lut_logic": 5, "lut_memory": 11}
    assert summarise("xc7", cells)["lut"] == 16
    for family in ("xc7", "xc6s"):
        f = _figures(family, cells)
        assert (f["lut"], f["lut_logic"], f["lut_memory"], f["inv"]) == (16, 5, 11, 5)
    with pytest.raises(ValueError, match=r"^Xilinx LUT-memory cell must be one of RAM32X1S, .*, "
                                         r"not 'RAM16X1S'$"):
        xilinx_luts({"RAM16X1S": 1})


class _Checked(wiring.Component):
    """One LUT of logic and an invariant on a wide compare of its inputs."""
    a: wiring.In(16)
    b: wiring.In(16)
    o: wiring.Out(1)

    def elaborate(self, platform):
        m = Module()
        m.d.comb += [self.o.eq(self.a[0] ^ self.b[0]),
                     Assert(self.a + self.b != 0x1234, "sum"), Print("a", self.a)]
        return m


def test_hardware_synthesis_drops_the_gateware_checks():
    """Area and board synthesis remove Assert / Print first (session 9: their input cones were
    synthesised and placed, 11.7 % of the ULX3S top's LUT4): the adder and compare behind the
    assertion cost nothing; the bitstream flows run the same commands after read_rtlil."""
    from foc_servo.boards.area import STRIP_CHECKS, synth_area
    from foc_servo.boards.build import _overrides
    r = synth_area(_Checked(), "ice40")
    assert (r["lut4"], r["carry"]) == (1, 0) and "$check" not in r["cells"]
    for name in ("icebreaker", "ulx3s"):
        assert _overrides(get_board(name), NAME)["script_after_read"] == STRIP_CHECKS


class _ReadRegisters(wiring.Component):
    """Four 256 × 8 ROMs (block RAMs), their read data registered four ways: a plain
    reset-less register on an asynchronous read (``plain``, loaded every clock), one with an
    enable (``gated``), one with the domain's reset (``reset``), and a synchronous read port
    (``sync``)."""
    addr: wiring.In(8)
    en: wiring.In(1)
    plain: wiring.Out(8)
    gated: wiring.Out(8)
    reset: wiring.Out(8)
    sync: wiring.Out(8)

    def elaborate(self, platform):
        from amaranth.lib.memory import Memory
        m = Module()
        for k, name in enumerate(("plain", "gated", "reset", "sync")):
            init = [(i * (37 + 2 * k) + k) % 256 for i in range(256)]
            m.submodules[f"rom_{name}"] = rom = Memory(shape=8, depth=256, init=init)
            rd = rom.read_port(domain="sync" if name == "sync" else "comb")
            m.d.comb += rd.addr.eq(self.addr)
            if name == "sync":
                m.d.comb += self.sync.eq(rd.data)
                continue
            q = Signal(8, reset_less=name != "reset", name=f"q_{name}")
            if name == "gated":
                with m.If(self.en):
                    m.d.sync += q.eq(rd.data)
            else:
                m.d.sync += q.eq(rd.data)
            m.d.comb += getattr(self, name).eq(q)
        return m


def _init_wires(text):
    """The wires of an RTLIL text that carry an ``init`` attribute."""
    return set(re.findall(r"^[ \t]*attribute \\init \S+\n(?:[ \t]*attribute .*\n)*[ \t]*wire "
                          r".*?(\S+)$", text, re.M))


def test_ram_read_init_free_drops_only_every_clock_read_registers():
    """``ram_read_init_free`` (the iCE40 board flow, before synthesis) drops the power-up value
    of a reset-less register loaded from an asynchronous read on every clock, and of the port
    Amaranth drives from it, only: a register with an enable or a reset keeps it. yosys then
    needs no power-up emulation for that read port (its AND per read bit and its flip-flop);
    the others keep theirs."""
    from foc_servo.boards.area import _synth_rtlil, ports, ram_read_init_free
    block = _ReadRegisters()
    text = rtlil.convert(block, name="rr", ports=ports(block))
    free = ram_read_init_free(text)
    assert _init_wires(text) - _init_wires(free) == {"\\q_plain", "\\plain"}
    assert ram_read_init_free(free) == free
    # nothing but those init lines changed
    diff = [ln for ln in difflib.ndiff(text.splitlines(), free.splitlines())
            if ln[:1] in "+-"]
    assert diff == ["-   attribute \\init 8'00000000"] * 2
    before, after = (_synth_rtlil(t, "ice40", "rr") for t in (text, free))
    assert (before["bram"], after["bram"]) == (4, 4)
    # the emulation of each port: a flip-flop and an AND per read bit (here a LUT4 each)
    assert (before["ff"], before["lut4"]) == (3, 24)
    assert (after["ff"], after["lut4"]) == (2, 16)          # ``gated``'s and ``reset``'s stay


def _freed_registers(text):
    """``src`` of each ``$dff`` whose ``Q`` wire :func:`ram_read_init_free` frees."""
    from foc_servo.boards.area import ram_read_init_free
    module = r"^module \S+$.*?^end$"
    srcs = set()
    for before, after in zip(re.findall(module, text, re.M | re.S),
                             re.findall(module, ram_read_init_free(text), re.M | re.S)):
        for wire in _init_wires(before) - _init_wires(after):
            srcs |= set(re.findall(r'attribute \\src "([^"]+)"\n[ \t]*cell \$dff \S+\n'
                                   r'(?:[ \t]*(?:parameter|connect) .*\n)*?'
                                   r"[ \t]*connect \\Q " + re.escape(wire) + r"\n",
                                   before))
    return srcs


def test_icebreaker_plan_reads_the_ram_registers_without_power_up_value(tmp_path):
    """The iCEBreaker's build plan carries the RTLIL with those power-up values dropped and
    synthesises with ``ICE40_SYNTH_OPTS`` (the ULX3S's keeps Amaranth's RTLIL and yosys'
    defaults)."""
    from foc_servo.boards.area import ram_read_init_free
    from foc_servo.boards.build import ICE40_SYNTH_OPTS
    plans = {name: prepare(name, out_dir=tmp_path / name) for name in ("icebreaker", "ulx3s")}
    il = {name: (p["dir"] / f"{NAME}.il").read_text() for name, p in plans.items()}
    ys = {name: (p["dir"] / f"{NAME}.ys").read_text() for name, p in plans.items()}
    assert ram_read_init_free(il["icebreaker"]) == il["icebreaker"]
    assert ram_read_init_free(il["ulx3s"]) != il["ulx3s"]
    assert f"synth_ice40 {ICE40_SYNTH_OPTS} -top {NAME}" in ys["icebreaker"]
    assert ICE40_SYNTH_OPTS == "-dsp -dffe_min_ce_use 4"
    assert re.search(rf"^ *synth_ecp5 +-top {NAME}$", ys["ulx3s"], re.M)


#: The registers of the iCEBreaker's Top that :func:`~foc_servo.boards.area.ram_read_init_free`
#: frees: (module of ``hdl``, signal name).
_FREED = {("regs", "rd_data"), ("hostlink", "rd_data"), ("servo", "cfg_q"),
          ("servo", "rf_rd_q"), ("foc_engine", "data_q"), ("engine", "rf_a_data"),
          ("engine", "rf_b_data"), ("engine", "rd_data"), ("engine", "x3_delay_q"),
          ("engine", "x4_delay_q")}


def _vcd_after(path, t_cut):
    """A VCD's values at time ``t_cut`` (fs; after that time's changes) and its real changes
    after it, as sorted ``(time, signal, value)`` (the order within a time step varies)."""
    ids, now, t, header, after, snapshot = {}, {}, 0, True, [], None
    scope = []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if header:
            if line.startswith("$scope"):
                scope.append(line.split()[2])
            elif line.startswith("$upscope"):
                scope.pop()
            elif line.startswith("$var"):
                ids.setdefault(line.split()[3], ".".join(scope + [line.split()[4]]))
            header = not line.startswith("$enddefinitions")
            continue
        if not line or line.startswith("$"):
            continue
        if line[0] == "#":
            t = int(line[1:])
            if t > t_cut and snapshot is None:
                snapshot = dict(now)
            continue
        value, ident = line[1:].split() if line[0] in "bBrRsS" else (line[0], line[1:])
        if t > t_cut and now.get(ident) != value:
            after.append((t, ids[ident], value))
        now[ident] = value
    snapshot = now if snapshot is None else snapshot
    return {ids[i]: v for i, v in snapshot.items()}, sorted(after)


def test_freed_ram_registers_power_up_value_unseen_after_reset(tmp_path, monkeypatch):
    """Why dropping those power-up values is safe: the iCEBreaker's Top (engine loop, staging
    in block RAM; the scope in block RAM for the simulator) simulated with the ten registers
    powering up all ones instead of 0, the domain reset held for the first clock only (the
    board holds it ≥ 500), then 1 500 clocks (the export walk, ADC samples, current-loop
    runs): from the third clock edge on every signal is the same as with 0. Before it only
    the engine's reset-less datapath registers differ, which the test sees (so it can fail)."""
    from amaranth.hdl import ClockDomain, Elaboratable
    from amaranth.sim import Simulator
    from foc_servo.boards.area import ports
    import foc_servo.hdl.engine as engine
    import foc_servo.hdl.foc_engine as foc_engine
    import foc_servo.hdl.hostlink as hostlink
    import foc_servo.hdl.regs as regs
    import foc_servo.hdl.servo as servo
    period_fs = 30_000_000

    class Bench(Elaboratable):
        def __init__(self):
            self.top = Top(clk_hz=33.333e6, current_loop="engine", regs_staging="bram")
            self.cd = ClockDomain("sync")

        def elaborate(self, platform):
            m = Module()
            m.domains.sync = self.cd
            m.submodules.top = self.top
            return m

    def run(ones):
        made = []
        for mod in (engine, foc_engine, hostlink, regs, servo):
            def signal(*args, src_loc_at=0, _real=Signal, _mod=mod.__name__.rpartition(".")[2],
                       **kwargs):
                sig = _real(*args, src_loc_at=src_loc_at + 1, **kwargs)
                if kwargs.get("reset_less") and (_mod, sig.name) in _FREED:
                    made.append((_mod, sig.name, "{}:{}".format(*sig.src_loc)))
                    if ones:
                        sig = _real(*args, src_loc_at=src_loc_at + 1,
                                    **{**kwargs, "name": sig.name, "init": -1})
                return sig
            signal.like = Signal.like
            monkeypatch.setattr(mod, "Signal", signal)
        bench = Bench()
        sim = Simulator(bench)
        sim.add_clock(period_fs * 1e-15)

        async def testbench(ctx):
            ctx.set(bench.cd.rst, 1)
            await ctx.tick()
            ctx.set(bench.cd.rst, 0)
            await ctx.tick().repeat(1500)
        sim.add_testbench(testbench)
        vcd = tmp_path / f"{'ones' if ones else 'zero'}.vcd"
        with sim.write_vcd(str(vcd)):
            sim.run()
        monkeypatch.undo()
        assert sorted(m[:2] for m in made) == sorted(_FREED)
        if not ones:        # the registers the flow frees in this Top are these ten
            top = bench.top
            text = rtlil.convert(top, name="top", ports=ports(top))
            assert _freed_registers(text) == {m[2] for m in made}
        return vcd
    zero, ones = run(False), run(True)
    # before the first clock edge: the ten registers (and what they drive) differ
    at0 = _vcd_after(zero, 0)[0], _vcd_after(ones, 0)[0]
    assert {k.rpartition(".")[2] for k in at0[0] if at0[0][k] != at0[1][k]} >= \
        {name for _, name in _FREED}
    # the first two edges: only the engine's datapath registers differ; from the third
    # (75 ns: edges at 15, 45, 75 ns) on nothing does (from the fourth before session 16's
    # engine changes, AREA.md §7.66: fewer registers carry the power-up value on)
    for edge in (1, 2):
        a, b = _vcd_after(zero, edge * period_fs)[0], _vcd_after(ones, edge * period_fs)[0]
        differ = {k for k in a if a[k] != b[k]}
        assert differ and all(".current_loop.engine." in k for k in differ), edge
    assert _vcd_after(zero, 3 * period_fs) == _vcd_after(ones, 3 * period_fs)


def test_build_seed_reaches_nextpnr(tmp_path):
    """``seed`` becomes nextpnr's ``--seed`` in the written build script (none without it);
    a bad seed is refused before anything is written."""
    from foc_servo.boards.build import _overrides, prepare
    assert "--seed" not in _overrides(get_board("ulx3s"), NAME)["nextpnr_opts"]
    assert _overrides(get_board("ulx3s"), NAME, 3)["nextpnr_opts"].endswith(" --seed 3")
    plan = prepare("icebreaker", out_dir=tmp_path, seed=5)
    pnr = [c for c in plan["commands"] if c[0].startswith("nextpnr")]
    assert len(pnr) == 1 and pnr[0][pnr[0].index("--seed") + 1] == "5"
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(TypeError, match=r"^Build seed must be None or a non-negative "
                                            r"integer, not "):
            prepare("ulx3s", out_dir=tmp_path / "bad", seed=bad)
    assert not (tmp_path / "bad").exists()


def _verilog_ports(text):
    """Top-level ports of module ``foc_servo``, expanded to bits: {port name: width}."""
    body = text[text.index(f"module {NAME}("):]
    body = body[:body.index("endmodule")]
    ports = {}
    for m in re.finditer(r"^\s*(input|output|inout)\s+(?:wire\s+)?(?:\[(\d+):0\]\s*)?"
                         r"(\\?[\w$.\[\]]+)\s*;", body, re.M):
        ports[m.group(3).lstrip("\\")] = int(m.group(2) or 0) + 1
    return ports


@pytest.fixture(scope="module")
def vendor_trees(tmp_path_factory):
    out = tmp_path_factory.mktemp("trees")
    return {name: prepare(name, out_dir=out) for name in ("arty_s7", "atlys")}


def _check_tree_common(prep):
    root = prep["dir"]
    assert prep["board"].flow == "vendor"
    verilog = (root / f"{NAME}.v").read_text()
    # Verilog-2001: no SystemVerilog assertions or simulation prints left in
    assert not re.search(r"\bassert\b|\$write|\$display", verilog)
    # the zip is the tree
    with zipfile.ZipFile(prep["zip"]) as z:
        assert sorted(z.namelist()) == prep["files"]
        for f in z.namelist():
            assert z.read(f) == (root / f).read_bytes(), f
    # every script file the plan names is there
    for f in prep["files"]:
        assert (root / f).is_file(), f
    return verilog, _verilog_ports(verilog)


def test_vivado_tree_complete(vendor_trees):
    prep = vendor_trees["arty_s7"]
    root = prep["dir"]
    verilog, ports = _check_tree_common(prep)
    assert {f"{NAME}.v", f"{NAME}.tcl", f"{NAME}.xdc", f"build_{NAME}.sh"} <= set(prep["files"])
    tcl = (root / f"{NAME}.tcl").read_text()
    for line in ("create_project -force -name foc_servo -part xc7s50csga324-1",
                 "add_files foc_servo.v", "read_xdc foc_servo.xdc", "synth_design -top foc_servo",
                 "write_bitstream -force -bin_file foc_servo.bit"):
        assert line in tcl, line
    assert prep["commands"] == [["vivado", "-mode", "batch", "-log", "foc_servo.log",
                                 "-source", "foc_servo.tcl"]]
    xdc = (root / f"{NAME}.xdc").read_text()
    locs = {m.group(2).replace("\\", ""): m.group(1) for m in
            re.finditer(r'set_property LOC (\w+) \[get_ports "([^"]+)"\]', xdc)}
    # every top-level port bit has a LOC, and nothing else does
    bits = {f"{p}[{i}]" if w > 1 else p for p, w in ports.items() for i in range(w)}
    assert bits == set(locs)
    for r in pin_map("arty_s7"):
        port = f"motor_0__{r['port']}__io" + (f"[{r['bit']}]" if MOTOR_PORTS[r["port"]][0] > 1
                                              else "")
        assert locs[port] == r["fpga_pin"], port
    assert locs["clk100_0__io"] == "R2" and locs["uart_0__rx__io"] == "V12"
    assert 'create_clock -name clk100_0__io -period 10.0' in xdc
    # the MMCM as chosen: 100 MHz · 10 / 20 = 50 MHz, into a BUFG
    assert re.search(r"MMCME2_BASE #\([^;]*\.CLKFBOUT_MULT_F\(10\.0\)[^;]*"
                     r"\.CLKOUT0_DIVIDE_F\(20\.0\)[^;]*\.DIVCLK_DIVIDE\(32'd1\)", verilog)
    assert "BUFG " in verilog


def test_ise_tree_complete(vendor_trees):
    prep = vendor_trees["atlys"]
    root = prep["dir"]
    verilog, ports = _check_tree_common(prep)
    assert {f"{NAME}.v", f"{NAME}.prj", f"{NAME}.xst", f"{NAME}.ucf",
            f"build_{NAME}.sh"} <= set(prep["files"])
    assert "verilog work foc_servo.v" in (root / f"{NAME}.prj").read_text()
    xst = (root / f"{NAME}.xst").read_text()
    for line in ("-ifn foc_servo.prj", "-top foc_servo", "-p xc6slx45csg324-3"):
        assert line in xst, line
    assert [c[0] for c in prep["commands"]] == ["xst", "ngdbuild", "map", "par", "bitgen"]
    ucf = (root / f"{NAME}.ucf").read_text()
    locs = {m.group(1).replace("<", "[").replace(">", "]"): m.group(2) for m in
            re.finditer(r'NET "([^"]+)" LOC=(\w+);', ucf)}
    bits = {f"{p}[{i}]" if w > 1 else p for p, w in ports.items() for i in range(w)}
    assert bits == set(locs)
    for r in pin_map("atlys"):
        port = f"motor_0__{r['port']}__io" + (f"[{r['bit']}]" if MOTOR_PORTS[r["port"]][0] > 1
                                              else "")
        assert locs[port] == r["fpga_pin"], port
        assert f'NET "{port.replace("[", "<").replace("]", ">")}" IOSTANDARD=LVCMOS33;' in ucf
    assert locs["clk100_0__io"] == "L15" and locs["uart_0__tx__io"] == "B16"
    # the PLL as chosen: 100 MHz · 6 / 12 = 50 MHz
    assert re.search(r"PLL_BASE #\([^;]*\.CLKFBOUT_MULT\(32'd6\)[^;]*"
                     r"\.CLKOUT0_DIVIDE\(32'd12\)[^;]*\.DIVCLK_DIVIDE\(32'd1\)", verilog)


# --- the real builds (slow) -----------------------------------------------------------------------

@pytest.mark.slow
def test_icebreaker_bitstream_build(tmp_path):
    r = build("icebreaker", out_dir=tmp_path, progress=True)
    assert r["clock_mhz"] == 33.0 and r["lut_kind"] == "LUT4"     # the board's 33.333 asked
    assert r["lut"] > 0 and r["ff"] > 0 and r["dsp"] > 0
    pcf = (tmp_path / "icebreaker" / f"{NAME}.pcf").read_text()
    for row in pin_map("icebreaker"):
        bit = f"[{row['bit']}]" if MOTOR_PORTS[row["port"]][0] > 1 else ""
        assert f"set_io motor_0__{row['port']}__io{bit} {row['fpga_pin']}" in pcf
    util = r["utilisation"]["pnr_utilisation"]
    if r["fits"]:
        assert Path(r["artifacts"]["bitstream"]).stat().st_size > 100_000
        assert r["fmax_mhz"] >= r["clock_mhz"] and r["timing_met"] and r["dsp"] <= 8
    else:
        # nextpnr's refusal agrees with the netlist's counts: more logic cells than the UP5K's
        # 5 280 (a cell is a LUT4, a lone FF or a carry: 5 196 LUT4 alone fitted on 25 Nov while
        # the packed design needed 6 587 cells) or more multipliers than its 8 SB_MAC16, each
        # named in the error
        assert r["fits"] is False and "nextpnr-ice40" in r["error"]
        cells = r["utilisation"]["logic_cells"]["total"]["cells"]
        assert cells > 5280 or r["dsp"] > 8
        if cells > 5280:
            assert re.search(r"needs \d+ of 5280 ICESTORM_LC", r["error"])
        if r["dsp"] > 8:
            assert f"needs {r['dsp']} of 8 ICESTORM_DSP" in r["error"]
        assert r["fmax_mhz"] is None and r["timing_met"] is None
        assert r["artifacts"]["bitstream"] is None
    if "ICESTORM_LC" in util:
        lc = util["ICESTORM_LC"]
        assert lc["available"] == 5280
        # every LUT4 needs a logic cell; an LC holds at most one LUT4 and one FF
        assert r["lut"] <= lc["used"] <= r["lut"] + r["ff"]
        # the netlist estimate by nextpnr's packing rules (boards/ice40_cells.py) is close
        est = r["utilisation"]["logic_cells"]
        assert abs(est["total"]["cells"] - lc["used"]) <= 0.02 * lc["used"]
        assert sum(g["cells"] for g in est["by_source"].values()) == est["total"]["cells"]


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("FOC_SERVO_LONG_BUILDS", "0") == "0",
                    reason="the ULX3S place-and-route takes ~45 min on a 2-core machine: set "
                           "FOC_SERVO_LONG_BUILDS=1 to run it (kept out of CI's time budget)")
def test_ulx3s_bitstream_build(tmp_path):
    r = build("ulx3s", out_dir=tmp_path, progress=True)
    assert r["fits"] is True and r["error"] is None
    assert Path(r["artifacts"]["bitstream"]).stat().st_size > 100_000
    # Fmax and the verdict agree; meeting the 50 MHz clock is the gateware's target
    # (docs/AREA.md), reported, not asserted here (23 Nov: 53.0 MHz, then 45.7 MHz)
    assert r["clock_mhz"] == 50.0 and r["fmax_mhz"] > 0
    assert r["timing_met"] == (r["fmax_mhz"] >= r["clock_mhz"])
    # nextpnr derived the clock from the oscillator through the EHXPLLL's dividers itself
    assert [v["constraint"] for v in r["fmax"].values()] == [pytest.approx(50.0, rel=1e-4)]
    util = r["utilisation"]["pnr_utilisation"]
    # yosys' LUT4 + 2 · CCU2C against nextpnr's packed TRELLIS_COMB: packing adds only
    # route-through LUTs (measured: 15 602 → 16 972, 16 990 → 18 444: +9 %); flip-flops and
    # multipliers as is
    assert r["lut"] <= util["TRELLIS_COMB"]["used"] <= 1.15 * r["lut"]
    assert util["TRELLIS_FF"]["used"] == r["ff"]
    assert util["MULT18X18D"]["used"] == r["dsp"]
    lpf = (tmp_path / "ulx3s" / f"{NAME}.lpf").read_text()
    for row in pin_map("ulx3s"):
        bit = f"[{row['bit']}]" if MOTOR_PORTS[row["port"]][0] > 1 else ""
        assert f'LOCATE COMP "motor_0__{row["port"]}__io{bit}" SITE "{row["fpga_pin"]}";' in lpf


@pytest.mark.slow
@pytest.mark.parametrize("name, pll", [("arty_s7", "MMCME2_BASE"), ("atlys", "PLL_BASE")])
def test_vendor_estimate(tmp_path, name, pll):
    r = build(name, out_dir=tmp_path)
    assert r["fmax_mhz"] is None and r["timing_met"] is None
    assert r["error"] is None and r["fits"] is True
    assert r["lut"] > 0 and r["ff"] > 0 and r["lut_kind"] == "LUT6"
    u = r["utilisation"]
    assert r["lut"] == u["lut_logic"] + u["lut_memory"] and u["lut_memory"] > 0
    import json
    stat = json.loads((tmp_path / name / "estimate" / f"{NAME}.stat.json").read_text())
    cells = stat["design"]["num_cells_by_type"]
    # the board primitives went through yosys' cell library as instantiated
    assert cells[pll] == 1 and cells["BUFG"] == 1
    outputs = sum(w for w, d in MOTOR_PORTS.values() if d == "o") + 1 + 2   # + UART TX, LEDs
    assert sum(n for c, n in cells.items() if c.startswith("OBUF")) == outputs
