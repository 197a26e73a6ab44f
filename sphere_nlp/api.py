"""The Python API: :func:`parameterize` runs the whole pipeline and returns one result object."""

import copy
import functools
import math
import numbers
import os
import resource
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from . import errors, interrupts
from .certify import Certificate, certify, spherical_angles
from .repair import prepare_mesh
from .metrics import distortion_fields, distortion_summary, shrinkage_summary, usability_summary
from .mesh_io import (GLTF_FORMATS, check_mesh_path, read_mesh, write_image, write_json, write_material, write_mesh,
                      write_npz)
from .names import AREA_MODE_OF
from .nlp import DEFAULT_FORMULATION, FORMULATIONS, check_ipopt_options, failure_advice, status_kind
from .settings import DEFAULT_SETTINGS, SolverSettings
from .polish import authalic_route, default_budget
from .solve import check_floors, NO_VALID_START, ON_LIMIT, solve_angles, UNPLACEABLE_START
from .starts import checked_positions
from .targets import MODES, make_targets
from .texture import checker_image, spherical_uv, split_at_seams
from .unfold import sphere_positions


def solve_failure_message(status, iterations):
    """One line saying why an angle solve is not a result (IPOPT's status, or the constraints)."""
    if status == NO_VALID_START:
        return ("no valid starting map: no conformal map of the mesh could be untangled and its convex "
                "embedding folds in double precision (parts too thin to place)")
    if status == UNPLACEABLE_START:
        return ("the start's limbs shrink past what double precision holds (solve.unplaceable_start): "
                "an area mode maps such a shape")
    if status_kind(status) == "solved":
        # IPOPT converged, but to angles that break a constraint: a zero or negative angle or excess
        # ((3)-(5)), or an equality (6)-(8) off by more than 1e-8.
        return ("the angle solve ended outside the constraints: a zero or negative angle or excess, or "
                "an equality residual above 1e-8 (IPOPT status %s after %d iterations)" % (status, iterations))
    advice = failure_advice(status)
    return "the angle solve failed (IPOPT status %s after %d iterations)%s" % (
        status, iterations, ": " + advice if advice else "")


