"""``rpr-cosim fit``: a scene's parameters estimated from a recording (:mod:`.problem` the least
squares on the monolithic model, :mod:`.solve` the solver and the statistics, :mod:`.overlay` the
calibrated scene)."""
from .problem import Problem, Unknown, build, unknowns
from .solve import FitResult, solve

__all__ = ["FitResult", "Problem", "Unknown", "build", "solve", "unknowns"]
