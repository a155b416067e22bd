"""Leica's lens extension of E57 pinhole images
(http://www.libe57.org/E57_LEICA_Camera_Distortion.txt, written by Leica's software for the BLK
cameras): the calibrated fx, fy, cx, cy (scaled from the
calibration's image size to the image's) and OpenCV's k1-k3, p1, p2 become the pinhole photo's
§2.2 lens, in place of the nominal focal length with k = 0. A rational lens (k4-k6) is refitted
as §2.2's polynomial when the fit stays within RATIONAL_FIT_MAX_PX of it over the whole image,
checked here by projecting directions through both; otherwise the image is left out, saying why.
"""
from __future__ import annotations

import math
import uuid

import numpy as np
import pytest

from synth_scans import png_bytes
from vasl.readers import LEICA_DISTORTION_URI, RATIONAL_FIT_MAX_PX, read_e57

WIDTH, HEIGHT = 640, 480


def _write(path: str, lenses) -> None:
    """An E57 file of pinhole images only, one per dict of CV_* values in `lenses` (None: no
    extension), each with the nominal pinhole of a 4 mm lens on 10 µm pixels."""
    import pye57
    from pye57 import libe57

    e57 = pye57.E57(path, mode="w")
    imf = e57.image_file
    imf.extensionsAdd("dist", LEICA_DISTORTION_URI)
    png = png_bytes(WIDTH, HEIGHT, b"".join(b"\0" + bytes(3 * WIDTH) for _ in range(HEIGHT)))
    blobs = []
    for i, lens in enumerate(lenses):
        node = libe57.StructureNode(imf)
        node.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
        node.set("name", libe57.StringNode(imf, f"cam{i}"))
        pose = libe57.StructureNode(imf)
        rotation, translation = libe57.StructureNode(imf), libe57.StructureNode(imf)
        for key, v in zip("wxyz", (1.0, 0.0, 0.0, 0.0)):
            rotation.set(key, libe57.FloatNode(imf, v))
        for key, v in zip("xyz", (1.0, 2.0, 1.5)):
            translation.set(key, libe57.FloatNode(imf, v))
        pose.set("rotation", rotation)
        pose.set("translation", translation)
        node.set("pose", pose)
        rep = libe57.StructureNode(imf)
        rep.set("imageWidth", libe57.IntegerNode(imf, WIDTH, 0, 1 << 30))
        rep.set("imageHeight", libe57.IntegerNode(imf, HEIGHT, 0, 1 << 30))
        rep.set("focalLength", libe57.FloatNode(imf, 0.004))
        rep.set("pixelWidth", libe57.FloatNode(imf, 1e-5))
        rep.set("pixelHeight", libe57.FloatNode(imf, 1e-5))
        rep.set("principalPointX", libe57.FloatNode(imf, WIDTH / 2))
        rep.set("principalPointY", libe57.FloatNode(imf, HEIGHT / 2))
        blobs.append(libe57.BlobNode(imf, len(png)))
        rep.set("pngImage", blobs[-1])
        node.set("pinholeRepresentation", rep)
        if lens is not None:
            dist = libe57.StructureNode(imf)
            for key, v in lens.items():
                dist.set(f"dist:CV_{key}", libe57.IntegerNode(imf, v, 0, 1 << 20)
                         if key in ("WIDTH", "HEIGHT") else libe57.FloatNode(imf, float(v)))
            node.set("dist:distortion", dist)
        imf.root()["images2D"].append(node)
    for blob in blobs:
        blob.write(np.frombuffer(png, dtype=np.uint8).copy(), 0, len(png))
    e57.close()


