"""Every command under one contract, tried from outside with real processes and real signals.

- A SIGINT or SIGTERM at any moment, start-up included, ends the run with 130 / 143 and nothing
  written; a second signal during the clean-up does not change that.
- ``batch`` stops its workers on a signal: no process left, no file written afterwards, the summary
  listing exactly the meshes whose files are complete.
- Every subcommand checks all inputs, options and outputs before solving, refuses an output that
  names an input, and speaks in one line with the prefix ``sphere-nlp COMMAND:``.
- Text that is not a mesh is refused in bounded memory and time.
- ``--help`` lists every subcommand; a mistyped one gets a suggestion.
"""

import csv
import os
import random
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import meshgen
from conftest import MODELS, shared_mesh
from sphere_nlp import errors
from sphere_nlp.certify import certify
from sphere_nlp.cli import main
from sphere_nlp.commands import SUBCOMMANDS
from sphere_nlp.mesh_io import load_mesh, write_mesh
from sphere_nlp.shapes import icosphere

ROOT = Path(__file__).resolve().parents[1]


def env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def command(*args):
    return [sys.executable, "-m", "sphere_nlp", *map(str, args)]


def handler_installed(pid, signum=signal.SIGTERM):
    """Whether the process catches ``signum`` now (/proc/PID/status SigCgt). Python itself catches
    only SIGINT, so a caught SIGTERM means sphere_nlp's own handling has been installed."""
    try:
        with open("/proc/%d/status" % pid) as handle:
            for line in handle:
                if line.startswith("SigCgt:"):
                    return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    except OSError:
        pass
    return False


def one_line(stderr, prefix):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(prefix) and "Traceback" not in stderr, stderr
    return lines[0]


# --- 1. signals from the first instruction -------------------------------------------------------

@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc/PID/status")
def test_a_signal_at_a_random_moment_of_the_first_second_ends_the_run_with_nothing_written(tmp_path):
    # Before the interpreter runs sphere_nlp's first line (its own start-up, about 0.1 s) a signal is
    # Python's: SIGTERM kills the process by the signal (a shell shows 143), SIGINT may print
    # Python's KeyboardInterrupt. From the first line on, sphere_nlp's handling holds: the run
    # ends with 128 + the signal number and one line, whatever it was doing (importing numpy and
    # CasADi, reading, solving, writing), and a second signal 50 ms later changes nothing.
    # An area mode on a 2.5k-vertex ellipsoid runs for its whole budget (5 s at least), so every
    # signal of the first second finds the run under way, on a fast machine too.
    rng = random.Random(50)
    handled = 0
    mesh = tmp_path / "ellipsoid.off"
    write_mesh(mesh, *meshgen.ellipsoid(4))
    for k in range(24):
        folder = tmp_path / str(k)
        folder.mkdir()
        first = (signal.SIGINT, signal.SIGTERM)[k % 2]
        second = (None, signal.SIGINT, signal.SIGTERM)[k % 3]
        process = subprocess.Popen(command(mesh, "--target", "equal-areas", "-o", "out.off", "--report", "r.json",
                                           "--png"), cwd=folder, env=env(),
                                   stderr=subprocess.PIPE, text=True)
        time.sleep(rng.uniform(0.0, 1.0))
        ready = handler_installed(process.pid)
        process.send_signal(first)
        if second is not None:
            time.sleep(0.05)
            if process.poll() is None:
                process.send_signal(second)
        stderr = process.stderr.read()
        status = process.wait(timeout=60)
        assert os.listdir(folder) == [], (k, stderr)          # nothing written, no temporary file
        if ready:
            handled += 1
            # Two signals 50 ms apart may both arrive inside one C call (an extension's import, an
            # IPOPT iteration); Python then runs the lower-numbered one's handler first.
            assert status in (128 + first, 128 + (second or first)), (k, status, stderr)
            assert stderr.strip().splitlines()[-1] == ("sphere-nlp: interrupted; nothing written (%s)"
                                                       % signal.Signals(status - 128).name), stderr
            assert "Traceback" not in stderr and "WARNING" not in stderr, stderr
        else:
            # CPython's own start-up: killed by the signal, KeyboardInterrupt (130), or, when a SIGINT
            # lands in the import of the site module (more likely on a loaded machine), "Fatal Python
            # error: init_import_site" and status 1.
            assert (status in (-first, 128 + first)
                    or (status == 1 and "init_import_site" in stderr)), (k, status, stderr)
    assert handled >= 16, handled


