"""Real patients' CT as benchmark scenes, made the way NAF made its data: a CT volume in Hounsfield
units, converted to attenuation (water 1 at 0 HU, air 0), normalised to [0, 1] by its maximum and
projected to 50 cone-beam views over 180°, clean and with TIGRE/NAF detector noise.

    python benchmarks/real_anatomy.py --write data/real        # fetch the CTs (setup step) and write the scenes
    kneas-train k-neas --scene data/real/ts-chest.pickle        # any method, on a written scene
    python benchmarks/classical.py --scenes data/real/ts-chest.pickle --dice --trace

The CTs are the two test volumes that TotalSegmentator's source distribution on PyPI ships
(``totalsegmentator-2.18.0.tar.gz``, Apache-2.0; Wasserthal et al., Radiology: Artificial
Intelligence 2023): ``tests/reference_files/aorta_report/example_ct.nii.gz`` (a chest and upper
abdomen with contrast, 233 x 167 x 191 voxels of 1.5 mm) and ``tests/reference_files/example_ct.nii.gz``
(an abdomen and pelvis, 122 x 101 x 112 voxels of 3 mm). ``--write`` runs ``pip download`` once into
``--cache`` (the only network access; the scenes themselves are made offline).

Scenes:

* ``ts-chest``: the chest CT resampled (linear) to 128 voxels along its longest axis (2.73 mm voxels,
  128 x 92 x 105), a 256² detector;
* ``ts-abdomen``: the abdomen-pelvis CT on its own 3 mm grid (122 x 101 x 112), a 256² detector;
* ``ts-chest-noisy``, ``ts-abdomen-noisy``: the same with the noisy scans' detector noise
  (1e5 photons, electronic σ 10);
* ``ts-chest-fine``, ``ts-chest-fine-noisy``: ``ts-chest``'s truth and grid, its views projected from
  the CT's own 1.5 mm grid instead (added on 2026-12-05). The four scenes above are projected from
  the grid that is reconstructed and scored, by the projector the classical methods use, as NAF's
  are by TIGRE: a clean scan is then exactly the projection of some volume on that grid, and an
  iterative method approaches it for as long as it runs (the "inverse crime"). A scanner's object
  has detail finer than any grid; projected from 1.8 times finer voxels, the views differ from the
  truth's own projections by 0.7 % of their mean, and SART and CGLS stop improving after 7 and 21
  iterations, as they do on a scanner's data.
* ``ts-chest-fine-lowdose``, ``ts-abdomen-lowdose``, ``ts-abdomen-highdose``: other doses (added on
  2026-12-07): ``ts-chest-fine``'s and ``ts-abdomen``'s views with 2.5e4 photons a pixel (four times the
  noisy scans' noise variance) and ``ts-abdomen``'s with 1e6 (a tenth of it), electronic σ 10;
  ``ts-chest-fine-highdose``: ``ts-chest-fine``'s views with 1e6 photons; ``ts-chest-fine-3e5``,
  ``ts-abdomen-3e5``: 3e5 photons; ``ts-chest-highdose``: ``ts-chest``'s views with 1e6 photons (these
  four added later on 2026-12-07).

**Materials.** Real anatomy has no analytic surfaces, so the truth's materials are thresholds of the
true volume in HU (``HU_THRESHOLDS``): lung and other gas-filled tissue from -900 HU (the air outside
the body and in the airways is below it), fat from -400 (half way from lung parenchyma, about -800,
to fat, about -100), soft tissue from -30 (half way from fat to muscle and organs, +40), bone from
+250 (above contrast-enhanced blood in most of the aorta, below cancellous bone; the brightest
contrast is labelled bone). The thresholds travel in the pickle (``label_thresholds``, in the scene's
attenuation units) with the names (``materials``), so ``kneas-eval`` scores Dice against the labels
and Chamfer against the thresholds' surfaces of the interpolated volume, on any scene that carries them.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np

PACKAGE, VERSION = "TotalSegmentator", "2.18.0"
SDIST = f"totalsegmentator-{VERSION}.tar.gz"
SOURCES = {"chest": "tests/reference_files/aorta_report/example_ct.nii.gz", "abdomen": "tests/reference_files/example_ct.nii.gz"}
# (name, source, longest side in voxels or None for the CT's own grid, photons per pixel or None for a clean
# scan, views projected from the CT's own grid)
SCENES = (("ts-chest", "chest", 128, None, False), ("ts-abdomen", "abdomen", None, None, False),
          ("ts-chest-noisy", "chest", 128, 1e5, False), ("ts-abdomen-noisy", "abdomen", None, 1e5, False),
          ("ts-chest-fine", "chest", 128, None, True), ("ts-chest-fine-noisy", "chest", 128, 1e5, True),
          ("ts-chest-fine-lowdose", "chest", 128, 2.5e4, True), ("ts-abdomen-lowdose", "abdomen", None, 2.5e4, False),
          ("ts-abdomen-highdose", "abdomen", None, 1e6, False), ("ts-chest-fine-highdose", "chest", 128, 1e6, True),
          ("ts-chest-fine-3e5", "chest", 128, 3e5, True), ("ts-abdomen-3e5", "abdomen", None, 3e5, False),
          ("ts-chest-highdose", "chest", 128, 1e6, False))
HU_THRESHOLDS = (-900.0, -400.0, -30.0, 250.0)
MATERIALS = ("lung", "fat", "soft tissue", "bone")
N_DETECTOR, VIEWS = 256, 50


def fetch(cache: Path) -> Path:
    """The source distribution in ``cache`` (downloaded with pip the first time)."""
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / SDIST
    if not path.is_file():
        print(f"downloading {PACKAGE}=={VERSION}'s source distribution into {cache} (pip download)")
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", f"{PACKAGE}=={VERSION}",
                        "-d", str(cache)], check=True)
    return path


def read_ct(sdist: Path, member: str) -> tuple[np.ndarray, tuple[float, float, float]]:
    """``(HU [nx, ny, nz] float32, voxel size mm)`` of one CT of the source distribution."""
    import gzip
    import io

    import nibabel as nib

    with tarfile.open(sdist) as tar:
        data = tar.extractfile(f"totalsegmentator-{VERSION}/{member}").read()
    image = nib.Nifti1Image.from_bytes(gzip.decompress(data)) if data[:2] == b"\x1f\x8b" else nib.Nifti1Image.from_bytes(data)
    hu = np.asarray(image.dataobj, dtype=np.float32)
    return hu, tuple(float(z) for z in image.header.get_zooms()[:3])


def resample(hu: np.ndarray, voxel_mm, longest: int | None) -> tuple[np.ndarray, tuple[float, float, float]]:
    """``hu`` resampled (linear) so that its longest side has ``longest`` voxels, the box kept; None: as it is."""
    if longest is None:
        return hu, tuple(voxel_mm)
    from scipy.ndimage import zoom

    size = np.array(hu.shape) * np.array(voxel_mm)
    step = float(size.max()) / longest
    shape = np.maximum(1, np.round(size / step)).astype(int)
    out = zoom(hu, shape / np.array(hu.shape), order=1, mode="nearest", grid_mode=True)
    return out.astype(np.float32), tuple(float(v) for v in size / np.array(out.shape))


def project_finer(scene, fine_image: np.ndarray, fine_voxel_mm, cfg) -> None:
    """Replace ``scene``'s views by the projections of ``fine_image`` [nx, ny, nz] (attenuation in the
    scene's units), a finer grid of ``fine_voxel_mm`` over the same box, at the same angles and with the
    same detector (``cfg``'s noise added to them if it asks for it); the truth stays the scene's own."""
    from kneas_method.classical.projector import forward
    from kneas_method.data.simulate import finish_projections

    g = scene.geometry
    fine = g.on_grid(fine_image.shape)
    fine_mm = np.array(fine.d_voxel) * fine.mm_per_unit
    if not np.allclose(fine_mm, np.array(fine_voxel_mm, dtype=float), rtol=1e-3):
        raise ValueError(f"a grid of {fine_image.shape} voxels of {fine_voxel_mm} mm does not fill the scene's box "
                         f"({g.n_voxel} voxels of {np.array(g.d_voxel) * g.mm_per_unit} mm)")
    train = forward(np.ascontiguousarray(fine_image, dtype=np.float32), fine, scene.train.angles)
    val = forward(np.ascontiguousarray(fine_image, dtype=np.float32), fine, scene.val.angles)
    scene.train.projections, scene.val.projections = finish_projections(cfg, train, val)
    scene.meta["projected_from"] = {"n_voxel": list(fine_image.shape), "voxel_mm": [float(v) for v in fine_voxel_mm]}


def real_scene(name: str, sdist: Path):
    """The scene ``name`` of :data:`SCENES` (see the module docs)."""
    from kneas_method.data.naf import LABEL_THRESHOLDS_KEY, MATERIALS_KEY, attach_threshold_labels, threshold_labels
    from kneas_method.data.simulate import SimulationConfig, simulate_from_volume
    from kneas_method.data.volume_io import hu_to_mu

    spec = {s[0]: s for s in SCENES}
    if name not in spec:
        raise SystemExit(f"error: no real-anatomy scene {name!r}; scenes: {', '.join(spec)}")
    _, source, longest, photons, fine = spec[name]
    native_hu, native_mm = read_ct(sdist, SOURCES[source])
    hu, voxel_mm = resample(native_hu, native_mm, longest)
    mu = hu_to_mu(hu)
    top = float(mu.max())
    image = (mu / top).astype(np.float32)
    thresholds = [float(v) for v in hu_to_mu(np.array(HU_THRESHOLDS)) / top]
    cfg = SimulationConfig(n_detector=N_DETECTOR, n_train=VIEWS, n_val=VIEWS, noise=photons is not None, photons=photons or 1e5)
    meta = {LABEL_THRESHOLDS_KEY: thresholds, MATERIALS_KEY: list(MATERIALS), "hu_thresholds": list(HU_THRESHOLDS),
            "source_ct": f"{SDIST}:{SOURCES[source]}", "convert": True, "normalize": True, "hu_max": float(hu.max())}
    scene = simulate_from_volume(image, cfg, voxel_mm=voxel_mm, name=name, meta=meta)
    if fine:
        project_finer(scene, np.clip(hu_to_mu(native_hu) / top, 0, None), native_mm, cfg)
    scene.labels = threshold_labels(image, thresholds)
    attach_threshold_labels(scene, name)  # the materials and membership a load of the pickle gives
    return scene


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--write", type=Path, required=True, help="folder to write the scenes into, as NAF pickles")
    p.add_argument("--scenes", default=",".join(s[0] for s in SCENES), help="comma-separated scene names (default: all)")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "kneas" / "real-anatomy",
                   help="where the downloaded source distribution is kept")
    args = p.parse_args(argv)
    from kneas_method.data.naf import save_naf

    sdist = fetch(args.cache)
    args.write.mkdir(parents=True, exist_ok=True)
    for name in [s for s in args.scenes.split(",") if s]:
        scene = real_scene(name, sdist)
        path = save_naf(scene, args.write / f"{name}.pickle")
        counts = np.bincount(scene.labels.reshape(-1), minlength=len(MATERIALS) + 1) / scene.labels.size
        print(f"{path}: {tuple(scene.geometry.n_voxel)} voxels, {len(scene.train)} + {len(scene.val)} views, "
              + ", ".join(f"{m} {100 * c:.1f} %" for m, c in zip(("air",) + MATERIALS, counts)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
