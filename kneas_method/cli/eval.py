"""`kneas-eval` (placeholder until the evaluation work lands)."""

from .common import not_built_yet

main = not_built_yet("kneas-eval", "evaluation")
