"""kneas datamanagers."""
