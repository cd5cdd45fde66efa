"""kneas losses."""