def test_a_signal_inside_the_solve_stops_ipopt_and_a_second_one_does_not_cut_the_clean_up(tmp_path):
    mesh = tmp_path / "mesh.off"
    write_mesh(mesh, *meshgen.ellipsoid(4, axes=(1.0, 6.0, 0.2)))       # about 4 s in original-areas
    process = subprocess.Popen(command(mesh, "-o", "out.off", "--save-solution", "s.npz", "--target",
                                       "original-areas"), cwd=tmp_path, env=env(), stderr=subprocess.PIPE,
                               text=True)
    for line in process.stderr:
        if "mapping" in line:
            break
    time.sleep(1.0)
    sent = time.perf_counter()
    process.send_signal(signal.SIGTERM)
    time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    rest = process.stderr.read()
    status = process.wait(timeout=60)
    # The first signal decides, unless both reached Python together (inside one IPOPT iteration).
    assert status in (143, 130), rest
    assert rest.strip().splitlines() == ["sphere-nlp: interrupted; nothing written (%s)"
                                         % signal.Signals(status - 128).name]
    assert time.perf_counter() - sent < 5
    assert sorted(os.listdir(tmp_path)) == ["mesh.off"]


# --- 2. batch and signals -------------------------------------------------------------------------

def descendants(pid):
    """Every process below ``pid`` (Linux /proc)."""
    found = []
    for task in Path("/proc/%d/task" % pid).iterdir():
        try:
            children = (task / "children").read_text().split()
        except OSError:
            continue
        for child in map(int, children):
            found += [child] + descendants(child)
    return found


def alive(pid):
    try:
        with open("/proc/%d/status" % pid) as handle:
            return "zombie" not in handle.read()
    except OSError:
        return False


def folder_state(folder):
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(Path(folder).rglob("*"))}


def slow_and_quick_meshes(folder, slow=6):
    """Two quick meshes, then ``slow`` ones that take seconds each."""
    folder.mkdir()
    for i in range(2 + slow):
        write_mesh(folder / ("e%d.off" % i), *meshgen.ellipsoid(3 if i < 2 else 5, axes=(1.0, 1.2 + 0.1 * i, 0.7)))
    return folder


def check_stopped_batch(out, process, sent, signum, stderr):
    status = process.wait(timeout=30)
    took = time.perf_counter() - sent
    assert status == 128 + signum, stderr
    assert took < 2.5, took
    assert stderr.strip().splitlines()[-1].startswith("sphere-nlp batch: interrupted; every worker stopped")
    before = folder_state(out)
    time.sleep(2.0)                                        # nothing appears or changes afterwards
    assert folder_state(out) == before
    files = sorted(p.name for p in out.iterdir())
    assert not [f for f in files if f.endswith(".tmp")]
    spheres = {f[:-len(".sphere.off")] for f in files if f.endswith(".sphere.off")}
    reports = {f[:-len(".report.json")] for f in files if f.endswith(".report.json")}
    with open(out / "summary.csv") as handle:
        listed = {row["mesh"] for row in csv.DictReader(handle)}
    assert listed == reports == spheres and 0 < len(listed) < 8       # exactly the complete meshes
    for name in spheres:
        X, F = load_mesh(out / (name + ".sphere.off"))
        assert certify(X, F).valid


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads /proc")
def test_batch_jobs_2_stops_its_workers_on_sigterm_and_writes_nothing_afterwards(tmp_path):
    inputs = slow_and_quick_meshes(tmp_path / "in")
    out = tmp_path / "out"
    process = subprocess.Popen(command("batch", inputs, "--out", out, "--jobs", "2"), env=env(),
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "summary.csv").exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.02)
    time.sleep(0.5)                                        # the workers are inside their next meshes
    children = descendants(process.pid)
    assert len(children) >= 2
    sent = time.perf_counter()
    process.send_signal(signal.SIGTERM)
    stderr = process.stderr.read()
    check_stopped_batch(out, process, sent, signal.SIGTERM, stderr)
    assert not [pid for pid in children if alive(pid)]     # workers and the resource tracker: gone


