import re

import numpy as np
import pytest

from foc_servo.sim.vcd import _ident, write_vcd


def _parse(path):
    """A minimal VCD reader: {name: [(time, value)]} (value int for wires, float for reals)."""
    names, changes, now = {}, {}, 0
    text = path.read_text()
    head, body = text.split("$enddefinitions $end")
    for m in re.finditer(r"\$var (\w+) (\d+) (\S+) (\S+) \$end", head):
        kind, _, ident, name = m.groups()
        names[ident] = (name, kind)
        changes[name] = []
    for line in body.splitlines():
        line = line.strip()
        if not line or line.startswith("$"):
            continue
        if line.startswith("#"):
            now = int(line[1:])
        elif line[0] == "b":
            bits, ident = line[1:].split()
            changes[names[ident][0]].append((now, int(bits, 2)))
        elif line[0] == "r":
            val, ident = line[1:].split()
            changes[names[ident][0]].append((now, float(val)))
        else:
            changes[names[line[1:]][0]].append((now, int(line[0])))
    return changes


def test_vcd_identifiers_unique():
    ids = [_ident(k) for k in range(20000)]
    assert len(set(ids)) == len(ids)
    assert all(33 <= ord(c) <= 126 and c not in "#$" for i in ids for c in i)


def test_vcd_round_trip_digital_and_analog(tmp_path):
    path = tmp_path / "run.vcd"
    n = write_vcd(path, clk_hz=50e6,
                  digital=[("gate_h", 3, [10, 25, 26], [1, 5, 0], 0),
                           ("uart_tx", 1, [3, 7], [0, 1], 1)],
                  analog=[("speed_rpm", [0.0, 1e-6, 2.5e-6], [0.0, 12.5, -3.25])])
    assert n == 8
    ch = _parse(path)
    # Clock k at 50 MHz is 20·k ns.
    assert ch["gate_h"] == [(0, 0), (200, 1), (500, 5), (520, 0)]
    assert ch["uart_tx"] == [(0, 1), (60, 0), (140, 1)]
    assert ch["speed_rpm"] == [(0, 0.0), (0, 0.0), (1000, 12.5), (2500, -3.25)]
    times = [int(x[1:]) for x in path.read_text().split() if x.startswith("#")]
    assert times == sorted(times)


def test_vcd_rejects_bad_clock(tmp_path):
    with pytest.raises(ValueError, match=r"^write_vcd clk_hz must be a positive number, not 0$"):
        write_vcd(tmp_path / "x.vcd", clk_hz=0)


def test_vcd_33mhz_times_exact_to_the_ns(tmp_path):
    path = tmp_path / "run.vcd"
    clocks = np.arange(1, 1000)
    write_vcd(path, clk_hz=100e6 / 3, digital=[("led", 1, clocks, clocks & 1, 0)])
    ch = _parse(path)["led"][1:]
    assert [t for t, _ in ch] == [round(c * 30) for c in clocks]
