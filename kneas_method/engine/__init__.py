"""kneas engine: the orchestrator (``pipeline.train``), one pipeline per kind of run
(``neural_pipeline``, ``classical_pipeline``), the core of a neural run (``bounds_stage``, the
``trainer``), evaluation and reports, loading saved runs (``loading``), checkpoints and run folders.
The stages a procedure adds around the core live in ``kneas_method.stages``."""
