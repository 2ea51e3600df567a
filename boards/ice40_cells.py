"""Where an iCE40 design's logic cells go: nextpnr-ice40's packing rules applied to the netlist
yosys writes, counted per HDL source file.

An iCE40 logic cell (``ICESTORM_LC``) holds one LUT4, one flip-flop whose D input is that LUT's
output, and one carry. nextpnr-ice40's packer (``ice40/pack.cc``: ``pack_lut_lutffs``,
``pack_nonlut_ffs``, ``pack_carries``, ``merge_carry_luts``; chain legalisation after it) gives

* every ``SB_LUT4`` a cell; an ``SB_DFF*`` joins it when the LUT's output drives that D input and
  nothing else;
* every other flip-flop a cell of its own (its LUT a pass-through): **a flip-flop without a LUT of
  its own in front costs a whole cell** — a register loaded from a shared bus, a block RAM's or
  multiplier's output, a port, or another flip-flop;
* an ``SB_CARRY`` the cell of the LUT that reads its carry-in on I3 and its two operands on I1
  and I2 (an adder bit); any other carry — a comparator's, or the first bit of a chain with a
  constant carry-in — gets a cell of its own, into which a LUT of at most two inputs (on I2, I3,
  without a flip-flop) driving one of its operands may move;
* a carry chain whose carry-in comes from logic a feed-in cell, and a carry-out read by logic
  (a comparator's result) a feed-out cell.

So a design needs about ``LUT4 − merged LUTs + lone flip-flops + lone carries + chain cells``,
which is what :func:`logic_cells` counts. It is an estimate (nextpnr's choices depend on the
order it visits cells, and it adds its constant drivers): the iCEBreaker top of session 10,
11 738 estimated against 11 808 by nextpnr at the start, 9 831 against 9 847 later. Its use is
the breakdown: which source's flip-flops and carries cost cells of their own.
"""

import re
from collections import Counter, defaultdict

__all__ = ["logic_cells", "report_lines"]

_SOURCE = re.compile(r"(?:^|[/|])(?:hdl|boards)/(\w+)\.py:\d+")
_KEYS = ("cells", "lut4", "lut_merged", "ff", "ff_alone", "carry", "carry_alone", "chain")


def _top_module(netlist):
    modules = netlist.get("modules") or {}
    tops = [m for m in modules.values() if int(m.get("attributes", {}).get("top", "0"), 2)]
    if len(tops) != 1:
        tops = sorted(modules.values(), key=lambda m: len(m.get("cells", {})))[-1:]
    if not tops:
        raise ValueError("ice40 netlist has no modules")
    return tops[0]


def _source(cell):
    m = _SOURCE.search(cell.get("attributes", {}).get("src", ""))
    return m.group(1) if m else None


def _instances(module):
    """The instance paths of a flattened module (``top.servo.speed_loop``): every prefix of the
    ``hdlname`` attributes (the hierarchy, space-separated) of its nets and cells."""
    paths = set()
    for item in (*module.get("netnames", {}).values(), *module.get("cells", {}).values()):
        parts = item.get("attributes", {}).get("hdlname", "").split()
        paths.update(".".join(parts[:i]) for i in range(1, len(parts)))
    return paths


def _sources(cells, instances=None):
    """Each cell's HDL file stem: its ``src`` attribute, or for a cell without one (most LUTs
    after ABC) the file most cells with a ``src`` in its instance come from, else its parent
    instance's. A cell's instance is the longest prefix of its name (flattening names a cell
    after the net it drives) that is one of ``instances`` (:func:`_instances`; without them,
    the name up to its last dot): a LUT named after a block RAM's read data,
    ``top.servo.speed_loop.rf.0.0_RDATA…``, is the speed loop's."""
    def instance(name):
        if instances is None:
            return name.rpartition(".")[0]
        parts = name.split(".")
        for i in range(len(parts) - 1, 0, -1):
            if ".".join(parts[:i]) in instances:
                return ".".join(parts[:i])
        return ""
    votes = defaultdict(Counter)
    own = {}
    for name, cell in cells.items():
        own[name] = _source(cell)
        if own[name]:
            votes[instance(name)][own[name]] += 1
    result = {}
    for name, src in own.items():
        path = instance(name)
        while not src and path:
            if votes.get(path):
                src = votes[path].most_common(1)[0][0]
            path = path.rpartition(".")[0]
        result[name] = src or "(no source)"
    return result


