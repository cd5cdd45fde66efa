"""The run configuration trees and the method table of SPEC §6.

Two kinds of run, each a config tree of its own and a pipeline of its own
(nerfstudio's pipeline config per kind of method):

* :class:`TrainConfig` (neural methods: model, datamanager, trainer, bounds) ->
  :class:`~kneas_method.engine.neural_pipeline.NeuralPipeline`;
* :class:`ClassicalConfig` (FDK and the iterative methods of SPEC §7, 0 parameters) ->
  :class:`~kneas_method.engine.classical_pipeline.ClassicalPipeline`.

Both share :class:`RunConfig` (scene, views, preset, seed, device, folders) and
round-trip through JSON (``config.to_dict`` -> JSON -> ``config.update_from_dict``).
Settings left at ``None`` are decided by the preset (``presets.resolve``);
anything set explicitly (command line, JSON) wins over the preset.

Each method is a :class:`~kneas_method.registry.MethodSpecification` registered
under ``kneas.methods`` in ``pyproject.toml``; the neural ones differ only in
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

K of the K-material methods (kselector*, k-neas) is picked by the preset's K rule
when ``num_materials`` is None (the default) and the bounds are automatic (paper
and tiny: the BIC of the GMM fit, SPEC §4; cpu: the peaks of the bounds volume's
histogram, ``bic-valleys`` where it has fewer than two); ``--num-materials K`` fixes it; a ``--bounds`` file gives it. The
method's ``model.num_materials`` (3) is only the default shown by a dry run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal, Optional

from .classical.options import Algorithm, ReconstructionOptions
from .config import InstantiateConfig
from .datamanagers.ct import CTDataManagerConfig
from .model import ModelConfig
from .registry import MethodSpecification

Preset = Literal["auto", "paper", "cpu", "tiny"]
BoundsSource = Literal["wide", "auto", "none"]
BoundsMethod = Literal["gmm", "quantile", "bayes"]
BoundsKRule = Literal["bic", "bic-valleys", "peaks"]
BoundsVolume = Literal["prior", "fdk", "sart", "os-sart", "cgls", "asd-pocs"]
WarmStart = Literal["none", "fdk", "sart", "os-sart", "cgls", "asd-pocs"]
EvalProjections = Literal["rendered", "volume"]
AnchorRegion = Literal["box", "hull"]
OutsideRule = Literal["labels", "skip"]
Denoise = Literal["sure", "sure-gaussian", "none"]
CorrectionWeights = Literal["gradient", "ring"]
PRESETS: tuple[str, ...] = Preset.__args__


@dataclass
class TrainerConfig:
    """Optimisation and bookkeeping. ``None`` = the preset's value.

    Attributes:
        epochs: training epochs (one step per training projection per epoch; paper 1000).
        prior_epochs: epochs of the single-material prior model trained for the
            automatic bounds (SPEC §4); paper 1000.
        lr: Adam learning rate (paper 1e-3; None = the preset's).
        lr_decay_at: fraction of epochs after which the rate is multiplied by
            ``lr_decay_factor`` (paper 0.5 -> after 500 of 1000 epochs; factor 0.1; None = the preset's).
        eval_every: epochs between held-out evaluations during training (0 = only at the end).
        checkpoint_every: epochs between checkpoints (0 = only at the end).
        eval_chunk: rays per chunk when rendering full views for evaluation.
        eval_views: held-out views scored at intermediate evaluations (None = all).
        eval_projections: how the final evaluation, and the intermediate ones, make the
            held-out projections of their 2D metrics: ``rendered`` through the field (``model.num_eval_samples`` per ray;
            the paper), or ``volume``: the field sampled at the voxel centres (the volume the
            3D metrics score) and projected by the Joseph projector, the operator that scores
            the classical methods' volumes too; tens of times fewer field queries, whatever
            the detector size. None = the preset's (paper: rendered; cpu: volume).
        warm_start: ``none`` (the paper: train from the initialisation) or a classical
            method (``fdk``): before projection training, fit the model to the run's
            classical reconstruction at the voxel centres (``Trainer.warm_start``), an
            option beside the paper's procedure (SPEC §4). None = the preset's
            (paper: none; cpu: asd-pocs).
        warm_start_steps: Adam steps of the warm start (None = the preset's).
        warm_start_points: voxel centres per warm-start step.
        warm_start_occupancy: weight of the warm start's per-material occupancy
            cross-entropy (``CTModel.volume_loss_dict``; 0 = MSE only).
        warm_start_anchor: weight of the warm-start volume kept as a prior during projection
            training: ``anchor_points`` random voxel centres per step add this weight x the MSE
            between ``mu`` and that volume (``Trainer.anchor_loss``). Sparse views leave much of
            the volume unconstrained, and there the (TV-regularised) classical volume holds the
            field instead of the step noise; the projections still decide where they disagree.
            0 = off; None = the preset's (paper 0; cpu 0.01). Needs ``warm_start``.
        anchor_points: voxel centres per step of that prior.
        anchor_region: where those centres are drawn: ``box``, every voxel of the volume box;
            ``hull``, only the voxels the model's occupancy grid keeps (the visual hull), with the
            weight times their share of the box, so that the loss is the box's in expectation
            (outside the grid ``mu`` is 0 whatever the field, and a draw there moves nothing
            the volume shows) and every draw lands where the field can hold material. Without
            an occupancy grid both are the box.
        anchor_outside: what the ``box`` anchor does with its draws outside the model's occupancy
            grid, where ``mu`` is 0 whatever the field (so their value term has no gradient):
            ``labels`` queries the field there for their label term (keeping every distance
            positive where the volume is empty anyway, the earlier default);
            ``skip`` (default) leaves them out and queries the field only at the draws inside the
            grid: its value term and its gradient are the same, and the anchor's cost falls by the
            share of the box outside the grid (training 16 % shorter on jaw, about a quarter on
            abdomen; the four built-in scenes within −0.06 to +0.05 dB; docs/experiments.md).
        fit_outside: the same rule for the other fits to a volume, the warm start and the
            correction passes' fits (``Trainer._fit_steps``): ``skip`` (default) queries the
            field only at their draws inside the occupancy grid, with every mean over all the
            draws, so the value term's gradient is unchanged and the draws outside add no label,
            eikonal or curvature term; ``labels`` queries every draw (the earlier default).
        anchor_occupancy: weight, inside the anchor, of the warm start's per-material occupancy
            cross-entropy (``CTModel.occupancy_loss``): the prior keeps the labels the volume's
            values give under the bounds, not only its values. Where two materials' ranges meet
            near a level (a ventricle at 0.154 beside a boundary at 0.163), the projections
            cannot tell which material holds it and the MSE alone lets the neighbour take it.
            Only the labels two voxels or more from any other label count
            (``engine.anchor.label_interior``): at the volume's blurred edges its labels are
            wrong, and there the projections decide. 0 = the MSE alone; None = the preset's
            (paper 0; cpu 0.03).
        anchor_edge_contrast: each voxel of that prior counts ``1 / (1 + (g / g0)^2)`` in its MSE,
            ``g`` the volume's gradient per voxel and ``g0`` this fraction of its 99.5th percentile
            (``engine.anchor.edge_trust``): a classical volume's error grows with its gradient, so
            its sharp edges are held less and the projections place them; faint edges keep most
            of their weight. 0 = every voxel alike; None = the preset's (0 in every preset: measured
            in docs/experiments.md, not a gain on every scene).
        correction_passes: after training, this many passes of the band correction
            (``kneas_method.correction``, ``engine.correction_stage``): each solves for what the
            training views still say about the model's volume, in a band around its edges, against
            the scene grid's projector with that grid's discretisation error taken out (estimated
            from the model's own sharper field on a finer grid), then fits the model to the
            corrected volume in that band (``correction_steps`` Adam steps at ``correction_lr``),
            so the field, its surfaces included, carries the correction. Surface models only; a pass
            that finds nothing above the noise ends them. 0 = off; None = the preset's (paper and
            tiny 0; cpu 12).
        correction_iterations: CGLS iterations per pass at most (4: with the ring at half weight, 4
            instead of 3 gained abdomen +0.14 dB, docs/experiments.md).
        correction_weights: the column weights of each pass's CGLS in the band (``x = M z``: a
            voxel of weight ``w`` moves as if its unknown were ``w`` times less free). ``ring`` (the
            default): 1 at the steep voxels and ``correction_ring`` on the rest of the band;
            ``gradient``: the square root of the volume's gradient magnitude over its median on the
            band's steep voxels, at most 2 (at most 4 times that median), so the correction goes
            where the edges are steepest. Measured against ``ring`` (docs/experiments.md):
            abdomen +0.30 dB, jaw -0.16, but abdomen's bones' surfaces worse (cortical Dice
            0.925 -> 0.911, below the best thresholded classical volume's 0.916), so not the default.
        correction_ring: with ``correction_weights ring`` (None = 0.5; refused with
            ``gradient``), the weight of the band's voxels that are
            not steep themselves (its outer ring, one voxel wide): 1 solves in the whole band alike,
            0 at the steep voxels only (about half the unknowns); between, the ring's share of the
            correction is damped (column scaling). The discretisation estimate and the fit use the
            whole band whatever it is, so the fit holds the ring near the model's volume. Measured
            in docs/experiments.md, against 1: 0.5 chest +0.26, abdomen +0.17, foot +0.03,
            jaw 0.00 dB; 0 chest +0.42, abdomen +0.17, foot -0.03, jaw -0.05.
        correction_refresh: the discretisation error is computed afresh every this many passes
            and reused in between (1 = every pass): it moves little from one pass to the next, and
            computing it (the model queried on a finer grid) is the dearest part of a pass (3: the
            cpu preset's 12 passes cost what 10 did with 2, measured in docs/experiments.md).
        correction_noise_factor: a pass's iterations stop once the residual's mean square is within
            this factor of the data's noise variance (estimated from the residual; the discrepancy
            principle), so a noisy scan is not fitted to its noise (1.5: on the noisy held-out scans
            the residual is within 1.01 of its noise estimate before the first pass).
        correction_steps: Adam steps of each pass's fit of the model to the corrected volume.
        correction_lr: learning rate of each pass's fit.
        correction_points: band voxel centres per step of each pass's fit (and a quarter as many
            anywhere); the smoothing's fit uses as many.
        correction_curvature: weight of a surface-smoothness term in each pass's fit
            (``losses.curvature``: the distances' gradients one voxel apart should agree near a
            surface), so that what the views leave free of an edge is filled with a smooth surface
            rather than the correction's ripples. 0 = the fit's MSE and eikonal term alone.
        denoise: after the passes, ``sure`` smooths the model's volume with the filter that
            minimises Stein's unbiased estimate of its squared error (SURE) under the volume's own
            noise, its autocovariance between neighbouring voxels estimated from the volume
            (``kneas_method.denoise``): none, a Gaussian, or an edge-preserving bilateral filter
            (its SURE by Monte Carlo), the noise estimate raised while the choice's projections
            still fit the training views closer than their noise (the discrepancy principle);
            then fits the model to it (``denoise_steps`` at
            ``denoise_lr``, a pass's points and curvature term, in the voxels the model fills).
            Where no filter lowers the estimate (a clean scan) the volume is left as it is.
            ``sure-gaussian``: the Gaussians alone (the earlier rule). ``none``: no
            smoothing. Runs with the correction stage (``correction_passes`` > 0). None = the
            preset's (cpu ``sure``; paper and tiny ``none``). Measured (docs/experiments.md): the
            noisy held-out jaw 32.56 -> 34.77 dB with the Gaussian (0.8
            voxel), 36.43 dB with the bilateral (3 voxels); every clean scene unchanged (none chosen).
        denoise_steps: Adam steps of the fit of the model to the smoothed volume (more than a
            pass's: the whole filled volume moves, not a band).
        denoise_lr: learning rate of that fit.
        time_budget: seconds the whole run should take at most, from the command's start (the
            scene, the classical start, training, the passes, the smoothing, the evaluation;
            ``engine.budget``). Training gives way first: after 100 steps, where the rest of them
            and the band-correction passes (taken as 0.9 x the whole training's time) would not end
            30 s before the budget runs out, training is cut to the whole epochs that do (a quarter
            of them at least; ``config.json`` and ``metrics.json``'s ``training_budget`` say so).
            Then the passes: one that is not expected to end 30 s before it (its cost: the longest
            earlier pass of its kind, with or without a fresh discretisation estimate) is not
            started (``correction_budget``). The classical start and the evaluation never give way.
            The budget is for a grid of 128³ voxels or fewer; a larger grid gets it in proportion to
            its voxels. 0 = no budget; None = the preset's (cpu 600: goal 3's 10 minutes on a 2-core
            CPU; paper and tiny 0). A budget that binds makes the result depend on the machine's
            speed, and the run says so; give 0 for the same run everywhere.
        materials_refit_steps: where the bounds came from the peaks rule's fallback (the start's
            histogram had fewer than two peaks: a noisy scan), after the smoothing the same
            mixtures are fitted again to the trained volume after the same bilateral filter
            (``engine.materials_stage``); if they find more materials than the start did, the
            model is replaced by a fresh one with those bounds, fitted to the trained volume as the
            warm start fits, for this many steps. The start's noise hides materials that the
            trained, smoothed volume shows (the noisy foot's marrow, the noisy abdomen's bones).
            0 = off. Measured in docs/experiments.md.
        log_every: steps between loss-history / learning-rate records.
        max_bad_steps: this many non-finite losses in a row end the run (the last
            good checkpoint is kept).
    """

    epochs: Optional[int] = None
    prior_epochs: Optional[int] = None
    lr: Optional[float] = None
    lr_decay_at: Optional[float] = None
    lr_decay_factor: float = 0.1
    eval_every: Optional[int] = None
    checkpoint_every: Optional[int] = None
    eval_chunk: Optional[int] = None
    eval_views: Optional[int] = None
    eval_projections: Optional[EvalProjections] = None
    warm_start: Optional[WarmStart] = None
    warm_start_steps: Optional[int] = None
    warm_start_points: int = 16384
    warm_start_occupancy: float = 0.01
    warm_start_anchor: Optional[float] = None
    anchor_points: int = 4096
    anchor_region: AnchorRegion = "box"
    anchor_outside: OutsideRule = "skip"
    fit_outside: OutsideRule = "skip"
    anchor_occupancy: Optional[float] = None
    anchor_edge_contrast: Optional[float] = None
    correction_passes: Optional[int] = None
    correction_iterations: int = 4
    correction_weights: CorrectionWeights = "ring"
    correction_ring: Optional[float] = None
    correction_refresh: int = 3
    correction_noise_factor: float = 1.5
    correction_steps: int = 75
    correction_lr: float = 1e-4
    correction_points: int = 8192
    correction_curvature: float = 3e-3
    denoise: Optional[Denoise] = None
    denoise_steps: int = 300
    denoise_lr: float = 1e-3
    materials_refit_steps: int = 1500
    time_budget: Optional[float] = None
    log_every: int = 50
    max_bad_steps: int = 5


@dataclass
class RunConfig(InstantiateConfig):
    """What every run has, whatever its kind. ``setup(scene=, run_dir=, device=)`` builds the
    kind's pipeline (``_target``).

    Attributes:
        method: the registered method name this config came from.
        scene: built-in scene name or a path to a NAF pickle.
        views: keep this many training views, spread uniformly (None = all).
        preset: ``auto`` (paper with CUDA, else cpu); ``paper``: the paper's procedure (about 30 min
            on one H200); ``cpu``: ASD-POCS start, band correction (6-9 min on 2 cores, about 1 min on
            a GPU); ``tiny``: smoke runs. README "Presets" says what each does.
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
    views: Optional[int] = None
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
    """

    _target = "kneas_method.engine.classical_pipeline:ClassicalPipeline"
    method: str = "fdk"
    algorithm: Algorithm = "fdk"
    reconstruction: ReconstructionOptions = field(default_factory=ReconstructionOptions)


@dataclass
class TrainConfig(RunConfig):
    """A neural training run.

    Attributes:
        num_materials: K; overrides the method's default (None = method default).
        bounds: JSON file with ``{"alphas": [...], "betas": [...]}`` (data units, 1/m).
        bounds_source: where bounds come from when neither ``bounds`` nor
            ``model.alphas/betas`` are given: ``wide`` (NeAS defaults), ``auto``
            (GMM of SPEC §4) or ``none`` (no SDF).
        bounds_method: GMM boundary rule for automatic bounds: ``gmm`` (paper, SPEC §4),
            ``quantile`` or ``bayes`` (options beside the paper's; see ``bounds.GMMBounds``).
        bounds_max_materials: automatic bounds try K = 1..this (paper 4; None = the preset's:
            paper and tiny 4, cpu 8).
        bounds_k_rule: how automatic bounds pick K: ``bic`` (paper: the lowest BIC),
            ``bic-valleys`` (the lowest BIC among K whose boundaries are all valleys of the
            mixture density) or ``peaks`` (one material per peak of the volume's histogram,
            boundaries at its valleys, no mixture and no seed, material 1's labels from half
            its peak (``model.first_label_threshold``); bic-valleys where the histogram has
            fewer than two peaks); None = the preset's: cpu peaks (bic-valleys with a
            ``bounds_method`` other than ``gmm``), else bic.
        bounds_min_std: the GMM components' smallest standard deviation, as a fraction of
            the 99.5th-percentile attenuation (0 = sklearn's default regulariser; None = the
            preset's: 0 in every preset). Keeps a TV-flattened material from taking a spike component.
        bounds_gmm_restarts: k-means starts per GMM fit, the best kept (scikit-learn's ``n_init``;
            paper and tiny 1, cpu 3; None = the preset's). One start can end in a poor local
            optimum whose BIC then misjudges K.
        bounds_volume: the volume the automatic bounds are computed from: ``prior``
            (the paper: a trained NeAS-1M model, SPEC §4) or a classical reconstruction
            of the training views (``fdk``, ``sart``, ``asd-pocs``, ...: no prior training;
            an option beside the paper's procedure). None = the preset's (paper: prior; cpu: asd-pocs).
        reuse_prior: reuse a NeAS-1M prior already trained for the same scene, views,
            preset, seed and prior settings (``DIR/<scene>/neas-1m-prior/<key>/``).
        reconstruction: settings of the classical reconstruction used for the bounds
            or the warm start.
    """

    _target = "kneas_method.engine.neural_pipeline:NeuralPipeline"
    num_materials: Optional[int] = None
    bounds: Optional[str] = None
    bounds_source: BoundsSource = "auto"
    bounds_method: BoundsMethod = "gmm"
    bounds_max_materials: Optional[int] = None
    bounds_k_rule: Optional[BoundsKRule] = None
    bounds_min_std: Optional[float] = None
    bounds_gmm_restarts: Optional[int] = None
    bounds_volume: Optional[BoundsVolume] = None
    reuse_prior: bool = True
    reconstruction: ReconstructionOptions = field(default_factory=ReconstructionOptions)
    model: ModelConfig = field(default_factory=ModelConfig)
    datamanager: CTDataManagerConfig = field(default_factory=CTDataManagerConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)


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
