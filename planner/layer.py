"""One layer: islands → perimeters, scan-line infill, thin walls and gap beads → ordered Path2D beads."""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.balance import partition_shares
from planner.nearnet import allowance_for, fits, leaning_bead, small_loop, stretched
from planner.gapfill import centre_lines, pocket_line
from planner.infill import scan_fill
from planner.ordering import join_chains, link_into_loops, order_passes, seam_at
from planner.path2d import Path2D
from planner.perimeters import perimeter_loops, split_thin
from planner.reach import lone_ends, reach_fill, run_on
from planner.regions import polygons_of
from planner.stubs import drop_short, no_stubs
from planner.thin import Widths, layout, thin_beads, wall_width


ALLOWANCE_HINT = "buildable with --machining-allowance"
Groups = list[list[Path2D]]  # an island's beads: [perimeters, infill, gaps]


@dataclass(frozen=True)
class LayerCtx:
    """What every layer of a plan shares."""

    width: float
    step: float
    perimeters: int | None
    angle0_deg: float
    widths: Widths
    lone_share: float  # profile area / (w·h): what a lone bead fills
    min_length: float
    allowance: float = 0.0  # machining allowance the islands were grown by (mm)
    min_coverage: float = 0.97  # an island covered less gets narrower legal beads where they fit
    height: float = 0.0  # layer height (mm): how far the allowance reaches to the layers around (near-net)
    min_share: float = 0.0  # the narrowest strip (mm) the cell can weld: wire at its least feed, its max speed
    support_mm: float = 0.0  # near-net: the step out a layer may take over the stock filled under it (0: none)


@dataclass
class LayerPlan:
    region: shapely.Geometry
    paths: list[Path2D]
    end: np.ndarray
    travel_mm: float
    stats: dict[str, int] = field(default_factory=dict)
    issues: list[str] = field(default_factory=list)  # underfill: for the plan's verdict
    stubs: list[str] = field(default_factory=list)  # short beads dropped (no neighbour to merge into)
    groups: list[Groups] = field(default_factory=list)  # per island: [perimeters, infill, gaps], before ordering
    # near-net: features no legal bead fills inside the grown region, built standing out of it (the
    # verdict refuses them when the plan then stands out of its grown region over the figure)
    standout: list[str] = field(default_factory=list)


def plan_layer(polys: list[Polygon], index: int, ctx: LayerCtx, pos: np.ndarray) -> LayerPlan:
    """Beads of one layer's islands, ordered island by island to keep the travel short."""
    return placed(layer_groups(polys, index, ctx), pos)


# A layer's beads before they are ordered: region, per island [perimeters, infill, gaps], stats, issues, stubs,
# features built standing out of the grown region
LayerGroups = tuple[shapely.Geometry, list[Groups], dict[str, int], list[str], list[str], list[str]]


def layer_groups(polys: list[Polygon], index: int, ctx: LayerCtx) -> LayerGroups:
    """The beads of one layer's islands and their shares, not yet ordered: all that does not
    depend on where the torch is (so layers can be planned side by side, planner.plan)."""
    region = shapely.union_all(polys) if polys else Polygon()
    angle = ctx.angle0_deg + 90.0 * (index % 2)
    stats = {"loops": 0, "regions": 0}
    issues: list[str] = []
    stubs: list[str] = []
    standout: list[str] = []
    per_island = []
    for poly in polys:
        groups = _island(poly, index, angle, ctx, stats, (issues, standout))
        groups[2] = lone_ends(groups[2], poly, ctx.min_coverage, ctx.allowance)
        groups[2] += reach_fill(poly, [b for g in groups for b in g], ctx.widths, ctx.min_coverage, ctx.min_length,
                                ctx.allowance)
        groups[2] = run_on(groups[2], poly, ctx.min_length, ctx.allowance)
        groups = no_stubs(groups, ctx.min_length, poly, index, stubs, 1.5 * ctx.width)
        # two stubs welded together can still be short: dropped before the shares are drawn
        groups = [drop_short(g, ctx.min_length, index, stubs) for g in groups]
        if not any(groups):  # near-net: a small island gets one loop standing out into its stock
            loop = small_loop(poly, ctx.widths, ctx.allowance, ctx.min_length)
            groups[0] += [seam_at(loop, index)] if loop is not None else []
            standout += [_looped(poly, index, ctx.min_length)] if loop is not None else []
        if not any(groups) and poly.area > 0.05 * ctx.width ** 2:
            c = poly.representative_point()
            b = poly.bounds
            issues.append(f"layer {index}: feature at ({c.x:.1f}, {c.y:.1f}), {b[2] - b[0]:.2f} x {b[3] - b[1]:.2f} mm, "
                          f"gets no bead of at least {ctx.min_length:.1f} mm (min_bead_length_mm)")
        _balance_island(groups, poly, ctx.width, ctx.widths.lo, ctx.min_share, stubs, index)
        per_island.append(groups)
    return region, per_island, stats, issues, stubs, standout


