"""kneas engine."""
