"""Map a whole dataset: ``sphere-nlp batch INPUT... --out DIR`` and :func:`map_meshes`.

Every mesh goes through :func:`sphere_nlp.parameterize` and the usual writers, with the same options.
The output folder holds, per mesh ``NAME`` (the input's file name without its extension, with its
parent folders where two inputs have the same file name, e.g. ``sub-01/lh``):

- ``NAME.sphere.off`` (or ``.obj`` / ``.ply`` with ``--format``), only for a certified sphere;
- ``NAME.png`` with ``--png`` (the sphere's name with .png, as the main command names its picture),
  only for a certified sphere;
- ``NAME.report.json``: :meth:`~sphere_nlp.api.SphericalParameterization.report` with a ``batch``
  section (input, options, summary row), written last and also for a failed mesh;

and for the batch ``summary.csv`` and ``summary.md``: one row per mesh with its target (mode),
vertices, status, exit reason, time, iterations, distortion figures and peak memory. A mesh mapped
again loses the outputs of its earlier run that this run does not write (a picture, after a rerun
without ``--png``), so nothing in the folder belongs to another run's map. A worker writes a mesh's files as
temporary files; the batch renames them into place and rewrites the summary, at most every
:data:`COMMIT_INTERVAL_S` seconds for all meshes finished meanwhile, so the summary always lists
exactly the meshes whose files are complete.

A bad or failing mesh is a row (``bad input``, ``solve failed``, ``certificate failed`` or ``error``)
with its one-line reason, and the batch goes on. Re-running the same command skips the meshes whose
certified sphere and report are there (same input file, same target, weights and formulation; an
unconverged, projected sphere only under the same limits), unless ``--force``. ``--start SPHERE``
starts every mesh from one sphere, for a dataset whose meshes share its triangles.

Exit status: 0 every mesh has a certified sphere; 1 some mesh failed; 2 bad usage (no input, an
input that does not exist, two inputs with the same output name, an output that would replace an
input, bad options), found before anything runs; 130 / 143 SIGINT / SIGTERM: every worker is stopped
(local processes killed, Dask tasks cancelled and told to stop), nothing is written after the
signal, and the meshes finished but not yet recorded are dropped (a rerun maps them again).

Parallelism: ``--jobs N`` runs up to N meshes at a time in worker processes (one IPOPT each, BLAS
threads pinned to 1); the default is one per core, and a run starts only when its memory bound
(:func:`memory_bound_mb`) fits beside the runs already going, within the memory available when the
batch began. ``--scheduler ADDRESS`` sends the meshes as Dask futures to an existing
``dask.distributed`` cluster whose workers read the inputs and write the outputs on a shared path.
"""

import csv
import glob
import io
import json
import math
import os
import re
import signal
import socket
import sys
import threading
import time
import uuid
from collections import deque
from contextlib import contextmanager
from pathlib import Path

from . import errors, interrupts
from .heap import arrays_on_heap
from .mesh_io import (atomic_output, commit_staged, discard_staged, load_mesh, staged_outputs,
                      write_json)
from .nlp import DEFAULT_FORMULATION, FORMULATIONS
from .picture import picture_name
from .solve import ON_LIMIT
from .targets import MODES

# What a folder given as input contributes: the mesh files directly inside it.
INPUT_SUFFIXES = (".off", ".obj", ".ply", ".stl")
OUTPUT_FORMATS = ("off", "obj", "ply")

# Peak resident memory of one run, MB: BASE_MB + per-vertex slope, by target family and formulation.
# Fitted as an upper bound to the per-process peak RSS of benchmarks/results.json (each run in its own
# process, 502 to 172,966 vertices): angle modes <= 120 + 0.0200 V, area modes <= 120 + 0.0334 V
# (log-chord); the faithful formulation measured 0.085 MB a vertex (ellipsoid, 10,242 vertices,
# original-angles). MEMORY_MARGIN covers meshes unlike those measured.
BASE_MB = 120.0
MB_PER_VERTEX = {("angle", "log-chord"): 0.021, ("area", "log-chord"): 0.035,
                 ("angle", "other"): 0.09, ("area", "other"): 0.15}
MEMORY_MARGIN = 1.25
# Share of the memory available at the start that a local batch may plan to use.
MEMORY_BUDGET_SHARE = 0.8

# A run that breaks its worker process (killed for memory, a crash) is tried once more in a new one.
WORKER_ATTEMPTS = 2

# Finished meshes are renamed into place together with a rewritten summary at most this often, so
# that a dataset of many small meshes does not rewrite its summary for every one.
COMMIT_INTERVAL_S = 2.0
# After a signal, how long the Dask tasks of the batch get to stop before the batch exits.
DASK_STOP_WAIT_S = 1.5

SUMMARY_FIELDS = ("mesh", "input", "target", "vertices", "status", "reason", "time_s", "iterations",
                  "mean_abs_angle_diff_deg", "mean_abs_log_area", "qc_mean", "area_cv", "peak_rss_mb",
                  "output", "resumed")
# The columns of summary.md: (row key, header, format).
TABLE_COLUMNS = (("mesh", "mesh", "%s"), ("target", "target", "%s"), ("vertices", "vertices", "%d"), ("status", "status", "%s"),
                 ("reason", "exit reason", "%s"), ("time_s", "time (s)", "%.2f"),
                 ("iterations", "iterations", "%d"), ("mean_abs_angle_diff_deg", "mean abs Δangle (°)", "%.2f"),
                 ("mean_abs_log_area", "mean abs log area ratio", "%.3f"), ("qc_mean", "QC mean", "%.3f"),
                 ("peak_rss_mb", "peak RSS (MB)", "%.0f"), ("resumed", "resumed", "%s"))
CERTIFIED = ("certified", "certified, not optimal")

# The options that decide a sphere: a finished one made with other values is not reused.
RESULT_OPTIONS = ("target", "angle_weight", "area_weight", "formulation", "start")
LIMIT_OPTIONS = ("max_iter", "max_time", "on_limit")

# One IPOPT at a time in a process, even on a Dask worker that runs several threads.
_SOLVE_LOCK = threading.Lock()


# ----------------------------------------------------------------------------------------- inputs

