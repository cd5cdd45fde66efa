"""Classical CT reconstruction (SPEC §7): FDK and the iterative methods, as plain functions
of (projections, geometry), and :func:`~kneas_method.classical.reconstruct.reconstruct`, the one
entry the pipelines use (``kneas-train fdk|...`` and the neural methods' bounds / warm start)."""
