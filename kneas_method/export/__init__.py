"""kneas export."""
