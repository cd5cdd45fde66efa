"""kneas evaluation."""
