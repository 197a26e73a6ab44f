"""Benchmark: the whole pipeline on the shared meshes and on generated sizes, one command.

    python benchmarks/run.py                  # all cases, writes benchmarks/results.{json,md}
    python benchmarks/run.py --quick          # the meshes up to ~8k vertices only
    python benchmarks/run.py --cases knight.off spot.obj --modes original-angles
    python benchmarks/run.py --no-straightforward --cases --loop-from-coarse --modes original-areas
    python benchmarks/run.py --no-straightforward --cases koala.obj armadillo.obj --limbs --append   # limbed bodies
    python benchmarks/run.py ... --max-time 1200 --on-limit project   # stop each stage at 20 min, certified

Each case runs in its own subprocess (so peak memory is per case) with a wall-clock cap; a case
that hits the cap is recorded as such, with the stage, iteration, objective and constraint violation
it had reached (a line a minute says the same while it runs). The "straightforward" rows run the paper's formulation
verbatim (faithful, linear least-squares start) on ellipsoids of 2,562 and 10,242 vertices for the
speed-up ratio against the default path. ``--loop`` adds armadillo after one Loop subdivision (172,966
vertices); ``--loop-from-coarse`` the same mesh started from armadillo's own solution in the same mode
(:mod:`sphere_nlp.hierarchy`), its row's total time including that coarse solve.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SHARED = ROOT.parent / "shared" / "meshes"

SHARED_CASES = ["knight.off", "spot.obj", "bunny.off", "max_planck.obj", "elephant.obj",
                "cheburashka.off", "hand_closed.obj", "brain_lh_pial_fsaverage5.off",
                "armadillo_remeshed.obj", "armadillo.obj", "nefertiti.obj", "penguin.obj", "koala.obj", "cat.obj",
                "human_woman.obj"]
QUICK_CASES = SHARED_CASES[:7]
# tests/meshgen.py's generated bodies (--limbs): LIMBED_BODIES, a round body with limbs of 10-30
# radii, some clawed; THIN_LIMBED_BODIES, eight legs of 20-45 radii (the larger two with a tail);
# FINGERED_BODY, many thin short protrusions beside four thick limbs. tests/test_limbs.py's slow cases.
LIMBED_CASES = ("limbs:22k", "limbs:27k", "limbs:50k", "thin:27k", "thin:31k", "thin:50k", "fingered:27k")
# UNSOLVED_LIMBED_BODIES: shapes the default mode does not map yet; run only when named.
UNSOLVED_CASES = ("unsolved:20k", "unsolved:43k")

WORKER = r"""
import json, os, sys, time, resource
import numpy as np
sys.path.insert(0, %(root)r)
import sphere_nlp
from sphere_nlp.shapes import icosphere
spec = json.loads(sys.argv[1])
mesh = spec["mesh"]
if mesh.startswith("ellipsoid:"):
    V, F = icosphere(int(mesh.split(":")[1]))
    mesh = (V * np.array([1.0, 1.6, 0.7]), F)
elif mesh.startswith(("limbs:", "thin:", "fingered:", "unsolved:")):
    sys.path.insert(0, os.path.join(%(root)r, "tests"))
    import meshgen
    kind, size = mesh.split(":", 1)
    mesh = meshgen.limbed_body(**(meshgen.FINGERED_BODY if kind == "fingered" else
                                  {"limbs": meshgen.LIMBED_BODIES, "thin": meshgen.THIN_LIMBED_BODIES,
                                   "unsolved": meshgen.UNSOLVED_LIMBED_BODIES}[kind][size]))
