"""Shared image / depth / intrinsics loaders: values, colour order, and errors that name the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets.images import (
    decode_color,
    image_size,
    read_color,
    read_confidence,
    read_depth_npy,
    read_depth_png,
    read_intrinsics_txt,
    validate_intrinsics,
)
from voxfusion.core.errors import CaptureError, CaptureFormatError
from voxfusion.core.geometry import make_intrinsics


def test_colour_is_rgb_and_gray_expands(tmp_path: Path):
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 0] = 255  # blue
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    rgb = read_color(tmp_path / "c.png")
    assert rgb.shape == (4, 5, 3) and tuple(rgb[0, 0]) == (0, 0, 255)
    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 5), 7, np.uint8))
    assert tuple(read_color(tmp_path / "g.png")[1, 1]) == (7, 7, 7)
    ok, enc = cv2.imencode(".png", bgr)
    np.testing.assert_array_equal(decode_color(enc.tobytes(), "mem"), rgb)
    assert image_size(tmp_path / "c.png") == (5, 4)
    cv2.imwrite(str(tmp_path / "c16.png"), np.zeros((4, 5, 3), np.uint16))
    with pytest.raises(CaptureFormatError, match="8-bit"):
        read_color(tmp_path / "c16.png")


def test_missing_and_corrupt_files_are_named(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found") as e:
        read_color(tmp_path / "nope.png")
    assert e.value.path == tmp_path / "nope.png"
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    for fn in (read_color, partial_depth, image_size):
        with pytest.raises(CaptureError, match="corrupt") as e:
            fn(tmp_path / "bad.png")
        assert e.value.path == tmp_path / "bad.png"
    with pytest.raises(CaptureError, match="corrupt") as e:
        decode_color(b"xx", "archive.zip/0.jpg")
    assert str(e.value.path) == "archive.zip/0.jpg"


def partial_depth(path: Path) -> np.ndarray:
    return read_depth_png(path, 1000.0)


def test_depth_png_scale_invalid_values_and_bit_depth(tmp_path: Path):
    raw = np.array([[0, 1000, 65535], [2500, 5000, 1]], np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    d = read_depth_png(tmp_path / "d.png", 1000.0, invalid_values=(65535,))
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [[0, 1, 0], [2.5, 5, 0.001]])
    np.testing.assert_allclose(read_depth_png(tmp_path / "d.png", 5000.0)[1, 1], 1.0)
    cv2.imwrite(str(tmp_path / "d8.png"), np.zeros((3, 3), np.uint8))
    with pytest.raises(CaptureFormatError, match="uint16") as e:
        read_depth_png(tmp_path / "d8.png", 1000.0)
    assert e.value.path.name == "d8.png"
    cv2.imwrite(str(tmp_path / "rgb16.png"), np.zeros((3, 3, 3), np.uint16))
    with pytest.raises(CaptureFormatError, match="single-channel"):
        read_depth_png(tmp_path / "rgb16.png", 1000.0)


def test_depth_npy(tmp_path: Path):
    np.save(tmp_path / "mm.npy", np.array([[1500, 0]], np.uint16))
    np.testing.assert_allclose(read_depth_npy(tmp_path / "mm.npy"), [[1.5, 0.0]])
    np.save(tmp_path / "m.npy", np.array([[1.25, np.nan, -2.0]], np.float64))
    d = read_depth_npy(tmp_path / "m.npy")
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [[1.25, 0.0, 0.0]])
    (tmp_path / "bad.npy").write_bytes(b"nope")
    with pytest.raises(CaptureError, match="corrupt"):
        read_depth_npy(tmp_path / "bad.npy")
    np.save(tmp_path / "i.npy", np.zeros((2, 2), np.int32))
    with pytest.raises(CaptureFormatError, match="uint16 or float"):
        read_depth_npy(tmp_path / "i.npy")


def test_confidence_values_checked(tmp_path: Path):
    cv2.imwrite(str(tmp_path / "c.png"), np.array([[0, 1, 2]], np.uint8))
    np.testing.assert_array_equal(read_confidence(tmp_path / "c.png"), [[0, 1, 2]])
    cv2.imwrite(str(tmp_path / "p.png"), np.array([[0, 127, 255]], np.uint8))
    with pytest.raises(CaptureFormatError, match="0/1/2") as e:
        read_confidence(tmp_path / "p.png")
    assert e.value.path.name == "p.png"


def test_intrinsics_files_and_validation(tmp_path: Path):
    p = tmp_path / "k.txt"
    p.write_text("# fx fy cx cy\n500, 501, 320, 240\n")
    np.testing.assert_allclose(read_intrinsics_txt(p), make_intrinsics(500, 501, 320, 240))
    p.write_text("500 0 320\n0 501 240\n0 0 1\n")
    np.testing.assert_allclose(read_intrinsics_txt(p), make_intrinsics(500, 501, 320, 240))
    p.write_text("500 0 320 0\n0 501 240 0\n0 0 1 0\n0 0 0 1\n")
    np.testing.assert_allclose(read_intrinsics_txt(p), make_intrinsics(500, 501, 320, 240))
    p.write_text("500 x 320 240\n")
    with pytest.raises(CaptureFormatError, match="line 1"):
        read_intrinsics_txt(p)
    p.write_text("500 0\n0 501 240\n")
    with pytest.raises(CaptureFormatError, match="different lengths"):
        read_intrinsics_txt(p)
    with pytest.raises(CaptureError, match="not found"):
        read_intrinsics_txt(tmp_path / "none.txt")
    K = make_intrinsics(500, 501, 320, 240)
    np.testing.assert_allclose(validate_intrinsics(K, 640, 480, p), K)
    with pytest.raises(CaptureFormatError, match="principal point") as e:
        validate_intrinsics(K, 200, 150, p)
    assert e.value.path == p
    with pytest.raises(CaptureFormatError, match="focal"):
        validate_intrinsics(make_intrinsics(-1, 1, 1, 1), 4, 4, p)