def expand_inputs(inputs, exclude=None):
    """Mesh paths from files, folders (their mesh files), glob patterns and ``@list.txt`` files.

    A list file holds one input per line (blank lines and ``#`` comments skipped), relative to the list
    file's folder unless absolute; its lines may be files, folders or patterns too. Paths are returned
    absolute (symbolic links not resolved), in the order given, each once. Files inside ``exclude`` (the
    output folder) are left out of folders and patterns.

    Raises UsageError naming the first input that does not exist, a pattern or folder that matches no
    mesh, or an unreadable list file.

    Examples
    --------
    >>> import tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> for name in ("b.off", "a.obj", "notes.txt"):
    ...     open(os.path.join(d, name), "w").close()
    >>> [p.name for p in expand_inputs([d])]
    ['a.obj', 'b.off']
    >>> [p.name for p in expand_inputs([os.path.join(d, "*.off"), os.path.join(d, "b.off")])]
    ['b.off']

    Strings may be patterns or ``@list`` files; ``Path`` objects are taken as they are.
    """
    exclude = Path(os.path.abspath(exclude)) if exclude else None

    def excluded(path):
        return exclude is not None and (path == exclude or exclude in path.parents)

    found = []

    def add(item, base, from_list=None):
        where = " (in %s)" % from_list if from_list else ""
        text = str(item)
        if isinstance(item, str) and text.startswith("@") and from_list is None:
            _read_list(Path(text[1:]))
            return
        path = Path(os.path.abspath(os.path.join(base, os.path.expanduser(text))))
        # Path objects are taken literally; strings with *, ? or [ are patterns.
        if isinstance(item, str) and glob.has_magic(text):
            matches = sorted(Path(os.path.abspath(m)) for m in glob.glob(str(path), recursive=True))
            matches = [m for m in matches if m.is_file() and m.suffix.lower() in INPUT_SUFFIXES
                       and not excluded(m)]
            if not matches:
                raise errors.UsageError("no mesh file matches %s%s" % (text, where))
            found.extend(matches)
        elif path.is_dir():
            matches = sorted(m for m in path.iterdir()
                             if m.is_file() and m.suffix.lower() in INPUT_SUFFIXES and not excluded(m))
            if not matches:
                raise errors.UsageError("no mesh file (%s) in the folder %s%s"
                                        % (", ".join(INPUT_SUFFIXES), text, where))
            found.extend(matches)
        elif path.exists():
            found.append(path)
        else:
            raise errors.UsageError("no such file or folder: %s%s" % (text, where))

    def _read_list(list_path):
        try:
            lines = list_path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise errors.UsageError("cannot read the list file %s: %s"
                                    % (list_path, getattr(exc, "strerror", None) or exc)) from None
        entries = [line.strip() for line in lines]
        entries = [e for e in entries if e and not e.startswith("#")]
        if not entries:
            raise errors.UsageError("the list file %s names no input" % list_path)
        for entry in entries:
            add(entry, list_path.parent, from_list=list_path)

    for item in inputs:
        add(item, os.getcwd())
    unique, seen = [], set()
    for path in found:
        if path not in seen:
            seen.add(path)
            unique.append(path)
    return unique


def output_names(paths):
    """Each input's output name: its file name without extension, with as many parent folders as it
    takes to tell it from the other inputs' (``sub-01/lh`` and ``sub-02/lh``).

    Raises UsageError when two inputs would get the same name (``a.off`` and ``a.obj`` side by side).

    Examples
    --------
    >>> output_names([Path("/d/sub-01/lh.off"), Path("/d/sub-02/lh.off"), Path("/e/bunny.off")])
    ['sub-01/lh', 'sub-02/lh', 'bunny']
    """
    stems = [path.with_suffix("").parts[1:] for path in paths]    # without the root
    depth = [1] * len(paths)
    while True:
        names = ["/".join(stem[-d:]) for stem, d in zip(stems, depth)]
        holders = {}
        for i, name in enumerate(names):
            holders.setdefault(name, []).append(i)
        clashes = [group for group in holders.values() if len(group) > 1]
        if not clashes:
            return names
        for group in clashes:
            if all(depth[i] >= len(stems[i]) for i in group):
                raise errors.UsageError("%s and %s would write the same outputs (%s.*); give only one, or "
                                        "rename one" % (paths[group[0]], paths[group[1]], paths[group[0]].stem))
            for i in group:
                depth[i] = min(depth[i] + 1, len(stems[i]))


def count_vertices(path):
    """The number of vertices a mesh file declares (OFF, PLY headers; OBJ ``v`` lines), without parsing it.

    Returns None when it cannot tell (other formats, an unreadable file); only the memory bound uses it.
    """
    try:
        suffix = path.suffix.lower()
        if suffix == ".obj":
            with open(path, "rb") as handle:
                data = handle.read()
            return data.count(b"\nv ") + data.startswith(b"v ")
        with open(path, "rb") as handle:
            head = handle.read(4096).decode("ascii", "replace")
        if suffix == ".off":
            words = re.sub(r"#[^\n]*", "", head).split()
            if words and words[0].upper().endswith("OFF"):
                return int(words[1])
        if suffix == ".ply":
            match = re.search(r"element\s+vertex\s+(\d+)", head)
            if match:
                return int(match.group(1))
        if suffix == ".stl":
            return max(path.stat().st_size // 100, 4)      # ~50 bytes a face, two faces a vertex
    except (OSError, ValueError, IndexError):
        pass
    return None


def memory_bound_mb(vertices, target="original-angles", formulation=DEFAULT_FORMULATION):
    """Upper bound on one run's peak resident memory, MB (see :data:`MB_PER_VERTEX`).

    Examples
    --------
    >>> round(memory_bound_mb(50000, "equal-areas"))
    2338
    >>> memory_bound_mb(500) < memory_bound_mb(500, "original-areas") < memory_bound_mb(500, formulation="faithful")
    True
    """
    family = "area" if target.endswith("areas") else "angle"
    kind = "log-chord" if formulation == "log-chord" else "other"
    return MEMORY_MARGIN * (BASE_MB + MB_PER_VERTEX[family, kind] * (vertices or 0))


def available_memory_mb():
    """Memory available for new processes, MB: the kernel's MemAvailable within any cgroup limit."""
    available = None
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) / 1024
    except OSError:
        pass
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
        except (ValueError, OSError, AttributeError):
            return float("inf")
    try:                                                   # a container's limit (cgroup v2)
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            available = min(available, (int(limit) - used) / 2 ** 20)
    except (OSError, ValueError):
        pass
    return available


