# Ref: issue 7 item 4 (formal safety proofs); docs/PROOFS.md
"""The SymbiYosys proofs of :mod:`foc_servo.boards.prove`: each proof passes, each deliberately
broken variant fails on the property it breaks, and the spec's own pieces are right.

The dead-time, fault and abs_compare proofs (and their broken variants) run in the default
test run (a few seconds each); the PI, speed-loop, host-link and register-file proofs are
``slow``.
"""

import re

import pytest
from amaranth.hdl import Module, Signal
from amaranth.sim import Simulator

from foc_servo.boards.prove import (PROOFS, crc16_step, elaborate_with_internals, mutant, prove,
                                    sby_config, summary, table, writable_runs)
from foc_servo.hdl.gates import Gates
from foc_servo.host.protocol import crc16

# The property each broken variant must be caught by (a regex on the messages of its failing
# assertions).
CAUGHT_BY = {
    "deadtime": r"deadtime: phase [abc] turned on after less than the dead time off",
    "deadtime_n": r"deadtime: phase [abc] turned on after less than the dead time off",
    "fault": r"fault bound: a gate on 3 clocks after a fault",
    "fault_or": r"fault bound: a gate on 3 clocks after a fault",
    "fault_ram": r"fault bound: a gate on 3 clocks after a fault",
    "fault_ram16": r"fault bound: a gate on 3 clocks after a fault",
    "abs_compare": r"abs_compare: \|v\| > limit at (16|32) bit",
    "pi": r"pi exact: integrator update differs from clamp\(I \+ dI\) \(wrapped\)",
    "pi_speed": r"pi exact: integrator update differs from clamp\(I \+ dI\) \(wrapped\)",
    "speed_loop": r"speed wrap: R written unsaturated out of its range",
    "hostlink": r"hostlink crc: a write without a frame with a valid CRC",
    "hostlink_hold": r"hostlink crc: a write without a frame with a valid CRC",
    "hostlink_compact": r"hostlink crc: a write without a frame with a valid CRC",
    "regfile": r"regfile: \w+ (changed|pulsed) unwritten",
    "regfile_bram": r"regfile: \w+ (changed|pulsed) unwritten",
}
QUICK = ("deadtime", "deadtime_n", "fault", "fault_or", "fault_ram", "abs_compare")
SLOW = tuple(name for name in PROOFS if name not in QUICK)


def check_proven(name, tmp_path, cover=False):
    result = prove([name], out=tmp_path, cover=cover)[name]
    assert result["status"] == "proven", result
    assert result["depth"] == PROOFS[name].depth
    assert "successful proof by k-induction" in open(result["log"]).read()
    if cover:
        assert result["cover"] == "covered", result


def check_broken(name, tmp_path):
    result = prove([name], broken=True, out=tmp_path)[name]
    assert result["status"] == "failed", result
    assert any(re.fullmatch(CAUGHT_BY[name], message) for message in result["asserts_failed"]), \
        result["asserts_failed"]
    assert open(result["trace"]).read().startswith("$")     # a VCD counterexample


@pytest.mark.parametrize("name", QUICK)
def test_proven(name, tmp_path):
    check_proven(name, tmp_path)


