"""Regenerate every picture in docs/ from the current code, in a few seconds:

    python docs/make_pictures.py

* ``docs/cylinder.png``: the shipped cylinder mapped in the default mode, drawn by
  ``SphericalParameterization.write_png`` (what ``sphere-nlp models/cylinder.off --png`` draws);
* ``docs/fig3.png``: the paper's Fig. 3 with the four modes, drawn by ``sphere-nlp reproduce fig3``.
"""

import shutil
import sys
import tempfile
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

PICTURES = ("cylinder.png", "fig3.png")     # every picture in docs/ (tests/test_ux.py checks)


def main():
    import sphere_nlp
    from sphere_nlp.reproduce import reproduce_fig3

    result = sphere_nlp.parameterize(str(ROOT / "models" / "cylinder.off"))
    result.write_png(DOCS / "cylinder.png")
    with tempfile.TemporaryDirectory() as scratch:
        records = reproduce_fig3(scratch)
        if not all(record["valid"] for record in records):
            sys.exit("make_pictures: a Fig. 3 panel was not certified; docs/fig3.png left as it was")
        shutil.copyfile(Path(scratch) / "fig3.png", DOCS / "fig3.png")
    print("wrote " + ", ".join(str(DOCS / name) for name in PICTURES))


if __name__ == "__main__":
    main()
