"""Benchmarks: the figures behind the issues' targets, printed by ``foc-servo bench``.

Performance and accuracy are measured here, never asserted with timings in the tests.
"""

from concurrent.futures import ThreadPoolExecutor

from ..boards.area import convert_blocks, synth_areas
from ..hdl.catalog import ARITH_BLOCKS
from .verify import clarke, cordic, divider, pi

__all__ = ["bench_arith"]


def bench_arith(*, count=100_000, seed=1, area=True, progress=True):
    """Run every arithmetic block against its golden model on ``count`` random vectors (plus the
    corner cases) and, when ``area`` is set, synthesise each with yosys for iCE40 and Spartan-7 in
    parallel with the simulations. Returns a flat dict of figures (the ``--json`` keys)."""
    texts = convert_blocks(ARITH_BLOCKS) if area else None
    with ThreadPoolExecutor(max_workers=1) as pool:
        area_job = pool.submit(synth_areas, texts, jobs=1) if area else None
        c = cordic.run(count, seed=seed, progress=progress)
        p = pi.run(count, seed=seed, progress=progress)
        k = clarke.run(count, seed=seed, progress=progress)
        d = divider.run(count, seed=seed, progress=progress)
        areas = area_job.result() if area else None
    figures = {
        "cordic_max_err_lsb": c["max_err_lsb"],
        "cordic_rms_err_lsb": c["rms_err_lsb"],
        "cordic_latency_clk": c["latency_clk"],
        "cordic_throughput_per_clk": c["throughput_per_clk"],
        "cordic_mismatches": c["mismatches"],
        "pi_mismatches": p["mismatches"],
        "clarke_mismatches": k["mismatches"],
        "divider_mismatches": d["mismatches"],
        "divider_clk": d["clocks_per_division"],
        "pysim_clk_per_s": c["clk_per_s"],
        "vectors": {"cordic": c["vectors"], "pi": p["vectors"], "clarke": k["vectors"],
                    "divider": d["vectors"]},
        "sim_s": {"cordic": c["sim_s"], "pi": p["sim_s"], "clarke": k["sim_s"],
                  "divider": d["sim_s"]},
        "details": {"cordic": c, "pi": p, "clarke": k, "divider": d},
    }
    if areas is not None:
        figures["area"] = {name: {target: {key: value for key, value in fig.items()
                                           if key != "cells"}
                                  for target, fig in per_target.items()}
                           for name, per_target in areas.items()}
    return figures
