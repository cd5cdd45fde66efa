"""Held-out scenes: scans that are not built into kneas, to check that no default is tuned to the
built-in scenes (other anatomy, a finer detector, noise, texture). Not part of the test suite.

    python benchmarks/heldout.py --write data/heldout          # write the scenes as NAF pickles
    python benchmarks/classical.py --scenes heldout:head-256,heldout:jaw-noisy --dice
    kneas-train k-neas --scene data/heldout/head-256.pickle     # any method, on the written pickle

Scenes (``heldout:NAME`` in ``benchmarks/classical.py --scenes``):

* ``head-256``: a 3D Shepp-Logan-like head (rotated ellipsoids; skin, brain, ventricles,
  lesions, skull), 128³ voxels of 1.6 mm, a 256² detector (detector pixels at the isocentre
  0.74 voxels wide, where the built-in scenes have 1.5), 50 views, exact projections.
* ``head-vox256``: the same head on a 256³ grid of 0.8 mm voxels (the largest grid
  ``kneas-data import`` picks for a scan), a 256² detector (pixels 1.5 voxels wide at the
  isocentre), 50 views, exact projections: what a grid 8x larger costs.
* ``jaw-noisy``: the built-in jaw with TIGRE/NAF detector noise (1e5 photons, electronic σ 10).
* ``foot-noisy``, ``chest-noisy``: the built-in foot and chest with the same noise (added on
  2026-11-28, after the SURE smoothing was measured on jaw-noisy, to check it on scans it was not
  built on).
* ``abdomen-noisy``: the built-in abdomen with the same noise (added on 2026-11-28, after the
  bilateral filter's settings were chosen on the four noisy scans above, to check them on one they
  were not chosen on).
* ``head-noisy``: ``head-256`` (its phantom, 256² detector) with the same noise (added on
  2026-11-28, after the materials stage was built on the five noisy scans here, to check it on one it was
  not built on).
* ``knee``: other anatomy and another scanner (added on 2026-11-28): a knee (fat, muscle, femur,
  tibia, fibula and patella as cortical shells around marrow), a box 112 x 112 x 144 voxels of
  1.25 x 1.25 x 1.5 mm (not cubic, not isotropic), a 192² detector, a shorter source (750 mm
  from the axis, 1200 mm to the detector: a wider cone), 45 views over a full 360°, exact projections.
* ``knee-physical``: the same knee scan with the attenuation a scanner gives (added on
  2026-11-28): 75 times the levels, muscle at 20 /m as water at about 70 keV, so that the line integrals
  reach ~5 instead of ~0.07 (the built-in scenes' NAF-normalised volumes lie within [0, 1] /m).
* ``knee-long``: the knee with the leg going on 130 mm beyond the box at both ends (added on
  2026-11-28), as a scanner sees a leg: every view's top and bottom rows cross tissue outside the
  reconstructed box (a scan truncated along the axis).
* ``knee-long-noisy``: ``knee-long`` with the noisy scans' detector noise (added on 2026-11-28, after
  the longer box was built on ``knee-long``).
* ``knee-halffan``: the knee on an offset detector (added on 2026-11-28), as large-field cone-beam
  scanners extend their field of view: 112 of the 192 columns, shifted so that they see 16 columns
  past the central ray on one side and the whole object on the other; each view sees a little more
  than half the object, and the 360° orbit gives every point of it views from both sides.
* ``knee-narrow``: the knee on the middle 80 of the 192 columns (added on 2026-11-28): a field of
  view of 54 mm radius, narrower than the leg (62 mm), so most views miss part of it (truncated data).
* ``knee-narrow-noisy``: ``knee-narrow`` with the noisy scans' detector noise (added on 2026-11-28,
  with ``head-narrow``: a count chosen on clean data checked on noise, whose ASD-POCS peaks early).
* ``knee-long-narrow``: ``knee-long``'s leg on ``knee-narrow``'s detector (added on 2026-11-28): truncated
  along the axis and across it at once, as a cone-beam scan of a leg is; both mechanisms at once.
* ``head-narrow``: ``head-256`` on the middle 136 of its 256 columns (added on 2026-11-28, after the
  start's count for such scans was chosen on ``knee-narrow``, to check it on other anatomy and a
  larger detector): a field of view about 87 % of the head's width, as ``knee-narrow``'s is of the leg's.
* ``head-textured-noisy``: ``head-256``'s volume with a smooth ±10 % texture inside the object
  (not piecewise constant: TV's weak case), projected with the Joseph projector, with noise.

Written pickles keep the ground-truth volume and labels (PSNR/SSIM and, through ``kneas-eval``,
per-material Dice against the mean level of each label), but not the material names or the exact
membership of the head phantom, which is not built in (no Chamfer; ``classical.py`` with a
``heldout:NAME`` scene simulates it in memory and has both).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

SCENES = ("head-256", "head-vox256", "jaw-noisy", "head-textured-noisy", "foot-noisy", "chest-noisy", "abdomen-noisy", "head-noisy",
          "knee", "knee-physical", "knee-long", "knee-long-noisy", "knee-halffan", "knee-narrow",
          "knee-narrow-noisy", "head-narrow", "knee-long-narrow")


def head_phantom():
    """A 3D Shepp-Logan-like head: 5 materials, rotated ellipsoids, within ±92 mm."""
    from kneas_method.data.phantoms import Phantom, Primitive

    def e(centre, half, material, priority, euler=(0, 0, 0), name=""):
        return Primitive("ellipsoid", centre, half, material=material, priority=priority, euler=euler, name=name)

    return Phantom(
        name="head", description="3D Shepp-Logan-like head (held-out benchmark scene)",
        materials=("skin", "brain", "ventricle", "lesion", "skull"), levels=(0.2, 0.3, 0.15, 0.45, 0.9),
        primitives=(
            e((0, 0, 0), (69, 92, 81), 5, 1, name="skull"), e((0, -1.8, 0), (66, 87, 78), 2, 2, name="brain"),
            e((22, 0, 0), (11, 31, 22), 3, 3, (-18, 0, 0)), e((-22, 0, 0), (16, 41, 28), 3, 3, (18, 0, 0)),
            e((0, 35, -15), (21, 25, 35), 4, 4), e((0, 10, 25), (4.6, 4.6, 4.6), 4, 5),
            e((-8, -60, 6), (4.6, 2.3, 10), 4, 5), e((6, -60, -10), (4.6, 2.3, 10), 1, 5, (90, 0, 0)),
            e((0, -10, 62), (56, 40, 10), 1, 3),
        ),
    )


# knee-physical: the knee's levels in a scanner's units, muscle at 20.25 /m (water at about 70 keV,
# 0.02 /mm), where the built-in scenes' NAF-normalised volumes lie within [0, 1] /m
KNEE_PHYSICAL_SCALE = 75.0


def _knee_scan():
    from kneas_method.data.simulate import SimulationConfig

    return SimulationConfig(n_voxel=(112, 112, 144), voxel_mm=(1.25, 1.25, 1.5), dso_mm=750.0, dsd_mm=1200.0,
                            n_detector=192, n_train=45, n_val=10, total_angle_deg=360.0)


def knee_phantom(scale: float = 1.0, extend_mm: float = 0.0):
    """A knee: fat around muscle, femur, tibia, fibula and patella (cortical shells around marrow),
    within ±70 mm across and ±105 mm along the leg (z); levels times ``scale``; the leg and the bones'
    shafts ``extend_mm`` longer at both ends."""
    from kneas_method.data.phantoms import Phantom, Primitive

    FAT, MUSCLE, MARROW, CORTEX = 1, 2, 3, 4
    e = float(extend_mm)

    def p(kind, centre, half, material, priority, euler=(0, 0, 0), name=""):
        return Primitive(kind, centre, half, material=material, priority=priority, euler=euler, name=name)

    def bone(kind, centre, half, shell, priority, euler=(0, 0, 0), name=""):
        inner = tuple(h - shell for h in half)
        return [p(kind, centre, half, CORTEX, priority, euler, f"{name} cortex"),
                p(kind, centre, inner, MARROW, priority + 1, euler, f"{name} marrow")]

    return Phantom(
        name="knee", description="knee: fat, muscle, four bones (held-out benchmark scene)",
        materials=("fat", "muscle", "marrow", "cortical bone"), levels=tuple(scale * v for v in (0.16, 0.27, 0.47, 0.86)),
        primitives=(
            p("cylinder", (0, 0, 0), (62, 58, 100 + e), FAT, 1, name="skin and fat"),
            p("cylinder", (0, -2, 0), (55, 50, 101 + e), MUSCLE, 2, name="muscle"),
            p("ellipsoid", (0, 34, -8), (30, 10, 22), FAT, 3, name="infrapatellar fat pad"),
            *bone("cylinder", (0, -4, 55 + e / 2), (15, 14, 50 + e / 2), 4, 10, (0, 6, 0), "femur shaft"),
            *bone("ellipsoid", (-19, -6, 12), (17, 24, 20), 3, 12, (0, 0, 8), "lateral condyle"),
            *bone("ellipsoid", (19, -6, 12), (17, 24, 20), 3, 14, (0, 0, -8), "medial condyle"),
            *bone("ellipsoid", (0, -4, -16), (40, 30, 12), 3, 16, name="tibial plateau"),
            *bone("cylinder", (0, -6, -62 - e / 2), (16, 15, 45 + e / 2), 4, 18, (0, -4, 0), "tibia shaft"),
            *bone("cylinder", (-36, -16, -55 - e / 2), (6, 6, 40 + e / 2), 2.5, 20, (0, 5, 0), "fibula"),
            *bone("ellipsoid", (0, 42, 22), (18, 8, 20), 3, 22, (0, 0, 0), "patella"),
        ),
    )


def _texture(shape, seed: int = 0, sigma_voxels: float = 3.0, amplitude: float = 0.1) -> np.ndarray:
    """A smooth random field [shape] in [1 - amplitude, 1 + amplitude]."""
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(np.random.default_rng(seed).standard_normal(shape), sigma_voxels)
    return 1.0 + amplitude * field / np.abs(field).max()


def scene_from_spec(spec: str):
    """A benchmark's ``--scenes`` entry: ``heldout:NAME`` (:func:`heldout_scene`), else a built-in
    name or a NAF pickle path (``resolve_scene``)."""
    if spec.startswith("heldout:"):
        return heldout_scene(spec.split(":", 1)[1])
    from kneas_method.data.scenes import resolve_scene
    from kneas_method.errors import KneasError

    try:
        return resolve_scene(spec, flag="--scenes")
    except KneasError as exc:  # a benchmark's mistake is one line too, as the commands'
        raise SystemExit(f"error: {exc}") from None


def _offset_detector_scan(phantom, cfg, name: str, columns: int, past_centre: int):
    """``phantom`` scanned as ``cfg`` says (its detector noise too), but on ``columns`` of the detector's
    columns, shifted so that they reach ``past_centre`` columns past the central ray (an offset, half-fan detector)."""
    from kneas_method.data.scene import Scene, Views
    from kneas_method.data.simulate import _meta, finish_projections, make_angles, make_geometry

    full = make_geometry(cfg)
    nv = full.n_detector[1]
    du = full.d_detector[0]
    offset = (columns / 2 - past_centre) * du  # the kept columns' centre, from the central ray
    geometry = dataclasses.replace(full, n_detector=(columns, nv), off_detector=(offset, full.off_detector[1]))
    train_a, val_a = make_angles(cfg)
    train_p, val_p = finish_projections(cfg, np.asarray(phantom.project(geometry, train_a)), np.asarray(phantom.project(geometry, val_a)))
    train, val = Views(train_a, train_p), Views(val_a, val_p)
    return Scene(name, geometry, train, val, image=np.ascontiguousarray(phantom.volume(geometry), dtype=np.float32),
                 labels=np.ascontiguousarray(phantom.labels(geometry), dtype=np.uint8), materials=tuple(phantom.materials),
                 membership=lambda pts: phantom.label_at(geometry.model_to_mm(np.asarray(pts, dtype=np.float64))),
                 meta=_meta(cfg, phantom=str(phantom.name)), source=f"heldout:{name}")


def heldout_scene(name: str):
    """The held-out scene ``name`` (one of :data:`SCENES`), simulated in memory."""
    from kneas_method.data.simulate import SimulationConfig, simulate_from_volume, simulate_phantom

    head = SimulationConfig(n_voxel=128, voxel_mm=1.6, n_detector=256, n_train=50, n_val=10)
    if name == "head-256":
        scene = simulate_phantom(head_phantom(), head)
        scene.name = "head-256"  # the phantom is "head"; the scene is named as its pickle
        return scene
    if name == "head-noisy":
        scene = simulate_phantom(head_phantom(), dataclasses.replace(head, noise=True))
        scene.name = "head-noisy"
        return scene
    if name == "head-narrow":  # centred, too narrow for the head (which spans columns 50-205 of 256)
        cfg = dataclasses.replace(head, n_train=50, n_val=10)
        return _offset_detector_scan(head_phantom(), cfg, name, columns=136, past_centre=68)
    if name == "head-vox256":
        scene = simulate_phantom(head_phantom(), dataclasses.replace(head, n_voxel=256, voxel_mm=0.8))  # the same box, 8x the voxels
        scene.name = "head-vox256"
        return scene
    if name in ("jaw-noisy", "foot-noisy", "chest-noisy", "abdomen-noisy"):  # a built-in phantom's scan with NAF's detector noise
        scene = simulate_phantom(name.split("-")[0], SimulationConfig(n_train=50, n_val=10, noise=True))
        scene.name = name
        return scene
    if name == "knee-halffan":
        return _offset_detector_scan(knee_phantom(), _knee_scan(), name, columns=112, past_centre=16)
    if name in ("knee-narrow", "knee-narrow-noisy", "knee-long-narrow"):  # centred, too narrow for the leg
        cfg = dataclasses.replace(_knee_scan(), noise=name.endswith("-noisy"))
        phantom = knee_phantom(1.0, 130.0 if name == "knee-long-narrow" else 0.0)
        return _offset_detector_scan(phantom, cfg, name, columns=80, past_centre=40)
    if name in ("knee", "knee-physical", "knee-long", "knee-long-noisy"):
        cfg = dataclasses.replace(_knee_scan(), noise=name.endswith("-noisy"))
        phantom = knee_phantom(KNEE_PHYSICAL_SCALE if name == "knee-physical" else 1.0, 130.0 if name.startswith("knee-long") else 0.0)
        scene = simulate_phantom(phantom, cfg)
        scene.name = name
        return scene
    if name == "head-textured-noisy":
        clean = simulate_phantom(head_phantom(), SimulationConfig(n_voxel=128, voxel_mm=1.6, n_detector=256,
                                                                  n_train=1, n_val=1))
        volume = (clean.image * _texture(clean.image.shape)).astype(np.float32)
        noisy = SimulationConfig(n_voxel=128, voxel_mm=1.6, n_detector=256, n_train=50, n_val=10, noise=True)
        scene = simulate_from_volume(volume, noisy, name="head-textured-noisy")
        scene.labels, scene.materials = clean.labels, clean.materials
        return scene
    raise SystemExit(f"error: unknown held-out scene {name!r}; choose from {', '.join(SCENES)}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", required=True, help="folder to write <scene>.pickle into")
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated held-out scene names")
    args = ap.parse_args(argv)
    from kneas_method.data.naf import save_naf

    out = Path(args.write)
    out.mkdir(parents=True, exist_ok=True)
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        path = save_naf(heldout_scene(name), out / f"{name}.pickle")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
