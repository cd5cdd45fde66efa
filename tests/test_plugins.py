"""A third-party package adds a selector and a whole method through entry points, with no change to kneas."""

import dataclasses
import importlib
import json
import re
import sys
import textwrap

import numpy as np
import pytest
import torch

from kneas_method import presets, registry
from kneas_method.data.scene import Scene, Views
from kneas_method.geometry import Geometry

PLUGIN = textwrap.dedent(
    '''
    """Demo kneas plugin: a normalised-occupancy selector and a method using it."""
    from dataclasses import dataclass

    from kneas_method.methods import TrainConfig
    from kneas_method.model import ModelConfig
    from kneas_method.registry import MethodSpecification
    from kneas_method.selectors.base import Selector, SelectorConfig


    @dataclass
    class ShareSelectorConfig(SelectorConfig):
        _target = "kneas_demo_plugin:ShareSelector"
        power: float = 1.0


    class ShareSelector(Selector):
        """w_k = o_k^p / (1 + sum_j o_j^p): materials share the point."""

        def weights(self, occupancies, distances):
            o = occupancies ** self.config.power
            return o / (1.0 + o.sum(-1, keepdim=True))


    method = MethodSpecification(
        config=TrainConfig(
            method="demo-share",
            model=ModelConfig(selector="demo-share", selector_options={"power": 2.0}, attenuation="shared", num_materials=2),
        ),
        description="demo plugin method: shared attenuation with the share selector",
    )


    # a field of its own, with surfaces: a two-layer SDF network (the built-in has one hidden layer)
    import torch
    from torch import nn

    from kneas_method.fields.base import Field, FieldConfig, FieldOutputs, encode_points


    @dataclass
    class DeepSDFConfig(FieldConfig):
        _target = "kneas_demo_plugin:DeepSDF"
        has_surfaces = True
        feature_dim: int = 8


    class DeepSDF(Field):
        def __init__(self, config, *, encoding, num_materials):
            super().__init__(config)
            self.encoding, self.num_distances, self.feature_dim = encoding, num_materials, config.feature_dim
            self.mlp = nn.Sequential(nn.Linear(encoding.n_output_dims, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(),
                                     nn.Linear(32, num_materials + config.feature_dim))
            with torch.no_grad():
                self.mlp[-1].bias[:num_materials] += 0.1

        def get_outputs(self, points, with_gradients=False):
            out = self.mlp(encode_points(self.encoding, points, self.bound))
            return FieldOutputs(distances=out[:, : self.num_distances], features=out[:, self.num_distances :])


    deep_method = MethodSpecification(
        config=TrainConfig(method="demo-deep", model=ModelConfig(field="demo-deep", attenuation="shared", floater=True)),
        description="demo plugin method: K-NeAS on the plugin's own surface field",
    )


    # a stage of its own, after training, and a procedure that runs it
    from kneas_method.stages import PAPER, Procedure
    from kneas_method.stages.base import Stage, StageConfig


    @dataclass
    class MarkStageConfig(StageConfig):
        _target = "kneas_demo_plugin:MarkStage"
        name = "demo-mark"
        phase = "after-training"
        label: str = "marked"


    class MarkStage(Stage):
        def run(self, state):
            state.records[self.name] = {"label": self.config.label, "step": state.trainer.step,
                                        "materials": int(state.trainer.model.num_materials)}
            state.say(f"demo-mark: {self.config.label}")


    # settings as a plugin written before bounds_cover_percentile existed gives them: SPEC's top bound applies
    procedure = Procedure(name="demo-proc", description="the paper's, then a mark", stages=("demo-mark",),
                          settings={**PAPER.settings, "run": {k: v for k, v in PAPER.settings["run"].items()
                                                              if k != "bounds_cover_percentile"}})
    '''
)

ENTRY_POINTS = """\
[kneas.selectors]
demo-share = kneas_demo_plugin:ShareSelectorConfig

[kneas.fields]
demo-deep = kneas_demo_plugin:DeepSDFConfig

[kneas.methods]
demo-share = kneas_demo_plugin:method
demo-deep = kneas_demo_plugin:deep_method

[kneas.stages]
demo-mark = kneas_demo_plugin:MarkStageConfig

[kneas.procedures]
demo-proc = kneas_demo_plugin:procedure
"""


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    (tmp_path / "kneas_demo_plugin.py").write_text(PLUGIN)
    info = tmp_path / "kneas_demo_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: kneas-demo-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    yield
    sys.modules.pop("kneas_demo_plugin", None)


def ball_scene(n_views=4, n_det=12):
    g = Geometry.from_mm(mode="cone", DSD=1500.0, DSO=1000.0, nDetector=(n_det, n_det), dDetector=(192.0 / n_det,) * 2,
                         nVoxel=(16, 16, 16), dVoxel=(8.0, 8.0, 8.0))
    angles = np.linspace(0, np.pi, n_views, endpoint=False)
    o, d = g.rays(angles, dtype=torch.float64)
    r = 30.0 / g.mm_per_unit
    dn = d / d.norm(dim=-1, keepdim=True)
    closest = (o - (o * dn).sum(-1, keepdim=True) * dn).norm(dim=-1)
    p = (2.0 * 2 * torch.sqrt(torch.clamp(r**2 - closest**2, min=0)) / g.scale).float().numpy()
    return Scene(name="ball", geometry=g, train=Views(angles, p), val=Views(angles[:1], p[:1]))


