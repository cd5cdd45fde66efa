"""The optimiser of every fit (engine/optim.adam): fused where torch has it, the step torch's default
Adam takes (the naive oracle), and torch's default where the fused kernel is refused."""

import dataclasses

import torch

from kneas_method.engine.optim import adam


def _fit(make, steps: int = 6):
    """Parameters of a small MLP after ``steps`` steps of the optimiser ``make(params)`` on a fixed problem."""
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1))
    g = torch.Generator().manual_seed(1)
    x, y = torch.randn(64, 3, generator=g), torch.randn(64, 1, generator=g)
    optimizer = make(model.parameters())
    for _ in range(steps):
        optimizer.zero_grad()
        (model(x) - y).square().mean().backward()
        optimizer.step()
    return [p.detach().clone() for p in model.parameters()], optimizer


def test_adam_is_fused_on_the_cpu_and_takes_the_default_adam_step():
    fused, optimizer = _fit(lambda p: adam(p, 1e-2))
    assert optimizer.defaults["fused"] is True  # torch >= 2.4 has the CPU kernel
    plain, _ = _fit(lambda p: torch.optim.Adam(p, lr=1e-2))
    start, _ = _fit(lambda p: torch.optim.Adam(p, lr=1e-2), steps=0)
    assert any((a - s).abs().max() > 1e-3 for a, s in zip(fused, start))  # the steps moved the parameters
    for a, b in zip(fused, plain):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_adam_falls_back_to_the_default_where_fused_is_refused(monkeypatch):
    real = torch.optim.Adam

    def refusing(params, lr, fused=None, **kwargs):
        if fused:
            raise RuntimeError("`fused=True` requires all the params to be floating point Tensors of supported devices")
        return real(params, lr=lr, **kwargs)

    monkeypatch.setattr(torch.optim, "Adam", refusing)
    model = torch.nn.Linear(3, 2)
    optimizer = adam((p for p in model.parameters()), 1e-3)  # a generator: the fallback still gets every parameter
    assert not optimizer.defaults.get("fused")
    assert len(optimizer.param_groups[0]["params"]) == 2


def test_training_and_the_volume_fits_use_the_fused_adam(tiny_scene, tmp_path, monkeypatch):
    from kneas_method import presets, registry
    from kneas_method.data.naf import load_naf
    from kneas_method.engine.trainer import Trainer
    from kneas_method.stages import volume_fit

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-1m").config, method="neas-1m", preset="tiny"))
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, epochs=1, eval_every=0, checkpoint_every=0))
    trainer = Trainer(cfg, load_naf(tiny_scene), tmp_path, epochs=1, device="cpu", label="model")
    assert trainer.optimizer.defaults["fused"] is True
    made = []
    monkeypatch.setattr(volume_fit, "adam", lambda params, lr: made.append(lr) or adam(params, lr))
    points = torch.rand(32, 3) * 2 - 1
    volume_fit.fit_steps(trainer, points, torch.full((32,), 0.1), lambda: torch.arange(16), steps=2, lr=1e-3,
                         occupancy_weight=0.0, task="fit", info="", fix="")
    assert made == [1e-3]
