"""Compare sphere_nlp with baseline maps: ``python -m sphere_nlp compare MESH... --out DIR``.

Every method runs on every mesh; each (mesh, method) pair is one row of ``DIR/compare.json`` and of the
Markdown table ``DIR/compare.md``, with the validity and distortion of :func:`sphere_nlp.metrics.
distortion_summary` and the wall-clock time. A method that fails (a solve that does not converge, a map
with flipped triangles, an exception) is a row with ``valid`` false and a ``status`` saying why, not an
error: both files are rewritten atomically after every row, so an interrupted run keeps what it did.
The command checks every mesh before anything runs: one that cannot be read or is not a valid genus-0
surface ends it there (exit 2, nothing run or written). :func:`compare` itself, called from Python,
gives such a mesh one row saying why (method ``-``) and runs the others. ``--save-maps`` also writes
each valid map's sphere (OBJ with texture coordinates) and picture.

Methods: ``sphere_nlp:<mode>`` for the four target modes (``sphere_nlp`` selects all four),
``conformal``, ``cmcf``, ``alexa`` and ``tutte-projection`` (see :mod:`sphere_nlp.baselines`); ``all``
for every one. By default :data:`DEFAULT_METHODS`: sphere_nlp's conformal mode against the two conformal
baselines, seconds per mesh (the area modes and Alexa's relaxation take minutes on large meshes).

Exit status: 0 all rows written (whatever their validity); 2 an unknown method, a bad option value, a
rejected mesh, an output folder that cannot be written or an output that would replace an input (found
before anything runs; nothing written); 130 / 143 interrupted (the rows done so far are kept).
"""

import math
import time
from pathlib import Path

import numpy as np

from . import errors
from .metrics import SUMMARY_KEYS, distortion_summary
from .targets import MODES

SPHERE_NLP_METHODS = tuple("sphere_nlp:" + mode for mode in MODES)
BASELINE_METHODS = ("conformal", "cmcf", "alexa", "tutte-projection")
METHODS = SPHERE_NLP_METHODS + BASELINE_METHODS
DEFAULT_METHODS = ("sphere_nlp:original-angles", "conformal", "cmcf")
REJECTED_METHOD = "-"            # the method column of a rejected mesh's row

# The columns of compare.md: (row key, header, format).
TABLE_COLUMNS = (("mesh", "mesh", "%s"), ("method", "method", "%s"), ("valid", "valid", "%s"),
                 ("flipped", "flipped", "%d"), ("mean_abs_angle_diff_deg", "mean abs Δangle (°)", "%.2f"),
                 ("qc_mean", "QC mean", "%.3f"), ("qc_max", "QC max", "%.3g"),
                 ("mean_abs_log_area", "mean abs log area ratio", "%.3f"), ("time_s", "time (s)", "%.2f"),
                 ("status", "status", "%s"))


def parse_methods(text):
    """Method names from a comma-separated list; ``sphere_nlp`` expands to the four modes, ``all`` to
    every method.

    Examples
    --------
    >>> parse_methods("sphere_nlp:equal-areas,tutte-projection")
    ['sphere_nlp:equal-areas', 'tutte-projection']
    >>> len(parse_methods("sphere_nlp,cmcf")), len(parse_methods("all"))
    (5, 8)
    """
    methods = []
    for name in (part.strip() for part in text.split(",")):
        expanded = (SPHERE_NLP_METHODS if name == "sphere_nlp" else METHODS if name == "all" else (name,))
        for method in expanded:
            if method not in METHODS:
                raise errors.UsageError("unknown method %r; choose from %s (or sphere_nlp for its four modes, "
                                        "all for every method)"
                                        % (name, ", ".join(METHODS)))
            if method not in methods:
                methods.append(method)
    if not methods:
        raise errors.UsageError("no method given")
    return methods


def _run_baseline(method, vertices, faces):
    """Positions of a baseline and a note (iterations for Alexa)."""
    from . import baselines

    if method == "conformal":
        return baselines.conformal_map(vertices, faces), ""
    if method == "cmcf":
        return baselines.cmcf_map(vertices, faces), ""
    if method == "tutte-projection":
        return baselines.tutte_projection(vertices, faces), ""
    relaxed = baselines.alexa_relaxation(vertices, faces)
    return relaxed.positions, "%d iterations, %s" % (relaxed.iterations,
                                                     "converged" if relaxed.converged else "not converged")


