"""Use a sphere map: resample a shape, align two maps, transfer attributes, morph between shapes.

Everything works on plain arrays: a *map* is the input positions ``X`` (n, 3), the certified sphere
positions ``S`` (n, 3) and the shared faces ``F`` (t, 3). A point of the sphere is located in its
spherical triangle (:mod:`sphere_nlp.locate`) and any per-vertex quantity of the input is interpolated
there with the same barycentrics, so the input's shape, colours or fields can be read anywhere on
the sphere: at an icosphere's vertices (remeshing), at a grid (a geometry image), or at the sphere
positions of another shape (correspondence, transfer, morphing).
"""

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from . import errors
from .commands import check_output_folder, check_output_paths, run_subcommand, subcommand_parser
from .locate import SphereLocator, interpolate, nearest_corner
from .shapes import icosphere


def resample_at(X, S, F, points, locator=None):
    """The input's per-vertex values ``X`` (positions or any attribute) at sphere ``points`` (m, 3).

    Example
    -------
    >>> from sphere_nlp.shapes import icosphere
    >>> S, F = icosphere(3)
    >>> Y = resample_at(2.0 * S, S, F, icosphere(1)[0])
    >>> float(np.abs(np.linalg.norm(Y, axis=1) - 2).max()) < 0.02
    True
    """
    locator = locator or SphereLocator(S, F)
    face, bary = locator.locate(points)
    return interpolate(X, F, face, bary)


def resample_icosphere(X, S, F, level):
    """The input's shape on an icosphere of ``level`` (10 * 4**level + 2 vertices): (V, faces)."""
    P, G = icosphere(level)
    return resample_at(X, S, F, P), G


def grid_directions(size, layout="equirectangular"):
    """Unit directions of a ``size`` x ``size`` grid (``2 size`` wide for equirectangular): (h, w, 3).

    ``equirectangular``: rows from latitude +90 to -90 degrees at pixel centres, columns longitude
    -180 to 180 (the layout of :mod:`sphere_nlp.texture`). ``octahedral``: the unit square folded onto
    the octahedron |x| + |y| + |z| = 1 (lower hemisphere unfolded into the corners), then normalised,
    as in octahedral geometry images (Praun & Hoppe 2003).
    """
    if layout == "equirectangular":
        lat = np.pi / 2 - (np.arange(size) + 0.5) * np.pi / size
        lon = -np.pi + (np.arange(2 * size) + 0.5) * np.pi / size
        LON, LAT = np.meshgrid(lon, lat)
        D = np.stack([np.cos(LAT) * np.cos(LON), np.cos(LAT) * np.sin(LON), np.sin(LAT)], axis=-1)
    elif layout == "octahedral":
        u = -1 + (np.arange(size) + 0.5) * 2 / size
        U, W = np.meshgrid(u, u[::-1])
        Z = 1 - np.abs(U) - np.abs(W)
        lower = Z < 0
        U2 = np.where(lower, np.sign(U) * (1 - np.abs(W)), U)
        W2 = np.where(lower, np.sign(W) * (1 - np.abs(U)), W)
        D = np.stack([U2, W2, Z], axis=-1)
        D /= np.linalg.norm(D, axis=-1, keepdims=True)
    else:
        raise errors.UsageError("unknown grid layout %r: equirectangular or octahedral" % layout)
    return D


def geometry_image(X, S, F, size, layout="equirectangular"):
    """The input's per-vertex values sampled on a grid of sphere directions: (h, w, d) array."""
    D = grid_directions(size, layout)
    values = resample_at(X, S, F, D.reshape(-1, 3))
    return values.reshape(D.shape[:2] + np.shape(values)[1:])


def hausdorff(A, B, samples=50_000, seed=0):
    """Symmetric Hausdorff distance between two meshes ``(V, F)``, sampled.

    Each surface is sampled uniformly by area (plus its vertices); the distance is the larger of the
    two one-sided maxima of nearest-sample distances, so it over-estimates the exact value by at most
    about the sample spacing. Returns (hausdorff, mean one-sided distance).
    """
    import trimesh

    points = []
    for (V, F), s in zip((A, B), (seed, seed + 1)):
        mesh = trimesh.Trimesh(V, F, process=False)
        sample, _ = trimesh.sample.sample_surface(mesh, samples, seed=s)
        points.append(np.vstack([np.asarray(V, float), sample]))
    d_ab = cKDTree(points[1]).query(points[0])[0]
    d_ba = cKDTree(points[0]).query(points[1])[0]
    return float(max(d_ab.max(), d_ba.max())), float((d_ab.mean() + d_ba.mean()) / 2)


