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


@pytest.mark.parametrize("args, passed", [([], None), (["--current-loop", "engine"], "engine"),
                                          (["--current-loop", "pipelined"], None)])
def test_sim_current_loop_option_reaches_the_scenario(capsys, monkeypatch, args, passed):
    """`foc-servo sim ... --current-loop engine` passes ``current_loop`` on to the scenario (and
    from there ``CoSim`` → ``make_engine`` → ``SimTop`` → ``Top``), only when not the default (the
    default top's compiled-model source key stays the cached one); the JSON names it."""
    from foc_servo.sim import scenarios
    seen = {}

    def fake_step(**kw):
        seen.update(kw)
        info = dict.fromkeys(("motor_time_s", "wall_s", "sim_wall_s", "engine_s", "plant_s",
                              "clk_per_s", "clocks", "build_s"), 1.0)
        info.update(engine=kw["engine"], current_loop=kw.get("current_loop", "pipelined"))
        return scenarios.Result("step", {}, {"settle_s": 0.01}, info, None)

    monkeypatch.setattr(scenarios, "step", fake_step)
    main(["sim", "step", "--quiet", "--json", *args])
    fig = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert seen.get("current_loop") == passed
    assert fig["current_loop"] == (passed or "pipelined")


def test_sim_current_loop_option_rejects_unknown(capsys):
    with pytest.raises(SystemExit):
        main(["sim", "step", "--current-loop", "cordic"])
    assert "invalid choice: 'cordic'" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")  # only inspected
def test_simtop_builds_the_chosen_current_loop():
    """The SimTop of the simulation engines takes ``current_loop`` as a Top parameter, so it is in
    ``top_kwargs`` (the compiled model's source key) and in the Verilog (the model key)."""
    from foc_servo.hdl.foc_engine import EngineCurrentLoop
    from foc_servo.sim.engines.base import SimTop
    simtop = SimTop(current_loop="engine")
    assert simtop.top_kwargs == {"current_loop": "engine"}
    assert isinstance(simtop.top._loop, EngineCurrentLoop)


@pytest.mark.parametrize("args, passed", [([], None),          # None: the board's default
                                          (["--current-loop", "engine"], "engine"),
                                          (["--current-loop", "pipelined"], "pipelined")])
def test_build_current_loop_option_reaches_build(monkeypatch, args, passed):
    """``foc-servo build --current-loop`` reaches ``build(current_loop=...)`` (stubbed: no
    tools run here; tests/test_build.py follows it into Top and the report)."""
    import foc_servo.boards.build as build_mod
    seen = {}
    monkeypatch.setattr(build_mod, "build", lambda board, **kw: seen.update(board=board, **kw))
    main(["build", "--board", "ulx3s", "--quiet", "--json", *args])
    assert seen["board"] == "ulx3s" and seen["current_loop"] == passed
    assert seen["json"] is True and seen["progress"] is False and seen["clk_hz"] is None


def test_build_seed_option_reaches_build(monkeypatch):
    """``foc-servo build --seed N`` reaches ``build(seed=N)``; without it nextpnr keeps its own."""
    import foc_servo.boards.build as build_mod
    seen = {}
    monkeypatch.setattr(build_mod, "build", lambda board, **kw: seen.update(board=board, **kw))
    main(["build", "--board", "ulx3s", "--quiet"])
    assert seen["seed"] is None
    main(["build", "--board", "ulx3s", "--quiet", "--seed", "7"])
    assert seen["seed"] == 7


def test_build_current_loop_option_rejects_unknown(capsys):
    with pytest.raises(SystemExit):
        main(["build", "--board", "ulx3s", "--current-loop", "cordic"])
    err = capsys.readouterr().err
    assert "argument --current-loop: invalid choice: 'cordic'" in err
    assert "'pipelined'" in err and "'engine'" in err
