"""The CLI's promise under odd conditions: signals, output paths, odd files, limits, API misuse.

Every usage or output-path problem is found before any solving (exit 2, one line); one SIGINT or
SIGTERM at any moment ends the run (exit 130 / 143) with no output created or replaced and no
temporary file left; all outputs are renamed into place together after everything succeeded.
"""

import json
import os
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp import errors, interrupts, mesh_io
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import load_mesh, output_transaction, write_json, write_mesh
from sphere_nlp.shapes import octahedron, tetrahedron

import meshgen

ROOT = Path(__file__).resolve().parents[1]
PRECIOUS = "an existing file that an interrupted run must not touch\n"
TETRA_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def run_cli(capsys, *args):
    status = main([str(a) for a in args])
    return status, capsys.readouterr().err


def one_error_line(stderr, *fragments):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("sphere-nlp: error: ") and "Traceback" not in stderr, stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def listing(folder):
    """{name: bytes} of a folder's files, to compare before and after a run."""
    return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir()) if p.is_file()}


@pytest.fixture
def small_mesh(tmp_path):
    path = tmp_path / "in" / "ellipsoid.off"
    path.parent.mkdir()
    write_mesh(path, *meshgen.ellipsoid(2))
    return path


def env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


# --- 1. signals -----------------------------------------------------------------------------------

def _interrupt(folder, mesh, signum, wait_for, delay, extra=(), pause=None):
    """Start a real run, send ``signum`` ``delay`` s after stderr shows ``wait_for``; return
    (exit status, stderr, seconds from the signal to the exit)."""
    environment = env()
    if pause:
        environment["SPHERE_NLP_TEST_WRITE_PAUSE"] = pause
    process = subprocess.Popen([sys.executable, "-m", "sphere_nlp", str(mesh), "-o", "out.off",
                                "--report", "report.json", "--save-solution", "solution.npz", *extra],
                               cwd=folder, env=environment, stderr=subprocess.PIPE, text=True)
    lines = []
    for line in process.stderr:
        lines.append(line)
        if wait_for in line:
            break
    else:
        process.wait()
        pytest.fail("the run ended before %r: %s" % (wait_for, "".join(lines)))
    time.sleep(delay)
    sent = time.perf_counter()
    process.send_signal(signum)
    rest = process.stderr.read()
    status = process.wait(timeout=120)
    return status, "".join(lines) + rest, time.perf_counter() - sent


SLOW = pytest.mark.slow
MOMENTS = {
    # The original-areas solve of a stretched icosphere(4) takes about 16 s: interrupted inside IPOPT.
    "solve-sigint": (signal.SIGINT, "mapping", 2.0, ["--target", "original-areas"], None),
    "solve-sigterm": (signal.SIGTERM, "mapping", 2.0, ["--target", "original-areas"], None),
    # Writing: before any output, and when every temporary file is written and none is renamed.
    "write-start-sigint": (signal.SIGINT, "test pause at start", 0.2, [], "start:30"),
    "write-staged-sigterm": (signal.SIGTERM, "test pause at staged", 0.2, [], "staged:30"),
    "write-staged-sigint": (signal.SIGINT, "test pause at staged", 0.2, [], "staged:30"),
}


@pytest.mark.parametrize("moment", [pytest.param(m, marks=SLOW) if m in ("solve-sigterm", "write-start-sigint", "write-staged-sigint")
                                    else m for m in MOMENTS], ids=list(MOMENTS))
def test_one_signal_at_any_moment_ends_the_run_and_leaves_the_folder_as_it_was(moment, tmp_path):
    signum, wait_for, delay, extra, pause = MOMENTS[moment]
    mesh = tmp_path / "mesh.off"
    write_mesh(mesh, *(meshgen.ellipsoid(4, axes=(1.0, 6.0, 0.2)) if pause is None else meshgen.ellipsoid(2)))
    (tmp_path / "out.off").write_text(PRECIOUS)            # an existing output, to be kept as it is
    before = listing(tmp_path)
    status, stderr, after_signal = _interrupt(tmp_path, mesh, signum, wait_for, delay, extra, pause)
    assert status == 128 + signum, stderr
    assert stderr.strip().splitlines()[-1] == ("sphere-nlp: interrupted; nothing written (%s)"
                                                % signal.Signals(signum).name), stderr
    assert "wrote" not in stderr
    assert listing(tmp_path) == before                     # nothing created, replaced or left over
    assert after_signal < 15, after_signal                 # IPOPT did not carry on with its next stage