def usable_cores():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


# ------------------------------------------------------------------------------------ one mesh

def _reset_peak_memory():
    """Restart this process's peak-RSS count (Linux), so a worker's peak is that of its current mesh."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
    except OSError:
        pass


def _file_stamp(path):
    stat = os.stat(path)
    return {"input_size": stat.st_size, "input_mtime_ns": stat.st_mtime_ns}


def _remove(paths):
    for path in paths:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


def _row_from_result(task, result, status, reason, elapsed):
    from .api import peak_rss_mb

    distortion = result.distortion() if result.success else {}
    return {"mesh": task["name"], "input": task["input"], "target": task["options"]["target"],
            "vertices": int(len(result.vertices)),
            "status": status, "reason": reason, "time_s": round(elapsed, 3),
            "iterations": int(result.iterations),
            "mean_abs_angle_diff_deg": distortion.get("mean_abs_angle_diff_deg"),
            "mean_abs_log_area": distortion.get("mean_abs_log_area"),
            "qc_mean": distortion.get("qc_mean"), "area_cv": distortion.get("area_cv"),
            "peak_rss_mb": round(peak_rss_mb(), 1),
            "output": task["outputs"]["sphere"] if result.success else None, "resumed": False}


def failure_row(task, status, reason, elapsed=None, vertices=None):
    """A summary row for a mesh that produced no sphere."""
    row = dict.fromkeys(SUMMARY_FIELDS)
    row.update(mesh=task["name"], input=task["input"], target=task["options"]["target"], vertices=vertices,
               status=status, reason=reason,
               time_s=None if elapsed is None else round(elapsed, 3), resumed=False)
    return row


def map_one(task, stop_event=None):
    """Map one mesh of a batch and stage its outputs (runs in a worker); ``(row, staged, stale)``.

    ``task`` is a plain dict made by :func:`plan` (input, output names, options). The outputs are
    temporary files beside their destinations, ``staged`` [(temporary, destination)], the report
    last; ``stale`` are outputs of an earlier run this one leaves without a replacement (a failed
    mesh's old sphere). The batch renames and removes them (:func:`sphere_nlp.mesh_io.commit_staged`)
    when it records the row. Input errors, solve and certificate failures and running out of memory
    become rows; anything else (a bug, a file system error) is raised, for the caller (or Dask's
    retries) to deal with.

    ``stop_event``: the name of a Dask ``Event`` that, once set, stops the solve as a signal would
    (a Dask task cannot be killed); the mesh then raises :class:`~sphere_nlp.interrupts.Interrupted`.
    """
    with _SOLVE_LOCK:
        if stop_event is None:
            return _map_one(task)
        watcher = _StopWatcher(stop_event)
        try:
            if watcher.event.is_set():
                raise interrupts.Interrupted(signal.SIGTERM)
            row, staged, stale = _map_one(task)
        finally:
            watcher.close()
            interrupts.clear_stop()
        if watcher.event.is_set():        # told to stop while staging: the batch will not take them
            discard_staged(staged)
            raise interrupts.Interrupted(signal.SIGTERM)
        return row, staged, stale


class _StopWatcher:
    """A thread asking the solve of this process to stop once the Dask Event ``name`` is set."""

    def __init__(self, name, poll_s=0.5):
        from distributed import Event

        self.event = Event(name)
        self.done = threading.Event()
        self.poll_s = poll_s
        self.thread = threading.Thread(target=self._watch, daemon=True)
        self.thread.start()

    def _watch(self):
        while not self.done.is_set():
            try:
                if self.event.wait(timeout=self.poll_s):
                    interrupts.request_stop()
                    return
            except Exception:       # the scheduler is gone: nobody can ask any more
                return

    def close(self):
        self.done.set()


def earlier_outputs(task):
    """The files an earlier run wrote for this mesh that this run does not write (from its report):
    left in place they would sit beside the new sphere as if they showed it."""
    out = Path(task["out_dir"])
    try:
        earlier = json.loads((out / task["outputs"]["report"]).read_text())["batch"]["outputs"].values()
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return []
    current, own = set(task["outputs"].values()), task["name"] + "."
    # Only this mesh's own names (NAME.*) are taken from the report: never a file elsewhere.
    return [out / name for name in earlier
            if isinstance(name, str) and name not in current and name.startswith(own)
            and "/" not in name[len(own):] and (out / name).is_file()]


def _map_one(task):
    from .api import parameterize, solve_failure_message

    out = Path(task["out_dir"])
    outputs = {kind: out / name for kind, name in task["outputs"].items()}
    outputs["report"].parent.mkdir(parents=True, exist_ok=True)
    options = task["options"]
    produced = [outputs["sphere"]] + ([outputs["png"]] if "png" in outputs else [])
    earlier = earlier_outputs(task)
    batch_info = {"input": task["input"], "options": options, "outputs": task["outputs"],
                  "worker": "%s:%d" % (socket.gethostname(), os.getpid())}
    _reset_peak_memory()
    clock = time.perf_counter()
    try:
        batch_info.update(_file_stamp(task["input"]))
        start = None
        if options.get("start"):
            start, _ = load_mesh(options["start"])
        result = parameterize(task["input"], target=options["target"], angle_weight=options["angle_weight"],
                              area_weight=options["area_weight"], formulation=options["formulation"],
                              max_iter=options["max_iter"], max_time=options["max_time"],
                              on_limit=options["on_limit"], start=start, check=False)
    except (errors.MeshInputError, MemoryError, OSError) as exc:
        if isinstance(exc, errors.MeshInputError):
            status, reason = "bad input", str(exc)
        elif isinstance(exc, MemoryError):
            status, reason = "error", "out of memory"
        else:
            status, reason = "bad input", "cannot read %s: %s" % (task["input"], exc.strerror or exc)
        row = failure_row(task, status, reason, time.perf_counter() - clock)
        with staged_outputs() as staged:
            write_json(outputs["report"], {"success": False, "status": status, "reason": reason,
                                           "batch": {**batch_info, "summary": row}})
        return row, staged, produced + earlier
    with staged_outputs() as staged:
        if result.success:
            result.write(outputs["sphere"])
            if "png" in outputs:
                result.write_png(outputs["png"], measure=options["png_measure"])
            if result.converged:
                status, reason = "certified", result.status
            else:
                status = "certified, not optimal"
                reason = "%s; last iterate projected onto the constraints" % result.status
        elif not result.solved:
            status, reason = "solve failed", solve_failure_message(result.status, result.iterations)
        else:
            status = "certificate failed"
            reason = "the sphere failed its certificate: %s" % result.certificate.reason
        row = _row_from_result(task, result, status, reason, time.perf_counter() - clock)
        report = result.report()
        report["batch"] = {**batch_info, "summary": row}
        write_json(outputs["report"], report)     # last: a report beside a sphere marks it done
    return row, staged, earlier + ([] if result.success else produced)


def finished_row(task):
    """The summary row of a mesh done by an earlier run with compatible options, or None."""
    out = Path(task["out_dir"])
    try:
        report = json.loads((out / task["outputs"]["report"]).read_text())
        info = report["batch"]
        row = dict(info["summary"])
        row.setdefault("target", info["options"].get("target"))      # summaries before the target column
        if not report.get("success") or row.get("status") not in CERTIFIED:
            return None
        if info.get("input") != task["input"] or {k: info.get(k) for k in ("input_size", "input_mtime_ns")} \
                != _file_stamp(task["input"]):
            return None
        old, new = info["options"], task["options"]
        if any(old.get(k) != new[k] for k in RESULT_OPTIONS):
            return None
        if not report.get("converged") and any(old.get(k) != new[k] for k in LIMIT_OPTIONS):
            return None
        if not all((out / name).is_file() for name in task["outputs"].values()):
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    row["resumed"] = True
    return row


# ------------------------------------------------------------------------------------ the batch

def plan(paths, out_dir, options, png=False, output_format="off"):
    """The tasks of a batch: one plain dict per mesh (input, output names, options, memory bound)."""
    paths = [Path(os.path.abspath(p)) for p in paths]
    tasks = []
    for path, name in zip(paths, output_names(paths)):
        outputs = {"sphere": "%s.sphere.%s" % (name, output_format), "report": name + ".report.json"}
        if png:
            outputs["png"] = str(picture_name(outputs["sphere"]))
        vertices = count_vertices(path)
        tasks.append({"name": name, "input": str(path), "out_dir": str(out_dir), "outputs": outputs,
                      "options": dict(options), "vertices": vertices,
                      "memory_mb": memory_bound_mb(vertices, options["target"], options["formulation"])})
    return tasks


def _temporary_files(out_dir, tasks):
    """Leftovers of atomic writes (``.NAME.*.tmp``) of this batch's outputs, e.g. after a kill -9."""
    names = ["summary.csv", "summary.md"] + [n for t in tasks for n in t["outputs"].values()]
    found = []
    for name in names:
        target = out_dir / name
        found.extend(target.parent.glob("." + glob.escape(target.name) + ".*.tmp"))
    return found


def markdown_table(rows):
    """The summary rows as a Markdown table (None shows as an empty cell).

    Examples
    --------
    >>> print(markdown_table([{"mesh": "knight", "target": "original-angles", "vertices": 502, "status": "certified",
    ...                        "reason": "Solve_Succeeded", "time_s": 0.8, "iterations": 30,
    ...                        "mean_abs_angle_diff_deg": 3.1, "mean_abs_log_area": 0.9, "qc_mean": 1.1,
    ...                        "peak_rss_mb": 118, "resumed": False}]))
    | mesh | target | vertices | status | exit reason | time (s) | iterations | mean abs Δangle (°) | mean abs log area ratio | QC mean | peak RSS (MB) | resumed |
    |---|---|---|---|---|---|---|---|---|---|---|---|
    | knight | original-angles | 502 | certified | Solve_Succeeded | 0.80 | 30 | 3.10 | 0.900 | 1.100 | 118 |  |
    """
    lines = ["| " + " | ".join(header for _, header, _ in TABLE_COLUMNS) + " |",
             "|" + "---|" * len(TABLE_COLUMNS)]
    for row in rows:
        cells = []
        for key, _, fmt in TABLE_COLUMNS:
            value = row.get(key)
            if key == "resumed":
                value = "yes" if value else None
            cells.append(("" if value is None else fmt % value).replace("|", "\\|").replace("\n", " "))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_summary(out_dir, rows):
    """Write ``summary.csv`` and ``summary.md`` atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    with atomic_output(Path(out_dir) / "summary.csv") as out:
        out.write(buffer.getvalue())
    certified = sum(row["status"] in CERTIFIED for row in rows)
    with atomic_output(Path(out_dir) / "summary.md") as out:
        out.write("%d meshes: %d certified, %d failed\n\n" % (len(rows), certified, len(rows) - certified))
        out.write(markdown_table(rows) + "\n")


@contextmanager
def _single_threaded_blas():
    """Pin BLAS/OpenMP threads to 1 in the worker processes started within (they inherit the environment)."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {name: os.environ.get(name) for name in names}
    os.environ.update({name: "1" for name in names})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _stop_worker(signum, frame):
    """SIGTERM in a local worker: end at once. It writes only temporary files, which the batch
    removes; the batch itself stops its workers with SIGKILL (see _kill_workers)."""
    os._exit(128 + signum)


def _init_worker():
    # Ctrl-C reaches the whole process group; the workers leave it to the batch, which kills them.
    # The batch starts them with both signals blocked (see _signals_blocked), so that none arrives
    # before these handlers are in place.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop_worker)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, interrupts.SIGNALS)


@contextmanager
def _signals_blocked():
    """SIGINT and SIGTERM held back inside the block (delivered after it): worker processes started
    here inherit the blocked mask until their initializer has set their handlers."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, interrupts.SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _error_row(task, exc):
    """The row of a mesh whose run raised something unexpected (a bug, a file system error)."""
    return failure_row(task, "error", "%s: %s" % (type(exc).__name__, exc)), [], []


class _Recorder:
    """The batch's rows, and the finished meshes waiting to be renamed into place.

    A finished mesh's staged files are committed together with a rewritten summary, at most every
    :data:`COMMIT_INTERVAL_S` seconds and at the end (:meth:`flush`), with signals deferred, so the
    summary lists exactly the meshes whose files are in place; after a signal the meshes still
    waiting are discarded (:meth:`discard`), and nothing more is written.
    """

    def __init__(self, out_dir, tasks, notify):
        self.out_dir, self.tasks, self.notify = out_dir, tasks, notify
        self.rows = {}
        self.waiting = []           # (task, row, staged, stale)
        self.last_commit = time.monotonic()
        self.summary_due = False

    def summary_rows(self):
        return [self.rows[t["name"]] for t in self.tasks if t["name"] in self.rows]

    def resumed(self, task, row):
        """A mesh an earlier run finished: its files are in place."""
        self.rows[task["name"]] = row
        self.summary_due = True
        self.notify("done", task, row, ran=False)

    def finished(self, task, outcome):
        """A mesh mapped now: ``(row, staged, stale)`` from :func:`map_one`."""
        self.waiting.append((task,) + tuple(outcome))
        self.flush(force=False)

    def seconds_to_flush(self):
        """How long until the waiting meshes are due to be committed (None: none waiting)."""
        if not self.waiting:
            return None
        return max(0.0, self.last_commit + COMMIT_INTERVAL_S - time.monotonic())

    def flush(self, force=True):
        """Commit the waiting meshes and rewrite the summary (if due, or ``force``)."""
        if not (self.waiting or self.summary_due):
            return
        if not force and time.monotonic() - self.last_commit < COMMIT_INTERVAL_S:
            return
        done = []
        with interrupts.defer_signals():
            for task, row, staged, stale in self.waiting:
                commit_staged(staged, remove=[Path(self.out_dir) / stale_path for stale_path in stale])
                self.rows[task["name"]] = row
                done.append((task, row))
            self.waiting = []
            write_summary(self.out_dir, self.summary_rows())
            self.summary_due = False
        self.last_commit = time.monotonic()
        for task, row in done:
            self.notify("done", task, row)
        # A signal during the commit: the meshes are in place and listed; stop now.
        interrupts.raise_if_interrupted()

    def discard(self):
        """Remove the staged files of the meshes still waiting (after a signal)."""
        for _, _, staged, _ in self.waiting:
            discard_staged(staged)
        self.waiting = []


def _run_sequential(tasks, recorder, notify):
    """One mesh after the other in this process; a signal stops the running IPOPT too."""
    for task in tasks:
        notify("start", task)
        try:
            outcome = map_one(task)
        except Exception as exc:          # on this mesh only; a signal (KeyboardInterrupt) stops the batch
            outcome = _error_row(task, exc)
        interrupts.raise_if_interrupted()
        recorder.finished(task, outcome)


def _run_local(tasks, jobs, budget_mb, recorder, notify):
    """Up to ``jobs`` meshes at a time in worker processes, within ``budget_mb`` of planned memory."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    # spawn: fresh interpreters that read the pinned thread counts when they load BLAS.
    context = multiprocessing.get_context("spawn")

    def new_executor():
        return ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init_worker)

    pending = deque(tasks)
    running = {}
    attempts = {}
    with _single_threaded_blas():
        executor = new_executor()
        try:
            while pending or running:
                while pending and len(running) < jobs:
                    task = pending[0]
                    planned = sum(t["memory_mb"] for t in running.values())
                    if running and planned + task["memory_mb"] > budget_mb:
                        break                    # wait until it fits beside the runs going on
                    pending.popleft()
                    notify("start", task)
                    with _signals_blocked():     # a worker process may start here
                        running[executor.submit(map_one, task)] = task
                done, _ = wait(running, timeout=recorder.seconds_to_flush(), return_when=FIRST_COMPLETED)
                broken = False
                for future in done:
                    task = running.pop(future)
                    try:
                        recorder.finished(task, future.result())
                    except BrokenProcessPool:
                        broken = True
                        attempts[task["name"]] = attempts.get(task["name"], 0) + 1
                        if attempts[task["name"]] < WORKER_ATTEMPTS:
                            pending.appendleft(task)
                        else:
                            recorder.finished(task, (failure_row(
                                task, "error", "its worker process died (killed by the system, e.g. for "
                                "lack of memory, or crashed)"), [], []))
                    except Exception as exc:     # a bug or a file system error, on this mesh only
                        recorder.finished(task, _error_row(task, exc))
                recorder.flush(force=False)
                if broken:
                    for future, task in running.items():     # they died with the pool: run them again
                        pending.appendleft(task)
                    running.clear()
                    executor.shutdown(wait=False, cancel_futures=True)
                    executor = new_executor()
        except BaseException:
            _kill_workers(executor)
            raise
        executor.shutdown(wait=True)


