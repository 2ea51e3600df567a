# amaranth: UnusedElaboratable=no
# Ref: issue 6 item 3 (both engines give identical gate outputs and register values, cycle for
#      cycle); docs/PROTOCOL.md (frames); sim/engines/base.py (the engine API)
"""The simulation engines: pysim (reference) and compiled (Verilator) against each other and
against independent expectations (the values written over the host link, the UART codec).

The compiled model is built once (a minute or two) and cached under ``$FOC_SERVO_CACHE`` or
``~/.cache/foc-servo``; later runs take it from the cache. One SimTop configuration serves every
test (100 kHz PWM, UART at clk/8) so that only one model is ever built.
"""

import gc
import os
import time

import numpy as np
import pytest

from foc_servo.hdl.gates import Gates
from foc_servo.hdl.regmap import MAGIC, Scales
from foc_servo.hdl.uart import PHASE_BITS, uart_params
from foc_servo.host.protocol import (Command, ReplyStatus, cobs_decode, crc16, decode_reply,
                                     encode_request, frame)
from foc_servo.sim.engines import ENGINES, make_engine
from foc_servo.sim.engines import compiled as compiled_mod
from foc_servo.sim.engines.base import (EVENT_DTYPE, IN_BITS, IN_INIT, IN_LAYOUT, IN_MASKS,
                                        OUT_BITS, OUT_DTYPE, OUT_LAYOUT, OUT_MASKS,
                                        PORT_ADC_CODES, PORT_PINS_IN, Engine, SimTop,
                                        UartDecoder, UartFramingError, uart_events)

CLK = 50e6
BAUD = CLK / 8
KWARGS = dict(clk_hz=CLK, pwm_hz=100e3, baud=BAUD)
HALL_OK = (0b101, 0b100, 0b110, 0b010, 0b011, 0b001)    # valid Hall codes, in rotation order
CS = OUT_MASKS["adc_cs_n"]


@pytest.fixture(scope="module")
def pysim():
    return make_engine("pysim", **KWARGS)


@pytest.fixture(scope="module")
def compiled():
    start = time.perf_counter()
    engine = make_engine("compiled", **KWARGS)
    print(f"\ncompiled engine ready in {time.perf_counter() - start:.1f} s "
          f"({'built' if engine.built else 'cached'})")
    return engine


@pytest.fixture(params=ENGINES)
def engine(request):
    engine = request.getfixturevalue(request.param)
    engine.reset()
    return engine


# --- the scenario ---------------------------------------------------------------------------