def test_a_signal_inside_ipopt_stops_the_solve_and_is_raised_again(monkeypatch):
    """IPOPT catches what its callbacks raise; the recorded signal must still end parameterize."""
    V, F = meshgen.ellipsoid(3)
    calls = []
    # parameterize takes over SIGINT only from Python's default handler (see interrupts.handled_signals)
    signal.signal(signal.SIGINT, signal.default_int_handler)

    def progress(stage, iteration, *_):
        calls.append((stage, iteration))
        if iteration == 1:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt) as info:
        sphere_nlp.parameterize((V, F), target="equal-areas", progress=progress)
    assert isinstance(info.value, interrupts.Interrupted) and info.value.exit_status == 130
    # No later stage ran (the start's parts announce themselves before the first stage).
    assert max(i for _, i in calls) <= 2 and len({s for s, _ in calls if not s.startswith("start")}) == 1
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_signal_inside_a_finaliser_prints_no_traceback_and_still_ends_the_run(capfd, monkeypatch):
    """Python cannot raise out of a __del__: a signal raised there was printed as "Exception ignored
    in ..." with a traceback (once in 36 SIGINTs into a knight run) while the run went on; it is
    recorded, so the run's next check ends it, and nothing is printed."""
    import gc

    signal.signal(signal.SIGINT, signal.default_int_handler)
    monkeypatch.setattr(sys, "unraisablehook", sys.__unraisablehook__)     # Python's, not pytest's
    freed = []

    class Finalised:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            freed.extend(range(1000))           # bytecodes for the handler to run in

    with pytest.raises(interrupts.Interrupted):
        with interrupts.handled_signals():
            item = Finalised()
            item.cycle = item                   # freed by the collector, as library objects are
            del item
            gc.collect()
            assert interrupts.pending_signal() == signal.SIGINT and len(freed) < 1000
            interrupts.raise_if_interrupted()
    assert capfd.readouterr().err == ""
    assert sys.unraisablehook is sys.__unraisablehook__


def test_a_failed_rename_undoes_the_renames_before_it(tmp_path, monkeypatch):
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    first.write_text(PRECIOUS)
    real_replace = os.replace
    renamed = []

    def replace(source, target):
        if Path(target) == second:
            raise OSError(28, "No space left on device")
        renamed.append(target)
        real_replace(source, target)

    monkeypatch.setattr(mesh_io.os, "replace", replace)
    with pytest.raises(OSError):
        with output_transaction():
            write_json(first, {"new": 1})
            write_json(second, {"new": 2})
    assert renamed and first.read_text() == PRECIOUS and not second.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


# --- 2. byte-order marks --------------------------------------------------------------------------

