"""kneas fields."""