# -- alignment of two maps ---------------------------------------------------------------------------

def kabsch(P, Q, weights=None):
    """The rotation R (det +1) minimising sum w |R p - q|^2 over paired rows of P and Q (centred)."""
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    H = (np.asarray(P) * w[:, None]).T @ np.asarray(Q)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1, 1, d]) @ U.T


def _areas(S, F):
    T = S[F]
    return 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)


def first_moments(X, S, F):
    """M = integral over the sphere of (x(p) - mean) p^T dA: the degree-1 harmonic (ellipsoid) fit.

    If shape B is shape A rotated by Q and B's sphere is A's rotated by R, ``M_B = Q M_A R^T``; the
    singular vectors of M are the shape's principal axes in space (left) and on the sphere (right).
    """
    w = np.zeros(len(S))
    np.add.at(w, np.asarray(F).ravel(), np.repeat(_areas(S, F) / 3, 3))
    Xc = X - (w[:, None] * X).sum(axis=0) / w.sum()
    return (Xc * w[:, None]).T @ S


def _fit_error(XA, SA, XB, SB, FB, R, points):
    """RMS distance between A and B sampled at corresponding sphere points, after a rigid fit."""
    YA = XA
    YB = resample_at(XB, SB, FB, points @ R.T)
    YA = YA - YA.mean(axis=0)
    YB = YB - YB.mean(axis=0)
    Q = kabsch(YA, YB)
    return float(np.sqrt(np.mean(np.sum((YA @ Q.T - YB) ** 2, axis=1))))


def align_spheres(A, B, landmarks=None, level=3):
    """The rotation R of A's sphere onto B's sphere: A's sphere point p corresponds to B's point R p.

    ``A`` and ``B`` are maps ``(X, S, F)``. With ``landmarks`` (pairs of vertex indices ``(a, b)``,
    three or more), R is the Kabsch fit of A's sphere landmarks onto B's. Otherwise the principal axes
    of the two shapes' degree-1 harmonic fits (:func:`first_moments`) are matched; the axes' signs are
    ambiguous, so each of the 4 proper rotations they allow is tried and the one whose sphere-sampled
    shapes (icosphere of ``level``) agree best after a rigid fit wins.

    Example
    -------
    >>> from sphere_nlp.shapes import icosphere
    >>> S, F = icosphere(2)
    >>> X = S * [1.0, 1.5, 0.6] + 0.3 * S[:, [1]] ** 2
    >>> R0 = kabsch(np.eye(3), [[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    >>> R = align_spheres((X, S, F), (X, S @ R0.T, F))
    >>> bool(np.allclose(R, R0, atol=1e-6))
    True
    """
    XA, SA, FA = (np.asarray(a) for a in A)
    XB, SB, FB = (np.asarray(b) for b in B)
    if landmarks is not None:
        pairs = np.asarray(landmarks, np.int64).reshape(-1, 2)
        if len(pairs) < 3:
            raise errors.UsageError("landmarks: need at least 3 pairs, got %d" % len(pairs))
        return kabsch(SA[pairs[:, 0]], SB[pairs[:, 1]])
    _, _, VtA = np.linalg.svd(first_moments(XA, SA, FA))
    _, _, VtB = np.linalg.svd(first_moments(XB, SB, FB))
    points = icosphere(level)[0]
    XA_s = resample_at(XA, SA, FA, points)
    best = None
    for signs in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]):
        R = VtB.T @ np.diag(signs) @ VtA
        if np.linalg.det(R) < 0:            # the axes' own handedness differs: flip the last one
            R = VtB.T @ np.diag(np.multiply(signs, [1, 1, -1])) @ VtA
        err = _fit_error(XA_s, SA, XB, SB, FB, R, points)
        if best is None or err < best[0]:
            best = (err, R)
    return best[1]


