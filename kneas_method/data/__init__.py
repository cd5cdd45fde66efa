"""Scenes: NAF pickles (safe IO), built-in phantoms, projectors and the simulator; your own
scans through ITK and RTK's geometry XML (``scanner_import``, ``rtk_geometry``, ``rtk_export``)."""