def placed(lg: LayerGroups, pos: np.ndarray) -> LayerPlan:
    """The layer's beads ordered from where the torch is, island by island."""
    region, per_island, stats, issues, stubs, standout = lg
    ordered, end, travel = order_islands(per_island, pos)
    return LayerPlan(region, ordered, end, travel, stats, issues, stubs, per_island, standout)


def _island(poly: Polygon, index: int, angle: float, ctx: LayerCtx, stats: dict[str, int],
            notes: tuple[list[str], list[str]]) -> Groups:
    """An island's beads; `notes`: (features no legal bead fills, features built standing out of the grown region)."""
    w = ctx.width
    thick, thin = split_thin(poly, w)
    if ctx.allowance > 0.0 and thick and thin:
        thick, thin = _rejoined(thick, thin, w)
    # A piece narrower than two perimeters a side (w + 3 d*) gets the thin layout too: perimeters
    # there would leave a groove or a sliver loop lying on itself between them.
    narrow = [t.buffer(-0.5 * (w + 3 * ctx.step)).is_empty for t in thick]
    thin += [t for t, n in zip(thick, narrow) if n]
    groups: list[list[Path2D]] = [[], [], []]
    for t, n in zip(thick, narrow):
        if not n:
            _thick(t, index, angle, ctx, groups, stats)
    for t in thin:
        _thin(t, poly, index, ctx, groups, stats, notes)
    return groups


def _rejoined(thick: list[Polygon], thin: list[Polygon], w: float) -> tuple[list[Polygon], list[Polygon]]:
    """Near-net: thin pieces smaller than a bead's footprint that the split cut off a thick piece
    (the corner of a lobe the grown region fused on) go back to it: its loops then run round them,
    standing out into the stock where they must, instead of leaving them to no bead (issue 40)."""
    small = [t for t in thin if t.area < 0.25 * np.pi * w * w and any(t.distance(k) < 1e-6 for k in thick)]
    if not small:
        return thick, thin
    # slivers the union leaves (1e-7 mm²: the tray at 4 mm named one "0.00 mm wide") are no piece, as in split_thin
    joined = [p for p in polygons_of(shapely.union_all([*thick, *small]).buffer(0)) if p.area > 0.05 * w * w]
    return joined, [t for t in thin if not any(t is s for s in small)]


