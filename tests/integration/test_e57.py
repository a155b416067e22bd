"""Real scans from E57 files (../shared/data/e57, or $VASL_DATA_DIR/e57): the client's reader on
real, tiny and malformed files, and a real scan ingested into a real vasld whose render from the
scanner's own position reproduces the measured ranges. Skips, saying so, when the data is absent.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from vasl.readers import read_e57

from conftest import REPO
from synth_scans import equirect_pixels, linear_to_srgb

DATA = os.environ.get("VASL_DATA_DIR", os.path.join(REPO, "..", "shared", "data"))
E57 = os.path.join(DATA, "e57")
PUMP = os.path.join(E57, "real", "pumpAVisualReferenceImage.e57")


def _need(path: str) -> str:
    if not os.path.exists(path):
        pytest.skip(f"real data not found: {path} (set VASL_DATA_DIR to the shared data folder)")
    return path


def test_reads_real_and_tiny_e57():
    pump = read_e57(_need(PUMP))
    assert len(pump) == 1 and pump[0].scan == "pumpAVisualReferenceImage"
    cloud = pump[0].cloud
    assert len(cloud) == 155201
    assert cloud.xyz_m.dtype == np.float32 and np.all(np.isfinite(cloud.xyz_m))
    assert cloud.intensity is not None
    assert 0.0 <= float(cloud.intensity.min()) and float(cloud.intensity.max()) <= 1.0
    print(f"\npump: {len(cloud)} points, range {np.linalg.norm(cloud.xyz_m, axis=1).min():.3f}"
          f"-{np.linalg.norm(cloud.xyz_m, axis=1).max():.3f} m")

    # Spherical coordinates: the converted points lie at the stated ranges, in §2.1's axes.
    import pye57
    path = _need(os.path.join(E57, "tiny", "tiny_spherical.e57"))
    raw = pye57.E57(path).read_scan_raw(0)
    valid = raw["sphericalInvalidState"] == 0
    xyz = read_e57(path)[0].cloud.xyz_m.astype(np.float64)
    assert len(xyz) == int(valid.sum())
    np.testing.assert_allclose(np.linalg.norm(xyz, axis=1), raw["sphericalRange"][valid], rtol=1e-6)
    # Where the elevation lies in the standard (-π/2, π/2), the azimuth comes back as stated
    # (this test file also holds elevations beyond ±π/2, which flip the azimuth by π).
    el = raw["sphericalElevation"][valid]
    standard = np.cos(el) > 1e-3
    assert standard.sum() > 10
    az = np.arctan2(xyz[standard, 1], xyz[standard, 0])
    stated = raw["sphericalAzimuth"][valid][standard]
    np.testing.assert_allclose(np.cos(az - stated), 1.0, atol=1e-5)

    # Points flagged invalid are dropped.
    single = read_e57(_need(os.path.join(E57, "malformed", "cartesian_invalid_state_single.e57")))
    assert len(single[0].cloud) == 1


def test_e57_images_are_read_with_their_kind_and_pose_or_a_reason(server):
    """images2D: every image of a file is read with its kind, size and pose (a pinhole image's
    turned into §2.2's frame); one that cannot be ingested says why, and never stops its scan;
    a visual reference is kept with its scan."""
    pump = read_e57(_need(PUMP))[0]
    assert [(im.kind, im.width, im.height) for im in pump.images] == [("visual", 3072, 2304)]
    assert pump.images[0].problem == ""  # kept with the scan as a visual reference
    assert pump.images[0].data[:2] == b"\xff\xd8"  # its JPEG, read whole

    path = _need(os.path.join(E57, "tiny", "tiny_pc_and_images.e57"))
    scan = read_e57(path)[0]
    kinds = {im.kind: im for im in scan.images}
    assert sorted(kinds) == ["cylindrical", "pinhole", "spherical", "visual"]
    sph = kinds["spherical"]
    # Its stored rotation (w 0.5, x 1) is not a unit quaternion: normalised, and said so.
    assert sph.pose is not None and sph.notes and "normalised" in sph.notes[0]
    np.testing.assert_allclose(sph.pose.position_m, (1.0, 2.0, 3.0))
    np.testing.assert_allclose(sph.pose.quaternion_xyzw, (1 / math.sqrt(1.25), 0, 0,
                                                          0.5 / math.sqrt(1.25)), atol=1e-12)
    # 100 px of 0.0314 rad: half the sphere, sent as that part of it, centred (E57 spherical
    # images are centred on the camera's x axis).
    assert sph.problem == "" and sph.sphere == {"width_px": 200, "height_px": 100,
                                                "left_px": 50, "top_px": 0}
    assert "part of a 200x100 panorama of the sphere" in sph.notes[1]
    # Its cylinder is read (resampled by the server), but this writer's blob is zeros.
    assert kinds["cylindrical"].cylinder is not None
    assert "neither a JPEG nor a PNG" in kinds["cylindrical"].problem
    assert "neither a JPEG nor a PNG" in kinds["pinhole"].problem  # this writer's blob is zeros
    assert [im.kind for im in scan.ingestible_images] == ["spherical", "visual"]
    for im in scan.images:
        print(f"\n{im.name} ({im.kind} {im.width}x{im.height}): {im.problem}")

    # The CLI says so for each image and still ingests the scan's points.
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address,
                        "project", "create", "e57-images", "--vossel-size", "0.05"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "ingest",
                        "--project", "e57-images", "--quiet", path],
                       capture_output=True, text=True, timeout=300)
    print(r.stdout)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("not ingested") == 2
    assert "image 'visual' (visual): kept with the scan as a visual reference" in r.stdout
    assert "tiny_pc_and_images: version 1, 2 points" in r.stdout
    from vasl import Client
    with Client(server.address) as c:
        listed = c.list_scans("e57-images")[0]
        assert [v.name for v in listed.visual_references] == ["visual"]
        np.testing.assert_allclose(listed.visual_references[0].pose.position_m,
                                   listed.pose.position_m)  # no pose of its own: the scan's


@pytest.mark.parametrize("name", ["corrupt_crc.e57", "empty.e57", "empty_pc.e57",
                                  "lib-InvalidCVHeader.e57", "lib-ZeroPoints.e57",
                                  "lib-ZeroPointsInvalid.e57", "lib-bad-crc.e57"])
def test_malformed_e57_is_a_clear_value_error(name):
    path = _need(os.path.join(E57, "malformed", name))
    with pytest.raises(ValueError) as err:
        read_e57(path)
    assert path in str(err.value)
    print(f"\n{name}: {err.value}")


def test_real_e57_render_from_scanner_reproduces_ranges(server, client, tmp_path):
    """VASL-MODEL §8 on real data: rendered from the scanner's own position, the depth of the
    pixel each measured point falls in equals that point's range within two vossels for most
    points (the rest sit behind nearer points of the same pixel, or on silhouettes, where a
    pixel-centre ray can pass beside a one-vossel-thin structure its point hit)."""
    _need(PUMP)
    vossel_m = 0.02
    client.create_project("pump", vossel_size_m=vossel_m)
    cli = [sys.executable, "-m", "vasl.cli", "--server", server.address]
    r = subprocess.run(cli + ["ingest", PUMP, "--project", "pump", "--quiet"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    print("\n" + r.stdout.strip())
    info = client.get_project("pump")
    assert info.head_version == 1 and info.scan_count == 1

    # Its visual reference photo is kept with the scan, and comes back byte for byte.
    assert "kept with the scan as a visual reference" in r.stdout
    scan = client.list_scans("pump")[0]
    assert [(v.name, v.width_px, v.height_px) for v in scan.visual_references] == \
        [(read_e57(PUMP)[0].images[0].name, 3072, 2304)]
    assert [s.name for s in scan.sources] == ["lidar", "point-colour"]  # the photo is no source
    out = tmp_path / "reference.jpg"
    shown = subprocess.run(cli + ["reference", "--project", "pump", "--scan", scan.name,
                                  "--name", scan.visual_references[0].name, "-o", str(out)],
                           capture_output=True, text=True)
    assert shown.returncode == 0, shown.stdout + shown.stderr
    assert out.read_bytes() == read_e57(PUMP)[0].images[0].data
    print(shown.stdout.strip())

    width, height = 2048, 1024
    render = client.render("pump", [0.0, 0.0, 0.0], width, height)
    cloud = read_e57(PUMP)[0].cloud
    u, v, rng = equirect_pixels(cloud.xyz_m, width, height)
    depth = render.depth_m[v, u]
    hit = np.isfinite(depth)
    close = np.abs(depth - rng) < 2 * vossel_m
    share_hit = float(hit.mean())
    share_close = float(close[hit].mean())
    print(f"pump render from the scanner: {share_hit:.2%} of the points' pixels hit; depth within "
          f"2 vossels of the measured range for {share_close:.2%} of them; median |Z - r| "
          f"{np.median(np.abs(depth[hit] - rng[hit])) * 1000:.1f} mm")
    assert share_hit > 0.97
    assert share_close > 0.90

    # The scan's per-point colour became a source of its own, and the render shows it: at the
    # pixels of the points whose depth matches, the rendered colour against the point's own
    # colour (sRGB-encoded, peak 1) and as CIE76 ΔE.
    sources = [s for scan in client.list_scans("pump") for s in scan.sources]
    assert sorted(s.name for s in sources) == ["lidar", "point-colour"]
    assert cloud.rgb is not None
    at = hit & close
    shown = linear_to_srgb(render.rgb[v[at], u[at]])
    truth = linear_to_srgb(cloud.rgb[at])
    psnr = 10 * math.log10(1.0 / float(np.mean((shown - truth) ** 2)))
    delta_e = np.linalg.norm(_lab(render.rgb[v[at], u[at]]) - _lab(cloud.rgb[at]), axis=1)
    print(f"pump colour at {int(at.sum())} points: PSNR {psnr:.2f} dB (sRGB), mean ΔE "
          f"{float(delta_e.mean()):.2f}, median ΔE {float(np.median(delta_e)):.2f}")
    assert psnr >= 28.0


def _lab(linear: np.ndarray) -> np.ndarray:
    """Linear sRGB (D65) -> CIE L*a*b*."""
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = np.clip(np.asarray(linear, dtype=np.float64), 0.0, None) @ m.T
    xyz /= np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])],
                    axis=1)
