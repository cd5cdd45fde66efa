"""`kneas-bench` (placeholder until the experiments at scale work lands)."""

from .common import not_built_yet

main = not_built_yet("kneas-bench", "experiments at scale")
