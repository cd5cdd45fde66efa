"""User volumes: .npy, NIfTI, .mat, HU conversion and normalisation."""

import numpy as np
import pytest
import scipy.io

from kneas_method.data.volume_io import MU_WATER_PER_M, hu_to_mu, load_volume
from kneas_method.errors import SceneError


def hu_volume():
    """Air (-1000 HU) with a water cube (0 HU) and a bone cube (+1000 HU)."""
    v = np.full((6, 7, 5), -1000.0, np.float32)
    v[1:3, 1:3, 1:3] = 0.0
    v[3:5, 4:6, 2:4] = 1000.0
    return v


def test_hu_to_mu_follows_naf():
    mu = hu_to_mu(np.array([-1000.0, 0.0, 1000.0, -1500.0]))
    np.testing.assert_allclose(mu, [0.0, MU_WATER_PER_M, 2 * MU_WATER_PER_M, 0.0])
    # raw = (HU - intercept) / slope
    np.testing.assert_allclose(hu_to_mu(np.array([24.0]), rescale_slope=0.5, rescale_intercept=-12.0), [MU_WATER_PER_M])


def test_npy_plain_and_normalised(tmp_path):
    raw = np.random.default_rng(0).random((5, 6, 7)).astype(np.float64) * 3
    np.save(tmp_path / "v.npy", raw)
    vol, voxel = load_volume(tmp_path / "v.npy")
    assert vol.dtype == np.float32 and vol.shape == (5, 6, 7) and voxel is None
    assert vol.max() == pytest.approx(1.0)
    np.testing.assert_allclose(vol, raw / raw.max(), rtol=1e-6)
    vol2, _ = load_volume(tmp_path / "v.npy", normalize=False)
    np.testing.assert_allclose(vol2, raw, rtol=1e-6)


def test_npy_hu_conversion(tmp_path):
    np.save(tmp_path / "hu.npy", hu_volume())
    vol, _ = load_volume(tmp_path / "hu.npy", convert=True, normalize=False)
    assert vol[0, 0, 0] == 0.0
    assert vol[1, 1, 1] == pytest.approx(MU_WATER_PER_M)
    assert vol[3, 4, 2] == pytest.approx(2 * MU_WATER_PER_M)
    norm, _ = load_volume(tmp_path / "hu.npy", convert=True)
    assert norm.max() == pytest.approx(1.0) and norm[1, 1, 1] == pytest.approx(0.5)
    # negative values without --convert: a one-line error that suggests --convert
    with pytest.raises(SceneError, match="negative values.*--convert"):
        load_volume(tmp_path / "hu.npy")


def test_nifti_spacing_and_conversion(tmp_path):
    import nibabel as nib  # a dev dependency
    raw = (hu_volume() + 1024.0).astype(np.int16)  # scanner values with intercept -1024
    img = nib.Nifti1Image(raw, affine=np.diag([0.8, 0.9, 2.5, 1.0]))
    img.header.set_xyzt_units("mm")
    nib.save(img, tmp_path / "ct.nii.gz")
    vol, voxel = load_volume(tmp_path / "ct.nii.gz", convert=True, rescale_intercept=-1024.0, normalize=False)
    assert voxel == pytest.approx((0.8, 0.9, 2.5))
    assert vol.shape == (6, 7, 5)
    assert vol[1, 1, 1] == pytest.approx(MU_WATER_PER_M) and vol[0, 0, 0] == 0.0
    nib.save(nib.Nifti1Image(np.ones((3, 3, 3), np.float32), np.eye(4)), tmp_path / "plain.nii")
    vol, voxel = load_volume(tmp_path / "plain.nii")
    assert vol.shape == (3, 3, 3) and voxel == pytest.approx((1.0, 1.0, 1.0))


def test_mat_img_key_single_array_and_explicit_key(tmp_path):
    v = np.arange(24, dtype=np.float64).reshape(2, 3, 4) + 1
    scipy.io.savemat(tmp_path / "naf.mat", {"img": v, "other": np.ones((2, 2, 2))})
    vol, voxel = load_volume(tmp_path / "naf.mat", normalize=False)
    np.testing.assert_allclose(vol, v)
    assert voxel is None
    scipy.io.savemat(tmp_path / "one.mat", {"ct": v, "note": np.ones(3)})
    vol, _ = load_volume(tmp_path / "one.mat", normalize=False)
    np.testing.assert_allclose(vol, v)
    scipy.io.savemat(tmp_path / "two.mat", {"a": v, "b": v * 2})
    with pytest.raises(SceneError, match="2 3-D arrays.*--key"):
        load_volume(tmp_path / "two.mat")
    vol, _ = load_volume(tmp_path / "two.mat", key="b", normalize=False)
    np.testing.assert_allclose(vol, v * 2)
    with pytest.raises(SceneError, match="no variable 'c'; it has: a, b"):
        load_volume(tmp_path / "two.mat", key="c")
    scipy.io.savemat(tmp_path / "hu.mat", {"img": hu_volume()})
    vol, _ = load_volume(tmp_path / "hu.mat", convert=True)
    assert vol.max() == pytest.approx(1.0) and vol[1, 1, 1] == pytest.approx(0.5)


def test_volume_errors(tmp_path):
    with pytest.raises(SceneError, match="no such file"):
        load_volume(tmp_path / "missing.npy")
    (tmp_path / "v.raw").write_bytes(b"\0" * 8)
    with pytest.raises(SceneError, match="unsupported volume format '.raw'"):
        load_volume(tmp_path / "v.raw")
    np.save(tmp_path / "flat.npy", np.ones((4, 4)))
    with pytest.raises(SceneError, match="must be 3-D"):
        load_volume(tmp_path / "flat.npy")
    np.save(tmp_path / "nan.npy", np.full((2, 2, 2), np.nan))
    with pytest.raises(SceneError, match="NaN"):
        load_volume(tmp_path / "nan.npy")
    np.save(tmp_path / "zero.npy", np.zeros((2, 2, 2)))
    with pytest.raises(SceneError, match="all zero"):
        load_volume(tmp_path / "zero.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(SceneError, match="Python objects"):
        load_volume(tmp_path / "obj.npy")
    (tmp_path / "bad.nii.gz").write_bytes(b"garbage")
    with pytest.raises(SceneError, match="not a readable NIfTI"):
        load_volume(tmp_path / "bad.nii.gz")
    (tmp_path / "bad.mat").write_bytes(b"garbage")
    with pytest.raises(SceneError, match="not a readable .mat"):
        load_volume(tmp_path / "bad.mat")
