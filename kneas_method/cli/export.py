"""`kneas-export` (placeholder until the export work lands)."""

from .common import not_built_yet

main = not_built_yet("kneas-export", "export")
