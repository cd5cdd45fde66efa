"""`kneas-train` (placeholder until the training work lands)."""

from .common import not_built_yet

main = not_built_yet("kneas-train", "training")
