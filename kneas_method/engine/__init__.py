"""kneas engine: the training pipeline, the stage trainer, evaluation, checkpoints, run folders.

``train(config)`` is what ``kneas-train`` calls (imported lazily, so importing the
engine stays cheap); ``evaluate_model`` / ``evaluate_volume`` are the shared
evaluation used by ``kneas-train`` and ``kneas-eval``.
"""


def train(config):
    """Run ``kneas-train`` for a resolved TrainConfig; returns the exit code (see :mod:`.pipeline`)."""
    from .pipeline import train as _train

    return _train(config)


def evaluate_model(model, scene, config, device):
    """See :func:`kneas_method.engine.evaluate.evaluate_model`."""
    from .evaluate import evaluate_model as _evaluate_model

    return _evaluate_model(model, scene, config, device)


def evaluate_volume(volume, scene):
    """See :func:`kneas_method.engine.evaluate.evaluate_volume`."""
    from .evaluate import evaluate_volume as _evaluate_volume

    return _evaluate_volume(volume, scene)


__all__ = ["train", "evaluate_model", "evaluate_volume"]
