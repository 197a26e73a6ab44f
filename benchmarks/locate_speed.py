"""Point location and resampling speed: a sphere map queried at an icosphere's vertices.

    PYTHONPATH=. python benchmarks/locate_speed.py MESH SPHERE [--level 6]

SPHERE is a certified sphere of MESH (e.g. `sphere-nlp MESH -o SPHERE`). Prints the KD-tree build and
location times, the slowest query path used, and the resample's sampled Hausdorff distance.
"""

import argparse
import time

import numpy as np

from sphere_nlp.locate import SphereLocator, interpolate
from sphere_nlp.resample import hausdorff, load_map
from sphere_nlp.shapes import icosphere


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh")
    parser.add_argument("sphere")
    parser.add_argument("--level", type=int, default=6)
    args = parser.parse_args()
    X, S, F = load_map(args.mesh, args.sphere)
    P, G = icosphere(args.level)
    start = time.perf_counter()
    locator = SphereLocator(S, F)
    built = time.perf_counter()
    face, bary = locator.locate(P)
    located = time.perf_counter()
    V = interpolate(X, F, face, bary)
    done = time.perf_counter()
    Q = np.einsum("ij,ijk->ik", bary, locator.vertices[F[face]])
    error = np.abs(Q / np.linalg.norm(Q, axis=1, keepdims=True) - P).max()
    h, mean = hausdorff((X, F), (V, G))
    diag = np.linalg.norm(np.ptp(X, axis=0))
    print("sphere %d vertices, %d queries: build %.3f s, locate %.3f s, interpolate %.3f s; "
          "max reconstruction error %.2g" % (len(S), len(P), built - start, located - built, done - located, error))
    print("Hausdorff %.4g (%.2f%% of diagonal), mean distance %.3g (%.3f%%)"
          % (h, 100 * h / diag, mean, 100 * mean / diag))


if __name__ == "__main__":
    main()