@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16", "utf-32"])
def test_a_byte_order_mark_does_not_lose_the_first_vertex(encoding, tmp_path):
    plain, marked = tmp_path / "plain.obj", tmp_path / "marked.obj"
    plain.write_text(TETRA_OBJ)
    marked.write_bytes(TETRA_OBJ.encode(encoding))
    for reference, result in zip(load_mesh(plain), load_mesh(marked)):
        np.testing.assert_array_equal(result, reference)
    off = tmp_path / "marked.off"
    off.write_bytes(b"\xef\xbb\xbfOFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    np.testing.assert_array_equal(load_mesh(off)[1], load_mesh(plain)[1])


# --- 3. data loss: the input and one path for two outputs -----------------------------------------

@pytest.mark.parametrize("options", [
    ["-o", "{input}"],
    ["-o", "x.obj", "--textured-input", "x.obj"],
    ["--save-solution", "x.off", "-o", "x.off"],
    ["-o", "p.off", "--png", "--report", "p.png"],
    ["-o", "sub/../x.off", "--report", "x.off"],
    ["--textured-input", "{input_obj}"],
    ["-o", "p.obj", "--texture", "p.png", "--png"],
], ids=["output-is-input", "output-textured", "solution-output", "report-png", "same-file-other-spelling",
        "textured-is-input", "texture-png"])
def test_outputs_must_differ_from_each_other_and_from_the_input(options, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    source = tmp_path / "mesh.off"
    write_mesh(source, *meshgen.ellipsoid(2))
    source_obj = tmp_path / "mesh.obj"
    write_mesh(source_obj, *meshgen.ellipsoid(2))
    used = source_obj if "{input_obj}" in options else source
    options = [o.format(input=source, input_obj=source_obj) for o in options]
    before = listing(tmp_path)
    status, stderr = run_cli(capsys, used, *options)
    assert status == 2
    one_error_line(stderr)
    assert "mapping" not in stderr and listing(tmp_path) == before


# --- 4. output paths found before solving ---------------------------------------------------------

@pytest.mark.parametrize("option,name,fragment", [
    ("--textured-input", "missing/t.obj", "no such folder"),
    ("--save-solution", "missing/s.npz", "no such folder"),
    ("--report", "missing/r.json", "no such folder"),
    ("-o", "missing/o.off", "no such folder"),
    ("-o", "a_file.txt/o.off", "is not a folder"),
    ("-o", "a_folder.off", "it is a folder"),
    ("--report", "x" * 300 + ".json", "name too long"),
], ids=["textured", "solution", "report", "output", "parent-is-file", "output-is-folder", "too-long"])
def test_every_output_path_problem_is_found_before_solving(option, name, fragment, tmp_path, capsys,
                                                           monkeypatch, small_mesh):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file.txt").write_text("x")
    (tmp_path / "a_folder.off").mkdir()
    args = [option, name] if option == "-o" else ["-o", "sphere.off", option, name]
    before = listing(tmp_path)
    status, stderr = run_cli(capsys, small_mesh, *args)
    assert status == 2 and "mapping" not in stderr
    assert fragment in one_error_line(stderr, option).lower()
    assert listing(tmp_path) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_found_before_solving(tmp_path, capsys, small_mesh):
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        status, stderr = run_cli(capsys, small_mesh, "-o", folder / "x.off")
    finally:
        folder.chmod(0o700)
    assert status == 2 and "permission denied" in one_error_line(stderr).lower()


def test_huge_coordinates_map_or_fail_cleanly_with_nothing_written(tmp_path, capsys):
    V, F = octahedron()
    source = tmp_path / "huge.off"
    write_mesh(source, V * 1.7e308, F)             # the bounding box is wider than 1.8e308
    status, stderr = run_cli(capsys, source, "-o", tmp_path / "out.obj", "--textured-input",
                             tmp_path / "t.obj", "--png", "--report", tmp_path / "r.json",
                             "-q")
    assert "internal error" not in stderr, stderr
    if status == 0:
        assert {"out.obj", "t.obj", "out.png", "r.json"} <= set(os.listdir(tmp_path))
        V_out, F_out = load_mesh(tmp_path / "out.obj")
        np.testing.assert_allclose(np.linalg.norm(V_out, axis=1), 1.0, atol=1e-12)
    else:
        assert sorted(os.listdir(tmp_path)) == ["huge.off"]


def test_a_failure_after_some_outputs_were_staged_writes_none_of_them(tmp_path, capsys, monkeypatch,
                                                                       small_mesh):
    existing = tmp_path / "out.off"
    existing.write_text(PRECIOUS)

    def broken_png(self, path, measure="area"):
        raise RuntimeError("the picture failed")

    monkeypatch.setattr(sphere_nlp.api.SphericalParameterization, "write_png", broken_png)
    status, stderr = run_cli(capsys, small_mesh, "-o", existing, "--save-solution", tmp_path / "s.npz",
                             "--png", "-q")
    assert status == 1 and "nothing written" in stderr
    assert sorted(os.listdir(tmp_path)) == ["in", "out.off"] and existing.read_text() == PRECIOUS


# --- 5. limits that hold --------------------------------------------------------------------------

@pytest.mark.parametrize("option,value,fragment", [
    ("--max-time", "nan", "--max-time must be a finite number"),
    ("--max-time", "inf", "--max-time must be a finite number"),
    ("--max-time", "0", "--max-time must be > 0"),
    ("--max-time", "-1", "--max-time must be > 0"),
    ("--max-iter", "-5", "--max-iter must be >= 1"),
    ("--max-iter", "0", "--max-iter must be >= 1"),
    ("--angle-weight", "nan", "--angle-weight must be a finite number"),
    ("--area-weight", "inf", "--area-weight must be a finite number"),
    ("--area-weight", "-1", "--area-weight must be a finite number >= 0"),
], ids=lambda v: str(v))
def test_bad_limits_and_weights_are_usage_errors(option, value, fragment, tmp_path, capsys, small_mesh):
    status = main([str(small_mesh), "-o", str(tmp_path / "x.off"), option, value])
    captured = capsys.readouterr()
    assert status == 2 and captured.out == ""
    one_error_line(captured.err, fragment)
    assert not (tmp_path / "x.off").exists()


def test_max_time_bounds_the_whole_run_not_each_stage():
    # The area modes' NLP (start="conformal") runs several IPOPT stages (continuation steps, margin;
    # about 2 s here in all): the limit covers them together.
    V, F = meshgen.ellipsoid(3, axes=(1.0, 6.0, 0.2))
    limit = 0.5
    start = time.perf_counter()
    result = sphere_nlp.parameterize((V, F), target="original-areas", max_time=limit, check=False,
                                     start="conformal")
    elapsed = time.perf_counter() - start
    assert result.status == "Maximum_WallTime_Exceeded" and not result.success
    ran = [s for s in result.stages if s["iterations"] > 0]
    # The stated tolerance: one more IPOPT iteration past the limit, then the unfolding and certificate.
    # Time outside IPOPT (building each stage's NLP) is measured, not bounded: on a loaded machine it
    # alone can outlast the limit, and then no stage iterates at all.
    slowest_iteration = max((s["time_s"] / s["iterations"] for s in ran), default=0.0)
    in_ipopt = sum(s["time_s"] for s in result.stages)
    assert in_ipopt < limit + 2 * slowest_iteration + 0.5
    assert elapsed - result.timings["solve"] < result.timings["unfold"] + result.timings["certify"] + 0.5


def test_a_vertex_of_degree_1000_keeps_the_kkt_system_sparse_and_maps():
    # A finely segmented cap: both apexes of degree 1,000. The three vertex sums (7) left out are
    # at ordinary vertices (an apex's penalty Hessian alone had 8 million nonzeros), and the start
    # survives floating point, so the whole run takes about a second.
    from sphere_nlp.connectivity import build_connectivity
    from sphere_nlp.solve import independent_vertices

    V, F = meshgen.bipyramid(1000)
    degree = build_connectivity(F, len(V)).vertex_degree
    assert degree[independent_vertices(V / np.linalg.norm(V, axis=1, keepdims=True), degree)].max() == 4
    result = sphere_nlp.parameterize((V, F))
    assert result.certificate.valid and result.max_constraint_violation < 1e-8
    top, bottom = result.vertices[1000:]
    assert top @ bottom < -1 + 1e-6              # the symmetric map: apexes antipodal


# --- 6. exit codes and one-line messages ----------------------------------------------------------

@pytest.mark.parametrize("name,text", [
    ("big.off", "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 12345678901234567890\n"),
    ("big.obj", TETRA_OBJ.replace("f 2 3 4", "f 2 3 12345678901234567890")),
])
def test_a_twenty_digit_face_index_is_a_face_index_error(name, text, tmp_path, capsys):
    source = tmp_path / name
    source.write_text(text)
    with pytest.raises(errors.FaceIndexError, match="12345678901234567890"):
        load_mesh(source)
    status, stderr = run_cli(capsys, source, "-o", tmp_path / "x.off")
    assert status == 2
    one_error_line(stderr, "face 3 refers to vertex 12345678901234567890", "does not exist")


@pytest.mark.parametrize("name", ["m.off", "m.obj", "m.ply", "m.stl"])
def test_an_unreadable_file_is_one_line_exit_2(name, tmp_path, capsys, monkeypatch):
    source = tmp_path / name
    source.write_text("OFF\n" if name.endswith(".off") else "x\n")
    if os.geteuid() == 0:                   # root reads anything: make open() refuse as it would
        real_open = open

        def refusing_open(file, *args, **kwargs):
            if Path(file) == source:
                raise PermissionError(13, "Permission denied", str(file))
            return real_open(file, *args, **kwargs)

        monkeypatch.setattr("builtins.open", refusing_open)
    else:
        source.chmod(0)
    status, stderr = run_cli(capsys, source, "-o", tmp_path / "x.off")
    assert status == 2
    one_error_line(stderr, str(source), "Permission denied")


def test_argparse_errors_are_one_line_with_the_tools_prefix(capsys):
    for argv in ([], ["m.off", "--bogus"], ["m.off", "--max-iter", "abc"], ["m.off", "--target", "x"]):
        assert main(argv) == 2
        line = one_error_line(capsys.readouterr().err)
        assert line.endswith("(see sphere-nlp --help)")


@pytest.mark.parametrize("good", [True, False])
def test_a_closed_stderr_does_not_change_the_outcome(good, tmp_path):
    source = tmp_path / "mesh.off"
    if good:
        write_mesh(source, *meshgen.ellipsoid(2))
    else:
        source.write_text("OFF\n4 4 0\n")
    process = subprocess.run([sys.executable, "-m", "sphere_nlp", str(source), "-o", "out.off"], cwd=tmp_path,
                             env=env(), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                             preexec_fn=lambda: os.close(2), timeout=300)
    assert process.returncode == (0 if good else 2)
    assert (tmp_path / "out.off").exists() == good


# --- 7. messages for corrupt files ----------------------------------------------------------------

@pytest.mark.parametrize("name,data,fragment", [
    ("bad.stl", b"\x00\x01garbage that is neither ascii nor binary STL" * 3, "not an STL file"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "no end_header"),
    ("bad2.ply", b"not a ply at all\n", "not a PLY file"),
])
def test_corrupt_stl_and_ply_name_the_defect(name, data, fragment, tmp_path, capsys):
    source = tmp_path / name
    source.write_bytes(data)
    status, stderr = run_cli(capsys, source, "-o", tmp_path / "x.off")
    assert status == 2
    one_error_line(stderr, fragment)


# --- 8. default names -----------------------------------------------------------------------------

@pytest.mark.parametrize("name,expected", [("knight.v1.off", "knight.v1.sphere.off"),
                                           (".hidden.off", ".hidden.sphere.off"),
                                           ("plain.off", "plain.sphere.off")])
def test_default_output_keeps_every_part_of_the_name_but_the_extension(name, expected, tmp_path, capsys,
                                                                       monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_mesh(tmp_path / name, *tetrahedron())
    assert run_cli(capsys, name, "-q")[0] == 0
    assert sorted(os.listdir(tmp_path)) == sorted([name, expected])


def test_default_output_names_a_mode_other_than_the_default(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_mesh(tmp_path / "t.off", *tetrahedron())
    assert run_cli(capsys, "t.off", "-q")[0] == 0
    assert run_cli(capsys, "t.off", "-q", "--target", "equal-angles")[0] == 0
    # Two maps, two files: the second did not replace the first.
    assert sorted(os.listdir(tmp_path)) == ["t.equal-angles.sphere.off", "t.off", "t.sphere.off"]


# --- 9. the API -----------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs", [
    dict(max_iter="abc"), dict(max_iter=-5), dict(max_iter=2.5), dict(max_iter=True),
    dict(max_time=-1), dict(max_time=float("nan")), dict(max_time="10"),
    dict(angle_weight=float("nan")), dict(area_weight=float("inf")), dict(angle_weight=1j),
    dict(ipopt_options={"no_such_option": 1}), dict(ipopt_options={"tol": "abc"}),
    dict(ipopt_options={"max_iter": -1}),
], ids=lambda kw: ",".join("%s=%r" % item for item in kw.items()))
def test_api_bad_arguments_are_usage_errors(kwargs, capfd):
    with pytest.raises(errors.UsageError) as info:
        sphere_nlp.parameterize(octahedron(), **kwargs)
    assert "\n" not in str(info.value)
    assert capfd.readouterr().out == ""                    # no IPOPT option dump


@pytest.mark.parametrize("vertices", [
    octahedron()[0].astype(complex),
    [[10 ** 400, 0, 0]] + octahedron()[0][1:].tolist(),
], ids=["complex", "beyond-float"])
def test_api_rejects_complex_and_overflowing_coordinates(vertices):
    with pytest.raises(errors.UsageError):
        sphere_nlp.parameterize((vertices, octahedron()[1]))


# --- 10. garbage rejected cheaply -----------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".off", ".obj"])
def test_a_large_garbage_file_is_rejected_from_its_first_bytes(suffix, tmp_path):
    source = tmp_path / ("garbage" + suffix)
    line = b"1234567890" * 7 + b"\n"
    with open(source, "wb") as handle:
        for _ in range(50 * 2 ** 20 // (len(line) * 1024)):
            handle.write(line * 1024)
    tracemalloc.start()
    try:
        with pytest.raises(errors.UnreadableMeshError, match="not an (OFF|OBJ) file"):
            load_mesh(source)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * 2 ** 20                              # the header only, not 50 MB


def test_a_run_keeps_numpy_and_scipy_blas_on_one_thread_and_gives_the_threads_back():
    # OpenBLAS splits a reduction by its thread count: with the caller's thread count the map would
    # depend on the machine (api._bounded). The caller's setting is restored afterwards.
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]

    V, F = meshgen.ellipsoid(2)
    seen = []
    with threadpool_limits(limits=2, user_api="blas"):
        result = sphere_nlp.parameterize((V, F), progress=lambda *_: seen.append(blas_threads()))
        after = blas_threads()
    assert result.certificate.valid
    assert seen and all(threads and set(threads) == {1} for threads in seen)
    assert after and set(after) == {2}