def test_a_sequential_batch_stops_the_running_ipopt_on_sigint(tmp_path):
    inputs = slow_and_quick_meshes(tmp_path / "in", slow=2)
    out = tmp_path / "out"
    # A wall-clock limit instead of the area modes' default budget: the solver then runs to its
    # optimum within it (tens of seconds), where the default budget maps these meshes in 1-2 s.
    process = subprocess.Popen(command("batch", inputs, "--out", out, "--jobs", "1", "--target",
                                       "original-areas", "--max-time", "60"),
                               env=env(), stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "summary.csv").exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.02)
    time.sleep(0.5)
    sent = time.perf_counter()
    process.send_signal(signal.SIGINT)
    stderr = process.stderr.read()
    check_stopped_batch(out, process, sent, signal.SIGINT, stderr)


@pytest.mark.slow
def test_dask_tasks_of_an_interrupted_batch_stop_and_leave_no_file(tmp_path):
    distributed = pytest.importorskip("distributed")
    from sphere_nlp.batch import map_meshes

    inputs = slow_and_quick_meshes(tmp_path / "in", slow=3)
    out = tmp_path / "out"
    stopped = []

    def progress(event, task, row, counts):
        if event == "done" and not stopped:            # the first mesh is in place: "Ctrl-C"
            stopped.append(time.perf_counter())
            raise KeyboardInterrupt

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        with pytest.raises(KeyboardInterrupt):
            map_meshes([inputs], out, target="original-areas", client=client, progress=progress, max_time=60)
        took = time.perf_counter() - stopped[0]
        before = folder_state(out)
        time.sleep(2.0)
        assert folder_state(out) == before                 # the running tasks stopped, wrote nothing
        assert took < 3.0
        assert client.processing() in ({}, {w: () for w in client.processing()})   # nothing running
    files = sorted(p.name for p in out.iterdir())
    assert not [f for f in files if f.endswith(".tmp")]
    with open(out / "summary.csv") as handle:
        listed = {row["mesh"] for row in csv.DictReader(handle)}
    assert listed == {f[:-len(".report.json")] for f in files if f.endswith(".report.json")}


# --- 3. every subcommand under the main command's contract ----------------------------------------

def test_help_lists_every_subcommand_and_a_misspelt_one_gets_a_suggestion(capsys):
    help_text = subprocess.run(command("--help"), capture_output=True, text=True, env=env()).stdout
    for name in SUBCOMMANDS:
        assert any(line.split()[:1] == [name] and len(line.split()) > 3 for line in help_text.splitlines()), name
    assert set(SUBCOMMANDS) == {"reproduce", "compare", "batch", "resample", "transfer", "morph", "picture"}
    for argv in (["resampel", "x.off"], ["resampel"], ["bach", "meshes/", "--out", "o"]):
        assert main(argv) == 2
        line = one_line(capsys.readouterr().err, "sphere-nlp: error: unknown command")
        assert "did you mean %r" % ("resample" if argv[0] == "resampel" else "batch") in line
    assert main(["nonsense"]) == 2
    assert "unknown command 'nonsense'" in one_line(capsys.readouterr().err, "sphere-nlp: error:")
    assert main(["missing.off"]) == 2                      # a file name: reported as a missing file
    assert "cannot read missing.off: no such file" in one_line(capsys.readouterr().err, "sphere-nlp: error:")


