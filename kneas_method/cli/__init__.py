"""kneas cli."""
