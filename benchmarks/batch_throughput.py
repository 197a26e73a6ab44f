"""Throughput of a batch: 20 small shared meshes, one at a time, with --jobs 2, and on a local Dask cluster.

The eight small meshes of ../shared/meshes (knight, spot, bunny, max_planck, elephant, cheburashka,
hand_closed, penguin) cycled to 20, linked under distinct names into a temporary folder, mapped in
original-angles by ``sphere-nlp batch`` three ways, each into a fresh output folder:

- sequential: ``--jobs 1`` (every mesh in the batch's own process);
- ``--jobs 2``: two worker processes;
- Dask: ``--scheduler`` to a ``distributed.LocalCluster`` with 2 single-threaded worker processes.

Wall time is that of the whole command (start-up included). Appends one row per way to
benchmarks/batch_results.md (mesh count, mode, wall time, throughput, speed-up against sequential,
certified count, the load average as the run began, commit), and replaces the table of peak memory per mesh (from the sequential run's
summary) against the bound :func:`sphere_nlp.batch.memory_bound_mb` that the local scheduler plans with.

    python benchmarks/batch_throughput.py [--count 20] [--skip-dask]
"""

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "meshes"
MESHES = ("knight.off", "spot.obj", "bunny.off", "max_planck.obj", "elephant.obj", "cheburashka.off",
          "hand_closed.obj", "penguin.obj")
RESULTS = ROOT / "benchmarks" / "batch_results.md"
HEADER = ("| meshes | mode | run | wall (s) | meshes / min | speed-up | certified | load before | commit |\n"
          "|---|---|---|---|---|---|---|---|---|\n")
MEMORY_TITLE = "## Peak memory per mesh against the planning bound"


def commit():
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_batch(inputs, out, *extra):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    load = os.getloadavg()[0]
    clock = time.perf_counter()
    process = subprocess.run([sys.executable, "-m", "sphere_nlp", "batch", str(inputs), "--out", str(out),
                              "-q", *extra], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - clock
    if process.returncode not in (0, 1):
        sys.exit("batch failed (%d): %s" % (process.returncode, process.stderr.strip()))
    with open(out / "summary.csv") as handle:
        rows = list(csv.DictReader(handle))
    return wall, rows, load


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=20, help="meshes in the batch (default 20)")
    parser.add_argument("--skip-dask", action="store_true", help="leave out the Dask run")
    args = parser.parse_args()
    # The Dask scheduler runs in this process and the workers start from it: both must import this
    # checkout's sphere_nlp (Dask unpickles the task graph on the scheduler too).
    sys.path.insert(0, str(ROOT))
    os.environ["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    missing = [m for m in MESHES if not (SHARED / m).is_file()]
    if missing:
        sys.exit("shared meshes missing: %s" % ", ".join(missing))
    mode = "original-angles"
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        inputs = scratch / "in"
        inputs.mkdir()
        for i in range(args.count):
            name = MESHES[i % len(MESHES)]
            (inputs / ("%02d_%s" % (i, name))).symlink_to(SHARED / name)
        runs = []
        runs.append(("sequential", *run_batch(inputs, scratch / "sequential", "--jobs", "1")))
        sequential_rows = runs[0][2]
        runs.append(("--jobs 2", *run_batch(inputs, scratch / "jobs2", "--jobs", "2")))
        if not args.skip_dask:
            from distributed import LocalCluster

            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster:
                runs.append(("Dask LocalCluster, 2 workers",
                             *run_batch(inputs, scratch / "dask", "--scheduler", cluster.scheduler_address)))

    from sphere_nlp.batch import memory_bound_mb

    base = runs[0][1]
    lines = []
    for name, wall, rows, load in runs:
        certified = sum(r["status"].startswith("certified") for r in rows)
        lines.append("| %d | %s | %s | %.1f | %.1f | %.2f | %d/%d | %.1f | %s |"
                     % (len(rows), mode, name, wall, 60 * len(rows) / wall, base / wall, certified, len(rows),
                        load, commit()))
        print(lines[-1])
    seen, memory = set(), []
    for row in sequential_rows:
        mesh = row["mesh"].split("_", 1)[1]
        if mesh in seen or not row["peak_rss_mb"]:
            continue
        seen.add(mesh)
        vertices = int(row["vertices"])
        memory.append("| %s | %d | %.0f | %.0f |" % (mesh, vertices, float(row["peak_rss_mb"]),
                                                     memory_bound_mb(vertices, mode)))
    text = RESULTS.read_text() if RESULTS.exists() else ""
    if MEMORY_TITLE in text:
        text = text[:text.index(MEMORY_TITLE)].rstrip() + "\n"
    if not text:
        text = ("# Batch throughput\n\n`python benchmarks/batch_throughput.py`: a batch of the small shared "
                "meshes cycled to 20, mapped sequentially, with `--jobs 2` and on a local Dask cluster "
                "with 2 workers (wall time of the whole command, start-up included; speed-up against the "
                "sequential row of the same invocation; \"load before\" is the 1-minute load average as the run began, on "
                "a machine with %d cores: a load near or above that leaves the runs less than a core each).\n\n"
                % (os.cpu_count() or 1) + HEADER)
    text = text.rstrip("\n") + "\n" + "\n".join(lines) + "\n"
    text += ("\n%s\n\nPeak RSS of each mesh in the sequential run (the batch's own process, its peak reset "
             "before each mesh) against `memory_bound_mb` (%s, commit %s):\n\n| mesh | vertices | peak RSS (MB) "
             "| bound (MB) |\n|---|---|---|---|\n%s\n" % (MEMORY_TITLE, mode, commit(), "\n".join(memory)))
    RESULTS.write_text(text)
    print("wrote", RESULTS)


if __name__ == "__main__":
    main()