def _kill_workers(executor):
    """Stop the workers at once (SIGKILL): they write only temporary files, which the batch removes.

    SIGKILL rather than SIGTERM: a worker inside IPOPT's or MUMPS's C code would see a SIGTERM only
    at its next return to Python, and must write nothing after the batch was told to stop.
    """
    # ProcessPoolExecutor has no public way to stop running calls; its _processes are the workers.
    processes = list((getattr(executor, "_processes", None) or {}).values())
    for process in processes:
        try:
            process.kill()
        except (OSError, ValueError):
            pass
    executor.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.join(2.0)


def _map_one_on_dask(task, stop_event=None):
    """:func:`map_one` on a Dask worker, its large arrays on glibc's heap (:mod:`sphere_nlp.heap`).

    Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which also fixes glibc's mmap
    threshold at 128 KiB, so every larger numpy temporary was a fresh mmap: cheburashka.off took
    9.5-10.0 s on a worker instead of 7.6-8.6 s. The whole task runs heap-only, and the memory goes
    back to the system after each mesh, as the worker expects. A task told to stop (``stop_event``
    set) returns a row without files.
    """
    try:
        with arrays_on_heap():
            return map_one(task, stop_event)
    except interrupts.Interrupted:
        return failure_row(task, "error", "stopped: the batch was interrupted"), [], []


