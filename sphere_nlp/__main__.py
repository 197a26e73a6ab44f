"""``python -m sphere_nlp``: the signal handling first, then the command line (:mod:`sphere_nlp.cli`)."""

from . import interrupts

# Before numpy, CasADi and trimesh load (about 2 s): a signal from here on ends the run with
# 128 + its number and nothing written (see interrupts.program_started).
interrupts.program_started()

import sys  # noqa: E402

from .cli import main  # noqa: E402

sys.exit(main())
