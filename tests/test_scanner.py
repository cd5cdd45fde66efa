"""Your own scans: RTK geometry XML + projection images -> kneas, the RTK <-> kneas frame map, and back to RTK.

RTK itself (``itk-rtk``, part of the dev install) simulates the scans here, writes
their geometry with its own XML writer and reconstructs them with its own FDK,
so the frame map is checked against RTK, not against kneas's reading of it.
"""

from __future__ import annotations

import builtins
import math
import types

import numpy as np
import pytest

from kneas_method.cli import data as cli
from kneas_method.data.naf import load_naf, save_naf
from kneas_method.data.rtk_geometry import (
    KNEAS_TO_RTK,
    RTKGeometry,
    arc_normalise,
    projection_matrix,
    read_rtk_geometry,
    write_rtk_geometry,
)
from kneas_method.data.rtk_export import export_rtk
from kneas_method.data.scanner_import import detect_kind, import_scan, to_line_integrals
from kneas_method.data.scene import Scene
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from kneas_method.datamanagers.ct import CTDataManagerConfig, noise_air_threshold
from kneas_method.errors import KneasError, SceneError

try:  # itk-rtk comes with the dev install; without it these tests must fail, not be skipped
    import itk
    from itk import RTK as rtk
except ImportError as exc:  # pragma: no cover
    raise ImportError("tests/test_scanner.py needs itk-rtk, part of the dev install: pip install -e '.[dev]'") from exc

F3 = itk.Image[itk.F, 3]

# Scanner of the tests: a full 360° orbit of 72 views starting at 20°, detector offsets in u and v, a source
# offset along the rotation axis and a projection origin that is not the detector centre.
SID, SDD = 400.0, 600.0
PX, PY, SY = 7.0, -5.0, 3.0
NU, NV, DU, DV = 96, 64, 1.2, 1.0
ORIGIN_UV = (-(NU - 1) / 2 * DU + 4.0, -(NV - 1) / 2 * DV - 2.0)
# An asymmetric object in RTK's world (LPS, mm): (centre, semi-axes, density 1/mm), all inside the field of view.
ELLIPSOIDS = [((12.0, -6.0, 8.0), (20.0, 10.0, 12.0), 0.02),
              ((-18.0, 4.0, -6.0), (7.0, 7.0, 7.0), 0.04),
              ((4.0, -12.0, -14.0), (5.0, 4.0, 8.0), 0.03)]


def rtk_geometry(angles_deg, sid=SID, sdd=SDD, px=PX, py=PY, sy=SY):
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for a in angles_deg:
        g.AddProjection(sid, sdd, float(a), px, py, 0.0, 0.0, 0.0, sy)
    return g


def rtk_project(geometry, n_proj, origin=ORIGIN_UV, spacing=(DU, DV), size=(NU, NV)):
    """RTK's exact line integrals of :data:`ELLIPSOIDS` (density x mm), an ITK image (nU, nV, N)."""
    src = rtk.ConstantImageSource[F3].New()
    src.SetOrigin([origin[0], origin[1], 0.0])
    src.SetSpacing([spacing[0], spacing[1], 1.0])
    src.SetSize([size[0], size[1], n_proj])
    src.SetConstant(0.0)
    img = src.GetOutput()
    for centre, axes, density in ELLIPSOIDS:
        f = rtk.RayEllipsoidIntersectionImageFilter[F3, F3].New()
        f.SetInput(img)
        f.SetGeometry(geometry)
        f.SetDensity(density)
        f.SetCenter(list(centre))
        f.SetAxis(list(axes))
        f.SetAngle(0.0)
        f.Update()
        img = f.GetOutput()
        img.DisconnectPipeline()
    return img


def write_rtk_xml(geometry, path):
    w = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    w.SetFilename(str(path))
    w.SetObject(geometry)
    w.WriteFile()
    return path


def rtk_matrices(geometry):
    return np.stack([itk.array_from_vnl_matrix(geometry.GetMatrix(i).GetVnlMatrix().as_matrix())
                     for i in range(len(geometry.GetGantryAngles()))])


def truth_at(points_lps, mirror=(1, 1, 1)):
    """Exact attenuation (1/m) at world points [P, 3] (LPS mm), optionally of the mirrored object."""
    pts = np.asarray(points_lps) * np.asarray(mirror, dtype=float)
    out = np.zeros(len(pts))
    for centre, axes, density in ELLIPSOIDS:
        out += density * 1000.0 * (np.sum(((pts - centre) / np.asarray(axes)) ** 2, 1) <= 1.0)
    return out


def world_points(half=36.0, step=1.0):
    xs = np.arange(-half, half + 1e-9, step)
    return np.stack(np.meshgrid(xs, xs, xs, indexing="ij"), -1).reshape(-1, 3)


def sample_nifti(path, points_lps):
    """Trilinear samples of a NIfTI volume at world points given in LPS (NIfTI's affine is RAS)."""
    import nibabel as nib
    from scipy.ndimage import map_coordinates

    img = nib.load(str(path))
    ras = points_lps * np.array([-1.0, -1.0, 1.0])
    ijk = np.round((np.linalg.inv(img.affine) @ np.c_[ras, np.ones(len(ras))].T)[:3], 6)
    return map_coordinates(np.asarray(img.dataobj, dtype=np.float64), ijk, order=1, cval=0.0)


def sample_itk(image, points_lps):
    """Trilinear samples of an ITK image at world points (LPS, its own origin/spacing/direction)."""
    from scipy.ndimage import map_coordinates

    arr = itk.array_from_image(image).astype(np.float64)  # [k, j, i]
    origin, spacing = np.array(image.GetOrigin()), np.array(image.GetSpacing())
    direction = itk.array_from_matrix(image.GetDirection())
    ijk = np.round(np.linalg.solve(direction * spacing, (points_lps - origin).T), 6)  # [3, P] as (i, j, k); edges stay inside
    return map_coordinates(arr, ijk[::-1], order=1, cval=0.0)