def _thin(t: Polygon, island: Polygon, index: int, ctx: LayerCtx, groups: Groups, stats: dict[str, int],
          notes: tuple[list[str], list[str]]) -> None:
    """A thin piece: its width from the process (planner.thin), or an issue naming it."""
    issues, standout = notes
    W = wall_width(t, 0.02 * ctx.width)
    if not fits(W, ctx.widths):  # near-net: widened into the stock where that builds it
        wider = stretched(t, W, ctx.widths, ctx.allowance)
        if wider is not None:
            standout.append(_stood_out(t, index, W, wider[1], ctx))
            t, W = wider
        elif (bead := leaning_bead(t, island, ctx.widths, ctx.allowance)) is not None:
            standout.append(_stood_out(t, index, W, bead.width_mm, ctx))
            stats["regions"] += 1
            groups[2].append(bead)
            return
    lay = layout(W, ctx.widths)
    c = t.representative_point()
    if lay is None:
        issues.append(f"layer {index}: feature at ({c.x:.1f}, {c.y:.1f}) is {W:.2f} mm wide, narrower than "
                      f"the smallest legal bead ({ctx.widths.lo:.2f} mm)" + _hint(W, ctx))
        return
    beads, wide = thin_beads(t, lay, ctx.lone_share, ctx.widths, W)
    if wide or (lay.n > 1 and lay.filled < 0.97 * W):
        Wn = max(wide, default=W)
        issues.append(f"layer {index}: wall at ({c.x:.1f}, {c.y:.1f}) is {Wn:.2f} mm wide: no count of legal "
                      f"beads ({ctx.widths.lo:.2f}-{ctx.widths.hi:.2f} mm) fills it; {ctx.widths.hi:.2f} mm filled"
                      + _hint(Wn, ctx))
    stats["regions"] += sum(1 for b in beads if not b.closed) or bool(beads)
    stats["loops"] += sum(1 for b in beads if b.closed)
    groups[0] += [seam_at(b, index) if b.closed else b for b in beads if b.role == "perimeter"]
    groups[2] += [seam_at(b, index) if b.closed else b for b in beads if b.role != "perimeter"]


def _stood_out(t: Polygon, index: int, W: float, built: float, ctx: LayerCtx) -> str:
    """Near-net: a thin piece of the grown region no legal bead layout fills, built `built` mm wide
    standing out of it; with the allowance that builds it inside the grown region."""
    c = t.representative_point()
    wd = ctx.widths
    why = (f"narrower than the smallest legal bead ({wd.lo:.2f} mm)" if W < wd.lo else
           f"no count of legal beads ({wd.lo:.2f}-{wd.hi:.2f} mm) fills it")
    return (f"layer {index}: feature at ({c.x:.1f}, {c.y:.1f}) is {W:.2f} mm wide in the grown region, {why}: "
            f"built {built:.2f} mm wide, standing out of it" + _hint(W, ctx))


def _looped(island: Polygon, index: int, min_length: float) -> str:
    """Near-net: an island no bead of the minimum length fits in, built as one loop standing out of it."""
    c = island.representative_point()
    b = island.bounds
    return (f"layer {index}: feature at ({c.x:.1f}, {c.y:.1f}), {b[2] - b[0]:.2f} x {b[3] - b[1]:.2f} mm grown, "
            f"gets no bead of at least {min_length:.1f} mm inside the grown region: built as one loop standing out of it")


def _hint(W: float, ctx: LayerCtx) -> str:
    """What machining allowance would make a refused feature buildable (near-net, docs/contract.md §3.9):
    `W` wide at the plan's allowance, the allowance at which a legal bead layout fills it inside the
    grown region (standing out of it, the plan may stand out over the figure: planner.verdict)."""
    extra = allowance_for(W, ctx.widths, 2.0 * ctx.width)
    if extra is None:
        return ""
    return f" ({ALLOWANCE_HINT} {ctx.allowance + extra:.2f} mm)"


