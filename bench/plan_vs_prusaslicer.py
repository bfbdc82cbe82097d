"""`cell plan` against PrusaSlicer 2.5, wall time of the whole command each (same mesh, layer
height, width, 2 perimeters, full infill): the bench.plan_quality part set (target <= 1.0x on
every part) and icospheres of radius 50 mm at 2 mm layers, 6 mm beads (target <= 0.5x at 1.3M
faces, peak memory <= 1.2x PrusaSlicer's); and our growth with face count. Overhangs and
underfill are allowed in both (PrusaSlicer plans them silently): the comparison is of speed.

Each figure is the median of `--repeat` runs (default 3), ours and PrusaSlicer's alternating, so
both see the same load on a shared machine; peak memory is each process's maxrss (GNU time). The
project's modules are byte-compiled first (as an install does): a plan does not pay for it.

Also (issue 40): `--real DIR` adds the real parts bench.plan_quality knows (trimesh's models, in mm, at 4 and
8 mm beads) and `--torus` a 2.2M-face torus (the 1.3M-face target's second part).

Run: .venv/bin/python -m bench.plan_vs_prusaslicer [--quick] [--no-install] [--set-only] [--repeat N]
     [--real DIR] [--torus] [--only-extra] [--only NAME,NAME] [--no-ff-too] [--prusa-only]

`--prusa-only` times PrusaSlicer alone on the real parts (`--repeat` runs each, their least and median
wall time): which parts it takes 1 s or more on, the parts the <= 1.0x target applies to.
"""
from __future__ import annotations

import argparse
import compileall
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import trimesh

SIZES = {5: 20_480, 7: 327_680, 8: 1_310_720}  # icosphere subdivisions -> faces
RADIUS = 50.0
LAYER = 2.0
WIDTH = 6.0


def _prusa() -> str | None:
    for name in ("prusa-slicer", "PrusaSlicer", "prusa-slicer-console"):
        exe = shutil.which(name)
        if exe:
            return exe
    return None


def _install_prusa() -> str | None:
    """apt-get the Debian package when it is missing (root only); None when it cannot be had."""
    if _prusa() or shutil.which("apt-get") is None:
        return _prusa()
    print("PrusaSlicer missing: apt-get install -y prusa-slicer ...", flush=True)
    env = {"DEBIAN_FRONTEND": "noninteractive", "PATH": "/usr/sbin:/usr/bin:/sbin:/bin"}
    try:
        subprocess.run(["apt-get", "update", "-qq"], check=False, env=env, capture_output=True, timeout=600)
        subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends", "prusa-slicer"],
                       check=False, env=env, capture_output=True, timeout=1800)
    except (OSError, subprocess.TimeoutExpired) as exc:
        print(f"  could not install: {exc}")
    return _prusa()


ROOT = Path(__file__).resolve().parent.parent