def correspond(A, B, R=None, points=None):
    """Map points of A onto B through both spheres: B's surface point for each of A's vertices.

    ``points`` (m, 3) are sphere points of A (default: A's sphere vertices); R from
    :func:`align_spheres` (computed when omitted). Returns (B's positions (m, 3), B's faces index (m,),
    barycentrics (m, 3)).
    """
    XA, SA, FA = A
    XB, SB, FB = B
    R = align_spheres(A, B) if R is None else R
    points = SA if points is None else points
    face, bary = SphereLocator(SB, FB).locate(np.asarray(points) @ R.T)
    return interpolate(XB, FB, face, bary), face, bary


def transfer(values, A, B, R=None, kind="linear"):
    """Per-vertex ``values`` of A, read at each vertex of B through the aligned spheres.

    ``kind``: ``"linear"`` (barycentric; scalar fields, colours, any (n, d) array) or ``"nearest"``
    (the value of the nearest corner of the located triangle; labels, integers).
    """
    XA, SA, FA = A
    XB, SB, FB = B
    R = align_spheres(A, B) if R is None else R
    face, bary = SphereLocator(SA, FA).locate(np.asarray(SB) @ R)      # R^T applied to rows
    if kind == "nearest":
        return nearest_corner(values, FA, face, bary)
    if kind != "linear":
        raise errors.UsageError("unknown transfer kind %r: linear or nearest" % kind)
    return interpolate(np.asarray(values, float), FA, face, bary)


def similarity_fit(P, Q):
    """``Q`` moved onto paired rows ``P`` by the best rotation, uniform scale and translation."""
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    R = kabsch(Q - mq, P - mp)
    Qr = (Q - mq) @ R.T
    scale = np.sum(Qr * (P - mp)) / np.sum(Qr * Qr)
    return scale * Qr + mp


def size_ratio(A, B):
    """B's size over A's (maps or ``(X, F)`` pairs): the square root of their surface areas' ratio,
    which a rotation leaves alone and a scaling by k multiplies by k."""
    from .geometry import triangle_areas

    area = [float(triangle_areas(np.asarray(m[0], float), np.asarray(m[-1])).sum()) for m in (A, B)]
    return float(np.sqrt(area[1] / area[0])) if area[0] > 0 else float("inf")


def morph_frames(A, B, frames, R=None, fit=False):
    """In-between shapes on A's connectivity: B resampled at A's aligned sphere, blended linearly.

    Returns a list of ``frames`` (n, 3) arrays; the first is A, the last is B resampled onto A's
    sphere (faces: A's). With ``fit``, that B is first moved onto A by the best similarity transform
    (:func:`similarity_fit`), so the blend changes the shape, not its placement.
    """
    if frames < 2:
        raise errors.UsageError("--frames must be at least 2, got %d" % frames)
    XA = np.asarray(A[0], float)
    XB_on_A, _, _ = correspond(A, B, R)
    if fit:
        XB_on_A = similarity_fit(XA, XB_on_A)
    return [(1 - t) * XA + t * XB_on_A for t in np.linspace(0.0, 1.0, frames)]


# -- command line ------------------------------------------------------------------------------------

# A given sphere may have any radius (FreeSurfer's ?h.sphere: 100) if it is centred at the origin:
# every radius within this fraction of the median, the centroid within it of the origin (in radii).
SPHERE_RADIUS_SPREAD = 0.01


def unit_sphere(S, sphere_path):
    """``S`` (positions of a sphere file) on the unit sphere, and a note saying so if it was scaled.

    A sphere of another radius centred at the origin is projected radially onto the unit sphere;
    anything else is a UsageError.

    >>> from sphere_nlp.shapes import icosphere
    >>> S, note = unit_sphere(100 * icosphere(1)[0], "lh.sphere")
    >>> float(np.abs(np.linalg.norm(S, axis=1) - 1).max()) < 1e-15, note
    (True, 'lh.sphere: a sphere of radius 100, scaled onto the unit sphere')
    """
    S = np.asarray(S, float)
    radii = np.linalg.norm(S, axis=1)
    if np.all(np.abs(radii - 1) < 1e-9):
        return S, None
    radius = float(np.median(radii)) if len(radii) else 0.0
    centroid = float(np.linalg.norm(S.mean(axis=0))) if len(S) else 0.0
    if not (radius > 0 and np.isfinite(radius) and np.all(np.abs(radii / radius - 1) <= SPHERE_RADIUS_SPREAD)
            and centroid <= SPHERE_RADIUS_SPREAD * radius):
        raise errors.UsageError(
            "%s is not a sphere centred at the origin (radii %.4g to %.4g, centroid %.3g from the origin)"
            % (sphere_path, radii.min(), radii.max(), centroid))
    return S / radii[:, None], "%s: a sphere of radius %.4g, scaled onto the unit sphere" % (sphere_path, radius)


