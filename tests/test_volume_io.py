"""Loading CT volumes from DICOM series, NIfTI, MHA and NRRD, keeping the physical frame."""

import numpy as np
import pytest
import SimpleITK as sitk
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from appliance.errors import FluorosimError
from appliance.patient.volume_io import load_volume


def ramp_volume():
    """(nz, ny, nx) = (5, 6, 7) int16 HU with a distinct value in every voxel."""
    return (np.arange(5 * 6 * 7, dtype=np.int16).reshape(5, 6, 7) * 7 - 1000)


def sitk_image(arr, spacing=(0.8, 0.9, 2.5), origin=(-10.0, 20.0, 30.0), direction=None):
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    if direction is not None:
        img.SetDirection(direction)
    return img


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".mha", ".nrrd"])
def test_file_formats_keep_hu_and_frame(tmp_path, suffix):
    arr = ramp_volume()
    # rotated 90 degrees about z: voxel i runs along -y... a frame an axis-aligned reader would get wrong
    direction = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    path = tmp_path / f"ct{suffix}"
    sitk.WriteImage(sitk_image(arr, direction=direction), str(path))
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.hu, arr)
    assert vol.hu.dtype == np.int16
    # voxel (i, j, k) = (1, 0, 0) is 0.8 mm along the first direction column (0, 1, 0) from the origin
    p = vol.T_ct_from_voxel @ [1, 0, 0, 1]
    np.testing.assert_allclose(p[:3], [-10.0, 20.8, 30.0], atol=1e-5)
    p = vol.T_ct_from_voxel @ [0, 2, 3, 1]
    np.testing.assert_allclose(p[:3], [-10.0 - 1.8, 20.0, 30.0 + 7.5], atol=1e-5)


def test_float_volume_is_rounded_to_int16(tmp_path):
    arr = ramp_volume().astype(np.float32) + 0.4
    sitk.WriteImage(sitk_image(arr), str(tmp_path / "f.mha"))
    np.testing.assert_array_equal(load_volume(tmp_path / "f.mha").hu, ramp_volume())


def write_series(folder, arr, spacing=2.5, positions=None, slope=1.0, intercept=-1024.0, series_uid=None,
                 rows_override=None, tilt_mm_per_slice=0.0):
    """CT slices with pydicom: stored value = (HU - intercept) / slope, written in shuffled order."""
    folder.mkdir(exist_ok=True)
    series_uid = series_uid or generate_uid()
    study = generate_uid()
    nz = arr.shape[0]
    positions = positions if positions is not None else [100.0 + k * spacing for k in range(nz)]
    for n, k in enumerate(np.random.default_rng(0).permutation(nz)):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(folder / f"{n:03d}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.StudyInstanceUID = study
        ds.SeriesInstanceUID = series_uid
        ds.InstanceNumber = int(k) + 1
        ds.ImagePositionPatient = [-50.0, -40.0 + tilt_mm_per_slice * k, positions[k]]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.9, 0.8]            # row spacing (y), column spacing (x)
        ds.SliceThickness = spacing
        sl = arr[k]
        if rows_override and k == 0:
            sl = np.zeros((rows_override, arr.shape[2]), dtype=arr.dtype)
        ds.Rows, ds.Columns = sl.shape
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.RescaleSlope = slope
        ds.RescaleIntercept = intercept
        ds.PixelData = np.rint((sl.astype(np.float64) - intercept) / slope).astype(np.uint16).tobytes()
        ds.save_as(folder / f"{n:03d}.dcm", enforce_file_format=True)


def test_dicom_series_sorted_by_position_with_rescale(tmp_path):
    arr = ramp_volume()
    write_series(tmp_path / "s", arr, slope=1.0, intercept=-1024.0)
    vol = load_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.hu, arr)
    np.testing.assert_allclose(vol.T_ct_from_voxel @ [0, 0, 0, 1], [-50, -40, 100, 1])
    np.testing.assert_allclose(vol.T_ct_from_voxel @ [1, 1, 1, 1], [-50 + 0.8, -40 + 0.9, 102.5, 1])


def test_dicom_slope_two(tmp_path):
    arr = (ramp_volume() // 2) * 2
    write_series(tmp_path / "s", arr, slope=2.0, intercept=-1000.0)
    np.testing.assert_array_equal(load_volume(tmp_path / "s").hu, arr)


def test_dicom_missing_slice_is_named(tmp_path):
    arr = ramp_volume()
    write_series(tmp_path / "s", arr, positions=[0.0, 2.5, 5.0, 10.0, 12.5])
    with pytest.raises(FluorosimError, match=r"missing slice.*5\.00 and 10\.00"):
        load_volume(tmp_path / "s")


def test_dicom_uneven_spacing(tmp_path):
    write_series(tmp_path / "s", ramp_volume(), positions=[0.0, 2.5, 5.0, 8.6, 11.1])
    with pytest.raises(FluorosimError, match="uneven slice spacing"):
        load_volume(tmp_path / "s")


def test_dicom_mixed_series(tmp_path):
    write_series(tmp_path / "s", ramp_volume())
    write_series(tmp_path / "t", ramp_volume())
    for f in (tmp_path / "t").iterdir():
        f.rename(tmp_path / "s" / ("t" + f.name))
    with pytest.raises(FluorosimError, match="2 DICOM series"):
        load_volume(tmp_path / "s")


def test_dicom_slice_of_another_size(tmp_path):
    write_series(tmp_path / "s", ramp_volume(), rows_override=9)
    with pytest.raises(FluorosimError, match="mixed series"):
        load_volume(tmp_path / "s")


def test_bad_inputs_give_one_line(tmp_path):
    with pytest.raises(FluorosimError, match="no such file"):
        load_volume(tmp_path / "nothing.nii")
    (tmp_path / "broken.nii.gz").write_bytes(b"not a nifti at all")
    with pytest.raises(FluorosimError, match="cannot read"):
        load_volume(tmp_path / "broken.nii.gz")
    (tmp_path / "ct.xyz").write_bytes(b"x")
    with pytest.raises(FluorosimError, match="unknown volume format"):
        load_volume(tmp_path / "ct.xyz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FluorosimError, match="no DICOM images"):
        load_volume(tmp_path / "empty")
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 4), np.int16)), str(tmp_path / "flat.mha"))
    with pytest.raises(FluorosimError, match="2D image"):
        load_volume(tmp_path / "flat.mha")
    with pytest.raises(FluorosimError) as err:
        load_volume(tmp_path / "broken.nii.gz")
    assert "\n" not in str(err.value)


def test_dicom_gantry_tilt_is_refused(tmp_path):
    write_series(tmp_path / "s", ramp_volume(), tilt_mm_per_slice=0.5)
    with pytest.raises(FluorosimError, match="gantry tilt"):
        load_volume(tmp_path / "s")