def _metrics(mesh_vertices, positions, faces):
    """distortion_summary, or all None (and invalid) when a method produced no usable positions."""
    if positions is None or not np.isfinite(positions).all():
        return {**dict.fromkeys(SUMMARY_KEYS), "valid": False}
    return distortion_summary(mesh_vertices, positions, faces)


def run_method(method, mesh, prepared, max_time=None, keep=None):
    """One row: run ``method`` on a loaded mesh and measure it.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`.
    mesh : (vertices, faces)
        The mesh as read (sphere_nlp repairs it itself).
    prepared : sphere_nlp.repair.PreparedMesh
        The same mesh repaired, what the baselines run on and the metrics compare with.
    max_time : float, optional
        Wall-clock limit of each sphere_nlp run (see :func:`~sphere_nlp.api.parameterize`).
    keep : dict, optional
        Receives ``positions``, the map's sphere positions (None if it made none), for saving.

    Returns
    -------
    dict
        ``method``, ``valid``, ``status``, ``note``, ``time_s`` and the keys of
        :func:`~sphere_nlp.metrics.distortion_summary` (None where the method produced no positions).
    """
    from .api import parameterize, solve_failure_message

    clock = time.perf_counter()
    note = ""
    try:
        if method in SPHERE_NLP_METHODS:
            result = parameterize(mesh, target=method.split(":", 1)[1], max_time=max_time, check=False)
            elapsed = time.perf_counter() - clock
            positions = result.vertices
            if result.success:
                status = "certified"
            elif not result.solved:
                status = solve_failure_message(result.status, result.iterations)
            else:
                status = "certificate failed: " + result.certificate.reason
            note = "%d iterations" % result.iterations
        else:
            positions, note = _run_baseline(method, prepared.vertices, prepared.faces)
            elapsed = time.perf_counter() - clock
            status = ""
    except (MemoryError, errors.SphereNLPError, ArithmeticError, ValueError, RuntimeError,
            np.linalg.LinAlgError) as exc:
        # A method that breaks is a result of the comparison, not the end of it.
        elapsed = time.perf_counter() - clock
        positions, status = None, "error: %s: %s" % (type(exc).__name__, exc)
    row = {"method": method}
    with np.errstate(all="ignore"):
        row.update(_metrics(prepared.vertices, positions, prepared.faces))
    if method in SPHERE_NLP_METHODS and positions is not None:
        row["valid"] = bool(result.success)         # solved to tolerance *and* certified
    if not status:
        status = "valid" if row["valid"] else ("invalid: %s flipped" % row["flipped"]
                                               if row["flipped"] else "invalid")
    row.update(time_s=round(elapsed, 4), status=status, note=note)
    if keep is not None:
        keep["positions"] = positions
    return row


def markdown_table(rows):
    """The rows as a Markdown table (None shows as an empty cell).

    Examples
    --------
    >>> print(markdown_table([{"mesh": "m.off", "method": "cmcf", "valid": True, "flipped": 0,
    ...                        "mean_abs_angle_diff_deg": 1.0, "qc_mean": 1.1, "qc_max": None,
    ...                        "mean_abs_log_area": 0.2, "time_s": 0.5, "status": "valid"}]))
    | mesh | method | valid | flipped | mean abs Δangle (°) | QC mean | QC max | mean abs log area ratio | time (s) | status |
    |---|---|---|---|---|---|---|---|---|---|
    | m.off | cmcf | True | 0 | 1.00 | 1.100 |  | 0.200 | 0.50 | valid |
    """
    lines = ["| " + " | ".join(header for _, header, _ in TABLE_COLUMNS) + " |",
             "|" + "---|" * len(TABLE_COLUMNS)]
    for row in rows:
        cells = []
        for key, _, fmt in TABLE_COLUMNS:
            value = row.get(key)
            cell = "" if value is None else fmt % value
            cells.append(cell.replace("|", "\\|").replace("\n", " "))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_outputs(out_dir, rows):
    """Write ``compare.json`` and ``compare.md`` atomically."""
    from .mesh_io import atomic_output, write_json

    write_json(Path(out_dir) / "compare.json", rows)
    with atomic_output(Path(out_dir) / "compare.md") as out:
        out.write(markdown_table(rows) + "\n")


