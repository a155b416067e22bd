"""Our E57 reader (pye57's libe57) against an independent one: the `e57` package, Python
bindings of the Rust e57 crate (cry-inc). For every file in e57/tiny and e57/real, the scan
count, each scan's record count and pose, the image count and each image's pose agree with the
XML that `e57` reads (`e57.raw_xml`), and the points agree with `e57.read_points`: the same
number of valid points, the same world coordinates (ours are in each scan's frame: its pose
applied here), the same colours (theirs scaled by the file's limits, ours also linearised) and
the same intensities (theirs raw, ours scaled by the limits our reader settled on).

What the bindings do not expose is not compared: they have no image or pose API (poses and
images come from their XML instead) and no per-scan points (read_points concatenates every
scan's valid points, in order, with the poses applied). Every file here reads with pye57, so
read_e57 needs no fallback to `e57`."""
from __future__ import annotations

import glob
import math
import os
import xml.etree.ElementTree as ET

import e57  # the independent reader; deploy/setup.sh installs it (requirements.txt)
import numpy as np
import pytest

from conftest import REPO
from vasl.readers import read_e57, rotation_matrix
from vasl.types import srgb_to_linear


DATA = os.environ.get("VASL_DATA_DIR", os.path.join(REPO, "..", "shared", "data"))
FILES = sorted(glob.glob(os.path.join(DATA, "e57", "tiny", "*.e57"))
               + glob.glob(os.path.join(DATA, "e57", "real", "*.e57")))
NS = "{http://www.astm.org/COMMIT/E57/2010-e57-v1.0}"


def _number(node, key: str, default: float = 0.0) -> float:
    """A numeric child of an E57 XML node (an empty element is 0, as E57 says)."""
    child = node.find(NS + key)
    if child is None:
        return default
    text = (child.text or "").strip()
    if not text:
        return 0.0
    if child.get("type") == "ScaledInteger":
        return float(text) * float(child.get("scale", "1")) + float(child.get("offset", "0"))
    return float(text)


def _xml_pose(node):
    """(translation, unit quaternion x y z w) of an XML node's pose, None without one."""
    pose = node.find(NS + "pose")
    if pose is None:
        return None
    rotation, translation = pose.find(NS + "rotation"), pose.find(NS + "translation")
    w, x, y, z = ((_number(rotation, c) for c in "wxyz") if rotation is not None
                  else (1.0, 0.0, 0.0, 0.0))
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    t = [_number(translation, c) for c in "xyz"] if translation is not None else [0.0] * 3
    return np.array(t), np.array([x, y, z, w]) / norm


def _same_rotation(a, b) -> bool:
    """Two unit quaternions (x, y, z, w) give the same rotation (q and -q do)."""
    return abs(abs(float(np.dot(a, b))) - 1.0) < 1e-9


@pytest.mark.parametrize("path", FILES or [None], ids=[os.path.basename(f) for f in FILES] or
                         ["no-data"])
def test_read_e57_agrees_with_the_e57_package(path):
    if path is None:
        pytest.skip(f"real data not found under {DATA}/e57 (set VASL_DATA_DIR)")
    name = os.path.basename(path)
    root = ET.fromstring(e57.raw_xml(path))
    scans_xml = list(root.find(NS + "data3D") or [])
    images_xml = list(root.find(NS + "images2D") or [])
    ours = read_e57(path)
    with_points = [s for s in ours if s.points is not None]

    # Scans: count, record counts and poses.
    assert len(with_points) == len(scans_xml)
    for scan, node in zip(with_points, scans_xml):
        assert scan.points.records == int(node.find(NS + "points").get("recordCount"))
        pose = _xml_pose(node)
        t, q = pose if pose is not None else (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
        np.testing.assert_allclose(scan.pose.position_m, t, atol=1e-9)
        assert _same_rotation(np.array(scan.pose.quaternion_xyzw), q)

    # Images: count and poses (a pinhole image's pose was turned 180° about x into §2.2's
    # camera frame: turned back here).
    images = {id(im): im for s in ours for im in s.images}
    assert len(images) == len(images_xml)
    for im, node in zip(sorted(images.values(), key=lambda im: _order(im, images_xml)),
                        images_xml):
        pose = _xml_pose(node)
        assert (im.pose is None) == (pose is None), im.name
        if pose is None:
            continue
        q = np.array(im.pose.quaternion_xyzw)
        if im.kind == "pinhole":
            x, y, z, w = q
            q = np.array([w, z, -y, -x])  # q ⊗ (x 180°): −(the stored rotation)
        np.testing.assert_allclose(im.pose.position_m, pose[0], atol=1e-9)
        assert _same_rotation(q, pose[1]), im.name

    # Points: every scan's valid points, in the file's world frame.
    try:
        theirs = e57.read_points(path)
    except BaseException as e:  # the bindings panic (PanicException) on some files
        pytest.fail(f"{name}: the e57 package cannot read it: {e}")
    clouds = [s.cloud for s in with_points]
    world = np.concatenate([c.xyz_m.astype(np.float64) @ rotation_matrix(s.pose.quaternion_xyzw).T
                            + np.asarray(s.pose.position_m) for c, s in zip(clouds, with_points)])
    assert len(world) == len(theirs.points) == sum(s.points.count for s in with_points)
    scale = max(1.0, float(np.abs(theirs.points).max()))
    err = float(np.abs(world - theirs.points).max())
    assert err <= 1e-6 * scale * 4, f"{name}: coordinates differ by {err} m"
    compared = ["scan count", "record counts", "scan poses", "image count", "image poses",
                f"{len(world)} points (max |dx| {err:.2g} m)"]
    if all(c.rgb is not None for c in clouds) and len(theirs.color) == len(world):
        rgb = np.concatenate([c.rgb for c in clouds])
        np.testing.assert_allclose(rgb, srgb_to_linear(theirs.color), atol=2e-6)
        compared.append("colours")
    if all(c.intensity is not None for c in clouds) and len(theirs.intensity) == len(world):
        scaled = np.concatenate([(raw - lo) / (hi - lo) if hi > lo else np.ones_like(raw)
                                 for raw, (lo, hi) in _split_intensity(theirs, with_points)])
        np.testing.assert_allclose(np.concatenate([c.intensity for c in clouds]), scaled,
                                   atol=1e-5)
        compared.append("intensities")
    print(f"\n{name}: agree on {', '.join(compared)}")


def _order(image, nodes) -> int:
    """The index of an image's XML node (by name, then by kind) in images2D."""
    for i, node in enumerate(nodes):
        label = node.find(NS + "name")
        if label is not None and (label.text or "").strip() == image.name:
            return i
    return len(nodes)


def _split_intensity(theirs, scans):
    """The e57 package's raw intensities cut per scan, with each scan's limits."""
    raw = theirs.intensity.ravel().astype(np.float64)
    at = 0
    for scan in scans:
        n = scan.points.count
        yield raw[at:at + n], scan.points.intensity_limits
        at += n
