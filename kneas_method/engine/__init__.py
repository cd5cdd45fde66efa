"""kneas engine: the orchestrator (``pipeline.train``), one pipeline per kind of run
(``neural_pipeline``, ``classical_pipeline``), their stages (``bounds_stage``,
``classical_volume``, ``train_stage`` with the ``trainer``, ``evaluate``, ``report``),
loading saved runs (``loading``), checkpoints and run folders."""
