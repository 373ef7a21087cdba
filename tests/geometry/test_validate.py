"""validate_intrinsics against the image: principal point inside it (refused outside, warned off
centre) and a K calibrated at another resolution rescaled with the pixel-centre convention."""

import warnings

import numpy as np
import pytest

from threept_jax.geometry.validate import scale_intrinsics, validate_intrinsics


def _K(fx, fy, cx, cy, s=0.0):
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def test_rescaled_to_the_image_with_pixel_centres_at_integers():
    # Calibrated at 1280x960, images resized to 640x480 (s = 0.5). Pixel centre u = 700 lies
    # 700.5 px right of the left image edge, i.e. 350.25 px after halving, whose centre
    # coordinate is 349.75; likewise v = 100 -> 100.5 / 2 - 0.5 = 49.75.
    K = _K(1000.0, 1010.0, 700.0, 100.0, s=2.0)
    want = _K(500.0, 505.0, 349.75, 49.75, s=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (49.75 + 0.5) / 480 is off centre: warned, not here
        got = validate_intrinsics(K, image_hw=(480, 640), calibration_hw=(960, 1280))
    np.testing.assert_allclose(got, want, atol=1e-12)
    # The image centre stays the image centre: (639.5, 479.5) at 1280x960 -> (319.5, 239.5).
    centred = validate_intrinsics(_K(1000.0, 1000.0, 639.5, 479.5), image_hw=(480, 640),
                                  calibration_hw=(960, 1280))
    np.testing.assert_allclose(centred[:2, 2], [319.5, 239.5], atol=1e-12)
    # Upscaling by 3 along x only: cx' = (10 + 0.5) * 3 - 0.5 = 31.
    np.testing.assert_allclose(scale_intrinsics(_K(5.0, 5.0, 10.0, 10.0), (20, 20), (20, 60)),
                               _K(15.0, 5.0, 31.0, 10.0), atol=1e-12)


def test_k_of_a_larger_image_is_refused_and_names_the_calibration_size():
    # A K calibrated on 1280x960 frames used on 640x480 images: the principal point
    # (651, 489) lies beyond the right and bottom edges of the smaller image.
    K = _K(1000.0, 1000.0, 651.0, 489.0)
    with pytest.raises(ValueError, match=r"outside the 640x480 image.*calibration"):
        validate_intrinsics(K, "camera 0 K", image_hw=(480, 640))
    with pytest.raises(ValueError, match="outside"):
        validate_intrinsics(_K(100.0, 100.0, -3.0, 240.0), image_hw=(480, 640))
    got = validate_intrinsics(K, image_hw=(480, 640), calibration_hw=(960, 1280))
    np.testing.assert_allclose(got[:2, 2], [325.25, 244.25], atol=1e-12)  # 651.5 / 2 - 0.5


def test_off_centre_principal_point_warns_and_a_centred_one_does_not():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        validate_intrinsics(_K(500.0, 500.0, 330.0, 250.0), image_hw=(480, 640))
    # (600 + 0.5) / 640 = 0.94 of the width: inside the image but outside 20-80%.
    with pytest.warns(UserWarning, match="20-80%"):
        validate_intrinsics(_K(500.0, 500.0, 600.0, 240.0), image_hw=(480, 640))
    # A K for an image exactly twice the size has its principal point on the image corner.
    with pytest.warns(UserWarning, match="20-80%"):
        validate_intrinsics(_K(1000.0, 1000.0, 639.5, 479.5), image_hw=(480, 640))


def test_calibration_size_that_changes_the_aspect_ratio_warns():
    with pytest.warns(UserWarning, match="aspect"):
        got = validate_intrinsics(_K(1000.0, 1000.0, 639.5, 359.5), image_hw=(480, 640),
                                  calibration_hw=(720, 1280))
    # Per axis: sx = 0.5, sy = 480 / 720.
    np.testing.assert_allclose(got, _K(500.0, 1000.0 * 2 / 3, 319.5, 360 * 2 / 3 - 0.5),
                               atol=1e-9)
    with pytest.raises(ValueError, match="calibration size must be two positive integers"):
        validate_intrinsics(_K(1.0, 1.0, 0.0, 0.0), image_hw=(480, 640), calibration_hw=(0, 640))