def _adc_word(clock):
    """The ADC codes the 'plant' supplies for the conversion started at a CS fall at ``clock``:
    currents of a rotating vector, a U_dc code that identifies the conversion."""
    ia = round(2000 * np.sin(2 * np.pi * clock / 7000))
    ib = round(2000 * np.sin(2 * np.pi * clock / 7000 - 2 * np.pi / 3))
    udc = 16000 + (clock // 7) % 1000
    return sum((c & 0xFFFF) << (16 * k) for k, c in enumerate((ia, ib, udc, clock & 0x7FFF)))


def _merge_pins(changes, until):
    """Port-0 events from ``(clock, field, level)`` pin changes (one event per clock)."""
    changes = sorted(changes, key=lambda c: c[0])
    word = IN_INIT
    out = []
    for clock, field, level in changes:
        if clock > until:
            break
        word = (word & ~IN_MASKS[field]) | (level << IN_BITS[field])
        if out and out[-1][0] == clock:
            out[-1] = (clock, PORT_PINS_IN, word)
        else:
            out.append((clock, PORT_PINS_IN, word))
    return np.array(out, dtype=EVENT_DTYPE)


def _uart_changes(data, start):
    ev = uart_events(data, start_clock=start, clk_hz=CLK, baud=BAUD)
    levels = (ev["value"] >> np.uint64(IN_BITS["uart_rx"])) & np.uint64(1)
    return [(int(c), "uart_rx", int(v)) for c, v in zip(ev["clock"], levels)], int(ev["clock"][-1])


def _scenario(top):
    """Pin changes of the scenario and the requests sent (in order)."""
    addr = top.regmap
    changes = [(1, "hall", HALL_OK[0])]
    # Encoder: quadrature edges every 97 clocks (forwards), a Z pulse (the encoder aligns: LED 1).
    # Hall: bouncing across one sector boundary before the alignment (the plausibility check
    # skips reversals; a rotating Hall code would disagree with this slow encoder and trip).
    a = b = 0
    for k, clock in enumerate(range(300, 18_000, 97)):
        if k % 2 == 0:
            a ^= 1
            changes.append((clock, "enc_a", a))
        else:
            b ^= 1
            changes.append((clock, "enc_b", b))
    for k, clock in enumerate(range(1500, 9000, 1500)):
        changes.append((clock, "hall", HALL_OK[(k + 1) % 2]))
    changes.append((9001, "enc_z", 1))
    changes.append((9098, "enc_z", 0))
    # Host link: open-loop voltage at a rotating angle, then read-backs.
    write = [1, 0, 0, 0, 0, 1, 1200, 9000, 0x4000, 0x0300_0000]     # mode … ol_freq
    requests = [
        (Command.WRITE, addr["mode"].addr, write, None),
        (Command.READ, addr["mode"].addr, (), len(write)),
        (Command.READ, addr["id_magic"].addr, (), 1),
        (Command.READ, addr["st_udc"].addr, (), 1),
    ]
    start = 400
    sent = []
    for seq, (cmd, a0, data, count) in enumerate(requests, start=1):
        wire = frame(encode_request(cmd, seq, a0, count, data))
        ch, end = _uart_changes(wire, start)
        changes += ch
        sent.append((cmd, seq, a0, data, count))
        start = end + 80 * (12 + 5 * (count or 0)) + 200        # room for the reply
    return changes, sent, start, write


def _drive(engine, static, until):
    """Run ``engine`` to ``until``: stop at each CS fall and supply the conversion's codes from
    the next clock on (as the co-simulation does). Returns all output changes, the replies'
    bytes and the CS-fall clocks."""
    decoder = UartDecoder(CLK, BAUD)
    outs, rx, falls = [], bytearray(), []
    adc = np.zeros(0, dtype=EVENT_DTYPE)
    while engine.now < until:
        ev = np.concatenate([adc, static[static["clock"] > engine.now]])
        res = engine.run(until, ev, stop_mask=CS)
        outs.append(res.out)
        rx += decoder.feed(res.out, now=res.now)
        adc = np.zeros(0, dtype=EVENT_DTYPE)
        if res.stopped and not engine.pins_out & CS:
            falls.append(res.now)
            adc = np.array([(res.now + 1, PORT_ADC_CODES, _adc_word(res.now))], dtype=EVENT_DTYPE)
    return np.concatenate(outs), bytes(rx), falls


def _replies(rx):
    frames = [f for f in rx.split(b"\x00") if f]
    replies = []
    for f in frames:
        raw = cobs_decode(f)
        assert crc16(raw) == 0
        replies.append(decode_reply(raw[:-2]))
    return replies


def test_engines_identical_cycle_for_cycle_on_a_host_link_scenario(pysim, compiled):
    top = pysim.simtop.top
    changes, sent, until, write = _scenario(top)
    static = _merge_pins(changes, until)
    results = {}
    for engine in (pysim, compiled):
        engine.reset()
        start = time.perf_counter()
        results[engine.kind] = _drive(engine, static, until)
        wall = time.perf_counter() - start
        print(f"\n{engine.kind}: {until} clocks in {wall:.2f} s = {until / wall:,.0f} clocks/s")
    (out_p, rx_p, falls_p), (out_c, rx_c, falls_c) = results["pysim"], results["compiled"]
    np.testing.assert_array_equal(out_c, out_p)         # every output pin, cycle for cycle
    assert falls_c == falls_p and rx_c == rx_p

    # Independent expectations: the replies answer the requests with the written values.
    replies = _replies(rx_p)
    assert [(r.cmd, r.seq, r.status) for r in replies] == [
        (cmd, seq, ReplyStatus.OK) for cmd, seq, *_ in sent]
    assert replies[1].data == tuple(write[:1]) + (0,) + tuple(write[2:])   # strobe reads 0
    assert replies[2].data[0] == MAGIC
    assert replies[3].data[0] - 16000 in range(1000)    # a U_dc code the 'ADC' supplied
    # The drive ran: gates switched after the mode write, in complementary pairs with dead
    # time (never high and low on together), the ADC converted twice per PWM period.
    gh = (out_p["value"] & np.uint64(OUT_MASKS["gate_h"])) >> np.uint64(OUT_BITS["gate_h"])
    gl = (out_p["value"] & np.uint64(OUT_MASKS["gate_l"])) >> np.uint64(OUT_BITS["gate_l"])
    assert (gh & gl).max() == 0 and gh.max() > 0 and gl.max() > 0
    assert np.count_nonzero(np.diff(gh.astype(np.int64))) > 100
    period = top.pwm_period
    assert len(falls_p) >= 2 * (until // period) - 2
    led = (out_p["value"] >> np.uint64(OUT_BITS["led"])) & np.uint64(3)
    assert not (led & np.uint64(1)).any() and (led & np.uint64(2)).any()   # no trip; aligned


# --- the API --------------------------------------------------------------------------------

def test_layouts_and_bits():
    assert IN_LAYOUT.size == 9 and OUT_LAYOUT.size == 10
    assert IN_INIT == (1 << IN_BITS["uart_rx"]) | (1 << IN_BITS["fault_n"])
    assert OUT_MASKS["gate_h"] == 0b111 << OUT_BITS["gate_h"]
    assert EVENT_DTYPE.names == ("clock", "port", "value")
    assert OUT_DTYPE.names == ("clock", "value")


def test_initial_state(engine):
    assert engine.now == 0 and engine.pins_in == IN_INIT and engine.adc_codes == 0
    # uart_tx and adc_cs_n idle high, gates off, no trip yet.
    assert engine.pins_out == OUT_MASKS["uart_tx"] | OUT_MASKS["adc_cs_n"]
    assert engine.clk_hz == CLK


def _hall_event(clock, code=HALL_OK[0]):
    return (clock, PORT_PINS_IN, IN_INIT | (code << IN_BITS["hall"]))


def test_stop_semantics(engine):
    ref = engine.run(1500, np.array([_hall_event(1)], dtype=EVENT_DTYPE))
    assert not ref.stopped and ref.now == 1500 and engine.now == 1500
    words = np.concatenate([[ref.out_before], ref.out["value"]]).astype(np.int64)
    cs_changes = ref.out["clock"][((words[1:] ^ words[:-1]) & CS) != 0]
    assert len(cs_changes) >= 4

    engine.reset()
    late = 400                          # an event after the first stop: must not be applied
    ev = np.array([_hall_event(1), _hall_event(late, HALL_OK[1])], dtype=EVENT_DTYPE)
    first = engine.run(1500, ev, stop_mask=CS)
    assert first.stopped and first.now == cs_changes[0] < late == 400
    assert first.out["clock"][-1] == first.now
    assert engine.pins_in == _hall_event(1)[2]      # the clock-1 event applied, not the later one
    np.testing.assert_array_equal(first.out, ref.out[:len(first.out)])
    # Continue without the discarded event: the concatenation matches the reference run.
    outs = [first.out]
    while engine.now < 1500:
        before = engine.pins_out
        r = engine.run(1500, stop_mask=CS)
        assert r.out_before == before and (not r.stopped or r.now in cs_changes)
        outs.append(r.out)
    np.testing.assert_array_equal(np.concatenate(outs), ref.out)
    # until == now: nothing happens.
    r = engine.run(engine.now)
    assert r.now == 1500 and len(r.out) == 0 and not r.stopped


def test_events_take_effect_at_their_clock(engine):
    # The fault pin, low from the event's clock c (edge c samples it): the gates would be off
    # after edge c + fault_latency − 1 (tests/test_top.py); the trip LED (Protection.trip,
    # combinational from its register) comes Gates.trip_latency earlier.
    top = engine.simtop.top
    hall = _hall_event(1)
    fault = hall[2] & ~IN_MASKS["fault_n"]
    res = engine.run(100, np.array([hall, (50, 0, fault)], dtype=EVENT_DTYPE))
    trip = res.out["clock"][(res.out["value"] & np.uint64(1 << OUT_BITS["led"])) != 0]
    assert trip[0] == 50 + top.fault_latency - 1 - Gates.trip_latency
    assert engine.pins_in == fault


@pytest.mark.parametrize("args, exc, msg", [
    ((10, [(0, 0, 1)]), ValueError,
     r"^\w+Engine event clocks must be after the clock reached, 0, not 0 \(event 0: a past "
     r"event\)$"),
    ((10, [(5, 0, 1), (3, 0, 1)]), ValueError,
     r"^\w+Engine events must be sorted by clock, but event 1 \(clock 3\) comes after clock 5$"),
    ((10, [(5, 2, 1)]), ValueError, r"^\w+Engine event port must be 0 \(pins_in\) or 1 "
                                    r"\(adc_codes\), not 2 \(event 0\)$"),
    ((10, [(5, 0, 512)]), ValueError,
     r"^\w+Engine pins_in event value must be below 2\*\*9, not 512 \(event 0\)$"),
    ((10, None, 1 << 10), ValueError, r"^\w+Engine stop_mask must be 0 … 1023 \(pins_out bits\), "
                                      r"not 1024$"),
    ((10.0,), TypeError, r"^\w+Engine until must be an integer clock, not 10\.0$"),
    ((10, None, True), TypeError, r"^\w+Engine stop_mask must be an integer, not True$"),
    ((10, "events"), TypeError, r"^\w+Engine events must be an array of EVENT_DTYPE or "),
    ((10, np.zeros(2, dtype=[("clock", "u8"), ("value", "u8")])), TypeError,
     r"^\w+Engine events must be an array of EVENT_DTYPE, not one of "),
    ((10, np.array([(-1, 0, 0)], dtype=[("clock", "i8"), ("port", "u1"), ("value", "u8")])),
     ValueError, r"^\w+Engine event clocks must not be negative, not -1$"),
    ((10, np.array([(1, 0, 0.5)], dtype=[("clock", "u8"), ("port", "u1"), ("value", "f8")])),
     TypeError, r"^\w+Engine event values must be integers, not float64$"),
])
def test_bad_run_arguments(engine, args, exc, msg):
    with pytest.raises(exc, match=msg):
        engine.run(*args)
    assert engine.now == 0


def test_events_in_the_past_after_a_run(engine):
    engine.run(20)
    with pytest.raises(ValueError, match=r"must be after the clock reached, 20, not 20 "):
        engine.run(30, [(20, 0, IN_INIT)])
    with pytest.raises(ValueError, match=r"^\w+Engine until must be at least the clock reached, "
                                         r"20, not 19$"):
        engine.run(19)
    engine.run(30, [(21, 0, IN_INIT)])
    assert engine.now == 30


def test_out_buffer_overflow_is_handled(compiled):
    # A 3-entry C++ buffer: the Python side keeps calling; the result is the same.
    ev = np.array([_hall_event(1)], dtype=EVENT_DTYPE)
    compiled.reset()
    ref = compiled.run(3000, ev)
    assert len(ref.out) > 10
    compiled.reset()
    compiled.out_chunk = 3
    try:
        small = compiled.run(3000, ev)
        compiled.reset()
        stops = [compiled.run(3000, ev, stop_mask=CS)]
        while compiled.now < 3000:
            stops.append(compiled.run(3000, stop_mask=CS))
    finally:
        compiled.out_chunk = compiled_mod.OUT_CHUNK
    np.testing.assert_array_equal(small.out, ref.out)
    np.testing.assert_array_equal(np.concatenate([s.out for s in stops]), ref.out)
    with pytest.raises(TypeError, match=r"^CompiledEngine out_chunk must be a positive integer, "
                                        r"not 0$"):
        compiled.out_chunk = 0


def test_reset_repeats_the_run(engine):
    ev = np.array([_hall_event(1)], dtype=EVENT_DTYPE)
    a = engine.run(1200, ev)
    engine.reset()
    b = engine.run(1200, ev)
    np.testing.assert_array_equal(a.out, b.out)


def test_compiled_cache_is_reused(compiled, tmp_path, monkeypatch):
    builds = compiled_mod.builds
    mtime = compiled.lib_path.stat().st_mtime_ns
    lib, built = compiled_mod.build_model(compiled.verilog, progress=False)
    assert (lib, built) == (compiled.lib_path, False)
    assert compiled_mod.builds == builds and lib.stat().st_mtime_ns == mtime
    assert lib.parent.parent == compiled_mod.cache_dir() / "verilator"
    assert len(lib.parent.name) == 64                     # sha256 hex
    # No source locations in the Verilog: the model key follows the logic, not the line numbers
    # or the checkout's path.
    assert "(* src =" not in compiled.verilog and "simtop" in compiled.verilog
    monkeypatch.setenv("FOC_SERVO_CACHE", str(tmp_path))
    assert compiled_mod.cache_dir() == tmp_path
    # Another key (the Verilog changed): not in this (empty) cache.
    assert compiled_mod._key(compiled.verilog + "\n") != compiled_mod._key(compiled.verilog)


# --- the source key (skipping the Verilog conversion) ---------------------------------------

def test_source_files_follow_the_imports():
    files = compiled_mod.source_files()
    hdl_dir = files["foc_servo.hdl.top"].parent
    # Every hdl module, the ADC chip, the engines, and what they import from elsewhere in the
    # package (the host link's frame constants come from host/protocol.py).
    assert {f"foc_servo.hdl.{p.stem}" for p in hdl_dir.glob("*.py") if p.stem != "__init__"} \
        <= set(files)
    assert {"foc_servo.hdl", "foc_servo.sim.adc_chip", "foc_servo.sim.engines.base",
            "foc_servo.sim.engines.compiled", "foc_servo.host.protocol"} <= set(files)
    assert all(p.suffix == ".py" and p.is_file() for p in files.values())
    # What a fresh process imports to build a SimTop is all in the key's files.
    import subprocess
    import sys
    code = ("import sys; from foc_servo.sim.engines import compiled, make_engine; "
            "from foc_servo.sim.engines.base import SimTop; SimTop(); "
            "print(' '.join(m for m in sys.modules if m.startswith('foc_servo.')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True).stdout.split()
    assert "foc_servo.hdl.top" in loaded and set(loaded) <= set(files), \
        set(loaded) - set(files)


def test_source_digest_follows_every_byte(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("X = 1\n")
    b.write_text("Y = 2\n")
    files = {"pkg.a": a, "pkg.b": b}
    ref = compiled_mod._digest_files(files)
    assert compiled_mod._digest_files(dict(reversed(files.items()))) == ref
    b.write_text("Y = 3\n")
    assert compiled_mod._digest_files(files) != ref
    b.write_text("Y = 2\n")
    assert compiled_mod._digest_files(files) == ref
    assert compiled_mod._digest_files({"pkg.a": a, "pkg.c": b}) != ref    # a renamed module
    assert compiled_mod._digest_files({"pkg.a": a}) != ref                # a module less


def test_import_scan_finds_every_import(tmp_path):
    src = tmp_path / "m.py"
    src.write_text('"""from the docs: import nothing here"""\n'
                   "import os, foc_servo.hdl.top as t\n"
                   "from . import sibling\n"
                   "from ..up import (a,\n    b)\n"
                   "def f():\n    from .lazy import g\n")
    names = set(compiled_mod._imported_names("foc_servo.sim.m", src))
    assert {"os", "foc_servo.hdl.top", "foc_servo.sim", "foc_servo.sim.sibling", "foc_servo.up",
            "foc_servo.up.a", "foc_servo.up.b", "foc_servo.sim.lazy",
            "foc_servo.sim.lazy.g"} <= names


class _Opaque:
    pass


@pytest.mark.parametrize("a, b", [
    (dict(clk_hz=50e6), dict(clk_hz=50e6 + 1)),
    (dict(clk_hz=50e6), dict(clk_hz=50_000_000)),              # int and float kept apart
    (dict(pwm_hz=10e3), dict(pwm_hz=10e3, baud=115_200)),
    (dict(resets={"kp": 1}), dict(resets={"kp": 2})),
    (dict(scales=Scales(i_fs_a=40.0)), dict(scales=Scales(i_fs_a=20.0))),
])
def test_canonical_parameters_tell_configurations_apart(a, b):
    assert compiled_mod._canonical(a) != compiled_mod._canonical(b)
    assert compiled_mod._canonical(a) == compiled_mod._canonical(dict(reversed(a.items())))


def test_canonical_parameters_refuse_unknown_objects():
    with pytest.raises(compiled_mod._NoCanonicalForm):
        compiled_mod._canonical({"x": _Opaque()})


def test_source_key_is_off_when_a_source_is_newer_than_the_process(compiled, monkeypatch):
    st = compiled.simtop
    key = compiled_mod.source_key(st)
    if key is None:
        pytest.skip("a source file changed after this test session started")
    assert key == compiled_mod.source_key(st) and len(key) == 64
    # The process started 'before' the newest file: the modules in memory may be older.
    newest = max(p.stat().st_mtime_ns for p in compiled_mod.source_files().values())
    monkeypatch.setattr(compiled_mod, "_process_start_ns", lambda: newest)
    assert compiled_mod.source_key(st) is None
    monkeypatch.setattr(compiled_mod, "_process_start_ns", lambda: None)
    assert compiled_mod.source_key(st) is None
    monkeypatch.undo()
    # Another parameter set, unknown parameters, another toolchain: another key or none.
    other = SimTop(**dict(KWARGS, pwm_hz=50e3))
    compiled_mod._mark_elaborated(other)            # never elaborated: no warning
    assert compiled_mod.source_key(other) not in (None, key)
    monkeypatch.setattr(st, "_top_kwargs", {"scales": _Opaque()})
    assert compiled_mod.source_key(st) is None
    monkeypatch.undo()
    monkeypatch.setattr(compiled_mod, "_quick_toolchain_id", lambda: "another compiler")
    assert compiled_mod.source_key(st) not in (None, key)


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")
def test_cached_model_skips_the_verilog_conversion(compiled, monkeypatch):
    if compiled.source_key is None or compiled_mod.source_key(compiled.simtop) is None:
        pytest.skip("a source file changed after this test session started")
    def no_convert(*args, **kwargs):
        raise AssertionError("verilog.convert called for a cached model")
    monkeypatch.setattr(compiled_mod.verilog, "convert", no_convert)
    builds = compiled_mod.builds
    again = make_engine("compiled", **KWARGS)
    assert not again.converted and not again.built and compiled_mod.builds == builds
    assert again.lib_path == compiled.lib_path and again.source_key == compiled.source_key
    assert again.build_s < 5.0
    assert again.verilog == compiled.verilog        # read back from the cache
    # The same model: the same outputs.
    ev = np.array([_hall_event(1)], dtype=EVENT_DTYPE)
    compiled.reset()
    np.testing.assert_array_equal(again.run(3000, ev).out, compiled.run(3000, ev).out)
    # A source-map entry naming a model that is gone: converted again (here: refused).
    compiled_mod._source_map_file(compiled.source_key).write_text('{"model": "' + "0" * 64 + '"}')
    try:
        with pytest.raises(AssertionError, match="verilog.convert called"):
            make_engine("compiled", **KWARGS)
    finally:
        compiled_mod._remember(compiled.source_key, compiled.lib_path)
        gc.collect()        # the refused engine's SimTop warns here, inside the filter


def test_build_lock_makes_a_second_builder_wait(tmp_path, monkeypatch):
    import threading
    monkeypatch.setenv("FOC_SERVO_CACHE", str(tmp_path))
    verilog_text = "// not built: the first builder finishes while the second waits\n"
    key = compiled_mod._key(verilog_text)
    result = {}

    def second():
        result["value"] = compiled_mod.build_model(verilog_text, progress=False)

    with compiled_mod._build_lock(key):
        thread = threading.Thread(target=second)
        thread.start()
        thread.join(0.5)
        assert thread.is_alive()                    # waiting for the lock
        final = tmp_path / "verilator" / key        # 'the first builder' finishes
        final.mkdir(parents=True)
        (final / compiled_mod._LIB).write_bytes(b"")
    thread.join(10)
    assert result["value"] == (final / compiled_mod._LIB, False)
    assert sorted(p.name for p in (tmp_path / "verilator").iterdir()) == [key]


@pytest.mark.filterwarnings("ignore::amaranth.hdl.UnusedElaboratable")
def test_make_engine_bad_parameters():
    with pytest.raises(ValueError, match=r"^Engine kind must be one of 'pysim', 'compiled', "
                                         r"not 'cxxrtl'$"):
        make_engine("cxxrtl")
    with pytest.raises(TypeError, match=r"^Top clk_hz must be a positive number in Hz, "
                                        r"not '50e6'$"):
        make_engine("pysim", clk_hz="50e6")
    gc.collect()        # the half-built SimTop and Top warn here, inside the filter
    with pytest.raises(TypeError, match=r"^Engine simtop must be a SimTop, not 'top'$"):
        Engine("top")


def test_simtop_exposes_top_and_ports(pysim):
    st = pysim.simtop
    assert isinstance(st, SimTop)
    assert st.top.clk_hz == CLK and st.clk_hz == CLK
    names = [p.name for p in st.ports()]
    assert names == ["pins_in", "adc_codes", "pins_out", "clk"]


# --- the UART codec -------------------------------------------------------------------------

def _as_out(events, offset=0):
    """uart_rx events turned into out events of a line at bit ``offset`` (for the decoder)."""
    levels = (events["value"] >> np.uint64(IN_BITS["uart_rx"])) & np.uint64(1)
    out = np.zeros(len(events), dtype=OUT_DTYPE)
    out["clock"] = events["clock"]
    out["value"] = levels << np.uint64(offset)
    return out


@pytest.mark.parametrize("clk_hz, baud", [(50e6, 50e6 / 8), (50e6, 3e6), (33.333e6, 3e6),
                                          (50e6, 115_200)])
def test_uart_codec_round_trip(clk_hz, baud):
    data = bytes([0x00, 0xFF, 0x55, 0xAA, 0x01, 0x80]) + bytes(range(0, 256, 17))
    ev = uart_events(data, start_clock=5, clk_hz=clk_hz, baud=baud)
    # Bit j starts at ceil(j · 2**24 / inc): the first start bit at clock 5, the line idle after.
    inc = uart_params("x", clk_hz, baud)
    assert ev["clock"][0] == 5 and (ev["value"][0] >> np.uint64(IN_BITS["uart_rx"])) & 1 == 0
    assert ev["clock"][-1] == 5 + -(-10 * len(data) * (1 << PHASE_BITS) // inc)
    assert ev["value"][-1] == IN_INIT and (ev["port"] == PORT_PINS_IN).all()
    dec = UartDecoder(clk_hz, baud)
    assert dec.feed(_as_out(ev), now=int(ev["clock"][-1])) == data and not dec.busy
    # Fed in arbitrary pieces, with and without `now`: the same bytes.
    dec = UartDecoder(clk_hz, baud)
    got = bytearray()
    out = _as_out(ev, offset=3)
    for piece in np.array_split(out, 7):
        got += dec.feed(piece, tx_offset=3)
    got += dec.feed(out[:0], tx_offset=3, now=int(ev["clock"][-1]))
    assert bytes(got) == data and dec.bytes_out == len(data)


def test_uart_events_keep_the_other_pins():
    word = IN_INIT | IN_MASKS["enc_a"] | (5 << IN_BITS["hall"])
    ev = uart_events(b"\x0f", start_clock=10, clk_hz=CLK, baud=BAUD, current_pins_in=word)
    assert ((ev["value"] & ~np.uint64(IN_MASKS["uart_rx"])) == word & ~IN_MASKS["uart_rx"]).all()
    with pytest.raises(ValueError, match=r"^uart_events needs the uart_rx line idle"):
        uart_events(b"x", start_clock=10, clk_hz=CLK, baud=BAUD,
                    current_pins_in=word & ~IN_MASKS["uart_rx"])
    with pytest.raises(ValueError, match=r"^uart_events baud must be at most clk_hz / 8"):
        uart_events(b"x", start_clock=10, clk_hz=CLK, baud=CLK / 4)
    with pytest.raises(ValueError, match=r"^uart_events start_clock must be at least 1, not 0$"):
        uart_events(b"x", start_clock=0, clk_hz=CLK, baud=BAUD)
    assert len(uart_events(b"", start_clock=10, clk_hz=CLK, baud=BAUD)) == 0


def test_uart_decoder_framing_error_and_glitch():
    bit = 8                               # clk/8: 8 clocks per bit
    # A byte whose stop bit is low (a break), then a one-clock glitch, then a good 0x5A.
    out = [(100, 0), (100 + 10 * bit + 20, 1)]
    out += [(300, 0), (301, 1)]
    start = 400
    levels = [0] + [(0x5A >> k) & 1 for k in range(8)] + [1]
    out += [(start + j * bit, v) for j, v in enumerate(levels)]
    arr = np.zeros(len(out), dtype=OUT_DTYPE)
    arr["clock"] = [c for c, _ in out]
    arr["value"] = [v for _, v in out]
    dec = UartDecoder(CLK, CLK / 8)
    with pytest.raises(UartFramingError, match=r"^UART framing error: the stop bit of the byte "
                                               r"that started at clock 100 is low$"):
        dec.feed(arr, now=1000)
    assert dec.feed(arr[:0], now=1000) == b"\x5a"


# --- throughput (slow: prints the figures of the report) ------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("kind, clocks", [("compiled", 2_000_000), ("pysim", 20_000)])
def test_engine_throughput_whole_top(kind, clocks, request):
    """Clocks per second on the whole top at 50 MHz / 10 kHz PWM: one run() per PWM period
    (5000 clocks) with ~170 encoder events each (an encoder at ~1000 r/min)."""
    engine = make_engine(kind, clk_hz=50e6, pwm_hz=10e3, baud=115_200)
    period = engine.simtop.top.pwm_period
    edges = np.arange(1, clocks + 1, 29, dtype=np.int64)   # 172 edges per 5000 clocks
    a = ((np.arange(len(edges)) + 1) // 2) % 2
    b = (np.arange(len(edges)) // 2) % 2
    words = (IN_INIT | (HALL_OK[0] << IN_BITS["hall"]) | (a << IN_BITS["enc_a"])
             | (b << IN_BITS["enc_b"]))
    ev = np.zeros(len(edges), dtype=EVENT_DTYPE)
    ev["clock"], ev["port"], ev["value"] = edges, PORT_PINS_IN, words
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    calls = 0
    while engine.now < clocks:
        end = min(clocks, engine.now + period)
        lo = np.searchsorted(ev["clock"], engine.now, side="right")
        hi = np.searchsorted(ev["clock"], end, side="right")
        engine.run(end, ev[lo:hi])
        calls += 1
    wall, cpu = time.perf_counter() - start_wall, time.process_time() - start_cpu
    print(f"\n{kind}: {clocks} clocks, {calls} calls, {len(ev) / calls:.0f} events/call: "
          f"{clocks / wall:,.0f} clocks/s wall, {clocks / cpu:,.0f} clocks/s CPU "
          f"(load {os.getloadavg()[0]:.1f})")


# --- the build (slow: compiles a small model twice at once) --------------------------------

_TINY = """
module simtop(clk, pins_in, adc_codes, pins_out);
  input clk;
  input [8:0] pins_in;
  input [63:0] adc_codes;
  output [9:0] pins_out;
  reg [15:0] count = 16'd0;
  always @(posedge clk) begin
    count <= count + 16'd1;
    assert (count != 16'd100);
  end
  assign pins_out = count[12:3] ^ {1'b0, pins_in};
endmodule
"""


@pytest.mark.slow
def test_compiled_build_is_safe_in_parallel_and_reports_assertions(tmp_path):
    import subprocess
    import sys
    src = tmp_path / "tiny.v"
    src.write_text(_TINY)
    code = ("import sys; from foc_servo.sim.engines.compiled import build_model; "
            "p, b = build_model(open(sys.argv[1]).read(), progress=False); print(p, b)")
    env = dict(os.environ, FOC_SERVO_CACHE=str(tmp_path / "cache"))
    # The leftover of a build that was killed (SIGTERM/SIGKILL skip the clean-up): removed.
    stale = tmp_path / "cache" / "verilator" / f"{compiled_mod._key(_TINY)[:16]}.building-dead"
    (stale / "obj").mkdir(parents=True)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(src)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(2)]
    results = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), results
    lines = [out.split() for out, _ in results]
    # One process built the model, the other waited on the lock and took it.
    assert lines[0][0] == lines[1][0] and {lines[0][1], lines[1][1]} == {"True", "False"}
    entries = list((tmp_path / "cache" / "verilator").iterdir())
    assert [e.name for e in entries] == [os.path.basename(os.path.dirname(lines[0][0]))]
    # The harness: the model runs, and a failed assertion stops it at its clock (status 2).
    lib = compiled_mod._load(lines[0][0])
    handle = lib.foc_create(0)
    buf = np.zeros(64, dtype=OUT_DTYPE)
    res = np.zeros(3, dtype=np.uint64)
    empty = np.zeros(1, dtype=np.uint64)
    status = lib.foc_run(handle, 1000, empty.ctypes.data, empty.ctypes.data, empty.ctypes.data,
                         0, buf.ctypes.data, len(buf), 0, res.ctypes.data)
    lib.foc_destroy(handle)
    assert status == 2 and res[0] == 101            # count was 100 before edge 101
    assert buf["clock"][:res[1]].tolist() == list(range(8, 101, 8))