t0 = time.perf_counter()
# Where the run is, for the parent to report if the case hits its cap: the stages so far with their
# iteration counts and the current stage's last iteration (rewritten at most every 2 s).
seen = {"stages": [], "written": 0.0}
def progress(stage, iteration, objective, violation, elapsed):
    if not seen["stages"] or seen["stages"][-1][0] != stage or iteration < seen["stages"][-1][1]:
        seen["stages"].append([stage, 0])
    seen["stages"][-1][1] = iteration
    now = time.perf_counter()
    if now - seen["written"] >= 2.0:
        seen["written"] = now
        snapshot = {"stages": seen["stages"], "objective": objective, "violation": violation,
                    "elapsed_s": now - t0}
        with open(spec["progress_file"] + ".tmp", "w") as f:
            json.dump(snapshot, f)
        os.replace(spec["progress_file"] + ".tmp", spec["progress_file"])
start, coarse = spec.get("start"), None
# The caller's per-stage limit and what a stopped main stage yields, for every solve of the case.
limits = {"max_time": spec["max_time"], "on_limit": spec["on_limit"]}
if isinstance(mesh, str) and mesh.startswith(("loop:", "loop-from-coarse:")):
    import trimesh
    m = trimesh.load(mesh.split(":", 1)[1], process=False, force="mesh")
    if mesh.startswith("loop-from-coarse:"):
        # The hierarchy: solve the mesh itself, then start its subdivision from that solution.
        from sphere_nlp.hierarchy import prolong_to_subdivision
        # The NLP's own hierarchy: the coarse solve is the NLP alone (start "conformal").
        coarse = sphere_nlp.parameterize((m.vertices, m.faces), target=spec["mode"],
                                         formulation=spec["formulation"], check=True, start="conformal",
                                         **limits,
                                         progress=lambda stage, *a: progress("coarse " + stage, *a))
        coarse_positions = coarse.vertices[coarse.vertex_map]
    V, F = trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=1)
    mesh = (V, F)
    if coarse is not None:
        start = prolong_to_subdivision(coarse_positions, F)
r = sphere_nlp.parameterize(mesh, target=spec["mode"], formulation=spec["formulation"],
                            start=start, check=False, progress=progress, **limits)
out = r.report()
out["wall_s"] = time.perf_counter() - t0
if limits["max_time"] is not None:
    out["max_time_s"], out["on_limit"] = limits["max_time"], limits["on_limit"]
if coarse is not None:
    # The row's total is the whole job: the coarse solve, the subdivision and the fine solve.
    out["coarse"] = {"vertices": int(len(coarse.vertices)), "iterations": int(coarse.iterations),
                     "objective": float(coarse.objective), "total_s": float(coarse.timings["total"]),
                     "converged": bool(coarse.converged), "status": coarse.status}
    out["timings_s"]["fine_total"] = out["timings_s"]["total"]
    out["timings_s"]["total"] = out["wall_s"]
print("RESULT " + json.dumps(out))
"""


def read_progress(path):
    """The worker's last progress snapshot, or None (not written yet)."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def progress_text(snapshot, elapsed_s):
    """One line on where a running case is: minutes, stage, iteration, objective, violation."""
    stage, iteration = snapshot["stages"][-1]
    return "%.1f min: %s iteration %d, objective %.6g, violation %.1e" % (
        elapsed_s / 60, stage, iteration, snapshot["objective"], snapshot["violation"])