def _thick(t: Polygon, index: int, angle: float, ctx: LayerCtx, groups: Groups, stats: dict[str, int]) -> None:
    w, step = ctx.width, ctx.step
    min_sp = ctx.widths.r_lo * w
    slivers: list[Polygon] = []
    if ctx.perimeters == 0:
        loops: list[list[Path2D]] = []
        inset = 0.5 * w - step  # infill centres from half a bead inside
    else:
        loops, inset, slivers = perimeter_loops(t, w, step, ctx.perimeters, min_spacing=min_sp, min_length=ctx.min_length)
    stats["loops"] += sum(len(lv) for lv in loops)
    gaps: list[Path2D] = []
    for s in slivers:  # where loops meet (Fang): one centre line instead of a loop on itself
        gaps += [Path2D("gap", b.points, w, b.closed, step) for b in centre_lines(s.buffer(0.25 * step), w)]
    filled: list[Path2D] = []
    if loops or ctx.perimeters == 0:
        # Ding 2015: the first scan row d* from the last perimeter, the rows d* apart.
        infill_region = t.buffer(-(inset + step))
        stats["regions"] += len(polygons_of(infill_region))
        chains = scan_fill(infill_region, step, w, angle, min_sp) if not infill_region.is_empty else []
        filled = list(chains)
        if len(chains) > 1:
            chains = join_chains(chains, 2.5 * step, t.buffer(-inset + 0.1 * step))
        inner, chains = _linked(loops[-1] if loops else [], chains, 2.0 * step)
        outer = [lp for lv in loops[:-1] for lp in lv]
        groups[0] += [seam_at(lp, index) if lp.closed else lp for lp in outer + inner]
        groups[1] += chains
        rest = t.buffer(-(inset + 0.5 * w))
    else:
        rest = t
    gaps += _pockets(rest, filled + gaps, w, stats)
    stats["regions"] += len(gaps) and 1
    groups[2] += [seam_at(b, index) if b.closed else b for b in gaps]


def _linked(loops: list[Path2D], chains: list[Path2D], reach: float) -> tuple[list[Path2D], list[Path2D]]:
    """The innermost loops continued into the infill chains (planner.ordering.link_into_loops); a ring
    trimmed at Ding's spacing (open beads, planner.ring_spacing) is no loop to link into."""
    inner, chains = link_into_loops([lp for lp in loops if lp.closed], chains, reach)
    return inner + [lp for lp in loops if not lp.closed], chains


def _pockets(rest: shapely.Geometry, reach: list[Path2D], w: float, stats: dict[str, int]) -> list[Path2D]:
    """Centre-line gap beads for what neither the perimeters nor the scan lines reach."""
    if reach and not rest.is_empty:
        lines = np.array([shapely.linestrings(c.points) for c in reach], dtype=object)
        rest = rest.difference(shapely.union_all(shapely.buffer(lines, 0.5 * w, quad_segs=4)))
    out: list[Path2D] = []
    for piece in polygons_of(rest):
        if piece.area > 0.2 * w * w:
            # A small pocket (a lune at a row's end) is nearly straight: no medial axis needed.
            small = piece.area < 2.0 * w * w and len(piece.interiors) == 0
            beads = pocket_line(piece, w, 0.2 * w) if small else centre_lines(piece, w, min_width=0.2 * w)
            stats["regions"] += bool(beads)
            out += beads
    return out


def _balance_island(groups: list[list[Path2D]], poly: Polygon, width: float, narrowest: float,
                    min_share: float = 0.0, dropped: list[str] | None = None, index: int = 0) -> None:
    """Each bead's share: the part of the island nearest to it (planner.balance.partition_shares),
    so the island's beads lay its area × h exactly, lone beads their wall's whole section.

    A gap bead left less than a quarter of its width (at least the narrowest legal bead's: it is
    welded at least that wide) lies on its neighbours: there is nothing for it to fill and the cell
    could not weld so little; it is removed and the island shared again. So is any other bead left a
    share under `min_share` — less metal a mm than the cell lays at its fastest with the least wire
    feed (issue 40: a Fang sliver loop would need 9,402 mm/min) — when its neighbours cover it;
    it is named in `dropped`.
    """
    for attempt in range(3):
        beads = [b for g in groups for b in g]
        if not beads:
            return
        shares = partition_shares(poly, beads, width).tolist()
        idle = {id(b) for b, s in zip(beads, shares) if b.role == "gap" and s < 0.25 * max(b.width_mm, narrowest)}
        weak = _unweldable(beads, shares, min_share, idle)
        idle |= set(weak)
        if not idle or len(idle) == len(beads) or attempt == 2:
            break
        for b, s in zip(beads, shares):
            if id(b) in weak and dropped is not None:
                c = b.points.mean(axis=0)
                dropped.append(f"layer {index}: {b.role} bead at ({c[0]:.1f}, {c[1]:.1f}) of {b.length:.1f} mm dropped: "
                               f"its {s:.2f} mm share is less metal than the cell lays at its max speed "
                               f"({min_share:.2f} mm), and {weak[id(b)]}")
        for g in groups:
            g[:] = [b for b in g if id(b) not in idle]
    it = iter(shares)
    for g in groups:
        g[:] = [Path2D(b.role, b.points, b.width_mm, b.closed, next(it), b.lone) for b in g]


