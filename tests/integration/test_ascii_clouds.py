"""ASCII point clouds (Leica PTS, XYZ, CSV: one point a line, world coordinates, no scanner
position): read chunk by chunk into the scanner's frame with the pose the user gives (as a LAS
file is), the intensity scaled into [0, 1] by the range the file's first pass finds (Leica PTS's
-2048..2047 among them), colour linearised. Through vasld the room scan, written as a PTS file
at survey coordinates, renders from the scanner with each point's range at its pixel
(VASL-MODEL §2.1, §8) within two vossels, which holds only if the frame was turned right."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import run_cli
from synth_scans import render_agreement, room_points
from vasl import Pose
from vasl.readers import read_ascii_cloud, rotation_matrix, world_to_sensor

VOSSEL_M = 0.05
SCANNER = (500_012.345, 5_000_067.891, 101.6)
YAW = math.radians(-40.0)
QUATERNION = (0.0, 0.0, math.sin(YAW / 2), math.cos(YAW / 2))
N = 200_000


def _room(seed: int = 21):
    local = room_points(N, seed=seed)
    world = local @ rotation_matrix(QUATERNION).T + np.asarray(SCANNER)
    leica = np.round((local[:, 2] + 2.0) / 4.0 * 4095 - 2048).astype(int)  # -2048..2047
    rgb = ((np.abs(local) * [40, 50, 60]) % 256).astype(int)
    return local, world, leica, rgb


def _write_pts(path: str, world, leica, rgb, blocks: int = 2) -> None:
    """A Leica PTS file: each block a count line, then x y z intensity r g b."""
    with open(path, "w") as f:
        for part in np.array_split(np.arange(len(world)), blocks):
            f.write(f"{len(part)}\n")
            np.savetxt(f, np.column_stack([world[part], leica[part], rgb[part]]),
                       fmt="%.4f %.4f %.4f %d %d %d %d")


def test_pts_and_csv_come_in_the_scanners_frame(tmp_path):
    local, world, leica, rgb = _room()
    pose = Pose.make(SCANNER, QUATERNION)
    pts = str(tmp_path / "room.pts")
    _write_pts(pts, world, leica, rgb)
    points = read_ascii_cloud(pts, pose)
    assert points.count == N and points.has_intensity and points.has_rgb
    assert "intensity -2048..2047 (Leica): (i + 2048) / 4095" in points.notes
    cloud = points.read()
    err = float(np.abs(cloud.xyz_m - local).max())
    print(f"\nPTS at x ≈ 500 km: {N} points, sensor-frame error {err * 1000:.3f} mm; "
          f"{points.notes}")
    assert err < 1e-4  # the file's 0.1 mm, float64 through the pose
    np.testing.assert_allclose(cloud.intensity, (leica + 2048) / 4095, atol=1e-6)
    srgb = rgb / 255.0
    np.testing.assert_allclose(cloud.rgb, np.where(srgb <= 0.04045, srgb / 12.92,
                                                   ((srgb + 0.055) / 1.055) ** 2.4), atol=1e-6)

    # A CSV with a header line, commas, intensity 0..255, no colour.
    csv = tmp_path / "room.csv"
    with open(csv, "w") as f:
        f.write("X,Y,Z,Intensity\n")
        np.savetxt(f, np.column_stack([world[:5000], np.arange(5000) % 256]),
                   fmt="%.4f,%.4f,%.4f,%d")
    points = read_ascii_cloud(str(csv), pose)
    cloud = points.read()
    assert len(cloud) == 5000 and cloud.rgb is None
    assert np.abs(cloud.xyz_m - local[:5000]).max() < 1e-4
    np.testing.assert_allclose(cloud.intensity, (np.arange(5000) % 256) / 255.0, atol=1e-6)


def test_a_coordinate_that_is_not_a_number_is_a_no_return(tmp_path):
    path = tmp_path / "gaps.xyz"
    path.write_text("1 2 3 0.5\nnan nan nan 0.5\n4 5 6 nan\n")
    cloud = read_ascii_cloud(str(path), (0, 0, 0)).read()
    assert cloud.xyz_m.tolist() == [[1, 2, 3], [0, 0, 0], [4, 5, 6]]
    assert cloud.intensity.tolist() == [0.5, 0.5, 0.0]


@pytest.mark.parametrize("body, message", [
    ("1 2 3 4 5\n", "has 5 numbers"),
    ("1 2 3\n4 5 six\n", "not numbers"),
    ("1 2 3\n4 5 6 7\n", "where the first point line has 3"),
    ("12\n", "holds no point"),
])
def test_malformed_ascii_cloud_is_refused_naming_the_file(tmp_path, body, message):
    path = tmp_path / "bad.xyz"
    path.write_text(body)
    with pytest.raises(ValueError, match=message) as e:
        read_ascii_cloud(str(path), (0, 0, 0))
    assert str(path) in str(e.value)
    with pytest.raises(ValueError, match="records no scanner position"):
        read_ascii_cloud(str(path))


def test_pts_ingests_with_its_pose_and_renders_from_the_scanner(server, client, tmp_path):
    local, world, leica, rgb = _room(seed=22)
    pts = str(tmp_path / "room.pts")
    _write_pts(pts, world, leica, rgb)
    client.create_project("pts", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", pts, "--project", "pts", "--quiet",
                "--pose", ",".join(repr(v) for v in SCANNER + QUATERNION))
    print("\n" + r.stdout.strip())
    assert f"room: version 1, {N} points" in r.stdout
    assert "(Leica)" in r.stdout
    assert [s.name for s in client.list_scans("pts")[0].sources] == ["lidar", "point-colour"]
    p = world_to_sensor(world, Pose.make(SCANNER, QUATERNION))
    assert render_agreement(client, "pts", (SCANNER, QUATERNION), p, VOSSEL_M) >= 0.95
    r = run_cli(server, "ingest", pts, "--project", "pts", check=False)
    assert r.returncode == 2 and "records no scanner position" in r.stderr
