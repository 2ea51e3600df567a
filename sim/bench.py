"""Benchmarks: the figures behind the issues' targets, printed by ``foc-servo bench``.

Performance and accuracy are measured here, never asserted with timings in the tests. Each
gateware-against-model check is an independent simulation, so they run in parallel worker
processes (Amaranth's simulator is single-threaded), and the yosys area runs go alongside them.
"""

import importlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed

from ..boards.area import convert_blocks, synth_areas
from ..hdl import catalog

__all__ = ["bench_arith", "bench_io", "bench_control", "run_jobs"]


def _call(module, function, kwargs):
    mod = importlib.import_module(f"{__package__}.verify.{module}")
    start = time.perf_counter()
    result = getattr(mod, function)(**kwargs)
    return result, time.perf_counter() - start


def run_jobs(jobs, *, workers=2, progress=True):
    """Run ``{name: (verify_module, function, kwargs)}`` in ``workers`` processes; returns
    ``{name: result}``. Progress (one line per finished job) goes to stderr."""
    results = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(_call, *job): name for name, job in jobs.items()}
        if progress:
            print(f"bench: {len(jobs)} simulations on {workers} processes: {', '.join(jobs)}",
                  file=sys.stderr, flush=True)
        for future in as_completed(futures):
            name = futures[future]
            results[name], seconds = future.result()
            if progress:
                print(f"bench: {name} done in {seconds:.0f} s ({len(results)}/{len(jobs)})",
                      file=sys.stderr, flush=True)
    return results


def _with_area(blocks, jobs, *, area, workers, progress):
    """Run the simulation ``jobs`` and, if ``area``, yosys on ``blocks`` at the same time."""
    texts = convert_blocks(blocks) if area else None
    with ThreadPoolExecutor(max_workers=1) as pool:
        area_job = pool.submit(synth_areas, texts, jobs=1) if area else None
        results = run_jobs(jobs, workers=workers, progress=progress)
        areas = area_job.result() if area else None
    if areas is not None:
        areas = {name: {target: {k: v for k, v in fig.items() if k != "cells"}
                        for target, fig in per_target.items()}
                 for name, per_target in areas.items()}
    return results, areas


def bench_arith(*, count=100_000, seed=1, area=True, progress=True, workers=2):
    """Every arithmetic block against its golden model on ``count`` random vectors (plus the
    corner cases); with ``area``, yosys cell counts for iCE40 and Spartan-7. Returns a flat dict of
    figures (the ``--json`` keys)."""
    common = {"seed": seed}
    jobs = {
        "cordic": ("cordic", "run", {"count": count, **common}),
        "rotator": ("rotator", "run", {"count": count, **common}),
        "pi": ("pi", "run", {"count": count, **common}),
        "clarke": ("clarke", "run", {"count": count, **common}),
        "divider": ("divider", "run", {"count": count, **common}),
    }
    r, areas = _with_area(catalog.ARITH_BLOCKS, jobs, area=area, workers=workers,
                          progress=progress)
    c, p, k, d = r["cordic"], r["pi"], r["clarke"], r["divider"]
    figures = {
        "cordic_max_err_lsb": c["max_err_lsb"],
        "cordic_rms_err_lsb": c["rms_err_lsb"],
        "cordic_latency_clk": c["latency_clk"],
        "cordic_throughput_per_clk": c["throughput_per_clk"],
        "cordic_mismatches": c["mismatches"],
        "rotator_max_err_lsb": r["rotator"]["max_err_lsb"],
        "rotator_rms_err_lsb": r["rotator"]["rms_err_lsb"],
        "rotator_latency_clk": r["rotator"]["latency_clk"],
        "rotator_mismatches": r["rotator"]["mismatches"],
        "pi_mismatches": p["mismatches"],
        "clarke_mismatches": k["mismatches"],
        "divider_mismatches": d["mismatches"],
        "divider_clk": d["clocks_per_division"],
        "pysim_clk_per_s": c["clk_per_s"],
        "vectors": {name: r[name]["vectors"] for name in jobs},
        "details": r,
    }
    if areas is not None:
        figures["area"] = areas
    return figures