def test_subcommands_do_not_import_the_command_line_module():
    # The registry lives in sphere_nlp.commands: cli and every subcommand use it, none imports cli.
    code = ("import sys, sphere_nlp.resample, sphere_nlp.compare, sphere_nlp.batch, sphere_nlp.reproduce; "
            "print('sphere_nlp.cli' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env(), cwd=ROOT)
    assert out.stdout.strip() == "False", out.stderr


def test_view_takes_a_negative_azimuth_as_its_own_argument(tmp_path, capsys):
    for view in (["--view", "-60,20"], ["--view=-60,20"]):
        status = main([str(MODELS / "cylinder.off"), "-o", str(tmp_path / "s.off"), "--png", *view, "-q"])
        assert status == 0, capsys.readouterr().err
    assert main([str(MODELS / "cylinder.off"), "--view", "-60"]) == 2
    assert "expected AZIMUTH,ELEVATION" in one_line(capsys.readouterr().err, "sphere-nlp: error:")


@pytest.mark.parametrize("option,fragment", [
    (["--view", "nan,20"], "must be finite numbers of degrees, not 'nan,20'"),
    (["--view=inf,20"], "must be finite numbers of degrees, not 'inf,20'"),
    (["--view=-60,inf"], "must be finite numbers of degrees"),
    (["--view", "10,95"], "the elevation must be between -90 and 90 degrees, not 95"),
    (["--corner-floor", "nan"], "--corner-floor must be a number in [0, 1)"),
    (["--area-floor", "1"], "--area-floor must be a number in [0, 1)"),
    (["--area-floor=-0.5"], "--area-floor must be a number in [0, 1)"),
    (["--angle-weight", "inf"], "--angle-weight must be a finite number"),
    (["--area-weight", "-1"], "--area-weight must be a finite number >= 0"),
    (["--max-time", "nan"], "--max-time must be a finite number"),
    (["--max-iter", "0"], "--max-iter must be >= 1"),
    (["--up", "w"], "argument --up"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_every_numeric_option_is_checked_before_solving(option, fragment, tmp_path, capsys):
    outputs = ["-o", str(tmp_path / "s.off"), "--png"]
    started = time.perf_counter()
    assert main([str(MODELS / "cylinder.off"), *outputs, *option, "-q"]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and line.startswith("sphere-nlp: error: ") and fragment in line, line
    assert time.perf_counter() - started < 5 and os.listdir(tmp_path) == []


def test_batch_max_time_must_be_finite(tmp_path, capsys):
    assert main(["batch", str(MODELS / "cylinder.off"), "--out", str(tmp_path / "o"), "--max-time", "inf"]) == 2
    assert "--max-time must be a finite number of seconds > 0, not inf" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


# A run whose picture step meets a warning, as numpy's RuntimeWarnings or a library's notes reach it.
WARNING_PROGRAM = """
import runpy, sys, warnings
from sphere_nlp import picture
render_png = picture.render_png
def warned(*args, **kwargs):
    warnings.warn("invalid value encountered in divide", RuntimeWarning)
    return render_png(*args, **kwargs)
picture.render_png = warned
sys.argv = ["sphere-nlp"] + sys.argv[1:]
runpy.run_module("sphere_nlp", run_name="__main__")
"""


def test_quiet_silences_warnings_too(tmp_path):
    for quiet in ([], ["-q"]):
        p = subprocess.run([sys.executable, "-c", WARNING_PROGRAM, str(MODELS / "cylinder.off"), "-o",
                            str(tmp_path / "s.off"), "--png", *quiet],
                           capture_output=True, text=True, env=env(), cwd=tmp_path)
        assert p.returncode == 0, p.stderr
        assert ("RuntimeWarning" in p.stderr) == (not quiet), p.stderr
    assert p.stderr == ""                                   # -q: errors only, and there was none


@pytest.fixture
def meshes(tmp_path):
    S, F = icosphere(2)
    write_mesh(tmp_path / "a.off", S * [1.0, 1.4, 0.8], F)
    write_mesh(tmp_path / "b.off", S * [1.2, 1.0, 0.9], F)
    write_mesh(tmp_path / "torus.off", *meshgen.torus())
    np.save(tmp_path / "v.npy", np.arange(len(S), dtype=float))
    np.save(tmp_path / "short.npy", np.arange(5, dtype=float))
    return tmp_path


@pytest.mark.parametrize("argv,fragment", [
    (["resample", "{a}", "-o", "{a}"], "is the input mesh"),
    (["transfer", "{a}", "{b}", "--values", "{v}", "-o", "{v}"], "is the --values file"),
    (["resample", "{a}", "--sphere", "{d}/a.sphere.off", "-o", "{d}/a.sphere.off"], "is the --sphere file"),
    (["morph", "{a}", "{torus}", "--out", "{d}/m"], "torus.off: mesh has genus 1"),
    (["transfer", "{a}", "{torus}", "--values", "{v}", "-o", "{d}/o.npy"], "torus.off: mesh has genus 1"),
    (["transfer", "{a}", "{b}", "--values", "{short}", "-o", "{d}/o.npy"], "has 5 rows, A has 162 vertices"),
    (["resample", "{a}", "--sphere", "{b}", "-o", "{d}/r.off"], "is not a sphere centred at the origin"),
    (["compare", "{a}", "--out", "{d}", "--max-time", "-1"], "--max-time must be"),
    (["compare", "{a}", "--out", "{a}"], "it is a file, not a folder"),
    (["batch", "{a}", "--out", "{d}/o", "--jobs", "0"], "--jobs must be at least 1"),
    (["batch", "{a}", "--out", "{d}/o", "--max-iter", "0"], "--max-iter"),
    (["batch", "{d}/missing.off", "--out", "{d}/o"], "no such file or folder"),
    (["batch", "{a}", "--out", "{d}/o", "--bogus"], "unrecognized arguments: --bogus"),
    (["batch", "{a}", "{b}", "--out", "{d}", "--start", "{d}/a.sphere.off"], "would replace the --start sphere"),
    (["reproduce", "fig3", "--out", "{a}"], "it is a file, not a folder"),
    (["picture", "{a}", "{d}/a.sphere.off", "-o", "{a}"], "-o {d}/a.off is the input mesh"),
    (["picture", "{a}", "{d}/a.sphere.off", "-o", "{d}/a.sphere.off"], "is the sphere"),
    (["picture", "{a}", "{d}/a.sphere.off", "-o", "{d}/p.jpg"], "a picture must end in .png"),
    (["picture", "{a}", "{b}"], "b.off is not a sphere centred at the origin"),
    (["picture", "{a}", "{torus}"], "torus.off is not a sphere of {d}/a.off: 60 vertices / 120 faces against 162 / 320"),
    (["picture", "{a}", "{d}/missing.off"], "cannot read {d}/missing.off: no such file"),
    (["picture", "{a}", "{d}/a.sphere.off", "--view", "10,95"], "the elevation must be between -90 and 90"),
    (["picture", "{a}", "{d}/a.sphere.off", "--up", "w"], "argument --up"),
], ids=lambda v: v if isinstance(v, str) else " ".join(v[:1]))
def test_subcommands_check_everything_before_solving_in_one_line(argv, fragment, meshes, capsys):
    (meshes / "a.sphere.off").write_bytes((meshes / "a.off").read_bytes())     # a --start for batch
    argv = [a.format(a=meshes / "a.off", b=meshes / "b.off", v=meshes / "v.npy", short=meshes / "short.npy",
                     torus=meshes / "torus.off", d=meshes) for a in argv]
    before = folder_state(meshes)
    started = time.perf_counter()
    assert main(argv) == 2
    line = one_line(capsys.readouterr().err, "sphere-nlp %s: error: " % argv[0])
    assert fragment.format(d=meshes) in line, line
    assert time.perf_counter() - started < 10              # nothing was solved
    assert folder_state(meshes) == before                  # nothing written, the inputs untouched


def test_a_sphere_of_another_radius_is_scaled_and_the_run_says_so(tmp_path, capsys):
    S, F = icosphere(2)
    X = S * [1.0, 1.5, 0.7]
    write_mesh(tmp_path / "a.off", X, F)
    write_mesh(tmp_path / "a.sphere.off", 100.0 * S, F)    # FreeSurfer's radius
    assert main(["resample", str(tmp_path / "a.off"), "--sphere", str(tmp_path / "a.sphere.off"),
                 "--icosphere", "2", "-o", str(tmp_path / "r.off")]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == "sphere-nlp resample: %s: a sphere of radius 100, scaled onto the unit sphere" % (
        tmp_path / "a.sphere.off")
    V, G = load_mesh(tmp_path / "r.off")
    assert np.abs(V - X).max() < 1e-9                      # the same sphere vertices: the input back


def test_freesurfer_sphere_of_the_brain_resamples(tmp_path, capsys):
    brain = shared_mesh("brain_lh_pial_fsaverage5.off")
    sphere = shared_mesh("brain_lh_sphere_fsaverage5_reference.off")
    assert main(["resample", str(brain), "--sphere", str(sphere), "--icosphere", "3", "-o",
                 str(tmp_path / "r.off")]) == 0
    assert "a sphere of radius 100, scaled onto the unit sphere" in capsys.readouterr().err
    assert len(load_mesh(tmp_path / "r.off")[0]) == 642


# --- 4. non-mesh text in bounded memory -----------------------------------------------------------

PEAK_RSS_PROGRAM = """
import atexit, resource, runpy, sys
atexit.register(lambda: print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, flush=True))
sys.argv = ["sphere-nlp"] + sys.argv[1:]
runpy.run_module("sphere_nlp", run_name="__main__")
"""


@pytest.mark.parametrize("name,start,line", [
    ("garbage.off", b"OFF\n", b"1234567890 " * 7 + b"\n"),
    ("counts.off", b"OFF\n1000 2000 0\n", b"1234567890 " * 7 + b"\n"),
    ("prose.obj", b"v 1 2 3\n", b"lorem ipsum dolor sit amet, consectetur adipiscing elit\n"),
])
def test_fifty_megabytes_of_text_that_is_no_mesh_are_refused_in_bounded_memory(name, start, line, tmp_path):
    source = tmp_path / name
    with open(source, "wb") as handle:
        handle.write(start)
        block = line * (2 ** 20 // len(line))
        for _ in range(50):
            handle.write(block)
    started = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", PEAK_RSS_PROGRAM, str(source), "-o", str(tmp_path / "x.off")],
                       capture_output=True, text=True, env=env(), cwd=tmp_path)
    took = time.perf_counter() - started
    assert p.returncode == 2
    one_line(p.stderr, "sphere-nlp: error: cannot read %s" % source)
    peak_mb = int(p.stdout.split()[-1]) / 1024
    assert peak_mb <= 300, peak_mb
    assert took <= 5, took
    assert sorted(os.listdir(tmp_path)) == [name]


@pytest.mark.parametrize("name,text,fragment", [
    ("prose.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                  "property float z\nend_header\nnot numbers at all\n", "not a PLY file"),
    ("prose.stl", "solid x\nthis is not a facet\n", "not an STL file"),
])
def test_ply_and_stl_text_without_a_mesh_body_are_refused_from_the_first_lines(name, text, fragment, tmp_path):
    source = tmp_path / name
    source.write_text(text)
    with pytest.raises(Exception, match=fragment):
        load_mesh(source)


@pytest.mark.slow
def test_a_real_mesh_of_sixty_megabytes_still_loads_in_bounded_memory(tmp_path):
    V, F = icosphere(8)                                    # 655,362 vertices: a 69 MB OFF
    write_mesh(tmp_path / "big.off", V * [1.0, 2.0, 3.0], F)
    code = ("import resource; from sphere_nlp.mesh_io import load_mesh; V, F = load_mesh(%r); "
            "print(len(V), len(F), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)" % str(tmp_path / "big.off"))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env())
    n_vertices, n_faces, peak_kb = map(int, p.stdout.split())
    assert (n_vertices, n_faces) == (len(V), len(F))
    assert peak_kb / 1024 < 400                            # the arrays (47 MB) and the interpreter


# --- 5. --max-time from the start of the process, and failure lines that are true -----------------

def test_max_time_counts_from_the_start_of_the_process(tmp_path):
    # A limit shorter than the imports: the run stops before IPOPT's first iteration and says so.
    p = subprocess.run(command(MODELS / "cylinder.off", "-o", tmp_path / "s.off", "--max-time", "0.2"),
                       capture_output=True, text=True, env=env())
    assert p.returncode == 1
    line = p.stderr.strip().splitlines()[-1]
    assert "Maximum_WallTime_Exceeded" in line and "before IPOPT's first iteration" in line
    assert line.endswith("; nothing written") and not (tmp_path / "s.off").exists()


@pytest.mark.parametrize("raised,line", [
    (lambda: errors.SolveError("the angle solve failed (IPOPT status Invalid_Number_Detected after 0 "
                               "iterations)"),
     "sphere-nlp resample: error: the angle solve failed (IPOPT status Invalid_Number_Detected after 0 "
     "iterations); nothing written"),
    (lambda: errors.CertificateError("the sphere failed its certificate: 2 flipped triangles"),
     "sphere-nlp resample: error: the sphere failed its certificate: 2 flipped triangles; nothing written"),
    (MemoryError, "sphere-nlp resample: error: out of memory; nothing written"),
    (lambda: KeyError("x"), "sphere-nlp resample: internal error: KeyError: 'x'; nothing written"),
])
def test_every_exit_1_line_of_a_subcommand_says_what_was_written(raised, line, capsys):
    from sphere_nlp.commands import run_subcommand, subcommand_parser

    def body(args, say):
        raise raised()

    status = run_subcommand(subcommand_parser("resample", "test"), [], body, interrupted="nothing written")
    assert status == 1
    assert capsys.readouterr().err.splitlines() == [line]


def test_a_failed_batch_says_what_it_wrote_even_when_quiet(tmp_path, capsys):
    write_mesh(tmp_path / "torus.off", *meshgen.torus())
    write_mesh(tmp_path / "ball.off", *icosphere(1))
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "torus.off"), str(tmp_path / "ball.off"), "--out", str(out), "-q"]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "sphere-nlp batch: error: 1 of 2 mesh(es) failed (reasons in %s); wrote the 1 certified (0 already "
        "done) and the summary to %s" % (out / "summary.md", out)]
    assert (out / "ball.sphere.off").exists() and not (out / "torus.sphere.off").exists()