def validated_mesh(path):
    """``(X, F)`` of the mesh file ``path`` after the checks and repairs of a run (MeshInputError
    naming the file otherwise), before anything is solved."""
    from .mesh_io import load_mesh
    from .repair import prepare_mesh

    V, F = load_mesh(path)
    try:
        prepared = prepare_mesh(V, F)
    except errors.MeshInputError as exc:
        raise type(exc)("%s: %s" % (path, exc)) from None
    return prepared


def checked_sphere(mesh_path, sphere_path):
    """``(X, S, F)`` of a mesh and its given sphere (any radius, centred), checked and certified;
    and the note of :func:`unit_sphere` (or None)."""
    from .certify import certify
    from .mesh_io import load_mesh

    X, F = load_mesh(mesh_path)[:2]
    try:
        S, FS = load_mesh(sphere_path)[:2]
    except errors.MeshInputError as exc:
        raise errors.UsageError(str(exc)) from None
    if len(S) != len(X) or np.shape(FS) != np.shape(F) or not np.array_equal(FS, F):
        raise errors.UsageError("%s is not a sphere of %s: %d vertices / %d faces against %d / %d, or "
                                "other faces" % (sphere_path, mesh_path, len(S), len(FS), len(X), len(F)))
    S, note = unit_sphere(S, sphere_path)
    cert = certify(S, F)
    if not cert.valid:
        raise errors.UsageError("%s is not a certified sphere: %s" % (sphere_path, cert.reason))
    return (np.asarray(X, float), S, np.asarray(F, np.int64)), note


def load_map(mesh_path, sphere_path=None, say=print, target="original-angles"):
    """``(X, S, F)`` for a mesh: read an existing sphere (checked against the mesh and certified;
    any radius, centred at the origin) or map it in the mode ``target``.

    Either way ``say`` gets the shrink line of :func:`sphere_nlp.metrics.shrinkage_summary` when
    the map has shrunk parts of the surface past use: resampling or reading values through such a
    map loses those parts, whichever command made it.
    """
    from .metrics import shrinkage_summary

    if sphere_path is None:
        from .api import parameterize

        def on_stage(name):
            if name == "solve":                     # after the mesh was read and validated
                say("mapping %s (target %s)" % (mesh_path, target))

        result = parameterize(str(mesh_path), target=target, on_stage=on_stage)
        note = result.shrinkage()["note"]
        found = (np.asarray(result.input_vertices, float), np.asarray(result.vertices, float),
                 np.asarray(result.faces, np.int64))
    else:
        found, scaled = checked_sphere(mesh_path, sphere_path)
        if scaled:
            say(scaled)
        # A given sphere's mode is unknown: its numbers alone decide.
        note = shrinkage_summary(found[0], found[1], found[2], None)["note"]
    if note:
        say("%s: %s" % (sphere_path or mesh_path, note))
    return found


def add_target_option(parser, default, why):
    """``--target MODE`` of a subcommand that makes maps: the mode of the maps it makes (a sphere
    given with ``--sphere``... is used as it is)."""
    from .targets import MODES

    parser.add_argument("--target", default=default, choices=MODES, metavar="MODE",
                        help="mode of the maps made here (%s; default %s: %s); a sphere given is used "
                             "as it is" % (", ".join(MODES), default, why))


def _check_inputs(*paths):
    """UsageError for the first given path that is not a file, before any map is made."""
    for path in paths:
        if path and not Path(path).is_file():
            raise errors.UsageError("cannot read %s: no such file" % path)


