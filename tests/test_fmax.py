# Ref: issue 7 (ECP5 Fmax ≥ 100 MHz), boards/fmax.py
import gc
import warnings

import pytest
from amaranth.back import rtlil
from amaranth.hdl import UnusedElaboratable

from foc_servo.boards.fmax import (Harness, _critical_path, _dsp_path_ns, _signal, fmax_block,
                                   fmax_catalog)
from foc_servo.hdl.gates import Gates
from foc_servo.host.cli import main


def test_harness_leaves_three_pins_and_keeps_every_port():
    """The harness of the current loop (757 port bits) has the clock, reset and three pins; the
    scan chains hold one flip-flop per port bit."""
    from foc_servo.hdl.foc import CurrentLoop
    h = Harness(CurrentLoop())
    text = rtlil.convert(h, name="foc")
    top = text[text.index("module \\foc\n"):]
    top = top[:top.index("\nend\n")]
    ports = sorted(line.split()[-1] for line in top.splitlines()
                   if line.lstrip().startswith("wire") and (" input " in line
                                                           or " output " in line))
    assert ports == ["\\clk", "\\load", "\\rst", "\\si", "\\so"]
    widths = [int(line.split()[2]) for line in top.splitlines()
              if line.lstrip().startswith("wire") and line.split()[-1] in ("\\chain_i",
                                                                          "\\chain_o")]
    assert sum(widths) == 757
    assert h.port_bits == 757


def test_harness_rejects_a_non_component():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnusedElaboratable)     # the half-built object
        with pytest.raises(TypeError, match=r"^Block must be an amaranth wiring.Component, "
                                            r"not 3$"):
            Harness(3)
        gc.collect()


def test_signal_names_from_nextpnr_cells():
    assert _signal("dut.rem_b_TRELLIS_FF_Q_20") == "dut.rem_b"
    assert _signal("dut.d2_TRELLIS_FF_Q") == "dut.d2"
    assert _signal("dut.x_CCU2C_S0$CCU2_COMB1") == "dut.x"
    assert _signal("dut.a_LUT4_Z") == "dut.a"
    assert _signal("dut.p_MULT18X18D_P7") == "dut.p"
    assert _signal("chain_i_SB_DFFSR_Q_3_DFFLC") == "chain_i"
    assert _signal("dut.off_a_SB_DFFESR_Q_2_D_SB_CARRY_I0_CO_SB_CARRY_CI") == "dut.off_a"
    assert _signal("dut.engine.alt_a_SB_DFF_Q_23_D_SB_LUT4_O_LC") == "dut.engine.alt_a"


def test_critical_path_of_a_report():
    def step(kind, a, b, delay):
        return {"type": kind, "from": {"cell": a}, "to": {"cell": b}, "delay": delay}

    report = {"critical_paths": [{"path": [
        step("clk-to-q", "dut.a_TRELLIS_FF_Q", "dut.a_TRELLIS_FF_Q", 0.5),
        step("routing", "dut.a_TRELLIS_FF_Q", "dut.s_LUT4_Z", 1.0),
        step("logic", "dut.s_LUT4_Z", "dut.s_LUT4_Z", 0.25),
        step("routing", "dut.s_LUT4_Z", "dut.b_TRELLIS_FF_Q_3", 0.75),
    ]}]}
    cp = _critical_path(report)
    assert (cp["from"], cp["to"], cp["delay_ns"], cp["logic_ns"], cp["logic_levels"]) == \
        ("dut.a", "dut.b", 2.5, 0.25, 1)
    assert cp["through"] == ["dut.a", "dut.s", "dut.b"]
    assert _critical_path({}) is None
    assert _dsp_path_ns(report) is None


def test_ice40_report_with_unregistered_multipliers():
    """nextpnr-ice40 times an SB_MAC16 without registers as a pseudo-clock ($PACKER_GND_NET):
    the critical path is the real clock's worst register-to-register path, not the first listed
    (the DSP's inside) nor an I/O path, and the three DSP pieces add up to a bound."""
    def path(src, dst, delay, a="dut.a_SB_DFF_Q", b="dut.b_SB_DFF_Q"):
        return {"from": src, "to": dst, "path": [
            {"type": "clk-to-q", "from": {"cell": a}, "to": {"cell": a}, "delay": delay / 2},
            {"type": "logic", "from": {"cell": a}, "to": {"cell": b}, "delay": delay / 2}]}

    gnd, clk = "posedge $PACKER_GND_NET_$glb_clk", "posedge clk$SB_IO_IN_$glb_clk"
    report = {"critical_paths": [
        path(gnd, gnd, 3.0, "dut.p_SB_MAC16", "dut.p_SB_MAC16"),
        path(clk, clk, 20.0, "dut.x_SB_DFF_Q", "dut.y_SB_LUT4_O_LC"),
        path("<async>", clk, 30.0),
        path(gnd, clk, 16.0, "dut.p_SB_MAC16", "dut.q_SB_DFF_Q"),
        path(clk, gnd, 6.0, "dut.m_SB_DFF_Q", "dut.p_SB_MAC16"),
    ]}
    cp = _critical_path(report)
    assert (cp["from"], cp["to"], cp["delay_ns"]) == ("dut.x", "dut.y", 20.0)
    assert _dsp_path_ns(report) == 25.0


def test_fmax_family_errors():
    with pytest.raises(ValueError, match=r"^family must be one of ecp5, ice40, not 'xc7'$"):
        fmax_block("gates", family="xc7")
    with pytest.raises(SystemExit):
        main(["fmax", "--block", "gates", "--family", "xc7"])


def test_fmax_catalogue_and_errors():
    assert {"svpwm", "foc", "pi", "clarke", "encoder", "uart_rx", "uart_tx",
            "foc_engine"} <= set(fmax_catalog())
    with pytest.raises(ValueError, match=r"^Block must be one of .*, not 'nope'$"):
        fmax_block("nope")
    with pytest.raises(ValueError, match=r"^freq_mhz must be within 1…1000 MHz, not 0$"):
        fmax_block("gates", freq_mhz=0)
    with pytest.raises(SystemExit, match="unknown block 'nope'"):
        main(["fmax", "--block", "nope"])


@pytest.mark.slow
def test_fmax_of_the_gates_routes_and_reports(capsys, tmp_path):
    """A real place and route (≈ 15 s): the dead-time block is far above 100 MHz."""
    main(["fmax", "--block", "gates", "--json", "--quiet", "--out", str(tmp_path)])
    import json
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["block"] == "gates" and doc["fmax_mhz"] > 110 and doc["timing_met"]
    assert doc["critical_path"]["from"].startswith("dut.")
    assert (tmp_path / "gates" / "gates.nextpnr.log").exists()
    r = fmax_block("gates", Gates(dead_width=4))
    assert r["fmax_mhz"] > 110


@pytest.mark.slow
def test_ice40_fmax_of_the_gates_routes_and_reports(capsys):
    """A real UP5K place and route (≈ 5 s once the YoWASP tool is compiled): logic cells and the
    Fmax at the paper's 33.333 MHz constraint."""
    main(["fmax", "--family", "ice40", "--block", "gates", "--json", "--quiet"])
    import json
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["family"] == "ice40" and doc["freq_mhz"] == 33.333
    assert doc["fmax_mhz"] > 33.333 and doc["timing_met"]
    assert 50 < doc["utilisation"]["ICESTORM_LC"] < 1000
    assert doc["dsp_path_ns"] is None
    assert 0 < doc["port_bits"] < doc["utilisation"]["ICESTORM_LC"]     # the scan chains