def load_meshes(paths):
    """Read and check every mesh before anything runs.

    Returns ``(loaded, rejected)``: ``loaded`` is [(name, (V, F), PreparedMesh)] of the good meshes,
    ``rejected`` [(name, message)] of the others, each message naming the file and its defect.
    """
    from .mesh_io import load_mesh
    from .repair import prepare_mesh

    loaded, rejected = [], []
    for path in paths:
        try:
            vertices, faces = load_mesh(path)
            prepared = prepare_mesh(vertices, faces)
        except errors.MeshInputError as exc:
            message = str(exc) if str(path) in str(exc) else "%s: %s" % (path, exc)
            rejected.append((Path(path).name, message))
            continue
        loaded.append((Path(path).name, (vertices, faces), prepared))
    return loaded, rejected


def save_map(out_dir, name, method, mesh_vertices, positions, faces):
    """Write a valid map's sphere (OBJ with texture coordinates) and picture as
    ``DIR/<mesh stem>.<method>.obj`` and ``.png`` (``:`` in the method's name becomes ``-``);
    returns the two paths. Only certified positions are written."""
    from .certify import certify
    from .mesh_io import write_mesh
    from .picture import default_measure, render_png
    from .texture import spherical_uv

    if not certify(positions, faces).valid:
        return []
    stem = "%s.%s" % (Path(name).stem, method.replace(":", "-"))
    sphere, picture = Path(out_dir) / (stem + ".obj"), Path(out_dir) / (stem + ".png")
    corner_uv = spherical_uv(positions, faces)
    write_mesh(sphere, positions, faces, corner_uv)
    target = method.split(":", 1)[1] if method in SPHERE_NLP_METHODS else "original-angles"
    render_png(picture, mesh_vertices, positions, faces, measure=default_measure(target),
               title="%s: %s" % (name, method), corner_uv=corner_uv)
    return [sphere, picture]