def _check_maps(args, *pairs):
    """Every (mesh, sphere) of ``pairs`` read and checked before anything is solved: a mesh without
    a sphere is validated, a given sphere checked against its mesh. Returns the notes to say and
    each map's number of vertices (as a run numbers them: duplicates merged)."""
    notes, sizes = [], []
    for mesh, sphere in pairs:
        if sphere is None:
            sizes.append(len(validated_mesh(mesh).vertices))
        else:
            (X, _, _), note = checked_sphere(mesh, sphere)
            sizes.append(len(X))
            notes.append(note)
    return [note for note in notes if note], sizes


def _inputs(args, *names):
    """(what, path) of the run's inputs, for check_output_paths."""
    labels = {"mesh": "the input mesh", "a": "the mesh A", "b": "the mesh B", "sphere": "the --sphere file",
              "sphere_a": "the --sphere-a file", "sphere_b": "the --sphere-b file",
              "values": "the --values file"}
    return [(labels[name], getattr(args, name)) for name in names]


def _aligned_maps(args, landmarks, say, A=None):
    """The maps of ``args.a`` (unless given) and ``args.b``, and the rotation aligning B's sphere to A's."""
    A = load_map(args.a, args.sphere_a, say, args.target) if A is None else A
    B = load_map(args.b, args.sphere_b, say, args.target)
    _check_landmarks(landmarks, A, B)
    return A, B, align_spheres(A, B, landmarks)


def resample_main(argv=None):
    """``sphere-nlp resample MESH --icosphere K -o OUT [--sphere S.off]``."""
    parser = subcommand_parser(
        "resample",
        description="Write MESH's shape on an icosphere's connectivity, read through its sphere map "
                    "(mapped here, or given with --sphere), and report the Hausdorff distance.")
    parser.add_argument("mesh", metavar="MESH")
    parser.add_argument("--icosphere", type=int, default=5, metavar="K",
                        help="icosphere level: 10*4^K+2 vertices (default 5: 10242)")
    parser.add_argument("--sphere", metavar="S.off",
                        help="an existing sphere of MESH (same vertices and faces; any radius, centred at "
                             "the origin, e.g. FreeSurfer's radius-100 ?h.sphere: scaled to radius 1)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT", help="remeshed shape, .off/.obj/.ply")
    add_target_option(parser, "original-areas", "an icosphere samples the sphere evenly, so the map must "
                                                "keep every part its size; a conformal map shrinks limbs "
                                                "and the remesh loses them")
    parser.add_argument("-q", "--quiet", action="store_true")

    def check(args):
        from .mesh_io import check_mesh_path

        check_mesh_path(args.output)
        if not 0 <= args.icosphere <= 8:
            raise errors.UsageError("--icosphere must be between 0 and 8, got %d" % args.icosphere)
        _check_inputs(args.mesh, args.sphere)
        check_output_paths(_inputs(args, "mesh", "sphere"), [("-o", args.output)])
        args.notes, _ = _check_maps(args, (args.mesh, args.sphere))

    def body(args, say):
        from .mesh_io import output_transaction, write_mesh

        start = time.perf_counter()
        X, S, F = load_map(args.mesh, args.sphere, say, args.target)
        t_map = time.perf_counter() - start
        start = time.perf_counter()
        V, G = resample_icosphere(X, S, F, args.icosphere)
        t_resample = time.perf_counter() - start
        h, mean = hausdorff((X, F), (V, G))
        with output_transaction():
            write_mesh(args.output, V, G)
        diag = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
        say("wrote %s: %d vertices; map %.2f s, resample %.2f s; Hausdorff %.4g (%.3f%% of the bounding "
            "box diagonal), mean distance %.3g" % (args.output, len(V), t_map, t_resample, h, 100 * h / diag, mean))
        return 0

    return run_subcommand(parser, argv, body, check=check, interrupted="nothing written")


def morph_frame_names(frames):
    """The files ``sphere-nlp morph`` writes into its folder."""
    return ["frame_%03d.obj" % i for i in range(frames)] + ["strip.png"]