def _timed(cmd: list[str], cwd: Path) -> tuple[float, int, int, str, float]:
    """(wall s, peak RSS kB or 0, exit status, stdout + stderr, CPU s: user + system) of one command.

    The peak and the CPU time are GNU time's (/usr/bin/time -f): a child's own maxrss from wait4 would
    start at this bench's size (Linux carries the forked copy's high-water mark over exec). On a shared
    machine the wall time is the CPU time plus the waiting for a core: both are reported."""
    gnu_time = shutil.which("time", path="/usr/bin:/bin")
    with tempfile.TemporaryDirectory() as tmp:
        peak = Path(tmp) / "peak"
        run = [gnu_time, "-f", "%M %U %S", "-o", str(peak), *cmd] if gnu_time else cmd
        t0 = time.perf_counter()
        proc = subprocess.run(run, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        wall = time.perf_counter() - t0
        lines = peak.read_text().split() if peak.exists() else []
        ok = len(lines) >= 3 and lines[-3].isdigit()
        kb, cpu = (int(lines[-3]), float(lines[-2]) + float(lines[-1])) if ok else (0, 0.0)
        return wall, kb, proc.returncode, proc.stdout.decode(errors="replace"), cpu


def _ours_cmd(stl: Path, work: Path, width: float, layer: float, feed_forward: bool = True) -> list[str]:
    return [sys.executable, "-m", "controller.cli.main", "plan", str(stl), "--width", str(width),
            "--layer-height", str(layer), "--perimeters", "2", "--material", "inconel718-1.0mm",
            "--allow-outside", "--allow-underfill", "--allow-overhang",
            "--out", str(work / (stl.stem + ".job.json")), "--json", *([] if feed_forward else ["--no-feed-forward"])]


def _prusa_cmd(exe: str, stl: Path, work: Path, width: float, layer: float) -> list[str]:
    return [exe, "--export-gcode", "--layer-height", str(layer), "--first-layer-height", str(layer),
            "--nozzle-diameter", str(width), "--extrusion-width", str(width), "--perimeters", "2",
            "--fill-density", "100%", "--fill-pattern", "rectilinear", "--top-fill-pattern", "rectilinear",
            "--bottom-fill-pattern", "rectilinear", "--max-layer-height", str(layer), "--skirts", "0",
            "--center", "100,100", "--output", str(work / (stl.stem + ".gcode")), str(stl)]


class Figures:
    """Median wall time and peak memory of each side over alternating runs."""

    def __init__(self) -> None:
        self.wall: dict[str, list[float]] = {"ours": [], "prusa": [], "noff": []}
        self.rss: dict[str, list[int]] = {"ours": [], "prusa": [], "noff": []}
        self.cpu_s: dict[str, list[float]] = {"ours": [], "prusa": [], "noff": []}
        self.summary = ""
        self.prusa_error = ""

    def t(self, side: str) -> float:
        return statistics.median(self.wall[side])

    def cpu(self, side: str) -> float:
        return statistics.median(self.cpu_s[side])

    def mb(self, side: str) -> float:
        return statistics.median(self.rss[side]) / 1024.0


def compare(stl: Path, work: Path, exe: str | None, repeat: int, width: float = WIDTH, layer: float = LAYER,
            no_ff: bool = False) -> Figures:
    """`repeat` runs of `cell plan` and of PrusaSlicer on `stl`, alternating (`no_ff`: and of `cell plan
    --no-feed-forward`, the planner without issue 35's feed-forward)."""
    fig = Figures()
    for _ in range(repeat):
        if no_ff:
            wall, rss, code, out, cpu = _timed(_ours_cmd(stl, work, width, layer, feed_forward=False), ROOT)
            if code == 0:
                fig.wall["noff"].append(wall)
                fig.rss["noff"].append(rss)
                fig.cpu_s["noff"].append(cpu)
        wall, rss, code, out, cpu = _timed(_ours_cmd(stl, work, width, layer), ROOT)
        if code != 0:
            raise RuntimeError(f"cell plan failed: {out.strip()[-300:]}")
        fig.wall["ours"].append(wall)
        fig.rss["ours"].append(rss)
        fig.cpu_s["ours"].append(cpu)
        fig.summary = out.strip().splitlines()[-1]
        if exe is not None and not fig.prusa_error:
            wall, rss, code, out, cpu = _timed(_prusa_cmd(exe, stl, work, width, layer), work)
            if code != 0:
                fig.prusa_error = f"prusa-slicer failed ({code}): {out.strip().splitlines()[-1][-200:]}"
                continue
            fig.wall["prusa"].append(wall)
            fig.rss["prusa"].append(rss)
            fig.cpu_s["prusa"].append(cpu)
    return fig


def part_set(exe: str | None, work: Path, repeat: int, quick: bool) -> bool:
    """The bench.plan_quality parts at 6 mm beads and the process model's layer height."""
    # lazy: only this benchmark's path needs it
    from bench.plan_quality import parts
    from core.config import load_material
    from planner.process import inverse

    mat = load_material("inconel718-1.0mm")
    ok = True
    for name, mesh in parts(quick):
        width = 6.0
        layer = round(inverse(mat, width).height_mm, 4)
        stl = work / ("part-" + "".join(c if c.isalnum() else "_" for c in name) + ".stl")
        stl.write_bytes(mesh.export(file_type="stl"))
        fig = compare(stl, work, exe, repeat, width, layer)
        line = f"{name:28s} {len(mesh.faces):>7,} faces: cell plan {fig.t('ours'):5.2f} s"
        if fig.wall["prusa"]:
            ratio = fig.t("ours") / fig.t("prusa")
            ok = ok and ratio <= 1.0
            line += f" | prusa-slicer {fig.t('prusa'):5.2f} s | ratio {ratio:4.2f} {'ok' if ratio <= 1.0 else 'MISSED'}"
        print(line + (f" | {fig.prusa_error}" if fig.prusa_error else ""), flush=True)
    return ok


TORUS = (40.0, 10.0, 1536, 720)  # major, minor radius (mm), sections: 2,211,840 faces


def _verdict(fig: Figures, faces: int) -> tuple[str, bool]:
    """The targets of issue 40: <= 0.5x PrusaSlicer's wall time and <= 1.2x its memory at 1.3M faces and
    above; <= 1.0x where PrusaSlicer takes 1 s or more; none below that."""
    if not fig.wall["prusa"]:
        return "", True
    ratio, mem = fig.t("ours") / fig.t("prusa"), fig.mb("ours") / fig.mb("prusa")
    line = (f" | prusa-slicer {fig.t('prusa'):6.2f} s (cpu {fig.cpu('prusa'):6.2f}) {fig.mb('prusa'):5.0f} MB | ratio "
            f"{ratio:4.2f} (cpu {fig.cpu('ours') / max(fig.cpu('prusa'), 1e-3):4.2f}), memory {mem:4.2f}")
    if faces >= 1_300_000:
        ok = ratio <= 0.5 and mem <= 1.2
        return line + f" (target <= 0.5, <= 1.2: {'met' if ok else 'MISSED'})", ok
    if fig.t("prusa") >= 1.0:
        ok = ratio <= 1.0
        return line + f" (target <= 1.0: {'met' if ok else 'MISSED'})", ok
    return line, True


def extra(exe: str | None, work: Path, repeat: int, dirs: list[str], torus: bool, no_ff: bool = False,
          only: str = "") -> bool:
    """The real parts at 4 and 8 mm beads and the 2.2M-face torus at 6 mm, against PrusaSlicer."""
    # lazy: only this benchmark's path needs them
    from core.config import load_material
    from planner.process import inverse

    mat = load_material("inconel718-1.0mm")
    runs = _runs(dirs, only)
    if torus:
        R, r, a, b = TORUS
        runs.append(("torus", trimesh.creation.torus(major_radius=R, minor_radius=r, major_sections=a, minor_sections=b),
                     WIDTH))
    ok = True
    for name, mesh, width in runs:
        layer = round(inverse(mat, width).height_mm, 4)
        stl = work / ("x-" + "".join(c if c.isalnum() else "_" for c in name) + f"-{width:g}.stl")
        stl.write_bytes(mesh.export(file_type="stl"))
        fig = compare(stl, work, exe, repeat, width, layer, no_ff)
        verdict, good = _verdict(fig, len(mesh.faces))
        ok = ok and good
        print(f"{name:28s} {width:3g} mm {len(mesh.faces):>9,} faces: cell plan {fig.t('ours'):6.2f} s (cpu "
              f"{fig.cpu('ours'):6.2f}) {fig.mb('ours'):5.0f} MB{verdict}" + (f" | {fig.prusa_error}" if fig.prusa_error else ""), flush=True)
        if fig.wall["noff"]:
            base = f" | ratio {fig.t('noff') / fig.t('prusa'):4.2f} (cpu {fig.cpu('noff') / max(fig.cpu('prusa'), 1e-3):4.2f})" \
                if fig.wall["prusa"] else ""
            print(f"{'':28s} without the feed-forward: {fig.t('noff'):6.2f} s (cpu {fig.cpu('noff'):6.2f}) "
                  f"{fig.mb('noff'):5.0f} MB{base}", flush=True)
        del mesh
    return ok


def _runs(dirs: list[str], only: str) -> list[tuple[str, trimesh.Trimesh, float]]:
    # lazy: only this benchmark's path needs it
    from bench.plan_quality import real_parts

    return [(n, m, w) for n, m in real_parts(dirs) for w in (4.0, 8.0) if any(o in n for o in only.split(","))]


def prusa_survey(exe: str, work: Path, repeat: int, dirs: list[str], only: str) -> None:
    """PrusaSlicer alone on each real part: least and median wall (and CPU) time of `repeat` runs."""
    # lazy: only this benchmark's path needs them
    from core.config import load_material
    from planner.process import inverse

    mat = load_material("inconel718-1.0mm")
    for name, mesh, width in _runs(dirs, only):
        layer = round(inverse(mat, width).height_mm, 4)
        stl = work / ("p-" + "".join(c if c.isalnum() else "_" for c in name) + f"-{width:g}.stl")
        stl.write_bytes(mesh.export(file_type="stl"))
        walls, cpus, err = [], [], ""
        for _ in range(repeat):
            wall, _kb, code, out, cpu = _timed(_prusa_cmd(exe, stl, work, width, layer), work)
            if code != 0:
                err = out.strip().splitlines()[-1][-120:] if out.strip() else f"exit {code}"
                break
            walls.append(wall)
            cpus.append(cpu)
        if err:
            print(f"{name:28s} {width:3g} mm: prusa-slicer failed: {err}", flush=True)
            continue
        med = statistics.median(walls)
        print(f"{name:28s} {width:3g} mm {len(mesh.faces):>9,} faces: prusa-slicer wall min {min(walls):6.2f} s median "
              f"{med:6.2f} s, cpu median {statistics.median(cpus):6.2f} s, load {os.getloadavg()[0]:.1f} | "
              f"{'>= 1 s: target <= 1.0x' if min(walls) >= 1.0 else '< 1 s: no target'}", flush=True)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.plan_vs_prusaslicer")
    ap.add_argument("--quick", action="store_true", help="20k and 327k faces only, one run each")
    ap.add_argument("--no-install", action="store_true", help="do not apt-get PrusaSlicer when missing")
    ap.add_argument("--repeat", type=int, default=None,
                    help="alternating runs per part (the median is kept; default 3, quick 1)")
    ap.add_argument("--set-only", action="store_true", help="the part set only, no icospheres")
    ap.add_argument("--real", action="append", default=[], help="a directory of real parts (bench.plan_quality)")
    ap.add_argument("--torus", action="store_true", help="a 2.2M-face torus too")
    ap.add_argument("--only-extra", action="store_true", help="the real parts and the torus only")
    ap.add_argument("--only", default="", help="real parts whose name holds one of these (comma separated)")
    ap.add_argument("--no-ff-too", action="store_true",
                    help="also time the real parts with --no-feed-forward (issue 35's feed-forward left out)")
    ap.add_argument("--prusa-only", action="store_true", help="time PrusaSlicer alone on the real parts")
    args = ap.parse_args(argv)
    repeat = args.repeat or (1 if args.quick else 3)
    if args.prusa_only:
        exe = _prusa()
        if exe is None:
            print("PrusaSlicer is not installed")
            return 1
        with tempfile.TemporaryDirectory(prefix="bench-prusa-") as tmp:
            prusa_survey(exe, Path(tmp), repeat, args.real, args.only)
        return 0
    for pkg in ("core", "planner", "controller"):  # as installed: no module compiled during a timed run
        compileall.compile_dir(str(ROOT / pkg), quiet=1)
    subs = [5, 7] if args.quick else [5, 7, 8]
    exe = _prusa() if args.no_install else _install_prusa()
    if exe is None:
        print("PrusaSlicer 2.5 is not available (apt-get install prusa-slicer failed or not allowed): "
              "reporting our times only")
    ours: dict[int, float] = {}
    theirs: dict[int, float] = {}
    with tempfile.TemporaryDirectory(prefix="bench-plan-") as tmp:
        work = Path(tmp)
        extra_ok = extra(exe, work, repeat, args.real, args.torus, args.no_ff_too, args.only)
        if args.only_extra:
            return 0 if extra_ok else 1
        set_ok = part_set(exe, work, repeat, args.quick) and extra_ok
        print(f"target on every part of the set: <= 1.0x PrusaSlicer: {'met' if set_ok else 'MISSED'}")
        if args.set_only:
            return 0 if set_ok else 1
        mem = icospheres(exe, work, subs, repeat, ours, theirs)
    return 0 if set_ok and growth_verdicts(subs, ours, theirs) and mem else 1


def icospheres(exe: str | None, work: Path, subs: list[int], repeat: int, ours: dict[int, float],
               theirs: dict[int, float]) -> bool:
    """Icospheres of growing face count: our wall time (and PrusaSlicer's) into `ours` / `theirs`;
    True unless the peak memory at 1.3M faces is over 1.2x PrusaSlicer's."""
    ok = True
    for sub in subs:
        stl = work / f"icosphere{sub}.stl"
        stl.write_bytes(trimesh.creation.icosphere(subdivisions=sub, radius=RADIUS).export(file_type="stl"))
        fig = compare(stl, work, exe, repeat)
        ours[sub] = fig.t("ours")
        line = f"{SIZES[sub]:>9,} faces: cell plan {fig.t('ours'):6.2f} s (cpu {fig.cpu('ours'):6.2f}) {fig.mb('ours'):5.0f} MB"
        if fig.wall["prusa"]:
            theirs[sub] = fig.t("prusa")
            line += (f" | prusa-slicer {fig.t('prusa'):6.2f} s (cpu {fig.cpu('prusa'):6.2f}) {fig.mb('prusa'):5.0f} MB | ratio "
                     f"{ours[sub] / theirs[sub]:4.2f} (cpu {fig.cpu('ours') / max(fig.cpu('prusa'), 1e-3):4.2f}), memory "
                     f"{fig.mb('ours') / fig.mb('prusa'):4.2f}")
            if sub == 8:
                ok = fig.mb("ours") <= 1.2 * fig.mb("prusa")
                line += f" (target <= 1.2: {'met' if ok else 'MISSED'})"
        print(line + (f" | {fig.prusa_error}" if fig.prusa_error else ""), flush=True)
        if sub == 7:
            print(f"    summary: {fig.summary}")
    return ok


def growth_verdicts(subs: list[int], ours: dict[int, float], theirs: dict[int, float]) -> bool:
    """Print the growth exponent and the targets at 327k / 1.3M faces; True when all are met."""
    for a, b in zip(subs, subs[1:]):
        e = math.log(ours[b] / ours[a]) / math.log(SIZES[b] / SIZES[a])
        print(f"  {SIZES[a]:,} -> {SIZES[b]:,} faces: x{SIZES[b] / SIZES[a]:.0f} faces, x{ours[b] / ours[a]:.2f} time "
              f"(exponent {e:.2f})")
    first, last = subs[0], subs[-1]
    growth = math.log(ours[last] / ours[first]) / math.log(SIZES[last] / SIZES[first])
    print(f"growth exponent of our wall time in faces ({SIZES[first]:,} -> {SIZES[last]:,}): {growth:.2f} "
          f"(1.0 = linear; target <= 1)")
    ok = growth <= 1.0
    if 7 in theirs:
        verdict = ours[7] <= theirs[7]
        print(f"target at 327,680 faces: ours {ours[7]:.2f} s <= PrusaSlicer {theirs[7]:.2f} s: "
              f"{'met' if verdict else 'MISSED'}")
        ok = ok and verdict
    if 8 in theirs:
        verdict = ours[8] <= 0.5 * theirs[8]
        print(f"target at 1,310,720 faces: ours {ours[8]:.2f} s <= 0.5 x PrusaSlicer {theirs[8]:.2f} s: "
              f"{'met' if verdict else 'MISSED'}")
        ok = ok and verdict
    return ok


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