def compare(paths, out_dir, methods=DEFAULT_METHODS, max_time=None, progress=None, save_maps=False,
            loaded=None):
    """Run ``methods`` on every mesh in ``paths``; write and return the rows.

    Parameters
    ----------
    paths : list of str or Path
    out_dir : str or Path
        Created if missing; receives ``compare.json`` and ``compare.md`` (rewritten after every row).
    methods : list of str
        Names from :data:`METHODS`.
    max_time : float, optional
        Wall-clock limit of each sphere_nlp run.
    progress : callable(str), optional
        Receives one line per row, and one per rejected mesh before anything runs.
    save_maps : bool
        Also write each valid map's sphere and picture into ``out_dir`` (:func:`save_map`).
    loaded : tuple, optional
        What :func:`load_meshes` returned for ``paths``, if it was called already.

    Returns
    -------
    list of dict
        One row per (mesh, method): ``mesh``, ``method``, ``n_vertices``, ``valid``, ``flipped``, the
        other :func:`~sphere_nlp.metrics.distortion_summary` keys, ``time_s``, ``status``, ``note``;
        and one per rejected mesh, with ``method`` "-", ``valid`` False and ``status`` "rejected: ...".
        If every mesh is rejected, the first one's error is raised and nothing is written.

    Examples
    --------
    >>> import tempfile
    >>> from sphere_nlp.shapes import write_models
    >>> folder = tempfile.mkdtemp()
    >>> write_models(folder)
    >>> rows = compare([folder + "/cylinder.off"], folder, methods=["tutte-projection"])
    >>> rows[0]["method"], rows[0]["valid"], rows[0]["flipped"]
    ('tutte-projection', True, 0)
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise errors.UsageError("unknown method(s) %s; choose from %s" % (", ".join(unknown), ", ".join(METHODS)))
    meshes, rejected = load_meshes(paths) if loaded is None else loaded
    if not meshes:
        first = rejected[0][1]
        raise errors.MeshInputError(first if len(rejected) == 1 else "%s (and %d more rejected)"
                                    % (first, len(rejected) - 1))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [{"mesh": name, "method": REJECTED_METHOD, "valid": False, "status": "rejected: " + message}
            for name, message in rejected]
    if progress:
        for _, message in rejected:
            progress("skipping %s" % message)
        progress("%d mesh(es) x %d method(s) -> %s" % (len(meshes), len(methods), out_dir))
    for name, mesh, prepared in meshes:
        for method in methods:
            kept = {}
            row = {"mesh": name, "method": method, "n_vertices": len(prepared.vertices),
                   **run_method(method, mesh, prepared, max_time=max_time, keep=kept)}
            if save_maps and row["valid"]:
                row["files"] = [str(p) for p in save_map(out_dir, name, method, prepared.vertices,
                                                         kept["positions"], prepared.faces)]
            rows.append(row)
            write_outputs(out_dir, rows)
            if progress:
                qc = row.get("qc_mean")
                progress("%s: %s: %s, QC mean %s, %.2f s" % (name, method, row["status"],
                                                              "-" if qc is None else "%.3f" % qc, row["time_s"]))
    return rows


def output_files(paths, methods, out_dir, save_maps=False):
    """The files ``compare`` may write into ``out_dir`` (for checking them against the inputs)."""
    out_dir = Path(out_dir)
    names = ["compare.json", "compare.md"]
    if save_maps:
        names += ["%s.%s.%s" % (Path(p).stem, m.replace(":", "-"), ext) for p in paths for m in methods
                  for ext in ("obj", "png")]
    return [out_dir / name for name in names]


def main(argv=None):
    """``python -m sphere_nlp compare MESH... --out DIR [--methods ...] [--max-time S]``."""
    from .commands import check_output_folder, check_output_paths, run_subcommand, subcommand_parser

    parser = subcommand_parser(
        "compare",
        description="Map meshes with sphere_nlp and with baseline methods; write the validity and "
                    "distortion of every map to DIR/compare.json and DIR/compare.md. Every mesh is "
                    "checked first: a rejected one ends the command before anything runs.")
    parser.add_argument("meshes", nargs="+", metavar="MESH", help="input meshes")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                        help="comma-separated, from %s; 'sphere_nlp' = its four modes, 'all' = every "
                             "method (default: %s)" % (", ".join(METHODS), ",".join(DEFAULT_METHODS)))
    parser.add_argument("--save-maps", action="store_true",
                        help="also write each valid map's sphere (MESH.METHOD.obj, with texture "
                             "coordinates) and picture (MESH.METHOD.png) into DIR")
    parser.add_argument("--max-time", type=float, metavar="SECONDS",
                        help="wall-clock limit of each sphere_nlp run")
    parser.add_argument("-q", "--quiet", action="store_true", help="print only errors")

    def check(args):
        args.method_list = parse_methods(args.methods)
        if args.max_time is not None and not (math.isfinite(args.max_time) and args.max_time > 0):
            raise errors.UsageError("--max-time must be a finite number of seconds > 0, not %s" % args.max_time)
        check_output_folder("--out", args.out)
        if Path(args.out).is_dir():
            outputs = output_files(args.meshes, args.method_list, args.out, args.save_maps)
            check_output_paths([("an input mesh", path) for path in args.meshes],
                               [("--out", path) for path in outputs])
        # Every mesh read and validated before the first one is solved: exit 2 means nothing ran.
        args.loaded = load_meshes(args.meshes)
        rejected = args.loaded[1]
        if rejected:
            raise errors.MeshInputError(rejected[0][1] + ("" if len(rejected) == 1 else
                                                          " (and %d more mesh(es) rejected)" % (len(rejected) - 1)))

    def body(args, say):
        rows = compare(args.meshes, args.out, methods=args.method_list, max_time=args.max_time, progress=say,
                       save_maps=args.save_maps, loaded=args.loaded)
        say("wrote %s and %s (%d rows, %d valid)" % (Path(args.out) / "compare.json", Path(args.out) / "compare.md",
                                                     len(rows), sum(bool(r["valid"]) for r in rows)))
        return 0

    return run_subcommand(parser, argv, body, check=check,
                          interrupted=lambda args: "the rows done so far are in %s" % args.out)