def morph_main(argv=None):
    """``sphere-nlp morph A B --frames N --out DIR``."""
    parser = subcommand_parser(
        "morph",
        description="Write in-between meshes from A to B on A's connectivity (B resampled onto A's "
                    "sphere after aligning the spheres, then fitted onto A in place and size unless "
                    "--no-fit), DIR/frame_000.obj..., and DIR/strip.png; all of them or none.")
    parser.add_argument("a", metavar="A")
    parser.add_argument("b", metavar="B")
    parser.add_argument("--frames", type=int, default=30, metavar="N", help="number of frames (default 30)")
    parser.add_argument("--out", required=True, metavar="DIR")
    parser.add_argument("--sphere-a", metavar="SA.off", help="an existing sphere of A (any radius, centred)")
    parser.add_argument("--sphere-b", metavar="SB.off", help="an existing sphere of B (any radius, centred)")
    parser.add_argument("--landmarks", metavar="a:b,...",
                        help="vertex pairs (A index:B index, 3 or more) to align the spheres; default: "
                             "the shapes' principal axes")
    parser.add_argument("--fit", action=argparse.BooleanOptionalAction, default=True,
                        help="move B onto A by the best rotation, scale and translation before blending, "
                             "so the frames change the shape, not its size or place (default; --no-fit "
                             "blends B as it lies)")
    add_target_option(parser, "original-angles", "the main command's")
    parser.add_argument("-q", "--quiet", action="store_true")

    def check(args):
        if args.frames < 2:
            raise errors.UsageError("--frames must be at least 2, got %d" % args.frames)
        if args.frames > 10000:
            raise errors.UsageError("--frames must be at most 10000, got %d" % args.frames)
        check_output_folder("--out", args.out)
        args.landmarks_parsed = _parse_landmarks(args.landmarks)
        _check_inputs(args.a, args.b, args.sphere_a, args.sphere_b)
        out = Path(args.out)
        inputs = _inputs(args, "a", "b", "sphere_a", "sphere_b")
        if out.is_dir():
            check_output_paths(inputs, [("--out", out / name) for name in morph_frame_names(args.frames)])
        args.notes, _ = _check_maps(args, (args.a, args.sphere_a), (args.b, args.sphere_b))

    def body(args, say):
        from .mesh_io import created_folder, output_transaction, write_mesh

        for note in args.notes:
            say(note)
        A, B, R = _aligned_maps(args, args.landmarks_parsed, say)
        ratio = size_ratio(A, B)
        if not args.fit and not 0.5 <= ratio <= 2:
            say("B is %.3g times A's size (square root of the surface areas' ratio) and --no-fit keeps "
                "it so: the frames grow or shrink as much as they change shape" % ratio)
        frames = morph_frames(A, B, args.frames, R, fit=args.fit)
        out = Path(args.out)
        with created_folder(out), output_transaction():       # every frame and the strip, or none
            for name, V in zip(morph_frame_names(len(frames)), frames):
                write_mesh(out / name, V, A[2])
            write_strip(out / "strip.png", frames, A[2])
        say("wrote %d frames and strip.png to %s" % (len(frames), out))
        return 0

    return run_subcommand(parser, argv, body, check=check, interrupted="nothing written")


def _parse_landmarks(text):
    if not text:
        return None
    try:
        pairs = [tuple(int(i) for i in pair.split(":")) for pair in text.split(",")]
    except ValueError:
        pairs = []
    if len(pairs) < 3 or any(len(p) != 2 or min(p) < 0 for p in pairs):
        raise errors.UsageError("--landmarks must be 3 or more pairs a:b of vertex indices, got %r" % text)
    return pairs


def _read_values(path, rows):
    """The --values array, with ``rows`` rows (one per vertex of A), or UsageError."""
    try:
        values = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise errors.UsageError("cannot read %s as a .npy array: %s" % (path, getattr(exc, "strerror", None) or exc)) \
            from None
    if values.ndim == 0 or len(values) != rows:
        raise errors.UsageError("%s has %s rows, A has %d vertices: one row per vertex of A is needed"
                                % (path, len(values) if values.ndim else "no", rows))
    return values


