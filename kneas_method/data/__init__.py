"""Scenes: NAF pickles (safe IO), built-in phantoms, projectors and the simulator."""
