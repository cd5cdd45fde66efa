"""The run configuration trees and the method table of SPEC §6.

Two kinds of run, each a config tree of its own and a pipeline of its own
(nerfstudio's pipeline config per kind of method):

* :class:`TrainConfig` (neural methods: model, datamanager, trainer, bounds, procedure) ->
  :class:`~kneas_method.engine.neural_pipeline.NeuralPipeline`;
* :class:`ClassicalConfig` (FDK and the iterative methods of SPEC §7, 0 parameters) ->
  :class:`~kneas_method.engine.classical_pipeline.ClassicalPipeline`.

Both share :class:`RunConfig` (scene, views, preset, seed, device, folders) and
round-trip through JSON (``config.to_dict`` -> JSON -> ``config.update_from_dict``).
Settings left at ``None`` are decided by the preset (compute) or the procedure (fitting;
``presets.resolve``); anything set explicitly (command line, JSON) wins.

A method is its model. Each is a :class:`~kneas_method.registry.MethodSpecification`
registered under ``kneas.methods`` in ``pyproject.toml``; the neural ones differ only in
configuration:

| method | K | attenuation | selector | floater | bounds |
|---|---|---|---|---|---|
| neas-1m | 1 | single | soft (K = 1: mu_bar·Omega) | off | wide defaults or given |
| neas-2m | 2 | independent | hard | off | automatic or given |
| kselector | K (3) | independent | soft | off | automatic or given |
| kselector-floater | K (3) | independent | soft | on | automatic or given |
| kselector-shared | K (3) | shared | soft | off | automatic or given |
| k-neas | K (3) | shared | soft | on | automatic or given |
| naf | — | NAF field (hash grid + MLP, no SDF) | — | off | — |
| fdk | — | classical: FDK / FBP, no model | — | — | — |
| sart, os-sart, cgls, asd-pocs | — | classical iterative (SPEC §7), no model | — | — | — |

How a neural model is fitted is its procedure (``--procedure``, ``kneas_method.stages``): the
paper's, or ``refine-classical`` (the cpu preset's). K of the K-material methods (kselector*,
k-neas) is picked by the procedure's K rule when ``num_materials`` is None (the default) and the
bounds are automatic (paper: the BIC of the GMM fit, SPEC §4; refine-classical: the peaks of the
classical start's histogram, ``bic-valleys`` where it has fewer than two); ``--num-materials K``
fixes it; a ``--bounds`` file gives it. The method's ``model.num_materials`` (3) is only the default
shown by a dry run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal, Optional

from .classical.options import Algorithm, ReconstructionOptions
from .config import InstantiateConfig, at_least, check_ranges
from .datamanagers.ct import CTDataManagerConfig
from .errors import ConfigError
from .model import ModelConfig
from .registry import MethodSpecification
from .stages import StagesConfig

Preset = Literal["auto", "paper", "cpu", "tiny"]
BoundsSource = Literal["wide", "auto", "none"]
BoundsMethod = Literal["gmm", "quantile", "bayes"]
BoundsKRule = Literal["bic", "bic-valleys", "peaks"]
EvalProjections = Literal["rendered", "volume"]
PRESETS: tuple[str, ...] = Preset.__args__


@dataclass
class TrainerConfig:
    """The training schedule and its bookkeeping. ``None`` = the preset's value (``lr_decay_at``:
    the procedure's).

    Attributes:
        epochs: training epochs (one step per training projection per epoch; paper 1000).
        prior_epochs: epochs of the single-material prior model trained for the
            automatic bounds (SPEC §4); paper 1000.
        lr: Adam learning rate (paper 1e-3).
        lr_decay_at: fraction of the steps after which the rate is multiplied by
            ``lr_decay_factor`` (paper 0.5: after 500 of 1000 epochs).
        lr_decay_factor: that factor (paper 0.1).
        eval_every: epochs between held-out evaluations during training (0 = only at the end).
        checkpoint_every: epochs between checkpoints (0 = only at the end).
        eval_chunk: rays per chunk when rendering full views for evaluation.
        eval_views: held-out views scored at intermediate evaluations (None = all).
        eval_projections: how the final evaluation, and the intermediate ones, make the
            held-out projections of their 2D metrics: ``rendered`` through the field (``model.num_eval_samples`` per ray;
            the paper), or ``volume``: the field sampled at the voxel centres (the volume the
            3D metrics score) and projected by the Joseph projector, the operator that scores
            the classical methods' volumes too; tens of times fewer field queries, whatever
            the detector size (paper: rendered; cpu: volume).
        log_every: steps between loss-history / learning-rate records.
        max_bad_steps: this many non-finite losses in a row end the run (the last
            good checkpoint is kept).
    """

    epochs: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    prior_epochs: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    lr: Optional[float] = field(default=None, metadata=at_least(0, strict=True))
    lr_decay_at: Optional[float] = field(default=None, metadata=at_least(0, at_most=1))
    lr_decay_factor: float = field(default=0.1, metadata=at_least(0, strict=True))
    eval_every: Optional[int] = field(default=None, metadata=at_least(0, whole=True))
    checkpoint_every: Optional[int] = field(default=None, metadata=at_least(0, whole=True))
    eval_chunk: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    eval_views: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    eval_projections: Optional[EvalProjections] = None
    log_every: int = field(default=50, metadata=at_least(1, whole=True))
    max_bad_steps: int = field(default=5, metadata=at_least(0, whole=True))


@dataclass
class RunConfig(InstantiateConfig):
    """What every run has, whatever its kind. ``setup(scene=, run_dir=, device=)`` builds the
    kind's pipeline (``_target``).

    Attributes:
        method: the registered method name this config came from.
        scene: built-in scene name or a path to a NAF pickle.
        views: keep this many training views, spread uniformly (None = all).
        preset: how much compute: ``auto`` (paper with CUDA, else cpu); ``paper``: the paper's schedule
            and grid (its procedure by default); ``cpu``: a short schedule and a small grid for 2 CPU
            cores (the refine-classical procedure by default); ``tiny``: smoke runs.
        seed: seeds model initialisation and ray sampling.
        output_dir: parent folder of run folders.
        dry_run: build (the model), print the config and parameter count, don't train.
        device: ``auto`` (cuda if available), ``cpu``, ``cuda``, ``cuda:1``...
        data_dir: where public benchmark pickles ``<name>_50.pickle`` are looked for.
        resume: a run folder to continue (``kneas-train --resume RUN_DIR``); its
            ``config.json`` is used.
    """

    method: str = "k-neas"
    scene: str = "foot"
    views: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    preset: Preset = "auto"
    seed: int = 0
    output_dir: str = "outputs"
    dry_run: bool = False
    device: str = "auto"
    data_dir: str = "data"
    resume: Optional[str] = None


@dataclass
class ClassicalConfig(RunConfig):
    """A classical reconstruction run (SPEC §7): no model, no training, 0 parameters.

    Attributes:
        algorithm: the classical method.
        reconstruction: its settings.
        trace: score the volume after every iteration against the scene's true volume (a scene with
            one), and record in ``metrics.json`` (``trace``) the psnr3d of each count and the best count
            with its psnr3d and ssim3d: the oracle count no user can pick from the projections alone.
    """

    _target = "kneas_method.engine.classical_pipeline:ClassicalPipeline"
    method: str = "fdk"
    algorithm: Algorithm = "fdk"
    reconstruction: ReconstructionOptions = field(default_factory=ReconstructionOptions)
    trace: bool = False


@dataclass
class TrainConfig(RunConfig):
    """A neural training run: a method's model, fitted by a procedure at a preset's compute.

    Attributes:
        procedure: how the model is fitted: ``paper`` (a NeAS-1M prior, GMM bounds, training) or
            ``refine-classical`` (an ASD-POCS start, a warm start and an anchor to it, the visual
            hull, band correction, smoothing, materials refit, a time budget), or a plugin's
            (``kneas.procedures``); None = the preset's (paper and tiny: paper; cpu: refine-classical).
        skip_stages: stages of the procedure left out (``--skip-stages correction smoothing``).
        add_stages: registered stages run besides the procedure's (a plugin's, ``kneas.stages``).
        stages: each stage's settings.
        num_materials: K; overrides the method's default (None = method default).
        bounds: JSON file with ``{"alphas": [...], "betas": [...]}`` (data units, 1/m).
        bounds_source: where bounds come from when neither ``bounds`` nor
            ``model.alphas/betas`` are given: ``wide`` (NeAS defaults), ``auto``
            (GMM of SPEC §4) or ``none`` (no SDF).
        bounds_method: GMM boundary rule for automatic bounds: ``gmm`` (paper, SPEC §4),
            ``quantile`` or ``bayes`` (options beside the paper's; see ``bounds.GMMBounds``).
        bounds_max_materials: automatic bounds try K = 1..this (None = the procedure's: paper 4,
            refine-classical 8).
        bounds_k_rule: how automatic bounds pick K: ``bic`` (paper: the lowest BIC),
            ``bic-valleys`` (the lowest BIC among K whose boundaries are all valleys of the
            mixture density) or ``peaks`` (one material per peak of the volume's histogram,
            boundaries at its valleys, no mixture and no seed, material 1's labels from half
            its peak (``model.first_label_threshold``); bic-valleys where the histogram has
            fewer than two peaks); None = the procedure's: refine-classical peaks (bic-valleys with a
            ``bounds_method`` other than ``gmm``), paper bic.
        bounds_at_noise_k_rule: the K rule instead of ``bounds_k_rule`` where the classical start
            already fits the training views to their noise (a noisy scan; ``classical_start.start_fit``),
            the mixtures fitted to the start after the edge-preserving filter of the peaks rule's
            fallback: noise smears a scan's histogram so that only its two largest tissues keep a peak
            or a valley, while BIC counts the components the filtered values support. The same rule as
            ``bounds_k_rule`` (``--bounds-at-noise-k-rule peaks``): that rule everywhere. None = the
            procedure's: refine-classical bic (the paper's none: ``bounds_k_rule`` everywhere).
        bounds_min_std: the GMM components' smallest standard deviation, as a fraction of
            the 99.5th-percentile attenuation (0 = sklearn's default regulariser; None = the
            procedure's: 0). Keeps a TV-flattened material from taking a spike component.
        bounds_gmm_restarts: k-means starts per GMM fit, the best kept (scikit-learn's ``n_init``;
            None = the procedure's: paper 1, refine-classical 3).
        bounds_upper_percentile: the top bound ``b_K`` is ``bounds_upper_factor`` times this percentile of
            the non-air values (None = the procedure's: paper 99.5, SPEC §4; 100 covers the volume's
            whole range).
        bounds_upper_factor: see ``bounds_upper_percentile`` (None = the procedure's: paper 1.15).
        bounds_cover_percentile: the top bound is at least this percentile of the non-air values, so
            the last material holds the densest tissue a scan shows (a real scan's bone and contrast);
            0 = no floor (None = the procedure's: paper 0, refine-classical 99.99).
        reuse_prior: reuse a NeAS-1M prior already trained for the same scene, views,
            preset, seed and prior settings (``DIR/<scene>/neas-1m-prior/<key>/``).
        reconstruction: settings of the classical start's reconstruction.
    """

    _target = "kneas_method.engine.neural_pipeline:NeuralPipeline"
    procedure: Optional[str] = None
    skip_stages: tuple[str, ...] = ()
    add_stages: tuple[str, ...] = ()
    stages: StagesConfig = field(default_factory=StagesConfig)
    num_materials: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    bounds: Optional[str] = None
    bounds_source: BoundsSource = "auto"
    bounds_method: BoundsMethod = "gmm"
    bounds_max_materials: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    bounds_k_rule: Optional[BoundsKRule] = None
    bounds_at_noise_k_rule: Optional[BoundsKRule] = None
    bounds_min_std: Optional[float] = None
    bounds_gmm_restarts: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    bounds_upper_percentile: Optional[float] = field(default=None, metadata=at_least(0, strict=True, at_most=100))
    bounds_upper_factor: Optional[float] = field(default=None, metadata=at_least(0, strict=True))
    bounds_cover_percentile: Optional[float] = field(default=None, metadata=at_least(0, at_most=100))
    reuse_prior: bool = True
    reconstruction: ReconstructionOptions = field(default_factory=ReconstructionOptions)
    model: ModelConfig = field(default_factory=ModelConfig)
    datamanager: CTDataManagerConfig = field(default_factory=CTDataManagerConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)

    def check(self, prefix: str) -> None:
        check_ranges(self, prefix)
        v = self.bounds_min_std
        if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < 1):
            raise ConfigError(f"--bounds-min-std must be a fraction in [0, 1) of the 99.5th-percentile attenuation, got {v!r}")
        if self.bounds_k_rule == "peaks" and self.bounds_method != "gmm" and self.num_materials is None:
            raise ConfigError(f"--bounds-k-rule peaks places its own boundaries (the histogram's valleys), so --bounds-method "
                              f"{self.bounds_method} would not be used; drop --bounds-method or use another --bounds-k-rule")


def _config(method: str, *, K: int, attenuation: str = "shared", selector: str = "soft", floater: bool = False,
            bounds_source: str = "auto", field_name: str = "sdf") -> TrainConfig:
    return TrainConfig(
        method=method,
        bounds_source=bounds_source,
        model=ModelConfig(field=field_name, attenuation=attenuation, selector=selector, num_materials=K, floater=floater,
                          # The hard selector gives d_2 no gradient where d_2 >= 0, so the inner
                          # surface must start crossing the volume (no "start empty" bias).
                          field_options={"distance_bias": 0.0} if selector == "hard" else {}),
    )


neas_1m = MethodSpecification(
    config=_config("neas-1m", K=1, attenuation="single", bounds_source="wide"),
    description="NeAS, one material (single attenuation MLP, wide NeAS bounds); also the prior for automatic bounds",
)
neas_2m = MethodSpecification(
    config=_config("neas-2m", K=2, attenuation="independent", selector="hard"),
    description="NeAS, two materials: independent attenuation MLPs and the hard selector (K = 2 only)",
)
kselector = MethodSpecification(
    config=_config("kselector", K=3, attenuation="independent"),
    description="ablation: independent attenuation MLPs + soft K-material selector, no floater loss",
)
kselector_floater = MethodSpecification(
    config=_config("kselector-floater", K=3, attenuation="independent", floater=True),
    description="ablation: independent attenuation MLPs + soft K-material selector + floater loss",
)
kselector_shared = MethodSpecification(
    config=_config("kselector-shared", K=3, attenuation="shared"),
    description="ablation: shared attenuation body with K heads + soft selector, no floater loss",
)
k_neas = MethodSpecification(
    config=_config("k-neas", K=3, attenuation="shared", floater=True),
    description="K-NeAS: shared attenuation body with K heads, soft K-material selector, floater loss (K default 3)",
)
naf = MethodSpecification(
    config=dataclasses.replace(
        _config("naf", K=1, field_name="naf", bounds_source="none"),
        model=ModelConfig(field="naf", num_materials=1, floater=False, lambda_eikonal=0.0),
    ),
    description="NAF baseline: hash grid + MLP attenuation field, no surfaces",
)
fdk = MethodSpecification(
    config=ClassicalConfig(method="fdk", algorithm="fdk"),
    description="FDK baseline: filtered back-projection of the training views (no training, 0 parameters)",
)
sart = MethodSpecification(
    config=ClassicalConfig(method="sart", algorithm="sart"),
    description="SART: one update per view, 5 iterations, relaxation 0.5, positivity (no training, 0 parameters)",
)
os_sart = MethodSpecification(
    config=ClassicalConfig(method="os-sart", algorithm="os-sart"),
    description="OS-SART: SART updates on 10 view subsets, 10 iterations (no training, 0 parameters)",
)
cgls = MethodSpecification(
    config=ClassicalConfig(method="cgls", algorithm="cgls"),
    description="CGLS: conjugate gradients on the normal equations, stopped early (no training, 0 parameters)",
)
asd_pocs = MethodSpecification(
    config=ClassicalConfig(method="asd-pocs", algorithm="asd-pocs"),
    description="ASD-POCS: SART sweeps alternated with total-variation descent (Sidky & Pan 2008; no training, 0 parameters)",
)