def peak_rss_mb():
    """Peak resident memory of this process so far, in MB."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 2 ** 20


@dataclass
class SphericalParameterization:
    """Everything a run produced: positions, angles, status, statistics and certificate.

    Vertex numbering: ``vertices``, ``faces`` and ``input_vertices`` use the *repaired* vertex set.
    When no vertex was merged or dropped (the usual case) it is the input's, in input order. Otherwise
    the input's order is kept with unreferenced vertices removed and each group of coincident vertices
    represented by its lowest-numbered member; ``vertex_map[i]`` is the row of ``vertices`` that input
    vertex ``i`` became (-1 if it was dropped), so ``result.vertices[result.vertex_map[i]]`` is where
    input vertex ``i`` went. Faces are never removed or reordered: ``faces[i]`` is input face ``i``
    in the repaired numbering (with its winding reversed if it was re-oriented; see ``repairs``).

    Attributes
    ----------
    vertices : (n, 3) array
        Positions on the unit sphere, one per repaired vertex.
    faces : (t, 3) int array
        The triangles, in the repaired numbering, consistently oriented.
    input_vertices : (n, 3) array
        The input positions of the repaired vertices (input coordinates, not normalised).
    vertex_map : (n_input,) int array
        Row of ``vertices`` for each input vertex, -1 for a dropped (unreferenced) vertex.
    angles : (t, 3) array
        Solved spherical angles; ``angles[i, j]`` is at vertex ``faces[i, j]``.
    excess : (t,) array
        Solved spherical excesses (areas on the unit sphere).
    target_angles, target_excess : arrays
        The targets beta and e' of the objective.
    target : str
        Target mode (or "custom").
    formulation : str
    success : bool
        True when the solve succeeded (``solved``) and the certificate is valid.
    converged : bool
        True when the angle solve reached IPOPT's optimality tolerance; False when its margin stage
        stopped at ``max_iter`` or ``max_time`` and the result is that iterate projected onto the
        constraints (``solved`` and certified all the same, but not optimal; ``status`` says which
        limit). See :func:`sphere_nlp.solve.project_onto_constraints`.
    solved : bool
        True when IPOPT finished (``status`` is Solve_Succeeded or Solved_To_Acceptable_Level) with
        angles and excesses that satisfy the inequalities (3)-(5), or (``on_limit="project"``) when
        the projection of a stage stopped by a limit did (``converged`` False).
    status : str
        IPOPT's return status of the last stage.
    iterations : int
    objective : float
    max_constraint_violation : float
        max |residual| of constraints (6)-(8) at the returned angles and excesses.
    max_angle_error : float
        max |spherical angle measured from ``vertices`` - solved angle| (radians).
    certificate : Certificate
    stages : list of dict
        Per-IPOPT-run statistics.
    timings : dict
        Seconds per stage: load, build, solve, unfold, certify (these add up to total), total, and
        their parts, named ``stage.part`` and adding up to their stage: ``solve.start``,
        ``solve.authalic`` (area modes), ``solve.ipopt``, ``solve.other``, ``unfold.walk``, ``unfold.correction``,
        ``unfold.other`` (:func:`split_timings`; docs/design.md, "Where the time goes").
    repairs : list of str
        Repairs made to the input, one line each (merged or dropped vertices, flipped faces,
        normalised coordinates).
    unfold_info : dict
        Statistics of :func:`~sphere_nlp.unfold.unfold`: the walk's depth (``levels``) and in-walk
        repairs, and before (``walk_*``) and after (``corrected_*``) the Gauss-Newton correction the
        max and RMS |angle from positions - solved angle| (radians) and the max relative mismatch of
        edge chords against those of the solved angles; ``walk_s`` and ``correction_s`` seconds.
    peak_rss_mb : float
    start : str
        The solve's starting point: "conformal", "conformal-untangled", "surface-conformal",
        "surface-conformal-untangled" (the surface's own conformal map, where the one to the target
        angles could not be untangled), "embedding", "embedding-uncentred", "embedding-invalid" (no
        valid start: the embedding rounded to an invalid map, parts too thin for double precision;
        nothing is solved, status "No_Valid_Start"), "linear" or "given" (positions passed as
        ``start``).
    corner_weighting : str
        The angle term's corner weighting ("relative" or "uniform").
    floor_corners, floor_triangles : int
        Corners and triangles that end on their floor (``corner_floor``, ``area_floor``; within
        1% of it).
    recovery : dict or None
        Set when the solved angles could not be placed in double precision (the certificate
        failed) and the solve was run again with a higher area floor: ``reason`` (the first
        certificate's), ``area_floor`` (the one used), ``solved``, ``certified``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    input_vertices: np.ndarray
    angles: np.ndarray
    excess: np.ndarray
    target_angles: np.ndarray
    target_excess: np.ndarray
    target: str
    formulation: str
    success: bool
    status: str
    iterations: int
    objective: float
    max_constraint_violation: float
    max_angle_error: float
    certificate: Certificate
    vertex_map: np.ndarray = None
    solved: bool = False
    converged: bool = False
    stages: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    repairs: list = field(default_factory=list)
    unfold_info: dict = field(default_factory=dict)
    peak_rss_mb: float = 0.0
    start: str = ""
    corner_weighting: str = "uniform"
    floor_corners: int = 0
    floor_triangles: int = 0
    recovery: dict = None
    area_route: dict = None

    def __repr__(self):
        return ("SphericalParameterization(%d vertices, target=%r, status=%r, certified=%s, %.2f s)"
                % (len(self.vertices), self.target, self.status, self.certificate.valid,
                   self.timings.get("total", float("nan"))))

    def _refuse_unless_certified(self):
        """Raise (so nothing is written) unless the solve finished and the sphere is certified."""
        if not self.solved:
            raise errors.SolveError("refusing to write: "
                                    + solve_failure_message(self.status, self.iterations), self)
        if not self.certificate.valid:
            raise errors.CertificateError("refusing to write an uncertified sphere: "
                                          + self.certificate.reason, self)

    def texture_coordinates(self):
        """Per-corner (u, v) = (longitude / 2 pi + 0.5, latitude / pi + 0.5) of the sphere, (t, 3, 2).

        See :mod:`sphere_nlp.texture` for the convention, the seam and the poles.
        """
        return spherical_uv(self.vertices, self.faces)

    def write(self, path, texture=None):
        """Write the sphere mesh (OFF, OBJ, PLY, or glTF's .glb / .gltf, by extension).

        glTF holds 32-bit positions: the sphere is written only if, rounded so and projected back
        onto the unit sphere, it still passes the certificate (CertificateError otherwise).

        An OBJ also carries texture coordinates (:meth:`texture_coordinates`, ``f v/vt`` faces), so
        an equirectangular image (a world map, an environment map) wraps onto it as onto a globe.
        With ``texture`` (a .png path, OBJ only) a checkerboard image is written there and an MTL file
        beside the OBJ (same stem, ``.mtl``) that the OBJ references, so viewers show the texture.

        Refuses (raising :class:`SolveError` or :class:`CertificateError`, writing nothing) a result
        whose solve stopped short, e.g. at an iteration or time limit, even if its positions happen to
        pass the certificate, and any uncertified result.

        Example
        -------
        ``result.write("cylinder.obj", texture="checker.png")`` writes checker.png, cylinder.mtl and
        cylinder.obj.
        """
        self._refuse_unless_certified()
        check_mesh_path(path)
        if Path(path).suffix.lower() in GLTF_FORMATS:
            self._certify_as_float32(path)
        is_obj = Path(path).suffix.lower() == ".obj"
        uv = self.texture_coordinates() if is_obj else None
        material = self._write_texture(path, texture) if texture is not None else None
        write_mesh(path, self.vertices, self.faces, uv, material=material)

    def _certify_as_float32(self, path):
        """Raise CertificateError unless the sphere rounded to 32-bit floats (glTF's positions),
        projected back onto the unit sphere as a reader would, still passes the certificate: no
        flipped or degenerate triangle, degree 1. Rounding moves a vertex by about 1e-7, which can
        flip a triangle smaller than that."""
        rounded = np.asarray(self.vertices, np.float32).astype(float)
        rounded /= np.linalg.norm(rounded, axis=1, keepdims=True)
        cert = certify(rounded, self.faces)
        if not cert.valid:
            raise errors.CertificateError("refusing to write %s: glTF's 32-bit positions break the sphere's "
                                          "certificate (%s); write .off, .obj or .ply" % (path, cert.reason), self)

    def write_textured_input(self, path, texture=None):
        """Write the *input* mesh as OBJ with the sphere's texture coordinates.

        This is the file to paint or texture: positions are the input's (the repaired vertex set, see
        ``vertex_map``), ``vt`` are the longitude and latitude of each corner on the sphere, so an
        equirectangular image wraps onto the model through the spherical map. ``texture`` as in
        :meth:`write`. Refuses uncertified results like :meth:`write`.
        """
        self._refuse_unless_certified()
        if Path(path).suffix.lower() != ".obj":
            raise errors.UsageError("cannot write %s: a textured mesh must be .obj" % path)
        material = self._write_texture(path, texture) if texture is not None else None
        write_mesh(path, self.input_vertices, self.faces, self.texture_coordinates(), material=material)

    @staticmethod
    def _write_texture(obj_path, texture):
        """Write the checker PNG and the MTL for an OBJ; return the MTL's name for ``mtllib``."""
        obj_path, texture = Path(obj_path), Path(texture)
        if obj_path.suffix.lower() != ".obj":
            raise errors.UsageError("cannot texture %s: only OBJ carries texture coordinates" % obj_path)
        if texture.suffix.lower() != ".png":
            raise errors.UsageError("cannot write %s: a texture must be .png" % texture)
        folder = obj_path.parent
        mtl = obj_path.with_suffix(".mtl")
        write_image(texture, checker_image())
        # MTL paths are relative to the MTL file; forward slashes work in every viewer.
        write_material(mtl, Path(os.path.relpath(texture.resolve(), folder.resolve())).as_posix())
        return mtl.name

    def to_trimesh(self, textured=False, geometry="sphere"):
        """The result as a :class:`trimesh.Trimesh`.

        Parameters
        ----------
        textured : bool
            If True, vertices are split where texture coordinates differ (the seam and the poles,
            :func:`sphere_nlp.texture.split_at_seams`) and the mesh gets
            :class:`trimesh.visual.TextureVisuals` with the sphere's (u, v) and a checkerboard image,
            so ``mesh.show()`` or ``mesh.export("x.glb")`` shows the map. If False, one vertex per
            vertex of ``vertices`` and no visuals.
        geometry : "sphere" or "input"
            Positions on the unit sphere, or the input's (the repaired vertex set).

        Example
        -------
        >>> import sphere_nlp
        >>> result = sphere_nlp.parameterize("models/cylinder.off")     # doctest: +SKIP
        >>> mesh = result.to_trimesh(textured=True, geometry="input")   # doctest: +SKIP
        """
        import trimesh
        from trimesh.visual import TextureVisuals

        if geometry not in ("sphere", "input"):
            raise errors.UsageError("geometry must be 'sphere' or 'input', not %r" % (geometry,))
        positions = self.vertices if geometry == "sphere" else self.input_vertices
        if not textured:
            return trimesh.Trimesh(positions, self.faces, process=False)
        from PIL import Image

        source, faces, uv = split_at_seams(self.faces, self.texture_coordinates())
        visual = TextureVisuals(uv=uv, image=Image.fromarray(checker_image(), "RGB"))
        return trimesh.Trimesh(positions[source], faces, visual=visual, process=False)

    def distortion(self):
        """How far the map is from the input's angles and areas (a :mod:`~sphere_nlp.metrics` summary).

        A dict with ``mean_abs_angle_diff_deg`` (mean |chord-triangle corner angle - input corner
        angle|, degrees), ``mean_abs_log_area`` (mean |log(spherical area / input area scaled to total
        4 pi)|), ``qc_mean``, ``qc_max``, ``area_cv``, ``min_spherical_angle_deg`` and the certificate's
        fields. Measured against the input centred and scaled to unit size, so extreme coordinates
        (1e-150, 1e150) give the same numbers as moderate ones.
        """
        return self._once("distortion", lambda: distortion_summary(_unit_size(self.input_vertices), self.vertices,
                                                                   self.faces))

    def usability(self):
        """The independent check of :func:`sphere_nlp.metrics.usability_summary`: worst
        quasi-conformal ratio, corners below 0.1 x their target, smallest spherical triangle over
        the mean, mean angle distortion and mean |log area ratio| (input centred and scaled as in
        :meth:`distortion`)."""
        return self._once("usability", lambda: usability_summary(_unit_size(self.input_vertices), self.vertices,
                                                                 self.faces, self.target_angles,
                                                                 summary=self.distortion()))

    def _once(self, name, compute):
        """A copy of ``compute()``, computed at the first call for this result: the summaries
        take seconds at 10^5-10^6 vertices, and the run line, the report and the checks all ask."""
        cache = self.__dict__.setdefault("_summaries", {})
        if name not in cache:
            cache[name] = compute()
        return copy.deepcopy(cache[name])

    def shrinkage(self):
        """Whether the map shrank parts of the surface past use (an angle mode's limbs), and the
        line that says so and names the mode that keeps them (:func:`sphere_nlp.metrics.shrinkage_summary`)."""
        return shrinkage_summary(_unit_size(self.input_vertices), self.vertices, self.faces, self.target)

    def write_png(self, path, measure=None, view=None, up=None):
        """Write a PNG: the input mesh and the sphere coloured by distortion, and a checkerboarded mesh.

        ``measure`` is "area" (log area ratio) or "angle" (angle distortion, degrees); by default the
        one the mode does not optimise (angle distortion for the area modes, log area ratio for the
        angle modes), which is where its map pays. ``up`` is the input's up axis ("y", "-z", ... or
        a vector), drawn up; by default detected (:func:`sphere_nlp.picture.detect_up`: a flat base,
        else three or more legs, else +Y). ``view`` = (azimuth, elevation) in degrees around the upright mesh, by default the
        side with the most projected area. See
        :func:`sphere_nlp.picture.render_png`. Written atomically; refuses uncertified results like
        :meth:`write`.
        """
        self._refuse_unless_certified()
        if Path(path).suffix.lower() != ".png":
            raise errors.UsageError("cannot write %s: a picture must be .png" % path)
        from .picture import default_measure, render_png   # matplotlib loads only when a picture is wanted

        summary = self.distortion()
        title = ("%s: %d vertices, mean angle distortion %.1f°, mean |log area ratio| %.3f"
                 % (self.target, len(self.vertices), summary["mean_abs_angle_diff_deg"],
                    summary["mean_abs_log_area"]))
        return render_png(path, _unit_size(self.input_vertices), self.vertices, self.faces,
                          measure=measure or default_measure(self.target), title=title, view=view,
                          corner_uv=self.texture_coordinates(), up=up)

    def save_solution(self, path):
        """Write vertices, faces, angles, excess, the targets and the vertex map to an .npz archive."""
        write_npz(path, vertices=self.vertices, faces=self.faces, angles=self.angles, excess=self.excess,
                  target_angles=self.target_angles, target_excess=self.target_excess,
                  vertex_map=self.vertex_map)

    def save_distortion(self, path):
        """Write the map's distortion per face and per vertex to an .npz archive: the arrays of
        :func:`sphere_nlp.metrics.distortion_fields` (measured as :meth:`distortion` measures),
        with ``faces`` and ``vertex_map`` (per-vertex rows follow the sphere's vertices)."""
        self._refuse_unless_certified()
        fields = distortion_fields(_unit_size(self.input_vertices), self.vertices, self.faces)
        write_npz(path, faces=self.faces, vertex_map=self.vertex_map, **fields)

    def report(self):
        """A JSON-ready dict of the run's statistics."""
        return {
            "vertices": int(len(self.vertices)),
            "input_vertices": int(len(self.vertex_map)) if self.vertex_map is not None else None,
            "faces": int(len(self.faces)),
            "target": self.target,
            "formulation": self.formulation,
            "start": self.start,
            "corner_weighting": self.corner_weighting,
            "floor_corners": int(self.floor_corners),
            "floor_triangles": int(self.floor_triangles),
            "recovery": self.recovery,
            "area_route": self.area_route,
            "usability": self.usability() if np.isfinite(self.vertices).all() else None,
            "shrinkage": self.shrinkage() if np.isfinite(self.vertices).all() else None,
            "success": bool(self.success),
            "converged": bool(self.converged),
            "status": self.status,
            "iterations": int(self.iterations),
            "objective": float(self.objective),
            "max_constraint_violation": float(self.max_constraint_violation),
            "max_angle_error": float(self.max_angle_error),
            "certificate": self.certificate.to_dict(),
            "stages": self.stages,
            "timings_s": {k: round(float(v), 6) for k, v in self.timings.items()},
            "peak_rss_mb": round(float(self.peak_rss_mb), 1),
            "repairs": list(self.repairs),
            "distortion": self.distortion() if np.isfinite(self.vertices).all() else None,
            "unfold": {k: (float(v) if isinstance(v, (float, np.floating))
                           else int(v) if isinstance(v, np.integer) else v)
                       for k, v in self.unfold_info.items()},
        }

    def write_report(self, path):
        """Write :meth:`report` as JSON."""
        write_json(path, self.report())


def max_angle_error(positions, faces, angles):
    """max |spherical corner angle of the positions - solved angle|, inf if not finite."""
    error = float(np.max(np.abs(spherical_angles(positions, faces) - angles)))
    return error if np.isfinite(error) else float("inf")


def split_timings(timings, stages, area_route=None, unfold_info=None, start_s=0.0):
    """Add the parts of the solve and the unfold to ``timings``, each ``stage.part``.

    ``solve.start`` is the start (conformal map, untangling, gauge; ``start_s``), ``solve.ipopt``
    IPOPT's iterations (every run's ``time_s``), ``solve.authalic`` the area modes' authalic map,
    and ``solve.other`` the rest of the solve: the NLP's numeric evaluators and the checks between
    IPOPT runs. The unfold's
    ``unfold.walk`` and ``unfold.correction`` come from its statistics, ``unfold.other`` is the rest
    (chords, the seed, residuals); in the area modes the chosen map is unfolded inside the solve,
    so its unfold is part of ``solve.other``. The parts add up to their stage.

    Examples
    --------
    >>> t = {"solve": 10.0, "unfold": 3.0}
    >>> split_timings(t, [{"time_s": 6.0}, {"time_s": 1.5}], None, {"walk_s": 1.0, "correction_s": 1.5}, 2.0)
    >>> t["solve.start"], t["solve.ipopt"], t["solve.other"], t["unfold.walk"], t["unfold.other"]
    (2.0, 7.5, 0.5, 1.0, 0.5)
    """
    solve = timings.get("solve", 0.0)
    ipopt = min(sum(float(s.get("time_s", 0.0)) for s in stages), solve)
    authalic = 0.0
    if area_route is not None:
        authalic = min(float((area_route.get("authalic") or {}).get("seconds", 0.0)), solve - ipopt)
        timings["solve.authalic"] = authalic
    start = min(float(start_s), solve - ipopt - authalic)
    timings["solve.start"] = start
    timings["solve.ipopt"] = ipopt
    timings["solve.other"] = solve - ipopt - authalic - start
    if area_route is None and "unfold" in timings:
        info = unfold_info or {}
        walk = min(float(info.get("walk_s", 0.0)), timings["unfold"])
        correction = min(float(info.get("correction_s", 0.0)), timings["unfold"] - walk)
        timings["unfold.walk"], timings["unfold.correction"] = walk, correction
        timings["unfold.other"] = timings["unfold"] - walk - correction


def _start_in_repaired_numbering(start, prepared):
    """Start positions given per input vertex, or per vertex of the repaired mesh (as an earlier
    result's ``vertices``, or the sphere it wrote, have them), in the repaired numbering (the solve
    certifies them)."""
    start = np.asarray(start, dtype=float)
    vertex_map = prepared.vertex_map
    n_repaired = prepared.connectivity.n_vertices
    if start.ndim == 2 and start.shape == (n_repaired, 3) and n_repaired != len(vertex_map):
        return start
    if start.shape != (len(vertex_map), 3):
        rows = start.shape[0] if start.ndim == 2 and start.shape[1] == 3 else "x".join(map(str, start.shape))
        raise errors.UsageError("the start has %s positions, the mesh %d vertices: a start gives one position "
                                "per vertex" % (rows, len(vertex_map)))
    positions = np.zeros((n_repaired, 3))
    kept = vertex_map >= 0
    positions[vertex_map[kept]] = start[kept]
    return positions


def _unit_size(vertices):
    """Vertices centred on their bounding box and scaled into [-1, 1]^3.

    Angles and area ratios are unchanged; extreme coordinates (1e-150, 1e150) neither overflow nor
    underflow in the cross products of the distortion measures.
    """
    # Halved first: differences of coordinates near 1.8e308 would overflow.
    half = np.asarray(vertices, float) / 2
    low, high = half.min(axis=0), half.max(axis=0)
    size = float(np.max(high - low)) or 1.0
    return (half - (low + high) / 2) / size


def _as_arrays(mesh):
    """(vertices, faces, notes) from a path, a trimesh.Trimesh, or a (V, F) pair; ``notes`` says
    what reading a file changed (:func:`~sphere_nlp.mesh_io.read_mesh`).

    Arrays are passed on as given: :func:`~sphere_nlp.connectivity.check_arrays` converts them and reports
    malformed ones (ragged face lists, wrong shapes) as input errors.
    """
    if isinstance(mesh, (str, Path)):
        return read_mesh(mesh)
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return mesh.vertices, mesh.faces, []
    try:
        vertices, faces = mesh
    except (TypeError, ValueError):
        raise errors.UsageError("mesh must be a file path, a trimesh.Trimesh or a (vertices, faces) pair") \
            from None
    try:
        as_array = np.asarray(vertices)
    except (OverflowError, ValueError, TypeError):
        as_array = None                         # ragged: check_arrays says so
    if as_array is not None:
        if np.iscomplexobj(as_array):
            raise errors.UsageError("vertices must be real coordinates, not complex numbers")
        if as_array.dtype == object:
            try:
                as_array.astype(float)
            except OverflowError:
                raise errors.UsageError("vertex coordinates too large for floating point (beyond "
                                        "1.8e308)") from None
            except (TypeError, ValueError):
                pass
    return vertices, faces, []


def check_run_options(target="original-angles", formulation=DEFAULT_FORMULATION, on_limit="fail", max_iter=None,
                      max_time=None, angle_weight=None, area_weight=None, ipopt_options=None):
    """UsageError naming the first of :func:`parameterize`'s options that is not valid, before any work."""
    _check_arguments(angle_weight=angle_weight, area_weight=area_weight, max_iter=max_iter,
                     max_time=max_time, ipopt_options=ipopt_options)
    if target not in MODES:
        raise errors.UsageError("unknown target mode %r; choose one of %s" % (target, ", ".join(MODES)))
    if formulation not in FORMULATIONS:
        raise errors.UsageError("unknown formulation %r; choose one of %s"
                                % (formulation, ", ".join(FORMULATIONS)))
    if on_limit not in ON_LIMIT:
        raise errors.UsageError("unknown on_limit %r; choose one of %s" % (on_limit, ", ".join(ON_LIMIT)))


def _real(value, name):
    """``value`` as a float, or UsageError (strings, complex numbers, overflowing integers)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.floating, np.integer)):
        raise errors.UsageError("%s must be a number, not %r" % (name, value))
    try:
        return float(value)
    except OverflowError:
        raise errors.UsageError("%s=%s is too large" % (name, value)) from None


def _check_arguments(angle_weight, area_weight, max_iter, max_time, ipopt_options):
    """UsageError for a bad numeric argument or IPOPT option, before the mesh is read."""
    for name, value in (("angle_weight", angle_weight), ("area_weight", area_weight)):
        if value is not None:
            weight = _real(value, name)
            if not (np.isfinite(weight) and weight >= 0):
                raise errors.UsageError("%s must be a finite number >= 0, not %r" % (name, value))
    if max_iter is not None:
        if isinstance(max_iter, (bool, np.bool_)) or not isinstance(max_iter, (numbers.Integral, np.integer)):
            raise errors.UsageError("max_iter must be a whole number, not %r" % (max_iter,))
        if max_iter <= 0 or max_iter >= 2 ** 31:
            raise errors.UsageError("max_iter must be between 1 and 2**31 - 1, not %d" % max_iter)
    if max_time is not None:
        seconds = _real(max_time, "max_time")
        if not seconds > 0:
            raise errors.UsageError("max_time must be a number of seconds > 0 (inf: no limit), not %r"
                                    % (max_time,))
    if ipopt_options is not None:
        if not isinstance(ipopt_options, dict):
            raise errors.UsageError("ipopt_options must be a dict, not %s" % type(ipopt_options).__name__)
        try:
            check_ipopt_options(ipopt_options)
        except ValueError as exc:
            raise errors.UsageError(str(exc)) from None


def _area_mode_instead(found, targets, connectivity, prepared, budget, settings, progress, **solve_keywords):
    """The matching area mode's targets and its authalic route, for an angle-mode run whose start
    ``found`` shows limbs shrunk past what double precision holds (solve.unplaceable_start), whose
    angle optimum under the floors is out of reach. The route starts from that map where it is
    conformal to the surface's own metric, as its own start is (the equal modes' is conformal to
    2 pi / deg, from which thin:31k's areas stalled); its record says what was asked."""
    asked = targets.mode
    area_targets = make_targets(AREA_MODE_OF[asked], prepared.normalised_vertices, prepared.faces,
                                connectivity.vertex_degree)
    start = None
    if asked == "original-angles" or found.start.startswith("surface-"):
        start = found.start_positions, found.start
    route = authalic_route(connectivity, prepared.normalised_vertices, area_targets, budget=budget,
                           settings=settings, progress=progress, start=start, **solve_keywords)
    route.record.update(instead_of=asked, mode=area_targets.mode,
                        start_seconds=round(route.record["start_seconds"] + found.start_s, 3))
    return area_targets, route


def _bounded(function):
    """Run ``function`` with Ctrl-C stopping IPOPT too, ``max_time`` bounding the whole run, and
    numpy's and scipy's BLAS on one thread.

    See :mod:`sphere_nlp.interrupts`: a SIGINT inside IPOPT would otherwise end only one stage.
    A program that set its own SIGINT handler keeps it.

    One BLAS thread: OpenBLAS splits a dot product's sum by its thread count, so with one thread per
    core the map depended on the machine's core count (and a batch worker, pinned to one thread,
    mapped a mesh differently from the CLI); and the many small BLAS calls of the untangler's
    L-BFGS-B cost ~10x more with a second thread when another process holds the other core
    (docs/tuning.md, "One BLAS thread"). IPOPT's own linear algebra is not affected.
    """
    @functools.wraps(function)
    def bounded(*args, **kwargs):
        max_time = kwargs.get("max_time")
        if max_time is not None:
            max_time = _real(max_time, "max_time")
            if not (np.isfinite(max_time) and max_time > 0):
                max_time = None                 # rejected inside with its message
        with interrupts.handled_signals(signals=(signal.SIGINT,), only_default=True), \
                interrupts.deadline(max_time), threadpool_limits(limits=1, user_api="blas"):
            return function(*args, **kwargs)
    return bounded


@_bounded
def parameterize(mesh, target="original-angles", *, angle_weight=None, area_weight=None,
                 target_angles=None, target_excess=None, formulation=DEFAULT_FORMULATION, max_iter=None,
                 max_time=None, on_limit="fail", ipopt_options=None, progress=None, on_stage=None, start=None,
                 check=True, settings=None, corner_weighting=None, corner_floor=None, area_floor=None):
    """Map a closed genus-0 triangle mesh onto the unit sphere without overlaps.

    Parameters
    ----------
    mesh : str, Path, trimesh.Trimesh or (vertices, faces)
    target : {"original-angles", "original-areas", "equal-angles", "equal-areas"}
        What the map aims for; see :mod:`sphere_nlp.targets`.
    angle_weight, area_weight : float, optional
        Weights of the angle and area terms of the objective (defaults depend on the mode).
    target_angles : (t, 3) array, optional
        Custom target corner angles (radians), replacing the mode's.
    target_excess : (t,) array, optional
        Custom target triangle areas, rescaled to total 4 pi, replacing the mode's.
    formulation : {"log-chord", "substituted", "faithful"}
        NLP formulation; all reach the same optimum (see :mod:`sphere_nlp.nlp`). ``faithful`` is the
        paper verbatim with its staged solve; ``log-chord`` is the robust default.
    max_iter : int, optional
        IPOPT iteration limit per stage (>= 1).
    max_time : float, optional
        Wall-clock limit of the whole call, in seconds (> 0; ``math.inf``: none): every IPOPT
        stage stops at its first iteration past it, so the call returns after at most one more
        iteration, the unfolding and the certificate (and with ``on_limit="project"`` the
        projection, which may take a fifth of ``max_time`` plus 5 s more). The area modes have a
        default budget counted in work, not seconds (:func:`sphere_nlp.polish.default_budget`:
        300 to 3,000 steps of the authalic descent, then up to 30 IPOPT iterations of the polish
        per run, fewer on larger meshes), so that their map does not depend on the machine's speed or
        load; ``max_time`` replaces it,
        ``math.inf`` runs both stages to the end.
    on_limit : {"fail", "project"}
        When the main (margin) stage reaches ``max_iter`` or ``max_time``: fail (default: SolveError
        with ``check``, ``solved=False``), or project its last iterate onto the constraints and go
        on, so that a long solve still ends with a certified (but not optimal) sphere:
        ``converged=False`` and ``status`` says which limit. Log-chord only.
    ipopt_options : dict, optional
        Extra IPOPT options.
    progress : callable(stage, iteration, objective, violation, elapsed), optional
        Called once per IPOPT iteration.
    on_stage : callable(name), optional
        Called as each stage begins: "load", "build", "solve", "unfold", "certify".
    start : {"authalic", "auto", "conformal", "embedding", "linear"} or (n_input, 3) array, optional
        ``"authalic"`` (default in the area modes with log-chord): the authalic route of
        :mod:`sphere_nlp.polish`, a first-order authalic map that the NLP then polishes within the
        run's budget and never makes worse (its record is ``result.area_route``). Otherwise the
        starting point of the solve: a valid spherical triangulation, either the Mobius-centred
        conformal map when it is bijective or the convex embedding (``auto``, default for log-chord;
        see :func:`sphere_nlp.starts.starting_positions`), or the paper's linear least-squares start
        (default for faithful and substituted). An array gives the start's unit-sphere positions,
        one row per input vertex (or per vertex of the repaired mesh), which must form a valid
        spherical map of the mesh: an earlier result's ``vertices``, the map of a mesh with the same
        triangles (another shape of a series), or a coarser mesh's solution carried over to its
        subdivision (:func:`sphere_nlp.hierarchy.prolong_to_subdivision`). In the area modes a
        start already near the area targets skips the walk towards them
        (``SolverSettings.area_walk_distance``): solving a map again from itself takes a few
        iterations, and IPOPT then ends at an optimum near the start.
    check : bool
        Raise :class:`SolveError` / :class:`CertificateError` on failure (default). With False the
        result is returned with ``success=False`` instead.
    settings : SolverSettings, optional
        The solver's tuning constants (:class:`sphere_nlp.settings.SolverSettings`; docs/tuning.md).
    corner_weighting : {"relative", "uniform"}, optional
        How the angle term weighs the corners: relative errors (weights 1 / beta^2, as in
        angle-based flattening; default in the angle modes) or the paper's (9) verbatim
        ("uniform"; default in the area modes).
        See :mod:`sphere_nlp.targets`.
    corner_floor : float, optional
        Log-chord only: every spherical corner keeps u = alpha - e/2 >= this fraction of its target
        angle, and in the angle modes a corner whose target is below 10 degrees at least half of it
        (bounds; 0 disables both, and ``settings.sliver_band``; default ``settings.corner_floor``,
        in the area modes ``settings.area_mode_corner_floor``; the small-target rule is
        ``settings.small_corner_floor``, ``area_mode_small_corner_floor`` and
        ``small_corner_angle``). The area modes' default is
        0: their areas decide the shapes, and 0.1 costs area error (docs/tuning.md).
    area_floor : float, optional
        Log-chord only: every spherical triangle keeps at least this fraction of the mean area
        4 pi / t (0 disables; default ``settings.area_floor``). ``floor_corners`` and
        ``floor_triangles`` of the result count those that end on their floor. A solve whose
        angles cannot be placed in double precision is run once more with an area floor 1000
        times higher (at least 1e-10), reported in ``recovery``.

    Returns
    -------
    SphericalParameterization

    Raises
    ------
    UnreadableMeshError
        Missing, empty, truncated or unparsable file; polygons; no triangles.
    FaceIndexError
        Face indices out of range, not integers, or repeated within a face.
    NonFiniteCoordinatesError
        NaN or infinite coordinates.
    OpenBoundaryError, NonManifoldEdgeError, NonManifoldVertexError, ComponentsError, GenusError,
    OrientationError
        The surface is not a closed, manifold, connected, orientable genus-0 surface (after merging
        duplicate vertices).
    DegenerateFaceError
        A face whose smallest corner angle is below 1e-10 rad (zero area).
    UsageError
        Unknown target mode or formulation; weights that are not finite numbers >= 0; ``max_iter``
        not a whole number >= 1; ``max_time`` not a finite number > 0; an IPOPT option IPOPT
        rejects; complex or overflowing coordinates; bad custom targets; start positions that are
        not a valid spherical map of the mesh.
    KeyboardInterrupt
        Ctrl-C, also inside IPOPT (as :class:`sphere_nlp.interrupts.Interrupted`).
    SolveError
        IPOPT failed or hit ``max_iter`` / ``max_time`` (only with ``check=True``).
    CertificateError
        The sphere failed its certificate (only with ``check=True``).

    All input errors derive from :class:`MeshInputError`, all errors from :class:`SphereNLPError`;
    each carries a one-line message naming the defect.

    Examples
    --------
    >>> from sphere_nlp.shapes import cylinder
    >>> result = parameterize(cylinder(), target="equal-angles")
    >>> result.certificate.valid, result.max_constraint_violation < 1e-8
    (True, True)
    """
    check_run_options(target, formulation, on_limit, max_iter, max_time, angle_weight, area_weight,
                      ipopt_options)
    check_floors(corner_floor, area_floor)
    unlimited = max_time is not None and math.isinf(float(max_time))
    if unlimited:
        max_time = None
    timings = {}
    clock = time.perf_counter()
    run_started = clock

    def lap(name, next_stage=None):
        nonlocal clock
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock
        clock = now
        if next_stage and on_stage is not None:
            on_stage(next_stage)

    if on_stage is not None:
        on_stage("load")
    vertices, faces, read_notes = _as_arrays(mesh)
    lap("load", "build")
    prepared = prepare_mesh(vertices, faces)
    faces, connectivity = prepared.faces, prepared.connectivity
    # Targets are angles and area ratios, so the normalised copy gives the same ones without the
    # overflow, underflow and cancellation that extreme coordinates would cause.
    targets = make_targets(target, prepared.normalised_vertices, faces, connectivity.vertex_degree,
                           angle_weight=angle_weight, area_weight=area_weight,
                           target_angles=target_angles, target_excess=target_excess,
                           corner_weighting=corner_weighting)
    if start is not None and not isinstance(start, str):
        # Certified here, before the solve is announced, so a wrong start gets only its error.
        start = checked_positions(connectivity, _start_in_repaired_numbering(start, prepared))
    area_route = None
    # The area modes' default route, unless a corner floor is asked for: the authalic map keeps no
    # floors, so the NLP alone must.
    used = DEFAULT_SETTINGS if settings is None else settings
    if not isinstance(used, SolverSettings):
        raise errors.UsageError("settings must be a sphere_nlp.SolverSettings, not %s" % type(used).__name__)
    floors = corner_floor if corner_floor is not None else max(used.area_mode_corner_floor,
                                                               used.area_mode_small_corner_floor)
    # The run's own max_time bounds everything already (the decorator's deadline); without one,
    # the area modes' route has its default budget, counted in work; math.inf, none at all.
    budget = default_budget(connectivity.n_vertices, used) if max_time is None and not unlimited else None
    if (isinstance(start, str) and start == "authalic") or (start is None and targets.area_weight > 0
                                                            and formulation == "log-chord" and not floors):
        if formulation != "log-chord" or targets.area_weight == 0:
            raise errors.UsageError("start='authalic' is the area modes' route and needs the log-chord formulation")
        lap("build", "solve")
        route = authalic_route(connectivity, prepared.normalised_vertices, targets, budget=budget,
                               settings=settings, progress=progress, ipopt_options=ipopt_options,
                               max_iter=max_iter, corner_floor=corner_floor, area_floor=area_floor)
        solution, area_route = route.solution, route.record
        lap("solve", "unfold")
        positions, unfold_info = route.positions, route.unfold_info
    else:
        lap("build", "solve")
        solution = solve_angles(connectivity, targets, formulation=formulation, ipopt_options=ipopt_options,
                                max_iter=max_iter, max_time=max_time, progress=progress,
                                vertices=prepared.normalised_vertices, start=start, on_limit=on_limit,
                                settings=settings, corner_floor=corner_floor, area_floor=area_floor)
        if solution.status == UNPLACEABLE_START:
            targets, route = _area_mode_instead(solution, targets, connectivity, prepared, budget, settings,
                                                progress, ipopt_options=ipopt_options, max_iter=max_iter,
                                                corner_floor=corner_floor, area_floor=area_floor)
            solution, area_route = route.solution, route.record
            positions, unfold_info = route.positions, route.unfold_info
        lap("solve", "unfold")
    # Symbolic derivatives and IPOPT set-up happen inside the solve; book them as build time.
    build_s = sum(s["build_s"] for s in solution.stages)
    timings["solve"] -= build_s
    timings["build"] += build_s

    if area_route is not None:
        pass                                    # the route's map is certified and placed already
    elif not solution.success and (interrupts.deadline_passed() or solution.status == NO_VALID_START):
        # Out of time, or folded angles from no valid start, and nothing to write: the unfolding
        # of a failed iterate is skipped (bipyramid(1000) stopped by max_time: 26 s of unfolding
        # after the limit).
        positions, unfold_info = np.full((connectivity.n_vertices, 3), np.nan), {}
    else:
        positions, unfold_info = sphere_positions(connectivity, solution.angles, solution.excess)
    lap("unfold", "certify")
    certificate = certify(positions, faces)
    recovery = None
    if formulation == "log-chord" and solution.success and not certificate.valid and area_route is None:
        # Solved angles that double precision cannot place (triangles too small to unfold): solve
        # again with an area floor 1000 times higher (at least 1e-10 of the mean), once. Not after
        # the area modes' route, whose map is uncertified only when no valid start was found, from
        # which the NLP alone cannot do better (docs/design.md, the area modes).
        used = (settings or DEFAULT_SETTINGS).area_floor if area_floor is None else float(area_floor)
        tighter = max(1e3 * used, 1e-10)
        retry = solve_angles(connectivity, targets, formulation=formulation, ipopt_options=ipopt_options,
                             max_iter=max_iter, max_time=max_time, progress=progress,
                             vertices=prepared.normalised_vertices, start=start, on_limit=on_limit,
                             settings=settings, corner_floor=corner_floor, area_floor=tighter)
        recovery = {"reason": certificate.reason, "area_floor": tighter, "solved": bool(retry.success)}
        if retry.success:
            retry.stages = solution.stages + [dict(stage, name="recovery-" + stage["name"])
                                              for stage in retry.stages]
            retry.iterations += solution.iterations
            solution = retry
            positions, unfold_info = sphere_positions(connectivity, solution.angles, solution.excess)
            certificate = certify(positions, faces)
        recovery["certified"] = bool(certificate.valid)
    angle_error = max_angle_error(positions, faces, solution.angles)
    lap("certify")
    timings["total"] = time.perf_counter() - run_started
    split_timings(timings, solution.stages, area_route, unfold_info,
                  area_route.get("start_seconds", 0.0) if area_route is not None else solution.start_s)

    result = SphericalParameterization(
        vertices=positions, faces=faces, input_vertices=prepared.vertices, angles=solution.angles,
        excess=solution.excess, target_angles=targets.angles, target_excess=targets.excess,
        target=targets.mode, formulation=formulation, success=solution.success and certificate.valid,
        status=solution.status, iterations=solution.iterations, objective=solution.objective,
        max_constraint_violation=solution.max_constraint_violation, max_angle_error=angle_error,
        certificate=certificate, vertex_map=prepared.vertex_map, solved=solution.success,
        converged=solution.converged,
        stages=solution.stages, timings=timings, repairs=read_notes + prepared.repairs,
        unfold_info=unfold_info, peak_rss_mb=peak_rss_mb(), start=solution.start,
        corner_weighting=targets.corner_weighting, floor_corners=solution.floor_corners,
        floor_triangles=solution.floor_triangles, recovery=recovery, area_route=area_route)
    if check and not solution.success:
        raise errors.SolveError(area_route["reason"] if area_route is not None and area_route["answer"] == "none"
                                else solve_failure_message(solution.status, solution.iterations), result)
    if check and not certificate.valid:
        raise errors.CertificateError("the sphere failed its certificate: " + certificate.reason, result)
    return result