def _unweldable(beads: list[Path2D], shares: list[float], min_share: float, idle: set[int]) -> dict[int, str]:
    """Beads whose share is under what the cell can weld, with why dropping them is safe: the others
    cover their footprint (95 %), or they are gap beads (a pocket's centre line, an extra bead of
    variable width), whose small share the island's next partition gives to their neighbours
    (issue 40 item 2: the box at 4 mm was refused for one needing 6,308 mm/min)."""
    # a lone bead under it is no single-bead wall (that fills its wall's whole section) but one leaning
    # on the rest of its island (planner.nearnet.leaning_bead): a gap bead like the others
    low = [i for i, (b, s) in enumerate(zip(beads, shares)) if s < min_share and id(b) not in idle]
    if not low or len(low) == len(beads):
        return {}
    fps = shapely.buffer(np.array([shapely.linestrings(b.points) for b in beads], dtype=object),
                         np.array([0.5 * b.width_mm for b in beads]), quad_segs=4)
    tree = shapely.STRtree(fps)
    out: dict[int, str] = {}
    for i in low:
        near = [j for j in tree.query(fps[i]) if j != i and id(beads[j]) not in out.keys() | idle]
        others = shapely.union_all(fps[near]) if near else shapely.Polygon()
        if shapely.area(shapely.difference(fps[i], others)) <= 0.05 * shapely.area(fps[i]):
            out[id(beads[i])] = "its neighbours cover it"
        elif beads[i].role == "gap":
            out[id(beads[i])] = "its section goes to its neighbours"
    return out


def reseamed(lp: LayerPlan, index: int, pos: np.ndarray) -> LayerPlan:
    """The same layer plan for another layer index: seams moved on, beads ordered from `pos`."""
    groups = [[[seam_at(p, index) if p.closed else p for p in g] for g in isl] for isl in lp.groups]
    ordered, end, travel = order_islands(groups, pos)
    tag = f"layer {index}:"
    return replace(lp, paths=ordered, end=end, travel_mm=travel, groups=groups,
                   issues=[re.sub(r"^layer \d+:", tag, m) for m in lp.issues],
                   stubs=[re.sub(r"^layer \d+:", tag, m) for m in lp.stubs],
                   standout=[re.sub(r"^layer \d+:", tag, m) for m in lp.standout])


def _nearest_end(ends: np.ndarray, pos: np.ndarray) -> float:
    return float(np.min(np.hypot(*(ends - pos).T))) if len(ends) else float("inf")


def order_islands(per_island: list[Groups], pos: np.ndarray) -> tuple[list[Path2D], np.ndarray, float]:
    """Islands nearest first from `pos`, each ordered by `order_passes`; (beads, end, travel)."""
    ordered: list[Path2D] = []
    travel = 0.0
    todo = list(range(len(per_island)))
    ends = [np.array([p.points[k] for g in isl for p in g for k in (0, -1)]).reshape(-1, 2) for isl in per_island]
    while todo:
        # Next island: the one whose nearest bead end is closest to where the torch is.
        i = min(todo, key=lambda k: _nearest_end(ends[k], pos))
        todo.remove(i)
        seq, end = order_passes(per_island[i], pos)
        for p in seq:
            travel += float(np.hypot(*(p.points[0] - pos)))
            pos = p.points[-1]
        ordered += seq
        pos = end
    return ordered, pos, travel