def centre_of_mass(points, values, threshold):
    w = np.where(values > threshold, values, 0.0)
    return (points * w[:, None]).sum(0) / w.sum()


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """An RTK-simulated scan on disk: projections .mha (RTK's line integrals) + geometry XML by RTK's writer."""
    d = tmp_path_factory.mktemp("scan")
    angles = 20.0 + np.linspace(0.0, 360.0, 72, endpoint=False)
    geometry = rtk_geometry(angles)
    proj = rtk_project(geometry, len(angles))
    itk.imwrite(proj, str(d / "proj.mha"))
    write_rtk_xml(geometry, d / "geometry.xml")
    return types.SimpleNamespace(dir=d, proj=d / "proj.mha", xml=d / "geometry.xml", geometry=geometry, image=proj,
                                 angles=angles, p=itk.array_from_image(proj).astype(np.float64))


@pytest.fixture(scope="module")
def imported(scan):
    return import_scan([str(scan.proj)], scan.xml, volume_size=48)


def run_cli(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out = capsys.readouterr()
    return info.value.code, out.out, out.err


# --------------------------------------------------------------------------- RTK's geometry
def test_projection_matrix_and_xml_agree_with_rtk(tmp_path):
    """Our RTK matrix equals RTK's for tilts and all offsets; our XML and RTK's read each other exactly."""
    rng = np.random.default_rng(3)
    g = rtk.ThreeDCircularProjectionGeometry.New()
    params = []
    for _ in range(5):
        p = [float(v) for v in (rng.uniform(800, 1100), rng.uniform(1300, 1600), rng.uniform(0, 360), rng.uniform(-20, 20),
                                rng.uniform(-20, 20), rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(-5, 5), rng.uniform(-5, 5))]
        g.AddProjection(*p)
        params.append(p)
    theirs = rtk_matrices(g)
    for i, p in enumerate(params):
        np.testing.assert_allclose(projection_matrix(*p), theirs[i], atol=1e-9)
    # RTK's writer -> our reader: the same parameters (and the matrices RTK wrote pass our consistency check)
    ours = read_rtk_geometry(write_rtk_xml(g, tmp_path / "rtk.xml"))
    np.testing.assert_allclose(ours.gantry_deg, [p[2] for p in params], atol=1e-9)
    np.testing.assert_allclose(ours.source_offset_y, [p[8] for p in params], atol=1e-12)
    np.testing.assert_allclose(ours.in_plane_deg, np.mod([p[6] for p in params], 360), atol=1e-9)
    # our writer -> RTK's reader: the same matrices
    write_rtk_geometry(ours, tmp_path / "ours.xml")
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(tmp_path / "ours.xml"))
    reader.GenerateOutputInformation()
    np.testing.assert_allclose(rtk_matrices(reader.GetOutputObject()), theirs, rtol=1e-12, atol=1e-8)


def test_xml_reader_follows_rtk_semantics(tmp_path):
    """Values before the first <Projection> hold for all; a value set in one projection holds for the next."""
    xml = tmp_path / "g.xml"
    xml.write_text('<?xml version="1.0"?>\n<!DOCTYPE RTKGEOMETRY>\n<RTKThreeDCircularGeometry version="3">\n'
                   "<SourceToIsocenterDistance>1000</SourceToIsocenterDistance><SourceToDetectorDistance>1500</SourceToDetectorDistance>\n"
                   "<Projection><GantryAngle>0</GantryAngle></Projection>\n"
                   "<Projection><Angle>90</Angle><ProjectionOffsetX>3</ProjectionOffsetX></Projection>\n"
                   "<Projection><GantryAngle>180</GantryAngle></Projection>\n</RTKThreeDCircularGeometry>\n")
    g = read_rtk_geometry(xml)
    np.testing.assert_array_equal(g.gantry_deg, [0, 90, 180])
    np.testing.assert_array_equal(g.proj_offset_x, [0, 3, 3])
    np.testing.assert_array_equal(g.sid, [1000] * 3)


def test_frame_map_is_a_proper_rotation():
    assert np.linalg.det(KNEAS_TO_RTK) == pytest.approx(1.0)
    # kneas source at angle θ maps onto RTK's source at gantry angle θ
    for deg in (0.0, 37.0, 200.0):
        t = math.radians(deg)
        kneas_src = np.array([SID * math.cos(t), SID * math.sin(t), 0.0])
        g = RTKGeometry.circular([deg], SID, SDD)
        np.testing.assert_allclose(KNEAS_TO_RTK @ kneas_src, g.source_position(0), atol=1e-9)


def test_arc_normalise_keeps_short_scans_contiguous():
    deg = lambda a: np.degrees(arc_normalise(np.radians(a)))  # noqa: E731
    np.testing.assert_allclose(deg([300, 330, 0, 30, 60]), [300, 330, 360, 390, 420])
    shuffled = deg([30, 300, 120, 0, 90, 330, 60])  # same short scan, views in another order
    assert np.ptp(shuffled) == pytest.approx(180.0)
    np.testing.assert_allclose(np.mod(shuffled, 360), [30, 300, 120, 0, 90, 330, 60], atol=1e-9)