def run_case(mesh, mode, formulation, cap_s, start=None, report_every_s=60.0, max_time=None, on_limit="fail"):
    """Run one case in a subprocess; its report (dict), or a row saying it hit the cap or crashed.

    While it runs, a line every ``report_every_s`` seconds says where it is (once it has started
    iterating). ``max_time`` and ``on_limit`` are passed to :func:`sphere_nlp.parameterize` (a limit
    per IPOPT stage, and what a stopped main stage yields)."""
    with tempfile.TemporaryDirectory() as scratch:
        progress_file = os.path.join(scratch, "progress.json")
        spec = json.dumps({"mesh": mesh, "mode": mode, "formulation": formulation, "start": start,
                           "progress_file": progress_file, "max_time": max_time, "on_limit": on_limit})
        t0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, "-c", WORKER % {"root": str(ROOT)}, spec],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while True:
            left = cap_s - (time.perf_counter() - t0)
            try:
                # communicate() may be retried after a timeout without losing output.
                stdout, stderr = p.communicate(timeout=max(0.0, min(report_every_s, left)))
                break
            except subprocess.TimeoutExpired:
                snapshot, elapsed_s = read_progress(progress_file), time.perf_counter() - t0
                if elapsed_s < cap_s:
                    if snapshot:
                        print("  ... %s" % progress_text(snapshot, elapsed_s), flush=True)
                    continue
                p.kill()
                p.communicate()
                row = {"mesh": mesh, "mode": mode, "formulation": formulation, "status": "cap %d s hit" % cap_s,
                       "wall_s": time.perf_counter() - t0}
                if snapshot:
                    row["progress"] = snapshot
                return row
    line = [l for l in stdout.splitlines() if l.startswith("RESULT ")]
    if not line:
        return {"mesh": mesh, "mode": mode, "formulation": formulation, "status": "crashed",
                "error": stderr.strip().splitlines()[-1:] if stderr else "", "wall_s": time.perf_counter() - t0}
    out = json.loads(line[0][7:])
    out.update(mesh=mesh, mode=mode, formulation=formulation)
    return out


def mesh_label(mesh):
    """Short table name: the file name, 'ellipsoid:N', or 'loop:<file name>' for the subdivided case."""
    if mesh.startswith(("ellipsoid", "limbs:", "thin:", "fingered:", "unsolved:")):
        return mesh
    if mesh.startswith("loop:"):
        return "loop:" + Path(mesh[5:]).name
    if mesh.startswith("loop-from-coarse:"):
        return "loop:%s from its parent's solution" % Path(mesh.split(":", 1)[1]).name
    return Path(mesh).name


def fmt(x, spec="%.1f"):
    return "" if x is None else spec % x