def bench_io(*, count=10_000, seed=1, drift_counts=1_000_000, area=True, progress=True,
             workers=2):
    """The motor-side blocks: M/T speed error table, angle drift, SVPWM duties, dead time, fault
    latency, glitch filter, ADC round trip; with ``area``, yosys cell counts."""
    common = {"seed": seed}
    jobs = {
        "mt_speed": ("mt_speed", "run", {"count": count, **common}),
        "encoder": ("encoder", "run", {"count": count, "drift_counts": drift_counts, **common}),
        "svpwm": ("svpwm", "run", {"count": count, **common}),
        "protect": ("protect", "run", {"count": count, **common}),
        "adc": ("adc", "run", {"count": min(count, 2000), **common}),
        "fault_chain": ("fault_chain", "run", {}),
    }
    r, areas = _with_area(catalog.IO_BLOCKS, jobs, area=area, workers=workers,
                          progress=progress)
    mt, enc, sv, fc = r["mt_speed"], r["encoder"], r["svpwm"], r["fault_chain"]
    figures = {
        "mt_err_pct_10_10000": mt["mt_err_pct_10_10000"],
        "mt_err_pct_0p2_10": mt["mt_err_pct_0p2_10"],
        "mt_err_pct_10_10000_1mhz_16bit": mt["mt_err_pct_10_10000_1mhz"],
        "mt_err_pct_0p2_10_1mhz_16bit": mt["mt_err_pct_0p2_10_1mhz"],
        "mt_mismatches": mt["mismatches"],
        "mt_min_rpm_1mhz_16bit": mt["mt_min_rpm_1mhz_16bit"],
        "angle_drift_counts": enc["angle_drift_counts"],
        "angle_drift_counts_per_phase": drift_counts,
        "encoder_mismatches": enc["mismatches"],
        "glitch_short_counted": enc["glitch_short_counted"],
        "glitch_long_missed": enc["glitch_long_missed"],
        "svpwm_mismatches": sv["svpwm_mismatches"],
        "svpwm_commands": sv["svpwm_vectors"],
        "volt_seconds_err_counts": sv["volt_seconds_err_counts"],
        "overmod_angle_err_deg": sv["overmod_angle_err_deg"],
        "deadtime_violations": sv["deadtime_violations"],
        "fault_latency_clk_max": fc["fault_latency_clk_max"],
        "fault_latency_clk": fc["latency_clk"],
        "protect_mismatches": r["protect"]["mismatches"],
        "adc_mismatches": r["adc"]["mismatches"],
        "details": r,
    }
    if areas is not None:
        figures["area"] = areas
    return figures


def bench_control(*, count=2_000, seed=1, area=True, progress=True, workers=2):
    """The controller: the current loop against its model with its compute latency checked on
    every sample (``foc_latency_clk``, per stage in ``foc_latency_stages``), the register file,
    the speed loop / modes / scope; with ``area``, yosys cell counts of these blocks and of the
    whole top (several minutes)."""
    from ..hdl.foc import CurrentLoop
    common = {"seed": seed}
    jobs = {
        "foc": ("foc", "run", {"count": count, **common}),
        "regs": ("regs", "run", {"count": 10 * count, **common}),
        "servo": ("servo", "run", {"count": 10 * count, **common}),
    }
    r, areas = _with_area(catalog.CONTROL_BLOCKS, jobs, area=area, workers=workers,
                          progress=progress)
    foc = r["foc"]
    loop = CurrentLoop()
    loop._MustUse__silence = True       # only its published latencies are read
    figures = {
        "foc_latency_clk": foc["latency"],
        "foc_latency_errors": foc["latency_errors"],
        "foc_latency_stages": loop.stage_latency,
        "foc_mismatches": foc["mismatches"],
        "regs_mismatches": r["regs"]["mismatches"],
        "servo_mismatches": r["servo"]["mismatches"],
        "details": r,
    }
    if areas is not None:
        figures["area"] = areas
    return figures
