"""The foc-servo command: sub-commands run, and the JSON keys the issues name (a public
interface) are on the last line of `--json` output."""

import json

import pytest

from foc_servo.host.cli import main

ARITH_KEYS = {"cordic_max_err_lsb", "cordic_rms_err_lsb", "cordic_latency_clk", "pi_mismatches",
              "clarke_mismatches", "divider_mismatches", "divider_clk", "pysim_clk_per_s", "area"}
IO_KEYS = {"mt_err_pct_10_10000", "mt_err_pct_0p2_10", "mt_min_rpm_1mhz_16bit",
           "angle_drift_counts", "svpwm_mismatches", "deadtime_violations",
           "fault_latency_clk_max"}


def test_verilog_writes_a_block(tmp_path, capsys):
    main(["verilog", "--block", "gates", "--out", str(tmp_path)])
    assert "module gates" in (tmp_path / "gates.v").read_text()
    with pytest.raises(SystemExit, match=r"unknown block 'nope'"):
        main(["verilog", "--block", "nope", "--out", str(tmp_path)])


def test_bench_arith_json_keys(capsys):
    main(["bench", "arith", "--count", "20", "--quiet", "--no-area", "--json"])
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert ARITH_KEYS - {"area"} <= set(figures)
    assert figures["cordic_latency_clk"] == 22 and figures["divider_clk"] == 34
    assert figures["pi_mismatches"] == figures["clarke_mismatches"] == 0


@pytest.mark.slow
def test_bench_all_json_keys_with_area(capsys):
    main(["bench", "--count", "50", "--drift-counts", "1000", "--quiet", "--json"])
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert ARITH_KEYS | IO_KEYS <= set(figures)
    assert {"ice40", "xc7"} <= set(figures["area"]["cordic"])


def test_bench_rejects_bad_count(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--count", "0"])
    assert "must be at least 1, not 0" in capsys.readouterr().err


def test_bench_link_json_keys(capsys, monkeypatch):
    from foc_servo.sim.verify import link
    real_run = link.run
    monkeypatch.setattr(link, "run", lambda **kw: real_run(**{**kw, "rw": 5, "malformed": 12,
                                                                "uart_pairs": 1}))
    main(["bench", "link", "--quiet", "--json"])
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("rw_mismatches", "malformed_frames", "malformed_writes", "hangs"):
        assert figures[key] == (12 if key == "malformed_frames" else 0), key


def test_prove_json_keys(capsys):
    """`foc-servo prove NAME --json`: the issue's `proofs` mapping name → status."""
    assert main(["prove", "deadtime", "--quiet", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["proofs"] == {"deadtime": "proven"}


def test_prove_rejects_unknown_name():
    with pytest.raises(SystemExit, match=r"^foc-servo prove: unknown proof 'nosuch'; choose from "):
        main(["prove", "nosuch"])