# --------------------------------------------------------------------------- orientation: the promise
def test_imported_reconstruction_lands_where_rtk_puts_the_object(scan, imported, tmp_path):
    """Import RTK's scan, reconstruct with kneas's FDK, export: in world coordinates (NIfTI RAS / .mha LPS) it
    overlaps the true object and RTK's own FDK, and clearly not any mirror image of it."""
    from kneas_method.classical.fdk import fdk_reconstruct
    from kneas_method.export.volume import export_volume

    scene = imported
    assert scene.image is None and len(scene.val) == 0 and len(scene.train) == 72
    vol = fdk_reconstruct(scene)
    run = types.SimpleNamespace(model=None, volume=vol, scene=scene, config=types.SimpleNamespace(method="fdk"))
    info = export_volume(run, tmp_path / "export")
    assert {"attenuation_nifti", "attenuation_mha"} <= set(info["files"])

    pts = world_points()
    truth = truth_at(pts)
    kneas = sample_nifti(tmp_path / "export" / "attenuation.nii.gz", pts)
    corr = np.corrcoef(truth, kneas)[0, 1]
    mirrored = [np.corrcoef(truth_at(pts, m), kneas)[0, 1] for m in ((-1, 1, 1), (1, -1, 1), (1, 1, -1))]
    com_err = centre_of_mass(pts, kneas, 10.0) - centre_of_mass(pts, truth, 10.0)
    print(f"\norientation: corr(kneas, truth) {corr:.3f}; mirrored x/y/z {np.round(mirrored, 3).tolist()}; "
          f"centre-of-mass error {np.round(com_err, 3).tolist()} mm")
    assert corr > 0.85 and max(mirrored) < corr - 0.5
    assert np.all(np.abs(com_err) < 1.0)
    for centre, axes, density in ELLIPSOIDS:  # each blob where it belongs, at about its density
        inside = np.sum(((pts - centre) / (0.6 * np.asarray(axes))) ** 2, 1) <= 1.0
        assert kneas[inside].mean() == pytest.approx(density * 1000.0, rel=0.25)

    # the .mha (LPS, read by ITK) holds the same values at the same world points
    mha = itk.imread(str(tmp_path / "export" / "attenuation.mha"), itk.F)
    np.testing.assert_allclose(sample_itk(mha, pts), kneas, atol=1e-3 * kneas.max())

    # RTK's own FDK of the same files, on a world grid
    src = rtk.ConstantImageSource[F3].New()
    src.SetOrigin([-36.0] * 3)
    src.SetSpacing([2.0] * 3)
    src.SetSize([37] * 3)
    src.SetConstant(0.0)
    fdk = rtk.FDKConeBeamReconstructionFilter[F3].New()
    fdk.SetInput(0, src.GetOutput())
    fdk.SetInput(1, itk.imread(str(scan.proj), itk.F))
    fdk.SetGeometry(scan.geometry)
    fdk.Update()
    rtk_vals = sample_itk(fdk.GetOutput(), pts) * 1000.0  # RTK: 1/mm -> 1/m
    corr_rtk = np.corrcoef(kneas, rtk_vals)[0, 1]
    com_rtk = centre_of_mass(pts, kneas, 10.0) - centre_of_mass(pts, rtk_vals, 10.0)
    print(f"orientation: corr(kneas, RTK FDK) {corr_rtk:.3f}; centre-of-mass kneas - RTK {np.round(com_rtk, 3).tolist()} mm")
    assert corr_rtk > 0.95 and np.all(np.abs(com_rtk) < 0.5)


def test_volume_export_of_a_simulated_scene_keeps_kneas_xyz_as_ras(tmp_path):
    """Scenes without a scanner frame keep the NIfTI convention kneas xyz = RAS; their .mha is the same placement in LPS."""
    import nibabel as nib

    from kneas_method.export.volume import export_volume, volume_affine

    scene = simulate_phantom("foot", SimulationConfig(n_voxel=(10, 8, 6), voxel_mm=(20.0, 25.0, 30.0), n_detector=8,
                                                      n_train=2, n_val=1))
    run = types.SimpleNamespace(model=None, volume=scene.image, scene=scene, config=types.SimpleNamespace(method="fdk"))
    export_volume(run, tmp_path)
    nii = nib.load(str(tmp_path / "attenuation.nii.gz"))
    np.testing.assert_allclose(nii.affine, volume_affine(scene.geometry), atol=1e-6)
    mha = itk.imread(str(tmp_path / "attenuation.mha"), itk.F)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in scene.image.shape], indexing="ij"), -1).reshape(-1, 3)
    ras = (nii.affine @ np.c_[idx, np.ones(len(idx))].T)[:3].T
    np.testing.assert_allclose(sample_itk(mha, ras * np.array([-1.0, -1.0, 1.0])), scene.image.reshape(-1), atol=1e-6)


def test_short_scan_in_any_order_crossing_zero(tmp_path):
    """A 220° scan crossing 0°, views shuffled: the same reconstruction as in order, and the object in place."""
    from kneas_method.classical.fdk import fdk_reconstruct
    from kneas_method.export.volume import nifti_affine

    angles = np.mod(260.0 + np.linspace(0.0, 220.0, 44, endpoint=False), 360.0)
    order = np.random.default_rng(0).permutation(len(angles))
    scenes = []
    for name, a in (("sorted", angles), ("shuffled", angles[order])):
        g = rtk_geometry(a)
        itk.imwrite(rtk_project(g, len(a)), str(tmp_path / f"{name}.mha"))
        write_rtk_xml(g, tmp_path / f"{name}.xml")
        scenes.append(import_scan([str(tmp_path / f"{name}.mha")], tmp_path / f"{name}.xml", volume_size=32))
    a, b = scenes
    assert np.ptp(a.train.angles) == pytest.approx(math.radians(215.0))
    np.testing.assert_allclose(b.train.angles, a.train.angles[order], atol=1e-12)
    np.testing.assert_array_equal(b.train.projections, a.train.projections[order])
    va, vb = fdk_reconstruct(a), fdk_reconstruct(b)
    np.testing.assert_allclose(vb, va, atol=1e-4 * float(va.max()))
    # world position of every voxel -> truth there
    aff = np.diag([-1.0, -1.0, 1.0, 1.0]) @ nifti_affine(a)  # index -> LPS
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in va.shape], indexing="ij"), -1).reshape(-1, 3)
    pts = (aff @ np.c_[idx, np.ones(len(idx))].T)[:3].T
    assert np.corrcoef(truth_at(pts), va.reshape(-1))[0, 1] > 0.8


