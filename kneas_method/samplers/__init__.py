"""kneas samplers."""