def _project(lens: dict, x: np.ndarray, y: np.ndarray, k456=(0.0, 0.0, 0.0)):
    """OpenCV's projection of normalised directions (x, y) through `lens` (k4-k6 rational)."""
    r2 = x * x + y * y
    radial = (1 + lens["k1"] * r2 + lens["k2"] * r2 ** 2 + lens["k3"] * r2 ** 3) / \
        (1 + k456[0] * r2 + k456[1] * r2 ** 2 + k456[2] * r2 ** 3)
    xd = x * radial + 2 * lens["p1"] * x * y + lens["p2"] * (r2 + 2 * x * x)
    yd = y * radial + lens["p1"] * (r2 + 2 * y * y) + 2 * lens["p2"] * x * y
    return lens["fx_px"] * xd + lens["cx_px"], lens["fy_px"] * yd + lens["cy_px"]


def test_leica_lens_extension_gives_the_pinhole_its_calibrated_lens(tmp_path):
    brown = dict(FX=820.0, FY=818.0, CX=648.0, CY=474.0, K1=-0.12, K2=0.05, K3=-0.01,
                 P1=0.0004, P2=-0.0007, WIDTH=2 * WIDTH, HEIGHT=2 * HEIGHT)
    mild = dict(brown, K4=0.02, K5=0.0, K6=0.0)  # a rational lens a polynomial can follow
    wild = dict(brown, FX=300.0, FY=300.0, K1=0.9, K4=0.95, K5=0.4, K6=0.2)  # wide: it cannot
    path = str(tmp_path / "blk.e57")
    _write(path, [brown, mild, wild, None])
    scan, = read_e57(path)  # images of no scan: a camera-only scan
    cams = {im.name: im for im in scan.images}

    # The calibration's 1280 x 960 intrinsics scaled to the 640 x 480 image; k, p as written.
    lens = cams["cam0"].pinhole
    assert cams["cam0"].problem == ""
    assert lens == pytest.approx(dict(fx_px=410.0, fy_px=409.0, cx_px=324.0, cy_px=237.0,
                                      k1=-0.12, k2=0.05, k3=-0.01, p1=0.0004, p2=-0.0007),
                                 rel=1e-6)
    assert "Leica distortion extension" in cams["cam0"].notes[0]
    # Without the extension: the nominal 4 mm / 10 µm = 400 px and k = 0, as before.
    assert cams["cam3"].pinhole == dict(fx_px=400.0, fy_px=400.0, cx_px=320.0, cy_px=240.0,
                                        k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0)
    # The pose is turned into §2.2's frame whichever lens it has.
    assert cams["cam0"].pose == cams["cam3"].pose

    # The mild rational lens: every direction that lands in the image lands within the stated
    # fit of where the rational model puts it.
    refit = cams["cam1"].pinhole
    assert cams["cam1"].problem == "" and "refitted" in cams["cam1"].notes[0]
    u, v = np.meshgrid(np.linspace(0, WIDTH, 65), np.linspace(0, HEIGHT, 49))
    x = (u.ravel() - refit["cx_px"]) / refit["fx_px"]
    y = (v.ravel() - refit["cy_px"]) / refit["fy_px"]
    fitted = _project(refit, x, y)
    exact_k = dict(refit, k1=-0.12, k2=0.05, k3=-0.01)
    rational = _project(exact_k, x, y, k456=(0.02, 0.0, 0.0))
    worst = float(np.hypot(fitted[0] - rational[0], fitted[1] - rational[1]).max())
    ignored = float(np.hypot(*(np.subtract(_project(exact_k, x, y), rational))).max())
    print(f"\nrational k4 = 0.02 refitted as k1-k3 {refit['k1']:.4f} {refit['k2']:.4f} "
          f"{refit['k3']:.4f}: within {worst:.3f} px over the image; {ignored:.2f} px had k4 "
          "been dropped")
    assert worst <= RATIONAL_FIT_MAX_PX and ignored > 1.0

    # The wild one is left out, saying why.
    assert "rational" in cams["cam2"].problem and cams["cam2"].pinhole is None
    print(f"cam2: {cams['cam2'].problem}")
    assert [im.name for im in scan.ingestible_images] == ["cam0", "cam1", "cam3"]