def test_plugin_is_discovered(plugin, capsys):
    assert "demo-share" in registry.names("selectors")
    assert "demo-share" in registry.names("methods")
    assert "demo-share" not in registry.names("fields")
    from kneas_method.cli import train as cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0 and "demo-share" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        cli.main(["demo-share", "--dry-run", "--preset", "tiny"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and re.search(r"^parameters: [\d,]+$", out, re.M) and "selector=demo-share" in out
    # a built-in method with the plugin's selector, by name on the command line
    with pytest.raises(SystemExit) as exc:
        cli.main(["k-neas", "--dry-run", "--preset", "tiny", "--model.selector", "demo-share", "--model.selector-options", "power", "3"])
    assert exc.value.code == 0


def test_plugin_method_trains(plugin):
    spec = registry.load("methods", "demo-share")
    cfg = presets.resolve(dataclasses.replace(spec.config, preset="tiny"))
    scene = ball_scene()
    torch.manual_seed(0)
    dm = cfg.datamanager.setup(scene=scene, seed=0)
    model = cfg.model.setup(scale=scene.geometry.scale)
    assert type(model.selector).__name__ == "ShareSelector" and model.selector.config.power == 2.0
    model.set_bounds([1.0, 2.0], [0.0, 1.0])
    before = [p.detach().clone() for p in model.parameters()]
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    steps = 4 * dm.steps_per_epoch
    for step in range(steps):
        batch = dm.next_train()
        loss = model.loss_dict(batch, progress=step / steps)
        opt.zero_grad()
        loss["total"].backward()
        opt.step()
        losses.append(loss["intensity"].item())
    assert all(np.isfinite(losses))
    assert np.mean(losses[-4:]) < np.mean(losses[:4])
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, model.parameters()))


def test_plugin_surface_field_trains_as_an_sdf_method(plugin, tmp_path, capsys):
    """A field registered under a new name, with surfaces: the run estimates bounds (GMM, K by
    BIC), trains the K-material model on it and reports materials, like the built-in SDF field."""
    from kneas_method.model import field_has_surfaces

    from conftest import run, run_dir_of, simulated_foot

    spec = registry.load("methods", "demo-deep")
    assert field_has_surfaces(spec.config.model) and presets.k_from_data(spec.config)
    scene = simulated_foot(tmp_path, "plugfoot", 16, 15.0, n_train=4)
    code, out, err = run(["demo-deep", "--scene", str(scene), "--preset", "tiny", "--output-dir", str(tmp_path / "out"),
                          "--procedure", "refine-classical", "--stages.classical-start.algorithm", "fdk",
                          "--skip-stages", "correction", "smoothing", "materials-refit", "--stages.warm-start.steps", "5"], capsys)
    assert code == 0, err
    assert "bounds: GMM (gmm) on" in out and "BIC" in out
    metrics = json.loads((run_dir_of(out) / "metrics.json").read_text())
    assert metrics["num_materials"] >= 1 and len(metrics["alphas"]) == metrics["num_materials"]
    assert np.isfinite(metrics["psnr3d"])


def test_a_plugin_stage_runs_in_a_procedure(plugin, tmp_path, capsys):
    """A stage registered by a plugin (``kneas.stages``) runs in the plugin's procedure (``kneas.procedures``),
    is added to another with ``--add-stages``, takes its settings from a config file, and is recorded."""
    from conftest import run, run_dir_of, simulated_foot

    assert "demo-mark" in registry.names("stages") and "demo-proc" in presets.procedures()
    scene = simulated_foot(tmp_path, "markfoot", 16, 15.0, n_train=4)
    common = ["--scene", str(scene), "--preset", "tiny", "--trainer.epochs", "1", "--trainer.eval-every", "0"]
    code, out, err = run(["k-neas", *common, "--procedure", "demo-proc", "--output-dir", str(tmp_path / "a")], capsys)
    assert code == 0, err
    assert "procedure: demo-proc: the paper's, then a mark" in out and "demo-mark: marked" in out
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["procedure"] == "demo-proc" and metrics["stages"]["demo-mark"]["label"] == "marked"
    assert metrics["stages"]["demo-mark"]["step"] == metrics["steps"]  # after training
    # added to the paper's procedure, with its settings from a config file
    saved = json.loads((run_dir / "config.json").read_text())
    assert saved["bounds_cover_percentile"] == 0.0  # not given by the procedure: SPEC §4's 1.15 x the 99.5th percentile
    saved.update(procedure="paper", add_stages=["demo-mark"], output_dir=str(tmp_path / "b"))
    saved["stages"]["plugins"] = {"demo-mark": {"label": "from the file"}}
    path = tmp_path / "config.json"
    path.write_text(json.dumps(saved))
    code, out, err = run(["--config", str(path)], capsys)
    assert code == 0, err
    metrics = json.loads((run_dir_of(out) / "metrics.json").read_text())
    assert metrics["procedure"] == "paper" and metrics["stages"]["demo-mark"]["label"] == "from the file"