@pytest.mark.parametrize("name", QUICK)
def test_broken_caught(name, tmp_path):
    check_broken(name, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_proven_slow(name, tmp_path):
    check_proven(name, tmp_path, cover=True)


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_broken_caught_slow(name, tmp_path):
    check_broken(name, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", QUICK)
def test_covered(name, tmp_path):
    # The guarded events (a turn-on after a dead time of 3, gates back on after a fault and a
    # clear) are reachable: the properties do not hold vacuously.
    assert prove([name], out=tmp_path, cover=True)[name]["cover"] == "covered"


@pytest.mark.parametrize("broken", [False, True])
def test_speed_loop_spec_converts(broken):
    # The spec finds the SpeedLoop's internal signals and its mutation string (the slow tests
    # run the proof itself).
    from amaranth.back import rtlil
    assert "ctl_rom" in rtlil.convert(PROOFS["speed_loop"].spec(broken=broken), ports=[])


def test_shallow_induction_is_unknown(tmp_path, monkeypatch):
    # At depth 1 the fault path is not inductive (the trip needs 2 clocks): no counterexample
    # from reset, so "unknown", not "proven" and not "failed".
    import dataclasses
    from foc_servo.boards import prove as module
    monkeypatch.setitem(module.PROOFS, "fault",
                        dataclasses.replace(module.PROOFS["fault"], depth=1))
    result = prove(["fault"], out=tmp_path)["fault"]
    assert result["status"] == "unknown"
    assert result["reason"] == "unknown"
    assert result["induction_failed"]


def test_unknown_name():
    with pytest.raises(ValueError, match=r"^Proof name must be one of deadtime, .*, not 'dead'$"):
        prove(["dead"])


def test_summary():
    results = {"deadtime": {"status": "proven"}, "fault": {"status": "failed"}}
    doc = summary(results, broken=True)
    assert doc["proofs"] == {"deadtime": "proven", "fault": "failed"}
    assert doc["broken"] is True


def test_table():
    results = {"deadtime": {"status": "proven", "time_s": 5.25, "depth": 2, "cover": "covered"},
               "fault": {"status": "failed", "time_s": 6.0, "depth": 8,
                         "asserts_failed": ["fault bound: x", "fault latch: y"]}}
    lines = table(results).splitlines()
    assert re.fullmatch(r"deadtime +proven +5\.2 s +2  cover: covered", lines[1])
    assert re.fullmatch(r"fault +failed +6\.0 s +8  fault bound: x; fault latch: y", lines[2])
    # Names longer than the column widen it: the status column stays aligned.
    lines = table(results, suffix="_broken_variant").splitlines()
    assert {line.index(s) for line, s in zip(lines, ("status", "proven", "failed"))} == \
        {len("deadtime_broken_variant") + 1}


def test_sby_config():
    text = sby_config(5, timeout_s=30)
    assert re.search(r"^mode prove$", text, re.M)
    assert re.search(r"^depth 5$", text, re.M)
    assert re.search(r"^timeout 30$", text, re.M)
    assert re.search(r"^smtbmc --keep-going yices$", text, re.M)
    cover = sby_config(7, mode="cover")
    assert re.search(r"^mode cover$", cover, re.M)
    assert re.search(r"^smtbmc yices$", cover, re.M)


def test_mutant():
    broken = mutant(Gates, ("steady & long_enough", "steady"))
    assert broken is not Gates and broken.__name__ == "Gates"
    _, signals = elaborate_with_internals(broken(dead_width=4))
    assert signals["off_a"].shape().width == 4
    with pytest.raises(ValueError, match=r"^Mutation of Gates: 'no such code' must occur once "
                                         r"in its source, not 0 times$"):
        mutant(Gates, ("no such code", ""))


def test_internals():
    gates = Gates(dead_width=4)
    _, signals = elaborate_with_internals(gates)
    for p in "abc":
        assert signals[f"off_{p}"].shape().width == 4
    assert signals["high"] is gates.high.as_value()


def test_writable_runs():
    amap = ((0, 8, False), (0x10, 0x12, True), (0x12, 0x13, True), (0x13, 0x14, False),
            (0x14, 0x15, True))
    assert writable_runs(amap) == [(0x10, 0x13), (0x14, 0x15)]


def test_crc16_step():
    # The spec's bit-serial CRC against the host's (the check value of CRC-16/CCITT-FALSE).
    message = b"123456789"
    m = Module()
    byte = Signal(8)
    crc = Signal(16, init=0xFFFF)
    m.d.sync += crc.eq(crc16_step(m, crc, byte, "step"))
    sim = Simulator(m)
    sim.add_clock(1e-6)
    seen = []

    async def bench(ctx):
        for b in message:
            ctx.set(byte, b)
            await ctx.tick()
            seen.append(ctx.get(crc))

    sim.add_testbench(bench)
    sim.run()
    assert seen[-1] == crc16(message) == 0x29B1
    assert seen == [crc16(message[:k + 1]) for k in range(len(message))]