def current_commit():
    """The checkout's short commit hash (with "+" when it has uncommitted changes), or "?"."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return commit + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "?"


def progress_iterations(row):
    """'>= N' for a capped case: the IPOPT iterations its stages had reached ('>= coarse + fine' if
    it was started from its parent's solution), else ''."""
    stages = row.get("progress", {}).get("stages")
    if not stages:
        return ""
    coarse = sum(iteration for stage, iteration in stages if stage.startswith("coarse "))
    fine = sum(iteration for stage, iteration in stages if not stage.startswith("coarse "))
    if any(stage.startswith("coarse ") for stage, _ in stages):
        return ">= %d + %d" % (coarse, fine)
    return ">= %d" % fine


def iterations_text(row):
    """IPOPT iterations; 'coarse + fine' for a row started from its parent's solution."""
    if "iterations" not in row:
        return progress_iterations(row)
    if "coarse" in row:
        return "%d + %d" % (row["coarse"]["iterations"], row["iterations"])
    return row["iterations"]


def previous_summary(row):
    """What a replaced row said, kept beside its re-run: iterations, total seconds, objective, commit."""
    certified = row.get("certificate", {}).get("valid")
    return {"iterations": iterations_text(row), "total_s": row.get("timings_s", {}).get("total", row.get("wall_s")),
            "objective": row.get("objective") if certified else None, "certified": bool(certified),
            "commit": row.get("commit", "?")}


def previous_text(row):
    """The previous-row cell: 'iterations, total s, objective (commit)', or 'not certified' in place of
    the objective."""
    p = row.get("previous")
    if not p:
        return ""
    objective = fmt(p["objective"], "%.6g") if p["certified"] else "not certified"
    return "%s its, %s s, %s (%s)" % (p["iterations"], fmt(p["total_s"]), objective, p["commit"])


def replace_row(rows, new):
    """``rows`` with ``new`` in place of the row of the same case (mesh, mode, formulation), whose
    summary ``new`` keeps as "previous"."""
    key = (new["mesh"], new["mode"], new["formulation"])
    old = [row for row in rows if (row["mesh"], row["mode"], row["formulation"]) == key]
    if old:
        new["previous"] = previous_summary(old[-1])
    return [row for row in rows if (row["mesh"], row["mode"], row["formulation"]) != key] + [new]


def status_text(row):
    """The status cell; a capped case also says where it was (stage, iteration, objective, violation);
    a solve stopped by its per-stage time limit and projected onto the constraints says so (and so
    does the coarse solve of a hierarchy row)."""
    route = row.get("area_route")
    if route:
        # The area modes' authalic route (sphere_nlp.polish): which map is the answer, and the polish's end.
        polish = route.get("polish") or {}
        budget = route.get("budget")
        if isinstance(budget, dict):            # counted in work (sphere_nlp.polish.default_budget)
            budget = "budget %d steps, %d polish its" % (budget["descent_steps"], budget["polish_iterations"])
        else:                                   # a wall-clock budget, as the area modes had before
            budget = "%.3g-s budget" % budget if budget else "no budget"
        if route["answer"] == "none":
            return route["reason"]
        if route.get("instead_of"):
            # An angle mode whose start cannot be placed (sphere_nlp.solve.unplaceable_start).
            return "%s route instead (its start's limbs shrink past double precision): %s" % (
                route["mode"], status_text(dict(row, area_route=dict(route, instead_of=None))))
        if route["answer"] == "polished":
            end = "optimum" if polish.get("converged") else "budget's end, projected"
            return "authalic + polish (%s, polished to IPOPT's %s)" % (budget, end)
        authalic = route.get("authalic") or {}
        # The descent's reason in words: its step budget, time, tolerance or what stopped it.
        why = {"steps": "its step budget", "time": "its time", "tolerance": "its tolerance",
               "aim": "reaching 0.03 in its extra steps"}
        reason = authalic.get("descent_stopped")
        stopped = (", descent: %d steps, stopped by %s" % (authalic["descent_steps"], why.get(reason, reason))
                   if reason else "")
        return "authalic map (%s; %s%s)" % (budget, route.get("reason"), stopped)
    status = row.get("status", "")
    stopped = []
    if row.get("coarse") and row["coarse"].get("converged") is False:
        stopped.append("coarse")
    if row.get("success") and row.get("converged") is False:
        stopped.append("fine" if row.get("coarse") else "solve")
    if stopped:
        status += " (%s stopped at the %g-s stage limit and projected: not optimal)" % (
            " and ".join(stopped), row.get("max_time_s", float("nan")))
    progress = row.get("progress")
    if progress and progress.get("stages"):
        stage, iteration = progress["stages"][-1]
        status += " (in %s at iteration %d: objective %.6g, violation %.1e)" % (
            stage, iteration, progress["objective"], progress["violation"])
    return status


def existing_note(path_md):
    """The note above the table of an earlier results file ("" if none), which an --append keeps."""
    path = Path(path_md)
    if not path.exists():
        return ""
    before_table = path.read_text().split("\n| mesh |")[0].strip().split("\n\n")
    return before_table[3] if len(before_table) > 3 else ""


# Everything below this line of a results file is written by hand (runs outside the table, such as
# the 692k mesh's) and kept by --append.
POSTSCRIPT_MARK = "<!-- Notes below are written by hand; benchmarks/run.py --append keeps them. -->"


def existing_postscript(path_md):
    """The hand-written notes below :data:`POSTSCRIPT_MARK` of an earlier results file ("" if none)."""
    path = Path(path_md)
    if not path.exists() or POSTSCRIPT_MARK not in path.read_text():
        return ""
    return path.read_text().split(POSTSCRIPT_MARK, 1)[1].strip()


def write_tables(rows, path_md, note="", postscript=""):
    """The results as one table with a short header: the machine, how the rows were made, and each
    row's commit (earlier tables are in git's history); ``postscript``, hand-written notes, below
    :data:`POSTSCRIPT_MARK`."""
    lines = ["# Benchmark results", "",
             "Machine: %s; CasADi %s, IPOPT with MUMPS. Generated by `python benchmarks/run.py`; each row "
             "is one run of the whole pipeline (load to certificate) in its own process, at the commit "
             "in its last column. Times vary by about 20%% between runs on this machine, more when other "
             "jobs share it." % (_machine(), _casadi_version()), "",
             "The distortion columns are the independent check of the written map "
             "(`sphere_nlp.metrics.usability_summary`): QC max is the worst ratio of a triangle's affine map "
             "from its 3D shape to its chord triangle, QC max vs target the same from the shape the mode asks "
             "for (its target angles) over the triangles whose targets have no corner below 1°; the equal "
             "modes regularise the input's slivers by design, which only the first charges.", ""] + (
             [note, ""] if note else []) + [
             "| mesh | vertices | mode | formulation | status | certified | iterations | solve s | total s "
             "| peak RSS MB | objective | mean angle dist ° | mean abs log area | QC max | QC max vs target "
             "| min area / mean | max angle err | commit | previous row |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r.get("timings_s", {})
        cert = r.get("certificate", {})
        # The independent check of the written map (sphere_nlp.metrics.usability_summary).
        use = r.get("usability") or {}
        lines.append("| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s |" % (
            mesh_label(r["mesh"]),
            r.get("vertices", ""), r["mode"], r["formulation"], status_text(r),
            "yes" if cert.get("valid") else "no", iterations_text(r),
            fmt(t.get("solve")), fmt(t.get("total", r.get("wall_s"))), fmt(r.get("peak_rss_mb"), "%.0f"),
            fmt(r.get("objective"), "%.6g"), fmt(use.get("mean_abs_angle_diff_deg"), "%.2f"),
            fmt(use.get("mean_abs_log_area"), "%.3f"), fmt(use.get("qc_max"), "%.3g"),
            fmt(use.get("qc_max_target"), "%.3g"),
            fmt(use.get("min_area_ratio"), "%.1e"), fmt(r.get("max_angle_error"), "%.1e"),
            r.get("commit", "?"), previous_text(r)))
    ok = [r for r in rows if r.get("certificate", {}).get("valid") and r["formulation"] == "log-chord"
          and r["mode"] == "original-angles"]
    if len(ok) >= 3:
        n = np.array([r["vertices"] for r in ok], float)
        tt = np.array([r["timings_s"]["total"] for r in ok], float)
        slope = np.polyfit(np.log(n), np.log(tt), 1)[0]
        lines += ["", "Fitted time exponent (total time ~ vertices^k over the certified original-angles runs "
                  "above; different meshes need very different iteration counts, so this mixes shape "
                  "difficulty with size): k = %.2f" % slope]
    pairs = {}
    for r in rows:
        if r["mesh"].startswith("ellipsoid"):
            pairs.setdefault(r["mesh"], {})[r["formulation"]] = r
    for mesh, p in sorted(pairs.items()):
        if "faithful" in p and "log-chord" in p:
            a = p["faithful"].get("timings_s", {}).get("total", p["faithful"].get("wall_s"))
            b = p["log-chord"].get("timings_s", {}).get("total")
            if a and b:
                capped = "cap" in str(p["faithful"].get("status"))
                lines.append("Speed-up of the default path over the straightforward formulation on %s: %s%.1fx"
                             % (mesh, ">= " if capped else "", a / b))
    if postscript:
        lines += ["", POSTSCRIPT_MARK, "", postscript]
    Path(path_md).write_text("\n".join(lines) + "\n")


def _machine():
    """Cores and memory of this machine, e.g. '2 cores, 24 GiB'."""
    try:
        gib = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30
        return "%d cores, %.0f GiB" % (os.cpu_count() or 0, gib)
    except (ValueError, OSError, AttributeError):
        return "%d cores" % (os.cpu_count() or 0)


def _casadi_version():
    try:
        import casadi
        return casadi.__version__
    except ImportError:
        return "?"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="meshes up to ~8k vertices only")
    ap.add_argument("--cases", nargs="*", help="shared mesh file names to run")
    ap.add_argument("--modes", nargs="*", default=["original-angles"])
    ap.add_argument("--cap", type=float, default=900, help="wall-clock cap per case, seconds")
    ap.add_argument("--no-straightforward", action="store_true")
    ap.add_argument("--loop", action="store_true", help="also run armadillo after one Loop subdivision (in each of --modes)")
    ap.add_argument("--loop-from-coarse", action="store_true",
                    help="also run the Loop armadillo started from armadillo's own solution (sphere_nlp.hierarchy); "
                         "its total time includes that coarse solve")
    ap.add_argument("--limbs", nargs="*", choices=LIMBED_CASES + UNSOLVED_CASES, metavar="CASE",
                    help="also run tests/meshgen.py's limbed bodies (default all: %s), in each of --modes"
                         % ", ".join(LIMBED_CASES))
    ap.add_argument("--max-time", type=float, metavar="S",
                    help="IPOPT wall-clock limit per stage, passed to sphere_nlp.parameterize (with --on-limit)")
    ap.add_argument("--on-limit", choices=("fail", "project"), default="fail",
                    help="what a main stage stopped by --max-time yields: a failure, or its last iterate projected "
                         "onto the constraints (certified, not optimal; the row says so)")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--append", action="store_true",
                    help="add rows to the existing results file (replacing rows of the same cases)")
    ap.add_argument("--note", default="", help="one line about this run's conditions, put above the table "
                                                "(--append keeps the file's note unless given)")
    ap.add_argument("--sizes", nargs="*", type=int, default=[4, 5],
                    help="icosphere subdivisions of the straightforward-vs-default ellipsoids")
    args = ap.parse_args()
    if not SHARED.is_dir():
        sys.exit("benchmarks need ../shared/meshes beside the checkout")
    cases = (QUICK_CASES if args.quick else SHARED_CASES) if args.cases is None else args.cases
    rows = json.loads(Path(args.out + ".json").read_text()) if args.append else []
    note = args.note or (existing_note(args.out + ".md") if args.append else "")
    postscript = existing_postscript(args.out + ".md") if args.append else ""
    commit = current_commit()
    jobs = [(str(SHARED / c), m, "log-chord", None) for c in cases for m in args.modes]
    if not args.no_straightforward:
        for k in args.sizes:
            jobs += [("ellipsoid:%d" % k, "original-angles", "log-chord", None),
                     ("ellipsoid:%d" % k, "original-angles", "faithful", "linear")]
    if args.limbs is not None:
        jobs += [(case, m, "log-chord", None) for case in (args.limbs or LIMBED_CASES) for m in args.modes]
    if args.loop:
        jobs += [("loop:" + str(SHARED / "armadillo.obj"), m, "log-chord", None) for m in args.modes]
    if args.loop_from_coarse:
        jobs += [("loop-from-coarse:" + str(SHARED / "armadillo.obj"), m, "log-chord", None) for m in args.modes]
    for mesh, mode, form, start in jobs:
        r = run_case(mesh, mode, form, args.cap, start, max_time=args.max_time, on_limit=args.on_limit)
        r["commit"] = commit
        # A re-run replaces the earlier row of the same case (so --append can refresh a few cases),
        # keeping what it said beside it.
        rows = replace_row(rows, r)
        print("%-40s %-16s %-10s %-28s %s s" % (mesh_label(mesh), mode, form, r.get("status"),
                                                 fmt(r.get("timings_s", {}).get("total", r.get("wall_s")))),
              flush=True)
        Path(args.out + ".json").write_text(json.dumps(rows, indent=1))
        write_tables(rows, args.out + ".md", note, postscript)


if __name__ == "__main__":
    main()