def _run_dask(tasks, client, retries, recorder, notify):
    """Every mesh as a Dask future on ``client``'s cluster; rows as they complete.

    On a signal the futures are cancelled and the running tasks told to stop (a Dask Event their
    solves watch); the batch waits up to :data:`DASK_STOP_WAIT_S` for them and drops their files.
    """
    from distributed import wait

    workers = client.scheduler_info().get("workers", {}).values()
    memories = [w.get("resources", {}).get("MEMORY") for w in workers]
    # Workers started with `--resources MEMORY=<bytes>` get no more runs at once than fit in it.
    annotate = bool(memories) and all(m is not None for m in memories)
    largest = max(memories) if annotate else None
    batch_id = uuid.uuid4().hex[:8]
    stop_event = "sphere-nlp-stop-%s" % batch_id
    futures = {}
    try:
        for task in tasks:
            extra = {}
            if annotate:
                extra["resources"] = {"MEMORY": min(task["memory_mb"] * 2 ** 20, largest)}
            future = client.submit(_map_one_on_dask, task, stop_event,
                                   key="sphere-nlp-%s-%s" % (task["name"], batch_id),
                                   retries=retries, pure=False, **extra)
            futures[future] = task
            notify("start", task)
        remaining = set(futures)
        while remaining:
            try:
                done = wait(list(remaining), timeout=recorder.seconds_to_flush(),
                            return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = set()
            for future in done:
                remaining.discard(future)
                task = futures[future]
                if future.status == "finished":
                    outcome = future.result()
                elif future.status == "cancelled":
                    outcome = failure_row(task, "error", "its Dask task was cancelled"), [], []
                else:
                    outcome = _error_row(task, future.exception())
                recorder.finished(task, outcome)
            recorder.flush(force=False)
    except BaseException:
        _stop_dask_tasks(client, futures, stop_event)
        raise


def _stop_dask_tasks(client, futures, stop_event):
    """Tell the batch's tasks to stop, wait a little for them, cancel those still going, and remove
    the files of those that finished meanwhile."""
    from distributed import Event, wait

    try:
        # Running tasks stop at their next IPOPT iteration, queued ones as they start, and a task
        # that has staged its files removes them itself once it sees the event.
        Event(stop_event, client=client).set()
        try:
            wait(list(futures), timeout=DASK_STOP_WAIT_S)
        except TimeoutError:
            pass
        client.cancel([future for future in futures if not future.done()], force=True)
        for future in futures:
            if future.status == "finished":
                discard_staged(future.result()[1])
    except Exception:           # the cluster is gone: nothing more can be asked of it
        pass


def _load_client(address):
    try:
        from distributed import Client
    except ImportError:
        raise errors.UsageError("--scheduler needs dask.distributed: pip install 'sphere_nlp[cluster]'") \
            from None
    try:
        return Client(address, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise errors.UsageError("cannot connect to the Dask scheduler at %s: %s" % (address, exc)) from None


def map_meshes(paths, out_dir, target="original-angles", *, angle_weight=None, area_weight=None,
               formulation=DEFAULT_FORMULATION, max_iter=None, max_time=None, on_limit="fail",
               output_format="off", png=False, png_measure=None, force=False, jobs=1, client=None,
               retries=1, progress=None, start=None):
    """Map every mesh of ``paths`` onto the sphere, writing into ``out_dir``; the summary rows.

    Parameters
    ----------
    paths : list of str or Path
        Mesh files, folders, glob patterns or ``@list.txt`` files (see :func:`expand_inputs`).
    out_dir : str or Path
        Created if missing; receives the spheres, reports, pictures and ``summary.csv``/``summary.md``
        (see the module's description).
    target, angle_weight, area_weight, formulation, max_iter, max_time, on_limit
        As for :func:`sphere_nlp.parameterize`, for every mesh.
    output_format : {"off", "obj", "ply"}
        Format of the spheres; OBJ carries texture coordinates.
    png : bool
        Also write a picture per certified mesh, coloured by ``png_measure`` ("area" or "angle"; by
        default what the target mode does not optimise, as for a single mesh).
    force : bool
        Map every mesh again, even those already done by an earlier run.
    jobs : int or None
        Meshes mapped at a time in local worker processes; 1 maps them one after the other in this
        process; None: one per core. Runs start only while their memory bounds fit in the memory
        available at the start.
    client : distributed.Client, optional
        Run on this Dask cluster instead (``jobs`` is ignored); its workers must see ``paths`` and
        ``out_dir`` at the same paths (a shared file system).
    retries : int
        Dask retries of a mesh whose task raised (a lost file system, say); a mesh that fails to map
        is a row, not retried.
    progress : callable(event, task, row, counts), optional
        Called with "start" (row None) and "done" for each mesh; ``counts`` is a dict of done,
        failed, running and total.
    start : str or Path, optional
        A sphere mesh every solve starts from, for a dataset whose meshes share its triangles (one
        template's connectivity): a mesh's map is then found near it, and in the area modes without
        the walk when it is near that mesh's targets (:func:`sphere_nlp.parameterize`'s ``start``).
        A mesh it is not a valid map of is a "bad input" row.

    Returns
    -------
    list of dict
        One row per mesh, in input order, with the keys of :data:`SUMMARY_FIELDS`.

    Raises
    ------
    UsageError
        No input, an input that does not exist, two inputs with the same output name, a bad option,
        or an output folder that cannot be created. Nothing is run or written.

    Examples
    --------
    >>> import tempfile
    >>> from sphere_nlp.shapes import write_models
    >>> folder = tempfile.mkdtemp()
    >>> write_models(folder)
    >>> rows = map_meshes([folder + "/cylinder.off"], folder + "/out", target="equal-angles")
    >>> rows[0]["mesh"], rows[0]["status"], rows[0]["output"]
    ('cylinder', 'certified', 'cylinder.sphere.off')
    >>> map_meshes([folder + "/cylinder.off"], folder + "/out", target="equal-angles")[0]["resumed"]
    True
    """
    from .api import check_run_options

    check_run_options(target, formulation, on_limit, max_iter, max_time, angle_weight, area_weight)
    if output_format not in OUTPUT_FORMATS:
        raise errors.UsageError("unknown output format %r; choose one of %s"
                                % (output_format, ", ".join(OUTPUT_FORMATS)))
    if png_measure not in (None, "area", "angle"):
        raise errors.UsageError("unknown picture measure %r; choose area or angle" % png_measure)
    if jobs is not None and (not isinstance(jobs, int) or jobs < 1):
        raise errors.UsageError("jobs must be a positive integer (or None for one per core), not %r" % (jobs,))
    out_dir = Path(os.path.abspath(out_dir))
    paths = expand_inputs(paths, exclude=out_dir)
    if not paths:
        raise errors.UsageError("no input mesh given")
    if start is not None:
        start = os.path.abspath(start)
        try:
            load_mesh(start)                      # readable, before anything runs
        except errors.MeshInputError as exc:
            raise errors.UsageError("start: %s" % exc) from None
    options = {"target": target, "angle_weight": angle_weight, "area_weight": area_weight,
               "formulation": formulation, "max_iter": max_iter, "max_time": max_time,
               "on_limit": on_limit, "png_measure": png_measure, "start": start}
    tasks = plan(paths, out_dir, options, png=png, output_format=output_format)
    check_outputs(tasks, paths, start)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise errors.UsageError("cannot create the output folder %s: %s" % (out_dir, exc.strerror or exc)) \
            from None
    if not os.access(out_dir, os.W_OK):
        raise errors.UsageError("cannot write to the output folder %s" % out_dir)
    _remove(_temporary_files(out_dir, tasks))

    counts = {"done": 0, "failed": 0, "running": 0, "total": len(tasks)}

    def notify(event, task, row=None, ran=True):
        if event == "start":
            counts["running"] += 1
        else:
            counts["done"] += 1
            counts["running"] -= ran
            counts["failed"] += row["status"] not in CERTIFIED
        if progress is not None:
            progress(event, task, row, dict(counts))

    recorder = _Recorder(out_dir, tasks, notify)
    todo = []
    for task in tasks:
        row = None if force else finished_row(task)
        if row is None:
            todo.append(task)
        else:
            recorder.resumed(task, row)
    try:
        if client is not None:
            _run_dask(todo, client, retries, recorder, notify)
        else:
            jobs = usable_cores() if jobs is None else jobs
            jobs = min(jobs, len(todo))
            if jobs <= 1:
                _run_sequential(todo, recorder, notify)
            else:
                budget = MEMORY_BUDGET_SHARE * available_memory_mb()
                _run_local(todo, jobs, budget, recorder, notify)
        recorder.flush()
    except BaseException:
        recorder.discard()          # finished meshes not yet in place: dropped, nothing more written
        raise
    finally:
        _remove(_temporary_files(out_dir, tasks))
    return recorder.summary_rows()


def check_outputs(tasks, inputs, start=None):
    """UsageError if an output of the batch would replace one of its inputs (or the start sphere)."""
    from .commands import same_file

    sources = [("an input", path) for path in inputs] + ([("the --start sphere", start)] if start else [])
    names = ["summary.csv", "summary.md"] + [name for task in tasks for name in task["outputs"].values()]
    out_dir = Path(tasks[0]["out_dir"]) if tasks else None
    for name in names:
        for what, source in sources:
            if same_file(out_dir / name, source):
                raise errors.UsageError("the output %s would replace %s, %s: choose another --out folder"
                                        % (out_dir / name, what, source))


# ------------------------------------------------------------------------------ command line

def _format_duration(seconds):
    seconds = int(round(seconds))
    if seconds < 60:
        return "%d s" % seconds
    if seconds < 3600:
        return "%d min %02d s" % divmod(seconds, 60)
    return "%d h %02d min" % (seconds // 3600, seconds % 3600 // 60)


class BatchProgress:
    """Counts, failures and an ETA on stderr: one updating line on a terminal, a line a mesh otherwise.

    Every failed mesh also gets a line of its own with its reason. Nothing when quiet.
    """

    def __init__(self, quiet=False, stream=None):
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.pending = False
        self.first_start = None
        self.ran = 0

    def say(self, text):
        if self.quiet:
            return
        if self.pending:
            self.stream.write("\r\033[K")
            self.pending = False
        self.stream.write(text + "\n")
        self.stream.flush()

    def eta(self, counts):
        if not self.ran or self.first_start is None:
            return ""
        per_mesh = (time.monotonic() - self.first_start) / self.ran
        left = counts["total"] - counts["done"]
        return ", ETA %s" % _format_duration(per_mesh * left) if left else ""

    def __call__(self, event, task, row, counts):
        if event == "start":
            if self.first_start is None:
                self.first_start = time.monotonic()
            if self.tty:
                self.status_line(counts)
            return
        if not row["resumed"]:
            self.ran += 1
        done = "[%d/%d]" % (counts["done"], counts["total"])
        if row["status"] not in CERTIFIED:
            self.say("%s: %s %s: %s: %s" % (PROG, done, row["mesh"], row["status"], row["reason"]))
        elif not self.tty:
            what = ("already done" if row["resumed"] else "%s, %s vertices, %.1f s"
                    % (row["status"], row["vertices"], row["time_s"]))
            self.say("%s: %s %s: %s%s" % (PROG, done, row["mesh"], what, self.eta(counts)))
        if self.tty:
            self.status_line(counts)

    def status_line(self, counts):
        if self.quiet:
            return
        self.stream.write("\r\033[K%s: %d/%d done, %d failed, %d running%s"
                          % (PROG, counts["done"], counts["total"], counts["failed"], counts["running"],
                             self.eta(counts)))
        self.stream.flush()
        self.pending = True

    def finish_line(self):
        if self.pending:
            self.stream.write("\n")
            self.stream.flush()
            self.pending = False


PROG = "sphere-nlp batch"


def build_parser():
    from .commands import subcommand_parser

    parser = subcommand_parser(
        "batch",
        description="Map many meshes onto the sphere with the same options. DIR receives per mesh its "
                    "certified sphere NAME.sphere.off and NAME.report.json, and summary.csv and summary.md. "
                    "A failing mesh is recorded and the batch goes on; a rerun skips the meshes already "
                    "done. Exit status: 0 all certified, 1 some failed, 2 bad usage, 130 / 143 "
                    "interrupted (workers stopped; the summary lists exactly the meshes in DIR).",
        epilog="examples:\n  sphere-nlp batch meshes/ --out spheres\n"
               "  sphere-nlp batch 'data/**/*.obj' @more.txt --out spheres --jobs 2 --png\n"
               "  sphere-nlp batch meshes/ --out /shared/spheres --scheduler tcp://head:8786\n")
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="mesh files, folders (their .off/.obj/.ply/.stl files), glob patterns "
                             "('data/**/*.obj', quoted) or @list.txt (one input a line)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    out = parser.add_argument_group("outputs (per certified mesh)")
    out.add_argument("--format", choices=OUTPUT_FORMATS, default="off",
                     help="sphere format (default off); obj carries longitude/latitude texture coordinates")
    out.add_argument("--png", action="store_true",
                     help="also a picture beside each sphere, named after it (NAME.png), as the main command's "
                          "--png")
    out.add_argument("--png-measure", choices=("area", "angle"),
                     help="colouring of the pictures (default: what the target mode does not optimise, "
                          "angle distortion for the area modes, log area ratio for the angle modes)")
    method = parser.add_argument_group("method (as for a single mesh)")
    method.add_argument("--target", default="original-angles", choices=MODES, metavar="MODE",
                        help="%s (default: original-angles)" % ", ".join(MODES))
    method.add_argument("--angle-weight", type=float, metavar="W", help="weight of the angle term")
    method.add_argument("--area-weight", type=float, metavar="W", help="weight of the area term")
    method.add_argument("--formulation", default=DEFAULT_FORMULATION, choices=FORMULATIONS, metavar="F",
                        help="log-chord (default), substituted or faithful")
    method.add_argument("--start", metavar="SPHERE",
                        help="start every mesh from this sphere (meshes sharing its triangles, e.g. subjects "
                             "on one template); area modes then skip their walk where it is near")
    limits = parser.add_argument_group("solver limits, per mesh")
    limits.add_argument("--max-iter", type=int, metavar="N", help="IPOPT iteration limit of each stage (>= 1)")
    limits.add_argument("--max-time", type=float, metavar="S",
                        help="wall-clock limit of each mesh's whole run, seconds (> 0; as for a single mesh: "
                             "every IPOPT stage of that mesh stops at its first iteration past it)")
    limits.add_argument("--on-limit", choices=ON_LIMIT, default="fail",
                        help="at a limit: fail the mesh (default), or project and write a certified, not "
                             "optimal, sphere")
    run = parser.add_argument_group("running")
    run.add_argument("--force", action="store_true", help="map again the meshes an earlier run did")
    run.add_argument("--jobs", type=int, metavar="N",
                     help="meshes at a time in worker processes (default: one per core, as memory allows)")
    run.add_argument("--scheduler", metavar="ADDRESS",
                     help="run on this Dask distributed scheduler (e.g. tcp://host:8786); its workers "
                          "must see the inputs and DIR at the same paths")
    run.add_argument("--retries", type=int, default=1, metavar="N",
                     help="with --scheduler, Dask retries of a task that raised (default 1)")
    run.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    return parser


def check_arguments(args):
    """Every option value, input and output of ``sphere-nlp batch`` (UsageError), before anything runs."""
    from .api import check_run_options

    if args.jobs is not None and args.jobs < 1:
        raise errors.UsageError("--jobs must be at least 1, not %d" % args.jobs)
    if args.scheduler and args.jobs is not None:
        raise errors.UsageError("--jobs is for local runs; with --scheduler the cluster's workers "
                                "decide how many meshes run at a time")
    if args.retries < 0:
        raise errors.UsageError("--retries must be 0 or more, not %d" % args.retries)
    if args.max_time is not None and not (math.isfinite(args.max_time) and args.max_time > 0):
        # As for a single mesh: inf is no number of seconds (and would not survive the JSON summary).
        raise errors.UsageError("--max-time must be a finite number of seconds > 0, not %s" % args.max_time)
    try:
        check_run_options(args.target, args.formulation, args.on_limit, args.max_iter, args.max_time,
                          args.angle_weight, args.area_weight)
    except errors.UsageError as exc:           # the API's words for the options' values
        raise errors.UsageError(re.sub(r"\b(angle_weight|area_weight|max_iter|max_time)\b",
                                       lambda m: "--" + m.group(1).replace("_", "-"), str(exc))) from None
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise errors.UsageError("cannot write to --out %s: it is a file, not a folder" % out_dir)
    paths = expand_inputs(args.inputs, exclude=out_dir)
    output_names(paths)                       # a clash of names is found before anything is said
    start = None
    if args.start:
        start = os.path.abspath(args.start)
        try:
            load_mesh(start)
        except errors.MeshInputError as exc:
            raise errors.UsageError("--start: %s" % exc) from None
    options = dict.fromkeys(("target", "formulation"), None)
    options.update(target=args.target, formulation=args.formulation)
    check_outputs(plan(paths, Path(os.path.abspath(out_dir)), options, png=args.png, output_format=args.format),
                  paths, start)
    from .commands import check_output_folder
    check_output_folder("--out", out_dir)
    return paths


def main(argv=None):
    """``sphere-nlp batch INPUT... --out DIR [options]``; the exit status."""
    from .commands import SafeStream, run_subcommand

    parser = build_parser()
    stderr = SafeStream(sys.stderr)

    def check(args):
        args.paths = check_arguments(args)

    def body(args, say):
        progress = BatchProgress(quiet=args.quiet, stream=stderr)
        client = None
        try:
            if args.scheduler:
                client = _load_client(args.scheduler)
                where = "on the Dask cluster at %s" % args.scheduler
            else:
                jobs = min(args.jobs or usable_cores(), len(args.paths))
                where = "up to %d at a time" % jobs if jobs > 1 else "one at a time"
            say("%d mesh(es), target %s, %s -> %s" % (len(args.paths), args.target, where, args.out))
            try:
                rows = map_meshes(args.paths, args.out, target=args.target, angle_weight=args.angle_weight,
                                  area_weight=args.area_weight, formulation=args.formulation,
                                  max_iter=args.max_iter, max_time=args.max_time, on_limit=args.on_limit,
                                  output_format=args.format, png=args.png, png_measure=args.png_measure,
                                  force=args.force, jobs=args.jobs, client=client, retries=args.retries,
                                  progress=progress, start=args.start)
            finally:
                progress.finish_line()
        finally:
            if client is not None:
                client.close()
        failed = [row for row in rows if row["status"] not in CERTIFIED]
        resumed = sum(bool(row["resumed"]) for row in rows)
        if failed:
            # An error line, shown with -q too: what failed and what was written.
            stderr.write("sphere-nlp batch: error: %d of %d mesh(es) failed (reasons in %s); wrote the %d "
                         "certified (%d already done) and the summary to %s\n"
                         % (len(failed), len(rows), Path(args.out) / "summary.md", len(rows) - len(failed),
                            resumed, args.out))
            return 1
        say("%d certified (%d already done), 0 failed; summary in %s"
            % (len(rows), resumed, Path(args.out) / "summary.md"))
        return 0

    def interrupted(args):
        return ("every worker stopped; the meshes done so far are in %s, listed in its summary.csv; run the "
                "same command again to go on" % args.out)

    def failed(args):
        return "the meshes done so far are in %s, listed in its summary.csv" % args.out

    return run_subcommand(parser, argv, body, check=check, interrupted=interrupted, failed=failed)