def test_parallel_beam_geometry(tmp_path):
    """RTK's parallel beam (SourceToDetectorDistance 0) imports as kneas parallel mode, object in place."""
    from kneas_method.classical.fdk import fdk_reconstruct
    from kneas_method.export.volume import nifti_affine

    angles = np.linspace(0.0, 180.0, 60, endpoint=False)
    g = rtk_geometry(angles, sdd=0.0, sy=0.0)
    itk.imwrite(rtk_project(g, len(angles)), str(tmp_path / "par.mha"))
    write_rtk_xml(g, tmp_path / "par.xml")
    scene = import_scan([str(tmp_path / "par.mha")], tmp_path / "par.xml", volume_size=32)
    assert scene.geometry.mode == "parallel"
    vol = fdk_reconstruct(scene)
    aff = np.diag([-1.0, -1.0, 1.0, 1.0]) @ nifti_affine(scene)  # index -> LPS
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in vol.shape], indexing="ij"), -1).reshape(-1, 3)
    pts = (aff @ np.c_[idx, np.ones(len(idx))].T)[:3].T
    truth = truth_at(pts)
    corr = np.corrcoef(truth, vol.reshape(-1))[0, 1]
    assert corr > 0.8 and corr > np.corrcoef(truth_at(pts, (1, 1, -1)), vol.reshape(-1))[0, 1] + 0.4