def logic_cells(netlist):
    """Estimate the ``ICESTORM_LC`` cells of a flattened ``synth_ice40`` netlist.

    Parameters
    ----------
    netlist : dict
        Yosys' JSON netlist (``write_json``) after ``synth_ice40``, flattened.

    Returns
    -------
    dict
        ``total`` and ``by_source`` (HDL file stem → figures, the most cells first), each with
        ``cells`` (the estimate), ``lut4``, ``lut_merged`` (LUTs moved into a lone carry's
        cell), ``ff``, ``ff_alone`` (flip-flops that take a cell of their own), ``carry``,
        ``carry_alone`` (carries that take a cell of their own) and ``chain`` (feed-in / feed-out
        cells). A cell counts where yosys' ``src`` attribute says it came from; one without it
        (most LUTs after ABC) where most cells of its instance come from (:func:`_sources`),
        else as ``"(no source)"``.
    """
    module = _top_module(netlist)
    cells = module.get("cells", {})
    driver = {}
    users = defaultdict(list)
    for name, cell in cells.items():
        dirs = cell.get("port_directions", {})
        for port, bits in cell.get("connections", {}).items():
            for bit in bits:
                if isinstance(bit, str):        # a constant "0" / "1" / "x"
                    continue
                if dirs.get(port) == "output":
                    driver[bit] = name
                else:
                    users[bit].append((name, port))

    def bit(cell, port):
        bits = cell.get("connections", {}).get(port) or [None]
        return bits[0]

    def lut_alone(name):                # the LUT's output drives one flip-flop's D only
        o = bit(cells[name], "O")
        us = users.get(o, [])
        return not (len(us) == 1 and us[0][1] == "D"
                    and cells[us[0][0]]["type"].startswith("SB_DFF"))

    source = _sources(cells, _instances(module) or None)
    groups = defaultdict(Counter)
    lone_carries = []
    for name, cell in cells.items():
        kind = cell["type"]
        g = groups[source[name]]
        if kind == "SB_LUT4":
            g["lut4"] += 1
        elif kind.startswith("SB_DFF"):
            g["ff"] += 1
            d = bit(cell, "D")
            src = driver.get(d) if not isinstance(d, str) else None
            if not (src and cells[src]["type"] == "SB_LUT4" and len(users[d]) == 1):
                g["ff_alone"] += 1
        elif kind == "SB_CARRY":
            g["carry"] += 1
            ci, i0, i1 = bit(cell, "CI"), bit(cell, "I0"), bit(cell, "I1")
            paired = not isinstance(ci, str) and ci is not None and any(
                cells[u]["type"] == "SB_LUT4" and p == "I3"
                and bit(cells[u], "I1") == i0 and bit(cells[u], "I2") == i1
                for u, p in users[ci])
            if not paired:
                g["carry_alone"] += 1
                lone_carries.append(name)
            # Chain legalisation: a carry-in from logic needs a feed-in cell, a carry-out read
            # by logic (a comparator's result) a feed-out cell.
            if not isinstance(ci, str) and ci is not None \
                    and cells.get(driver.get(ci), {}).get("type") != "SB_CARRY":
                g["chain"] += 1
            co = bit(cell, "CO")
            if not isinstance(co, str) and any(
                    p not in ("CI", "I3") or cells[u]["type"] not in ("SB_CARRY", "SB_LUT4")
                    for u, p in users.get(co, [])):
                g["chain"] += 1
    # ``merge_carry_luts``: a LUT of at most two inputs (on I2, I3) without a flip-flop, driving
    # a lone carry's operand, moves into the carry's cell.
    merged = set()
    for name in lone_carries:
        for port in ("I0", "I1"):
            net = bit(cells[name], port)
            src = driver.get(net) if not isinstance(net, str) else None
            if (src and src not in merged and cells[src]["type"] == "SB_LUT4" and lut_alone(src)
                    and all(bit(cells[src], p) in ("0", "x") for p in ("I0", "I1"))):
                merged.add(src)
                groups[source[src]]["lut_merged"] += 1
                break
    total = Counter()
    by_source = {}
    for name, g in groups.items():
        g["cells"] = (g["lut4"] - g["lut_merged"] + g["ff_alone"] + g["carry_alone"]
                      + g["chain"])
        if g["cells"] or g["ff"] or g["carry"]:
            by_source[name] = {k: g[k] for k in _KEYS}
            total.update(by_source[name])
    by_source = dict(sorted(by_source.items(), key=lambda kv: (-kv[1]["cells"], kv[0])))
    return {"total": {k: total[k] for k in _KEYS}, "by_source": by_source}


def report_lines(estimate, *, limit=12):
    """A table of :func:`logic_cells`' result, the largest sources first."""
    head = f"  {'source':<18}{'cells':>7}{'LUT4':>7}{'FF':>7}{'FF alone':>10}{'carry':>7}" \
           f"{'alone':>7}"
    rows = list(estimate["by_source"].items())
    shown = rows[:limit]
    lines = [head]
    for source, g in shown + [("total", estimate["total"])]:
        lines.append(f"  {source:<18}{g['cells']:>7}{g['lut4']:>7}{g['ff']:>7}"
                     f"{g['ff_alone']:>10}{g['carry']:>7}{g['carry_alone']:>7}")
    if len(rows) > limit:
        lines.insert(len(shown) + 1, f"  ({len(rows) - limit} more sources)")
    return lines
