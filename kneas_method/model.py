"""CTModel: field + selector + Beer–Lambert renderer + losses, assembled from registered parts.

Units: points and ray parameters are in **model units** (the scene scaled into
the unit sphere); attenuation is in **data units** (1/m, what the NAF volume
stores; the bounds ``alpha``/``beta`` are in data units too). The renderer
converts segment lengths to metres with ``scale`` (model units per metre,
``geometry.scale``), so a rendered line integral equals the projection ``p``.

Components are chosen by registered name (``kneas.encodings``, ``kneas.fields``,
``kneas.attenuations``, ``kneas.selectors``,
``kneas.samplers``, ``kneas.losses``) and built through
:func:`kneas_method.registry.load`, so a plugin's name works unchanged in a JSON
config or on the command line. ``*_options`` dicts override the defaults of the
named component's config (by field name).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from torch import nn

from . import registry
from .config import InstantiateConfig, at_least, update_from_dict
from .errors import ConfigError
from .losses.curvature import surface_smoothness
from .renderer import RenderOutput, beer_lambert, integrate_samples, sample_points, segment_lengths, voxel_plane_samples

Options = dict[str, Union[int, float, str, bool]]
Quadrature = Literal["bins", "voxel-planes"]
PAPER_LAMBDA_EIKONAL = 0.01  # λ_reg of SPEC §3, used when the config leaves it unset


def build_component(group: str, name: str, options: Optional[dict] = None, where: Optional[str] = None) -> InstantiateConfig:
    """Config of the component registered as ``name`` in ``kneas.<group>``, with ``options`` applied.

    ``where`` names the setting the options came from (``model.encoding_options``) in errors."""
    obj = registry.load(group, name)
    cfg = obj() if isinstance(obj, type) else dataclasses.replace(obj)
    if not isinstance(cfg, InstantiateConfig):
        raise ConfigError(f"the {group} entry point {name!r} is not a component config (an InstantiateConfig subclass)")
    label = where or f"{group}:{name}"
    if options is not None:
        options = check_options(options, label)
    if options:
        cfg = update_from_dict(cfg, _parse_option_strings(cfg, options), where=label)
    return cfg


def check_options(options: Any, where: str) -> dict:
    """``options`` as a dict of setting name -> value, or a one-line ConfigError naming ``where`` and the fix.

    A config file can hold anything at that place (a list, a string, an empty name), and the
    command line gives what it was typed as; both are refused here before any dict() or lookup."""
    example = 'a JSON object such as {"num_levels": 8} in a config file, or NAME VALUE pairs on the command line'
    if not isinstance(options, dict):
        raise ConfigError(f"{where} must be settings by name ({example}), got {options!r}")
    for key, value in options.items():
        if not isinstance(key, str) or not key.strip():
            raise ConfigError(f"{where} has a setting with an empty name ({key!r}); give each setting its name ({example})")
        if isinstance(value, (list, tuple, dict)):
            raise ConfigError(f"{where}.{key} = {value!r}: a setting's value is one number, string or true/false ({example})")
    return dict(options)


def _parse_option_strings(cfg, options: dict) -> dict:
    """Command-line option values arrive as strings when the type is unknown; read numbers/bools via JSON."""
    import json
    import typing

    hints = typing.get_type_hints(type(cfg))
    out = {}
    for k, v in options.items():
        if isinstance(v, str) and hints.get(k) is not str:
            try:
                v = json.loads(v)
            except ValueError:
                pass
        if isinstance(v, int) and not isinstance(v, bool) and hints.get(k) in (float, Optional[float]):
            v = float(v)
        out[k] = v
    return out


@dataclass
class ModelConfig(InstantiateConfig):
    """The model's full configuration. ``None`` = decided by the preset (``presets.resolve``).

    Attributes:
        field: ``kneas.fields`` name of the main field: ``sdf`` (SDF + attenuation
            + selector) or ``naf`` (attenuation directly, no surfaces).
        encoding: ``kneas.encodings`` name of the encoding: ``hashgrid`` or ``frequency``.
        encoding_options: settings of the encoding config (e.g. ``num_levels``,
            ``log2_hashmap_size``); None = the preset's.
        attenuation: attenuation network: ``single``, ``shared``, ``independent``
            or any name registered under ``kneas.attenuations``.
        selector: ``kneas.selectors`` name: ``soft`` or ``hard``.
        num_materials: K (signed distance fields / attenuation heads).
        s_init: initial sharpness of ``Omega(d, s) = sigmoid(-s d)`` (1/model unit);
            None = the preset's (paper: 20).
        alphas: per material, the width of its attenuation range, data units (1/m); None =
            placeholders (NeAS wide bounds for K = 1) until ``set_bounds``.
        betas: per material, the lower end of its attenuation range, data units (1/m); None =
            placeholders, as for ``alphas``.
        ray_sampler: ``kneas.samplers`` name of the ray sampler.
        num_samples: points per ray in training (stratified, jittered) with the ``bins``
            quadrature; paper 320; None = the preset's.
        num_eval_samples: points per ray in evaluation (even) with the ``bins`` quadrature;
            paper 128; None = the preset's.
        floater: use the floater loss on air rays.
        floater_fraction: fraction of epochs with the floater loss on (0.2).
        lambda_floater: weight of the floater loss, ``λ_aux`` (0.1).
        lambda_eikonal: weight of the eikonal term, ``λ_reg`` (paper 0.01; None = the preset's:
            the cpu preset's short schedule uses a much smaller one).
        eikonal_mode: ``autograd`` (exact) or ``finite-difference``; None =
            autograd, or finite-difference with the tinycudann hash grid.
        eikonal_fraction: fraction of the training sample points the eikonal term
            is evaluated on (1.0 = all, reusing the render's SDF outputs).
        eikonal_fd_step: finite-difference step (model units); None = half the
            finest hash-grid cell.
        occupancy_grid: skip empty space (``kneas_method.occupancy``): a conservative
            visual hull carved from the training views (``set_occupancy``) puts every
            ray's samples on the stretch of the ray that can hold material, and ``mu``
            is zero outside it, in training, evaluation and export alike. None = the
            preset's (cpu: on, +3.9 dB on foot; paper and tiny: off).
        occupancy_resolution: cells of that grid per axis over the volume box.
        quadrature: how a ray's line integral is summed. ``bins`` (the paper's): ``num_samples``
            points in equal bins between near and far (jittered in training, even in
            evaluation). ``voxel-planes``: one point where the ray crosses each voxel-centre
            plane of its dominant axis (Joseph's rule, ``renderer.voxel_plane_samples``), on the
            scene's voxel grid (``set_voxel_grid``); ``num_samples`` is then unused. None = the
            preset's.
        first_label_threshold: the attenuation (data units) above which a volume's voxel counts
            as inside material 1 for the occupancy labels (warm start and anchor,
            :meth:`CTModel.label_thresholds`); None = ``alpha_1 / 2``. The ``peaks`` K rule sets it
            to half the first material's peak: its material 1 reaches up to the valley before the
            next material, so ``alpha_1 / 2`` can lie above material 1's own level.
        compile: ``torch.compile`` the fused SDF pass (values + distance gradients).
            Opt-in: measured on 2 CPU cores (cpu preset, torch 2.13)
            a training step with its anchor ran 15-18 % faster, but each new
            batch size costs a compile of 25-30 s with an empty inductor cache (3 s with a
            warm one) and a run meets at least three (warm start, training, the passes'
            fits), so a whole run on a fresh machine is slower than without it.
    """

    _target = "kneas_method.model:CTModel"
    field: str = "sdf"
    field_options: Options = dataclasses.field(default_factory=dict)
    encoding: str = "hashgrid"
    encoding_options: Optional[Options] = None
    attenuation: str = "shared"
    attenuation_options: Options = dataclasses.field(default_factory=dict)
    selector: str = "soft"
    selector_options: Options = dataclasses.field(default_factory=dict)
    num_materials: int = 3
    s_init: Optional[float] = dataclasses.field(default=None, metadata=at_least(0, strict=True))
    alphas: Optional[tuple[float, ...]] = None
    betas: Optional[tuple[float, ...]] = None
    ray_sampler: str = "stratified"
    num_samples: Optional[int] = dataclasses.field(default=None, metadata=at_least(1, whole=True))
    num_eval_samples: Optional[int] = dataclasses.field(default=None, metadata=at_least(1, whole=True))
    intensity_loss: str = "intensity"
    floater: bool = False
    floater_loss: str = "floater"
    floater_fraction: float = dataclasses.field(default=0.2, metadata=at_least(0))
    lambda_floater: float = dataclasses.field(default=0.1, metadata=at_least(0))
    eikonal_loss: str = "eikonal"
    eikonal_mode: Optional[str] = None
    eikonal_fraction: Optional[float] = dataclasses.field(default=None, metadata=at_least(0, strict=True))
    eikonal_fd_step: Optional[float] = dataclasses.field(default=None, metadata=at_least(0, strict=True))
    lambda_eikonal: Optional[float] = dataclasses.field(default=None, metadata=at_least(0))
    occupancy_grid: Optional[bool] = None
    occupancy_resolution: int = dataclasses.field(default=64, metadata=at_least(1, whole=True))
    quadrature: Optional[Quadrature] = None
    first_label_threshold: Optional[float] = None
    compile: bool = False


def _half_finest_cell(encoding_cfg, bound: float) -> float:
    """Half the finest grid cell in model units (1e-3 when the encoding has no grid)."""
    try:
        res = encoding_cfg.base_resolution * encoding_cfg.per_level_scale ** (encoding_cfg.num_levels - 1)
        return bound * 2.0 / math.ceil(res) / 2.0
    except AttributeError:
        return 1e-3


def field_has_surfaces(config: ModelConfig) -> bool:
    """True when the model's field (by its registered config) gives signed distances:
    materials, bounds and meshes apply. Decided from the registered class, never the name."""
    from .fields.base import FieldConfig

    cfg = build_component("fields", config.field, config.field_options, where="model.field_options")
    return bool(isinstance(cfg, FieldConfig) and cfg.has_surfaces)


class CTModel(nn.Module):
    """Field + selector + Beer–Lambert renderer.

    Args:
        config: :class:`ModelConfig`.
        scale: model units per metre (``geometry.scale``); 1.0 for dry runs.
        device: the device the model will run on (lets ``hashgrid`` pick tinycudann
            on CUDA); the caller still moves the model with ``.to(device)``.
    """

    def __init__(self, config: ModelConfig, scale: float = 1.0, device=None):
        super().__init__()
        from .fields.base import Field

        self.config = config
        self.scale = float(scale)
        # the attenuation unit the losses are measured in (data units per unit; engine.loss_scale): 1 for
        # NAF-normalised scans, larger for a scanner's units, so every loss weighs as on NAF's scale
        self.loss_scale = 1.0
        enc_cfg = build_component("encodings", config.encoding, config.encoding_options, where="model.encoding_options")
        encoding = enc_cfg.setup(device=device) if device is not None else enc_cfg.setup()
        field_cfg = build_component("fields", config.field, config.field_options, where="model.field_options")
        if not isinstance(config.num_materials, int) or isinstance(config.num_materials, bool):
            raise ConfigError(f"model.num_materials is {config.num_materials!r}; give a whole number of materials (--num-materials K)")
        K = config.num_materials
        self.field = field_cfg.setup(encoding=encoding, num_materials=K)
        if not isinstance(self.field, Field):
            raise ConfigError(f"the field {config.field!r} builds a {type(self.field).__name__}, not a kneas_method.fields.base.Field")
        self.has_surfaces = self.field.has_surfaces
        self.bound = self.field.bound
        if self.has_surfaces:
            att_cfg = build_component("attenuations", config.attenuation, config.attenuation_options, where="model.attenuation_options")
            self.attenuation = att_cfg.setup(feature_dim=self.field.feature_dim, num_materials=K)
            self.selector = build_component("selectors", config.selector, config.selector_options, where="model.selector_options").setup(num_materials=K)
            from .fields.sdf_field import SurfaceBoundary

            self.boundary = SurfaceBoundary(config.s_init if config.s_init is not None else 20.0)
            self.num_materials = K
            if config.alphas is not None or config.betas is not None:
                if config.alphas is None or config.betas is None:
                    raise ConfigError("give both model.alphas and model.betas (data units, one per material), or neither")
                self.set_bounds(config.alphas, config.betas)
        else:
            self.attenuation = self.selector = self.boundary = None
            self.num_materials = 0
            # a field without bounds gives mu in units of this (data units; the Trainer sets it to the
            # scan's loss_scale, so the network's outputs are NAF-scale on any scan); kept in checkpoints
            self.register_buffer("attenuation_unit", torch.ones((), dtype=torch.float32))
        self.ray_sampler = build_component("samplers", config.ray_sampler).setup()
        self.intensity_loss = build_component("losses", config.intensity_loss).setup()
        self.floater_loss = build_component("losses", config.floater_loss, {"fraction": config.floater_fraction}).setup()
        self.eikonal = None
        self.lambda_eikonal = PAPER_LAMBDA_EIKONAL if config.lambda_eikonal is None else float(config.lambda_eikonal)
        if self.has_surfaces and self.lambda_eikonal > 0:
            tcnn = getattr(encoding, "implementation", "torch") == "tcnn"
            mode = config.eikonal_mode or ("finite-difference" if tcnn else "autograd")
            if tcnn and mode == "autograd":
                raise ConfigError("the tinycudann hash grid has no second derivative, so the autograd eikonal cannot train it; "
                                  "use model.eikonal_mode finite-difference or the torch hash grid (encoding_options implementation torch)")
            ek_cfg = build_component("losses", config.eikonal_loss, {"mode": mode, "fd_step": config.eikonal_fd_step})
            self.eikonal = ek_cfg.setup(default_step=_half_finest_cell(enc_cfg, self.bound))
        if config.occupancy_grid:
            G = int(config.occupancy_resolution)
            if G < 2:
                raise ConfigError(f"model.occupancy_resolution must be at least 2 cells, got {G}")
            self.register_buffer("occupancy", torch.ones(G, G, G, dtype=torch.bool))
            self.register_buffer("occupancy_box", torch.tensor([[-self.bound] * 3, [self.bound] * 3], dtype=torch.float32))
        else:
            self.occupancy = None
        self.quadrature = config.quadrature or "bins"
        if self.quadrature == "voxel-planes":
            self.register_buffer("voxel_box", torch.tensor([[-self.bound] * 3, [self.bound] * 3], dtype=torch.float32))
            self.register_buffer("voxel_count", torch.zeros(3, dtype=torch.long))
        elif self.quadrature != "bins":
            raise ConfigError(f"model.quadrature is {config.quadrature!r}; choose bins or voxel-planes")
        self._with_gradients = self._field_with_gradients
        if config.compile and self.field.supports_gradients:
            self._with_gradients = torch.compile(self._field_with_gradients)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints from before the attenuation unit (2026-11-28, a74f8b3) were trained in data units
        if not self.has_surfaces and prefix + "attenuation_unit" not in state_dict:
            state_dict[prefix + "attenuation_unit"] = torch.ones((), dtype=torch.float32)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _field_with_gradients(self, points: torch.Tensor):
        """The field's outputs with the distance gradients of the same pass (forward mode)."""
        return self.field.get_outputs(points, with_gradients=True)

    # ------------------------------------------------------------------ setup
    def set_bounds(self, alphas: Sequence[float], betas: Sequence[float]) -> None:
        """Attenuation bounds per material (data units, length K); saved in the state_dict."""
        if not self.has_surfaces:
            raise ConfigError("this model has no materials (no SDF), so it takes no attenuation bounds")
        self.attenuation.set_bounds(alphas, betas)
        first, top = self.config.first_label_threshold, float(alphas[0]) + float(betas[0])
        if first is not None and not (math.isfinite(first) and 0 < first < top):
            raise ConfigError(f"model.first_label_threshold {first!r} must lie inside material 1's range (0, {top:.4g}); "
                              "give a value between air and the first material's level, or leave it out")

    def set_occupancy(self, occupied: torch.Tensor, lo, hi) -> None:
        """The empty-space grid: ``occupied [G, G, G]`` (bool) over the box ``[lo, hi]`` (model units)."""
        if self.occupancy is None:
            raise ConfigError("this model has no occupancy grid; set model.occupancy_grid true")
        if tuple(occupied.shape) != tuple(self.occupancy.shape):
            raise ConfigError(f"occupancy grid {tuple(occupied.shape)} does not match the model's {tuple(self.occupancy.shape)}")
        self.occupancy.copy_(occupied.to(self.occupancy.device, torch.bool))
        self.occupancy_box.copy_(torch.tensor([list(lo), list(hi)], dtype=torch.float32))

    def set_voxel_grid(self, counts: Sequence[int], lo, hi) -> None:
        """The voxel grid the ``voxel-planes`` quadrature samples on: ``counts`` voxels per axis
        over the box ``[lo, hi]`` (model units); saved in the state_dict."""
        if self.quadrature != "voxel-planes":
            raise ConfigError("this model sums rays in bins; the voxel grid is for model.quadrature voxel-planes")
        self.voxel_count.copy_(torch.tensor([int(c) for c in counts], dtype=torch.long))
        self.voxel_box.copy_(torch.tensor([list(lo), list(hi)], dtype=torch.float32))

    def occupied(self, points: torch.Tensor) -> Optional[torch.Tensor]:
        """``[P]`` 1 where ``points [P, 3]`` may hold material, 0 in empty space; None without a grid."""
        if self.occupancy is None:
            return None
        from .occupancy import occupancy_at

        return occupancy_at(self.occupancy, self.occupancy_box[0], self.occupancy_box[1], points.detach())

    def rays_through_occupied(self, origins: torch.Tensor, directions: torch.Tensor, near, far) -> Optional[torch.Tensor]:
        """``[R]`` bool: the rays ``origins, directions`` [R, 3] that cross a cell of the occupancy grid
        between ``near`` and ``far`` (``occupancy.ray_intervals``); the others render exactly 0. None
        without a grid."""
        if self.occupancy is None:
            return None
        from .occupancy import ray_intervals

        t0, t1 = ray_intervals(self.occupancy, self.occupancy_box[0], self.occupancy_box[1], origins, directions,
                               float(near), float(far))
        return t1 > t0

    @property
    def bounds(self) -> tuple[list[float], list[float]]:
        """Current ``(alphas, betas)`` in data units."""
        return self.attenuation.alphas.tolist(), self.attenuation.betas.tolist()

    def num_parameters(self) -> int:
        """Trainable parameter count."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    # ------------------------------------------------------------------ query
    def query(self, points: torch.Tensor) -> dict[str, torch.Tensor]:
        """Evaluate the field at points [P, 3] (model units).

        Returns ``mu`` [P] (data units); with an SDF also ``weights`` [P, K],
        ``distances`` [P, K] (model units) and ``mu_materials`` [P, K] (raw
        per-material attenuation, data units).
        """
        return self._materials(self.field.get_outputs(points), points)

    def _materials(self, out, points: torch.Tensor) -> dict[str, torch.Tensor]:
        """FieldOutputs at ``points`` -> ``mu`` (and, with surfaces, ``weights``, ``distances``,
        ``mu_materials``, ``grads``). Outside the occupancy grid (when there is one) ``mu`` and the
        weights are 0 and every distance is positive (outside every material; same magnitude)."""
        if out.distances is None:
            occ = self.occupied(points)
            mu = out.mu * self.attenuation_unit
            return {"mu": mu if occ is None else mu * occ}
        q = self.compose(points, out.distances, self.attenuation(out.features))
        if out.distance_gradients is not None:
            q["grads"] = out.distance_gradients
        return q

    def material_fields(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The smooth fields a surface model's attenuation is composed of, at ``points`` [P, 3]:
        ``(distances [P, K], mu_materials [P, K])``, before the selector and the occupancy grid."""
        out = self.field.get_outputs(points)
        return out.distances, self.attenuation(out.features)

    def compose(self, points: torch.Tensor, distances: torch.Tensor, mu_materials: torch.Tensor) -> dict[str, torch.Tensor]:
        """``mu`` [P], ``weights``, ``distances`` and ``mu_materials`` [P, K] at ``points`` [P, 3] from
        per-material distances and attenuations there (``material_fields``, or values interpolated
        from them): the selector at the current sharpness, then the occupancy grid (outside it ``mu``
        and the weights are 0 and every distance positive, same magnitude)."""
        occ = self.occupied(points)
        if occ is not None:
            distances = torch.where(occ[:, None] > 0, distances, distances.abs())
        mu, weights = self.selector(distances, mu_materials, self.boundary)
        if occ is not None:
            mu, weights = mu * occ, weights * occ[:, None]
        return {"mu": mu, "weights": weights, "distances": distances, "mu_materials": mu_materials}

    @property
    def fused_eikonal(self) -> bool:
        """True when the exact eikonal gradients come in forward mode from the render's pass."""
        return self.eikonal is not None and self.eikonal.config.mode == "autograd" and self.field.supports_gradients

    # ----------------------------------------------------------------- render
    def _render(self, origins, directions, near, far, n_samples, stratified, generator=None, points_grad=False, with_grads=False):
        """Rays -> ``(intensity [R], line [R], flat [P, 3], q)``: the sample points and the field there."""
        R = origins.shape[0]
        if self.occupancy is not None:  # samples only on the stretch of each ray that can hold material
            from .occupancy import ray_intervals

            if any(torch.is_tensor(v) and v.numel() > 1 for v in (near, far)):
                raise ConfigError("a model with an occupancy grid renders rays between one near and one far for all of "
                                  "them; pass scalars (the scene's geometry.near_far), not one per ray")

            near, far = ray_intervals(self.occupancy, self.occupancy_box[0], self.occupancy_box[1], origins, directions,
                                      float(near), float(far))
        if self.quadrature == "voxel-planes":
            if not bool((self.voxel_count > 0).all()):
                raise ConfigError("the model has no voxel grid for its voxel-planes quadrature; call set_voxel_grid "
                                  "(training does it from the scene) or use model.quadrature bins")
            near = torch.as_tensor(near, device=origins.device, dtype=origins.dtype).expand(R)
            far = torch.as_tensor(far, device=origins.device, dtype=origins.dtype).expand(R)
            ray, t, length = voxel_plane_samples(origins, directions, near, far, self.voxel_box[0], self.voxel_box[1],
                                                 self.voxel_count)
            flat = origins[ray] + t[:, None] * directions[ray]
        else:
            t = self.ray_sampler.sample(near, far, R, n_samples, stratified, device=origins.device, dtype=origins.dtype,
                                        generator=generator)
            flat = sample_points(origins, directions, t).reshape(-1, 3)
        if points_grad:
            flat = flat.detach().requires_grad_(True)
        if with_grads:  # distances, features and d distances / d x [P, K, 3] in one pass
            q = self._materials(self._with_gradients(flat.detach()), flat)
        else:
            q = self.query(flat)
        if self.quadrature == "voxel-planes":
            intensity, line = integrate_samples(q["mu"], ray, (length / self.scale)[ray], R)
        else:
            intensity, line = beer_lambert(q["mu"].reshape(R, n_samples), segment_lengths(t, directions, self.scale))
        return intensity, line, flat, q

    def render(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        near,
        far,
        n_samples: Optional[int] = None,
        stratified: Optional[bool] = None,
        generator: Optional[torch.Generator] = None,
    ) -> RenderOutput:
        """Render rays ``origins`` [R, 3], ``directions`` [R, 3] (unnormalised, model units).

        Args:
            near, far: ray-parameter range, scalars or [R] (model units; scalars with an
                occupancy grid, which finds each ray's stretch between them).
            n_samples: points per ray; default ``num_samples`` in training mode,
                ``num_eval_samples`` in eval mode.
            stratified: jittered bins (default: ``self.training``) or even spacing.
        """
        stratified = self.training if stratified is None else stratified
        if n_samples is None:
            n_samples = self.config.num_samples if self.training else self.config.num_eval_samples
        if n_samples is None:
            raise ConfigError("model.num_samples / num_eval_samples are unset; resolve the config with presets.resolve first")
        intensity, line, *_ = self._render(origins, directions, near, far, int(n_samples), stratified, generator)
        return RenderOutput(intensity, line)

    # ------------------------------------------------------------------ losses
    def volume_loss_dict(self, points: torch.Tensor, targets: torch.Tensor, occupancy_weight: float = 0.0,
                         curvature_weight: float = 0.0, steps: Optional[torch.Tensor] = None,
                         queried: Optional[torch.Tensor] = None) -> dict[str, torch.Tensor]:
        """Loss terms for fitting the field to a known attenuation volume (the warm start).

        Args:
            points: [P, 3] model units (voxel centres).
            targets: [P] attenuation in data units at those points.
            occupancy_weight: SDF models: weight of a binary cross-entropy between
                each material's occupancy ``Omega(d_k, s)`` and "the target reaches
                material k" (``target > beta_k``; for k = 1, ``> alpha_1 / 2``). Unlike
                the MSE it keeps a gradient where ``Omega`` is saturated, so a thin
                material (cortical shells) appears even from the start-empty init.
            curvature_weight: SDF models: weight of the surface-smoothness term
                (``losses.curvature.surface_smoothness``) between the distance gradients at
                ``points`` and at ``points + steps``.
            steps: [P, 3] model units, the short steps of that term (their length is also its width).
            queried: [P] bool, the points where the field is queried (inside the occupancy
                grid); ``None`` = every point. The others add their squared target to the value
                term (``mu`` is 0 there whatever the field) and nothing else, and every mean keeps
                all P points' count: the gradient is a query of every point's with the other
                points' label, eikonal and curvature terms left out (none queried: every point is).

        Returns ``volume`` (MSE of ``mu``), ``occupancy`` (when weighted), ``eikonal``
        (SDF models, already times ``lambda_eikonal``), ``curvature`` (when weighted) and ``total``.
        """
        kept = 0 if queried is None else int(queried.sum())
        if kept > 0:
            count = len(points)
            unseen = (targets[~queried] ** 2).sum()
            out = self.volume_loss_dict(points[queried], targets[queried], occupancy_weight=occupancy_weight,
                                        curvature_weight=curvature_weight, steps=None if steps is None else steps[queried])
            share = kept / count
            out = {k: v * share for k, v in out.items() if k != "total"}
            out["volume"] = out["volume"] + unseen / count / self.loss_scale ** 2
            out["total"] = sum(out.values())
            return out
        fused = self.fused_eikonal
        if fused:
            q = self._materials(self._with_gradients(points.detach()), points)
        else:
            points = points.detach().requires_grad_(self.eikonal is not None)
            q = self.query(points)
        out = {"volume": torch.mean((q["mu"] - targets) ** 2)}
        if self.loss_scale != 1.0:  # in units of loss_scale, as the intensity loss
            out["volume"] = out["volume"] / self.loss_scale ** 2
        if occupancy_weight > 0 and self.has_surfaces:
            out["occupancy"] = occupancy_weight * self.occupancy_loss(q["distances"], targets)
        if self.eikonal is not None:
            out["eikonal"] = self.lambda_eikonal * self.eikonal(self.field.distances, points, q.get("distances"), grads=q.get("grads"))
        if curvature_weight > 0 and self.has_surfaces:
            grads = q["grads"] if "grads" in q else self.distance_gradients(points)
            out["curvature"] = curvature_weight * surface_smoothness(grads, self.distance_gradients(points.detach() + steps),
                                                                     q["distances"], float(steps.norm(dim=-1).mean()))
        out["total"] = sum(out.values())
        return out

    def distance_gradients(self, points: torch.Tensor) -> torch.Tensor:
        """Spatial gradients [P, K, 3] of the signed distances at ``points`` [P, 3]: in forward mode
        where the field has it, else as the eikonal term gets them (autograd or finite differences)."""
        if self.field.supports_gradients:
            return self._with_gradients(points).distance_gradients
        if self.eikonal is None:
            raise ConfigError("the surface-smoothness term needs the distances' gradients: this field has no forward-mode "
                              "gradients and the model no eikonal term; give --model.lambda-eikonal > 0")
        return self.eikonal.gradients(self.field.distances, points)

    def label_thresholds(self) -> torch.Tensor:
        """``[K]`` the attenuation each material's label starts at (data units): ``beta_k``,
        and for k = 1 ``model.first_label_threshold``, by default ``alpha_1 / 2`` (half way
        from air to the first material's top)."""
        alphas, betas = self.attenuation.alphas, self.attenuation.betas
        first = self.config.first_label_threshold  # checked against the bounds in set_bounds, not here (every step)
        if first is None:
            return torch.cat([alphas[:1] / 2, betas[1:]])
        return torch.cat([alphas.new_tensor([float(first)]), betas[1:]])

    def occupancy_loss(self, distances: torch.Tensor, targets: torch.Tensor,
                       mask: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Mean binary cross-entropy between each material's occupancy ``Omega(d_k, s)`` and
        "the target attenuation reaches material k" (``target >`` :meth:`label_thresholds`):
        the labels a volume's values give under the model's bounds.

        Args:
            distances: ``[P, K]`` signed distances (model units) at the points.
            targets: ``[P]`` attenuation there (data units).
            mask: ``[P]`` bool, the points whose labels count (the mean is over them;
                none: 0); ``None`` = every point.
        """
        thresholds = self.label_thresholds().to(targets.dtype)
        reached = (targets[:, None] > thresholds[None, :]).to(targets.dtype)
        bce = F.binary_cross_entropy_with_logits(-self.boundary.s * distances, reached, reduction="none")
        if mask is None:
            return bce.mean()
        return (bce * mask[:, None].to(bce.dtype)).sum() / (mask.sum().clamp(min=1) * bce.shape[-1])

    def loss_dict(self, batch: dict[str, Any], progress: float, generator: Optional[torch.Generator] = None) -> dict[str, torch.Tensor]:
        """Weighted loss terms and ``total`` for one training batch.

        Args:
            batch: from the datamanager: ``origins`` [R, 3], ``directions`` [R, 3],
                ``projections`` [R] (measured line integrals), ``is_air`` [R] bool,
                ``near``, ``far`` (model units).
            progress: fraction of training done, in [0, 1] (epochs done / epochs);
                schedules the floater loss.

        Returns:
            ``intensity``, ``floater`` (while active), ``eikonal`` (SDF models),
            ``total``: scalar tensors, already multiplied by their λ.
        """
        cfg = self.config
        is_air = batch["is_air"]
        use_air = bool(cfg.floater and self.floater_loss.active(progress) and bool(is_air.any()))
        keep = slice(None) if use_air else ~is_air
        origins, directions, p, air = batch["origins"][keep], batch["directions"][keep], batch["projections"][keep], is_air[keep]
        n_samples = cfg.num_samples
        if n_samples is None:
            raise ConfigError("model.num_samples is unset; resolve the config with presets.resolve first")
        frac = 1.0 if cfg.eikonal_fraction is None else float(cfg.eikonal_fraction)
        fused = self.fused_eikonal
        eik_same = self.eikonal is not None and frac >= 1.0 and self.eikonal.config.mode == "autograd"
        intensity, line, flat, q = self._render(origins, directions, batch["near"], batch["far"], int(n_samples), True, generator,
                                                points_grad=eik_same and not fused, with_grads=eik_same and fused)
        if self.loss_scale != 1.0:  # the intensities of the scan in units of loss_scale (its line integrals / loss_scale)
            intensity, p = torch.exp(-line / self.loss_scale), p / self.loss_scale
        out: dict[str, torch.Tensor] = {}
        out["intensity"] = self.intensity_loss(intensity[~air], p[~air])
        if use_air:
            out["floater"] = cfg.lambda_floater * self.floater_loss(intensity[air])
        if self.eikonal is not None:
            inside = (flat.detach().abs() <= self.bound).all(-1)
            if eik_same:
                eik = self.eikonal(self.field.distances, flat, q["distances"], mask=inside, grads=q.get("grads"))
            else:
                n = max(1, int(round(frac * len(flat))))
                idx = torch.randperm(len(flat), device="cpu", generator=generator)[:n].to(flat.device) if n < len(flat) else slice(None)
                sub = flat[idx].detach()
                grads = self._with_gradients(sub).distance_gradients if fused else None
                eik = self.eikonal(self.field.distances, sub, None, mask=inside[idx], grads=grads)
            out["eikonal"] = self.lambda_eikonal * eik
        out["total"] = sum(out.values())
        return out