def transfer_main(argv=None):
    """``sphere-nlp transfer A B --values VALUES.npy -o OUT.npy [--kind nearest]``."""
    parser = subcommand_parser(
        "transfer",
        description="Read per-vertex values of A (.npy, one row per vertex: a scalar field, colours, "
                    "labels) at every vertex of B through the aligned spheres; write them as .npy.")
    parser.add_argument("a", metavar="A")
    parser.add_argument("b", metavar="B")
    parser.add_argument("--values", required=True, metavar="VALUES.npy", help="A's per-vertex values")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.npy", help="B's per-vertex values")
    parser.add_argument("--kind", choices=("linear", "nearest"), default="linear",
                        help="linear: barycentric (fields, colours; default); nearest: labels")
    parser.add_argument("--sphere-a", metavar="SA.off", help="an existing sphere of A (any radius, centred)")
    parser.add_argument("--sphere-b", metavar="SB.off", help="an existing sphere of B (any radius, centred)")
    parser.add_argument("--landmarks", metavar="a:b,...",
                        help="vertex pairs (A index:B index, 3 or more) to align the spheres; default: "
                             "the shapes' principal axes")
    add_target_option(parser, "original-angles", "the main command's")
    parser.add_argument("-q", "--quiet", action="store_true")

    def check(args):
        if not args.output.endswith(".npy"):
            raise errors.UsageError("cannot write %s: output must end in .npy" % args.output)
        args.landmarks_parsed = _parse_landmarks(args.landmarks)
        _check_inputs(args.a, args.b, args.values, args.sphere_a, args.sphere_b)
        check_output_paths(_inputs(args, "a", "b", "values", "sphere_a", "sphere_b"), [("-o", args.output)])
        args.notes, (rows, _) = _check_maps(args, (args.a, args.sphere_a), (args.b, args.sphere_b))
        args.values_array = _read_values(args.values, rows)       # one row per vertex of A

    def body(args, say):
        from .mesh_io import atomic_output, output_transaction

        for note in args.notes:
            say(note)
        A, B, R = _aligned_maps(args, args.landmarks_parsed, say)
        result = transfer(args.values_array, A, B, R, kind=args.kind)
        with output_transaction(), atomic_output(args.output, "wb") as handle:
            np.save(handle, result)
        say("wrote %s: %s values for %d vertices of %s" % (args.output, args.kind, len(result), args.b))
        return 0

    return run_subcommand(parser, argv, body, check=check, interrupted="nothing written")


def _check_landmarks(landmarks, A, B):
    if landmarks is not None and (max(p[0] for p in landmarks) >= len(A[0])
                                  or max(p[1] for p in landmarks) >= len(B[0])):
        raise errors.UsageError("--landmarks: a vertex index is out of range")


def write_strip(path, frames, faces, count=6, view=None, up=None):
    """A row of ``count`` frames (evenly chosen), shaded and upright, as a PNG written atomically
    (1440 x 440 pixels for six frames).

    ``up`` is the frames' up axis ("y", "-z", ... or a vector), by default that of the first frame
    (:func:`sphere_nlp.picture.detect_up`); ``view`` = (elevation, azimuth) in degrees.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .mesh_io import atomic_output
    from .picture import detect_up, upright_rotation

    upright = upright_rotation(detect_up(frames[0], faces) if up is None else up)
    pick = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    fig = plt.figure(figsize=(2.4 * len(pick), 4.4), dpi=100)
    for k, i in enumerate(pick):
        ax = fig.add_subplot(1, len(pick), k + 1, projection="3d")
        draw_mesh(ax, np.asarray(frames[i], float) @ upright.T, faces)
        if view is not None:
            ax.view_init(*view)
        ax.set_title("frame %d" % i, fontsize=11)
    fig.tight_layout()
    with atomic_output(path, "wb") as handle:
        fig.savefig(handle, format="png")
    plt.close(fig)


def draw_mesh(ax, V, F, colours=None):
    """Flat-shaded mesh on a 3d axis, equal aspect, no axes (colours: per-face RGB, optional)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    V = np.asarray(V, float)
    T = V[F]
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-300
    light = np.clip(n @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), 0, 1)
    base = np.array([0.75, 0.78, 0.85]) if colours is None else np.asarray(colours, float)
    shade = (0.25 + 0.75 * light)[:, None] * (base if base.ndim == 2 else base[None, :])
    ax.add_collection3d(Poly3DCollection(T, facecolors=np.clip(shade, 0, 1), linewidths=0))
    c, r = (V.max(axis=0) + V.min(axis=0)) / 2, (V.max(axis=0) - V.min(axis=0)).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1), zoom=1.3)      # the mesh, not the empty box around it, fills the panel
    ax.set_axis_off()