# --------------------------------------------------------------------------- the way back
def test_export_to_rtk_and_import_again(scan, imported, tmp_path):
    """export --rtk writes what RTK reads as the same scan; importing the export gives the same scene."""
    info = export_rtk(imported, tmp_path / "rtk")
    again = import_scan([info["files"]["projections"]], info["files"]["geometry"], volume_size=48)
    np.testing.assert_array_equal(again.train.projections, imported.train.projections)
    np.testing.assert_allclose(again.train.angles, imported.train.angles, atol=1e-12)
    ga, gb = again.geometry.to_mm(), imported.geometry.to_mm()
    for key in ("DSD", "DSO", "dDetector", "offDetector", "nVoxel", "dVoxel", "offOrigin"):
        np.testing.assert_allclose(ga[key], gb[key], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(again.meta["world_affine_lps"], imported.meta["world_affine_lps"], atol=1e-12)
    # RTK itself: its projector on the exported geometry + detector grid reproduces the exported projections
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(info["files"]["geometry"])
    reader.GenerateOutputInformation()
    exported = itk.imread(info["files"]["projections"], itk.F)
    sim = rtk_project(reader.GetOutputObject(), 72, origin=exported.GetOrigin(), spacing=exported.GetSpacing())
    np.testing.assert_allclose(itk.array_from_image(sim), itk.array_from_image(exported), atol=1e-5)
    np.testing.assert_allclose(itk.array_from_image(exported), scan.p, atol=1e-6)


def test_export_of_a_simulated_scene_round_trips(tmp_path, capsys):
    scene = simulate_phantom("foot", SimulationConfig(n_voxel=12, voxel_mm=20.0, n_detector=16, n_train=5, n_val=3,
                                                      total_angle_deg=360.0))
    path = save_naf(scene, tmp_path / "foot.pickle")
    code, out, _ = run_cli(["export", str(path), "--rtk", str(tmp_path / "rtk"), "--views", "all"], capsys)
    assert code == 0 and "rtkfdk" in out and (tmp_path / "rtk" / "image.mha").is_file()
    back = import_scan([str(tmp_path / "rtk" / "projections.mha")], tmp_path / "rtk" / "geometry.xml")
    both = np.concatenate([scene.train.projections, scene.val.projections])
    np.testing.assert_array_equal(back.train.projections, both)
    np.testing.assert_allclose(np.mod(back.train.angles, 2 * np.pi),
                               np.mod(np.concatenate([scene.train.angles, scene.val.angles]), 2 * np.pi), atol=1e-12)
    np.testing.assert_allclose(back.geometry.to_mm()["offDetector"], scene.geometry.to_mm()["offDetector"], atol=1e-9)
    # the ground truth written for RTK sits in RTK's world where the frame map puts kneas's voxels
    gt = itk.imread(str(tmp_path / "rtk" / "image.mha"), itk.F)
    idx = (3, 7, 5)
    kneas_mm = np.array([float(ax[i]) for ax, i in zip(scene.geometry.voxel_axes(), idx)]) * scene.geometry.mm_per_unit
    world = KNEAS_TO_RTK @ kneas_mm
    assert sample_itk(gt, world[None])[0] == pytest.approx(float(scene.image[idx]), abs=1e-5)


# --------------------------------------------------------------------------- raw counts
def test_counts_with_flat_dark_per_file_and_estimated_i0(scan, imported, tmp_path):
    """Raw counts, one file per projection (natural order), flat/dark fields or I0 from the air border."""
    rng = np.random.default_rng(0)
    p = scan.p  # [N, nV, nU] RTK order
    dark = 100.0 + 5.0 * rng.random(p.shape[1:])
    flat = dark + 3000.0 * (1.0 + 0.2 * np.linspace(0, 1, p.shape[2]))[None, :]  # non-uniform beam
    counts = np.round(dark + (flat - dark) * np.exp(-p)).astype(np.uint16)
    folder = tmp_path / "raw"
    folder.mkdir()
    spacing, origin = scan.image.GetSpacing(), scan.image.GetOrigin()

    def write(arr, path):
        img = itk.image_from_array(np.ascontiguousarray(arr))
        img.SetSpacing([spacing[0], spacing[1]])
        img.SetOrigin([origin[0], origin[1]])
        itk.imwrite(img, str(path))

    for k in range(len(p)):  # p1 .. p72: natural order, not p1, p10, p11, ...
        write(counts[k], folder / f"p{k + 1}.mha")
    write(flat.astype(np.float32), tmp_path / "flat.mha")
    write(dark.astype(np.float32), tmp_path / "dark.mha")
    scene = import_scan([str(folder)], scan.xml, flat=str(tmp_path / "flat.mha"), dark=str(tmp_path / "dark.mha"), volume_size=48)
    assert scene.meta["import"]["conversion"]["kind"] == "counts"
    np.testing.assert_allclose(scene.train.projections, imported.train.projections, atol=2e-3)

    # no flat: I0 from the air around the object (uniform beam here)
    i0 = 4000.0
    counts = rng.poisson(i0 * np.exp(-p)).astype(np.float32)
    img = itk.image_from_array(counts)
    img.SetSpacing(list(spacing))
    img.SetOrigin(list(origin))
    itk.imwrite(img, str(tmp_path / "counts.mha"))
    scene = import_scan([str(tmp_path / "counts.mha")], scan.xml, kind="counts", volume_size=48)
    conv = scene.meta["import"]["conversion"]
    assert conv["i0"] == pytest.approx(i0, rel=5e-3) and "air" in conv["i0_estimated_from"]
    assert abs(float(np.median(scene.train.projections - imported.train.projections))) < 2e-3
    assert scene.train.projections.min() < 0  # Poisson noise in air: kept


def test_kind_detection():
    rng = np.random.default_rng(0)
    p = np.zeros((4, 20, 30))
    p[:, 5:15, 8:22] = 1.0 + rng.random((4, 10, 14))
    assert detect_kind(p) == "line-integrals"
    assert detect_kind(np.exp(-p)) == "normalized"
    assert detect_kind(5000 * np.exp(-p)) == "counts"
    q, info = to_line_integrals(np.exp(-p), "auto")
    np.testing.assert_allclose(q, p, atol=1e-6)
    assert info["kind"] == "normalized" and info["detected"]


def test_tiff_stack_with_pixel_size_given(scan, imported, tmp_path):
    """A TIFF stack carries no detector geometry: --pixel-mm and --centre-detector supply it."""
    stack = itk.image_from_array(np.ascontiguousarray(scan.p.astype(np.float32)))
    itk.imwrite(stack, str(tmp_path / "stack.tif"))
    scene = import_scan([str(tmp_path / "stack.tif")], scan.xml, pixel_mm=[DU, DV], centre_detector=True, volume_size=48)
    np.testing.assert_allclose(scene.train.projections, imported.train.projections, atol=1e-6)
    # centred instead of ORIGIN_UV: the detector offsets differ by exactly the origin's offset from the centre
    off, ref = scene.geometry.to_mm()["offDetector"], imported.geometry.to_mm()["offDetector"]
    np.testing.assert_allclose(np.asarray(ref) - np.asarray(off), [4.0, 2.0], atol=1e-9)


# --------------------------------------------------------------------------- scenes without ground truth, noise
def test_imported_scene_is_a_normal_scene(imported, tmp_path, capsys):
    path = save_naf(imported, tmp_path / "scan.pickle")
    scene = load_naf(path)
    assert scene.image is None and len(scene.val) == 0
    assert scene.meta["import"]["projections"]["count"] == 1 and "world_affine_lps" in scene.meta
    assert len(scene.subsample_views(10).train) == 10
    dm = CTDataManagerConfig(num_object_rays=16, num_air_rays=4).setup(scene=scene, views=10)
    batch = dm.next_train()
    assert batch["origins"].shape == (20, 3) and batch["is_air"].sum() == 4
    code, out, _ = run_cli(["inspect", str(path)], capsys)
    assert code == 0 and "val: 0 views" in out and "image: none" in out and "imported from" in out


def test_noisy_naf_pickle_loads_and_yields_batches(tmp_path):
    cfg = SimulationConfig(n_voxel=12, voxel_mm=20.0, n_detector=24, n_train=4, n_val=2, noise=True, photons=1e4, seed=1)
    scene = simulate_phantom("foot", cfg)
    path = save_naf(scene, tmp_path / "noisy.pickle")
    back = load_naf(path)
    p = back.train.projections
    assert p.min() < 0  # TIGRE-style noise in air: negative values, kept
    np.testing.assert_array_equal(p, scene.train.projections)
    threshold, sigma = noise_air_threshold(p)
    assert 0 < threshold < 0.2 and sigma == pytest.approx(1 / math.sqrt(1e4), rel=0.3)
    dm = CTDataManagerConfig(num_object_rays=32, num_air_rays=16).setup(scene=back, seed=0)
    assert dm.air_threshold == threshold and dm.notes and "noisy" in dm.notes[0]
    for _ in range(4):
        batch = dm.next_train()
        obj = batch["projections"][~batch["is_air"]]
        air = batch["projections"][batch["is_air"]]
        assert len(obj) == 32 and len(air) == 16
        assert float(obj.min()) > threshold and float(air.max()) <= threshold
    # noise-free data keep SPEC §1's split exactly: air is p == 0
    clean = simulate_phantom("foot", SimulationConfig(**{**cfg.to_dict(), "noise": False}))
    assert noise_air_threshold(clean.train.projections) == (0.0, 0.0)


# --------------------------------------------------------------------------- DICOM volumes
@pytest.fixture
def keep_locale():
    """GDCM's DICOM writer sets the process locale to "C" (ASCII text files from then on); put it back."""
    import locale

    saved = locale.setlocale(locale.LC_ALL)
    yield
    locale.setlocale(locale.LC_ALL, saved)


def test_simulate_from_a_dicom_series(tmp_path, capsys, keep_locale):
    hu = np.full((6, 7, 8), -1000, np.int16)  # ITK order [z, y, x]
    hu[1:5, 2:6, 2:7] = 400
    folder = tmp_path / "series"
    folder.mkdir()
    for k in range(hu.shape[0]):
        s = itk.image_from_array(np.ascontiguousarray(hu[k]))
        s.SetSpacing([5.0, 6.0])
        d = s.GetMetaDataDictionary()
        d["0020|0032"] = f"0\\0\\{8.0 * k}"
        d["0020|0037"] = "1\\0\\0\\0\\1\\0"
        d["0020|000e"] = "1.2.826.0.1.3680043.2.1125.1"
        d["0020|000d"] = "1.2.826.0.1.3680043.2.1125.2"
        d["0020|0013"] = str(k + 1)
        io = itk.GDCMImageIO.New()
        io.KeepOriginalUIDOn()
        itk.imwrite(s, str(folder / f"slice{k:02d}.dcm"), imageio=io)
    out = tmp_path / "ct.pickle"
    code, _, err = run_cli(["simulate", "--volume", str(folder), "--convert", "-o", str(out), "--n-detector", "12",
                            "--views", "3", "--n-val", "1"], capsys)
    assert code == 0, err
    scene = load_naf(out)
    assert scene.image.shape == (8, 7, 6)  # [x, y, z]
    np.testing.assert_allclose(scene.geometry.to_mm()["dVoxel"], [5.0, 6.0, 8.0])
    assert scene.image[4, 3, 2] == pytest.approx(1.0) and scene.image[0, 0, 0] == 0.0


# --------------------------------------------------------------------------- what is refused, in one line
def _xml(tmp_path, body, name="g.xml", version=3):
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0"?>\n<RTKThreeDCircularGeometry version="{version}">\n{body}\n</RTKThreeDCircularGeometry>\n')
    return path


def _projections(n):
    return "".join(f"<Projection><GantryAngle>{a}</GantryAngle></Projection>" for a in np.linspace(0, 360, n, endpoint=False))


BASE = "<SourceToIsocenterDistance>400</SourceToIsocenterDistance><SourceToDetectorDistance>600</SourceToDetectorDistance>"
REFUSED = [
    ("tilt", BASE + "<InPlaneAngle>2</InPlaneAngle>" + _projections(72), "InPlaneAngle is 2 deg; kneas supports only untilted"),
    ("out of plane", BASE + "<OutOfPlaneAngle>-1.5</OutOfPlaneAngle>" + _projections(72), "OutOfPlaneAngle is -1.5 deg"),
    ("source offset x", BASE + "<SourceOffsetX>4</SourceOffsetX>" + _projections(72), "SourceOffsetX is 4 mm"),
    ("varying SID", "<SourceToDetectorDistance>600</SourceToDetectorDistance>" + "".join(
        f"<Projection><GantryAngle>{5 * k}</GantryAngle><SourceToIsocenterDistance>{400 + (k == 9)}</SourceToIsocenterDistance></Projection>"
        for k in range(72)), r"SourceToIsocenterDistance differs between projections \(400 in projection 0, 401 in projection 9\)"),
    ("cylindrical", BASE + "<RadiusCylindricalDetector>900</RadiusCylindricalDetector>" + _projections(72), "cylindrical detectors"),
    ("count mismatch", BASE + _projections(70), "72 projection images but g.xml describes 70 projections"),
    ("old version", BASE + _projections(72), "version '1' is not supported"),
    ("not xml", None, "is not readable XML"),
    ("wrong root", None, "not <RTKThreeDCircularGeometry>"),
    ("bad matrix", BASE + "<Projection><GantryAngle>0</GantryAngle><Matrix>1 2 3 4 5 6 7 8 9 10 11 12</Matrix></Projection>",
     "the <Matrix> of projection 0 disagrees with its parameters"),
]


@pytest.mark.parametrize("case,body,message", REFUSED, ids=[r[0] for r in REFUSED])
def test_refused_geometries_are_one_line_errors(scan, tmp_path, capsys, case, body, message):
    if case == "not xml":
        xml = tmp_path / "g.xml"
        xml.write_text("<RTKThreeDCircularGeometry version='3'><Projection>")
    elif case == "wrong root":
        xml = tmp_path / "g.xml"
        xml.write_text("<?xml version='1.0'?><Geometry/>")
    else:
        xml = _xml(tmp_path, body, version=1 if case == "old version" else 3)
    code, out, err = run_cli(["import", str(scan.proj), "--geometry", str(xml), "-o", str(tmp_path / "s.pickle")], capsys)
    assert code == 2 and "Traceback" not in err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    import re

    assert re.search(message, " ".join(err.split())), err
    assert not (tmp_path / "s.pickle").exists()


def test_pixel_spacing_in_metres_is_refused_with_the_fix(scan, tmp_path, capsys):
    """Pixel sizes written in metres make a detector a thousand times too small: refused, naming --pixel-mm."""
    stack = itk.image_from_array(np.ascontiguousarray(scan.p.astype(np.float32)))
    itk.imwrite(stack, str(tmp_path / "stack.tif"))
    argv = ["import", str(tmp_path / "stack.tif"), "--geometry", str(scan.xml), "--centre-detector", "--volume-size", "16",
            "-o", str(tmp_path / "s.pickle")]
    code, _, err = run_cli([*argv, "--pixel-mm", str(DU / 1000), str(DV / 1000)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "probably in metres" in err and f"--pixel-mm {DU:.4g} {DV:.4g}" in err and not (tmp_path / "s.pickle").exists()
    code, _, err = run_cli([*argv, "--pixel-mm", str(DU), str(DV)], capsys)  # in mm it imports
    assert code == 0, err


def test_stack_with_the_projection_axis_elsewhere_says_so(scan, tmp_path, capsys):
    """A stack written with the projection index on an image axis: the count error says which axis to move."""
    moved = itk.image_from_array(np.ascontiguousarray(np.transpose(scan.p, (2, 1, 0)).astype(np.float32)))
    itk.imwrite(moved, str(tmp_path / "moved.mha"))
    code, _, err = run_cli(["import", str(tmp_path / "moved.mha"), "--geometry", str(scan.xml), "-o", str(tmp_path / "s.pickle")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    msg = " ".join(err.split())
    assert f"{NU} projection images but geometry.xml describes 72 projections" in msg
    assert "one of the image axes has 72 entries" in msg and "[projection, v, u]" in msg


def test_output_under_a_file_is_refused_before_reading(scan, tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    code, _, err = run_cli(["import", str(scan.proj), "--geometry", str(scan.xml), "-o", str(blocker / "s.pickle")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"{blocker} is a file, not a folder" in " ".join(err.split()), err


def test_counts_without_air_or_flat_ask_for_flat_or_i0(scan, tmp_path, capsys):
    """Raw counts whose border is not air: kneas cannot find I0 and says how to give it."""
    ramp = np.linspace(0.5, 8.0, NU)[None, None, :]  # an object over the whole detector
    counts = (4000.0 * np.exp(-(scan.p + ramp))).astype(np.float32)
    img = itk.image_from_array(counts)
    itk.imwrite(img, str(tmp_path / "counts.mha"))
    code, _, err = run_cli(["import", str(tmp_path / "counts.mha"), "--geometry", str(scan.xml), "--kind", "counts",
                            "-o", str(tmp_path / "s.pickle")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--flat FLAT" in err and "--i0 VALUE" in err
    # with --i0 it imports
    code, out, err = run_cli(["import", str(tmp_path / "counts.mha"), "--geometry", str(scan.xml), "--i0", "4000",
                              "--volume-size", "16", "-o", str(tmp_path / "s.pickle")], capsys)
    assert code == 0, err
    np.testing.assert_allclose(load_naf(tmp_path / "s.pickle").train.projections[:, ::-1], scan.p + ramp, atol=1e-4)


def test_bad_files_are_one_line_errors(scan, tmp_path, capsys):
    cases = [
        (["import", str(tmp_path / "missing.mha"), "--geometry", str(scan.xml)], "no such file or folder"),
        (["import", str(tmp_path / "*.nothing"), "--geometry", str(scan.xml)], "matches no files"),
        (["import", str(scan.proj), "--geometry", str(tmp_path / "missing.xml")], "no such geometry file"),
    ]
    (tmp_path / "broken.mha").write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementDataFile = nowhere.raw\n")
    cases.append((["import", str(tmp_path / "broken.mha"), "--geometry", str(scan.xml)], "ITK cannot read it"))
    for argv, message in cases:
        code, _, err = run_cli([*argv, "-o", str(tmp_path / "s.pickle")], capsys)
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_truncated_file_says_so_in_one_line(scan, tmp_path, capfd):
    """A projection file cut short: ITK's reader prints its reason on the C++ stderr and raises an
    exception that blames the path; the error is one line that says the file is truncated, and
    nothing of ITK's own output reaches the terminal."""
    data = scan.proj.read_bytes()
    (tmp_path / "cut.mha").write_bytes(data[: len(data) // 2])
    with pytest.raises(SystemExit) as info:
        cli.main(["import", str(tmp_path / "cut.mha"), "--geometry", str(scan.xml), "-o", str(tmp_path / "s.pickle")])
    err = capfd.readouterr().err
    assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert "cut.mha: ITK cannot read it" in err and "truncated" in err and "No such file" not in err, err


def test_missing_itk_is_one_line(scan, tmp_path, monkeypatch, capsys):
    real_import = builtins.__import__

    def no_itk(name, *args, **kwargs):
        if name == "itk" or name.startswith("itk."):
            raise ImportError("No module named 'itk'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_itk)
    code, _, err = run_cli(["import", str(scan.proj), "--geometry", str(scan.xml), "-o", str(tmp_path / "s.pickle")], capsys)
    assert code == 2 and "pip install 'kneas[scanner]'" in err and len(err.strip().splitlines()) == 1
    scene = simulate_phantom("foot", SimulationConfig(n_voxel=8, voxel_mm=30.0, n_detector=8, n_train=2, n_val=1))
    with pytest.raises(KneasError, match=r"pip install 'kneas\[scanner\]'"):
        export_rtk(scene, tmp_path / "rtk")


def test_loader_names_what_is_clearly_not_line_integrals(imported, tmp_path):
    from kneas_method.data.naf import check_line_integrals

    p = imported.train.projections
    check_line_integrals(p - 0.01, "scan", "train.projections")  # a small negative offset (noise/I0): fine
    with pytest.raises(SceneError, match="far below 0"):
        check_line_integrals(-p - 0.2, "scan", "train.projections")
    bad = p.copy()
    bad[:, :8] = -2.0
    with pytest.raises(SceneError, match="wildly negative"):
        check_line_integrals(bad, "scan", "train.projections")
    with pytest.raises(SceneError, match="NaN/inf"):
        check_line_integrals(np.full(p.shape, np.nan, np.float32), "scan", "train.projections")
    assert isinstance(imported, Scene)


def test_nan_or_inf_pixels_are_refused_naming_the_views(scan, tmp_path, capsys):
    p = scan.p.astype(np.float32).copy()
    p[3, 5, 7], p[40, 0, 0] = np.nan, np.inf
    itk.imwrite(itk.image_from_array(p), str(tmp_path / "nan.mha"))
    code, _, err = run_cli(["import", str(tmp_path / "nan.mha"), "--geometry", str(scan.xml), "-o", str(tmp_path / "s.pickle")], capsys)
    msg = " ".join(err.split())
    assert code == 2 and len(err.strip().splitlines()) == 1 and "2 NaN/inf pixels in 2 of 72 projections (indices 3, 40" in msg, err
    assert not (tmp_path / "s.pickle").exists()


def test_an_i0_below_the_airs_counts_is_refused_with_the_fix(scan, tmp_path, capsys):
    counts = (61000.0 * np.exp(-scan.p)).astype(np.float32)
    itk.imwrite(itk.image_from_array(counts), str(tmp_path / "counts.mha"))
    argv = ["import", str(tmp_path / "counts.mha"), "--geometry", str(scan.xml), "--volume-size", "16", "-o", str(tmp_path / "s.pickle")]
    code, _, err = run_cli([*argv, "--i0", "1000"], capsys)
    msg = " ".join(err.split())
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--i0 1000 is below the counts at the projections' border" in msg, err
    assert "leave --i0 out" in msg and "geometry:" not in msg
    code, _, err = run_cli([*argv, "--i0", "61000"], capsys)  # the right one imports
    assert code == 0, err


def test_a_forced_kind_the_values_contradict_is_warned_about(scan, tmp_path, capsys):
    intensities = np.exp(-scan.p).astype(np.float32)
    itk.imwrite(itk.image_from_array(intensities), str(tmp_path / "norm.mha"))
    argv = ["import", str(tmp_path / "norm.mha"), "--geometry", str(scan.xml), "--volume-size", "16", "-o", str(tmp_path / "s.pickle")]
    code, out, err = run_cli([*argv, "--kind", "line-integrals"], capsys)
    assert code == 0, err
    warning = [line for line in out.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "--kind line-integrals" in warning[0] and "read as normalized" in " ".join(out.split())
    code, out, err = run_cli([*argv, "--kind", "normalized"], capsys)  # the kind they are: no warning
    assert code == 0 and "warning:" not in out, out


def test_a_detector_without_pixel_size_or_origin_is_refused_naming_the_flags(scan, tmp_path, capsys):
    """A TIFF stack carries no pixel size or origin: read as 1 mm pixels from the central ray, the field
    of view every view sees is a sliver; refused, naming --pixel-mm and --centre-detector."""
    itk.imwrite(itk.image_from_array(np.ascontiguousarray(scan.p.astype(np.float32))), str(tmp_path / "stack.tif"))
    short = tmp_path / "short.xml"  # a short scan (200°), whose field of view is the part of the detector on both sides
    write_rtk_xml(rtk_geometry(np.linspace(0.0, 200.0, len(scan.angles)), px=0.0), short)
    argv = ["import", str(tmp_path / "stack.tif"), "--geometry", str(short), "--volume-size", "16", "-o", str(tmp_path / "s.pickle")]
    code, _, err = run_cli(argv, capsys)
    msg = " ".join(err.split())
    assert code == 2 and len(err.strip().splitlines()) == 1 and "the field of view every projection sees is" in msg, err
    assert "--pixel-mm and --centre-detector" in msg and not (tmp_path / "s.pickle").exists()
    code, _, err = run_cli([*argv, "--pixel-mm", str(DU), str(DV), "--centre-detector"], capsys)
    assert code == 0, err


def test_the_scene_is_named_after_its_pickle(scan, tmp_path, capsys):
    code, _, err = run_cli(["import", str(scan.proj), "--geometry", str(scan.xml), "--volume-size", "16",
                            "-o", str(tmp_path / "myknee.pickle")], capsys)
    assert code == 0, err
    assert load_naf(tmp_path / "myknee.pickle").name == "myknee"


def test_rtk_export_to_a_folder_that_cannot_be_made_is_one_line(imported, tmp_path, capsys):
    save_naf(imported, tmp_path / "scan.pickle")
    (tmp_path / "afile").write_text("x")
    code, _, err = run_cli(["export", str(tmp_path / "scan.pickle"), "--rtk", str(tmp_path / "afile" / "rtk")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "is a file, not a folder; choose another with --rtk" in " ".join(err.split()), err


def test_repeated_angles_and_a_limited_arc_are_named_in_notes(scan, imported, tmp_path):
    assert not [n for n in imported.meta["import"]["notes"] if "angle" in n]  # a full orbit: nothing to say
    short = tmp_path / "short.xml"  # a short scan of 200 deg across 0 deg: enough for this fan (about 27 deg)
    write_rtk_xml(rtk_geometry(np.mod(np.linspace(300.0, 500.0, len(scan.angles)), 360.0)), short)
    notes = import_scan([str(scan.proj)], short, volume_size=16).meta["import"]["notes"]
    assert not [n for n in notes if "limited-angle" in n or "repeat" in n], notes
    limited = tmp_path / "limited.xml"  # 36 angles over 86 deg, each twice
    half = np.linspace(0.0, 86.0, len(scan.angles) // 2)
    write_rtk_xml(rtk_geometry(np.repeat(half, 2)), limited)
    notes = " ".join(import_scan([str(scan.proj)], limited, volume_size=16).meta["import"]["notes"])
    assert "36 of the 72 projections repeat another's angle" in notes and "span 86.0 deg" in notes and "limited-angle" in notes
