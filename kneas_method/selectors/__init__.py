"""kneas selectors."""
