"""The names the command line offers as choices, in a module of the standard library alone.

``sphere-nlp --help`` and ``--version`` build the parser from these without importing numpy, SciPy
or CasADi (0.6 s of imports to print a line); the modules that use them import them from here.
"""

# What a map aims for (sphere_nlp.targets).
MODES = ("equal-angles", "equal-areas", "original-angles", "original-areas")
# The area mode that maps a shape instead of an angle mode whose start cannot be placed
# (sphere_nlp.solve.unplaceable_start).
AREA_MODE_OF = {"original-angles": "original-areas", "equal-angles": "equal-areas"}
# How the angle term weighs the corners (sphere_nlp.targets).
CORNER_WEIGHTINGS = ("relative", "uniform")
# The NLP's formulations (sphere_nlp.nlp).
FORMULATIONS = ("log-chord", "substituted", "faithful")
DEFAULT_FORMULATION = "log-chord"
# What a margin stage stopped by the caller's limits yields (sphere_nlp.solve's on_limit).
ON_LIMIT = ("fail", "project")
