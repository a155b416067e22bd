"""PTX input (Leica's structured ASCII scans, also written by FARO SCENE, Trimble RealWorks and
CloudCompare): a file of several scans, each a full range grid with its scanner pose and a 4x4
transform. The reader must give each scan's points in its scanner's frame whichever way the
file stores them (in the scanner's own frame with the pose as transform, already registered
with an identity transform, or with the transform written for column vectors), keep "no return"
cells as the (0, 0, 0) marker, give each point its grid cell, and refuse a malformed file naming
the line. Through vasld, a two-scan PTX at survey coordinates (x ≈ 500 km, y ≈ 5000 km) is two
scans whose render from the scanner holds each point's range at its pixel (VASL-MODEL §2.1,
§8) within two vossels, which holds only if both frames were read right."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import run_cli
from synth_scans import render_agreement, room_grid, write_ptx
from vasl import Pose
from vasl.readers import read_ptx, rotation_matrix

ROWS, COLUMNS = 360, 720
VOSSEL_M = 0.05
FAR = np.array([500_012.345, 5_000_067.891, 101.6])  # the scanner, at UTM-like coordinates


def _yaw(deg: float):
    a = math.radians(deg)
    return (0.0, 0.0, math.sin(a / 2), math.cos(a / 2))


def _tilted(yaw_deg: float, roll_deg: float):
    """A quaternion (x, y, z, w) of a yaw then a small roll (a scanner not quite level)."""
    r = rotation_matrix(_yaw(yaw_deg)) @ rotation_matrix(
        (math.sin(math.radians(roll_deg) / 2), 0.0, 0.0, math.cos(math.radians(roll_deg) / 2)))
    from vasl.readers import quaternion_from_matrix

    return quaternion_from_matrix(r)


def _matrix(position, quaternion) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation_matrix(quaternion)
    m[:3, 3] = position
    return m


def _scan(missing_every: int = 7):
    """The room as a grid, with every `missing_every`-th cell a "no return" (0, 0, 0), its
    intensity and colour."""
    local = room_grid(ROWS, COLUMNS)
    missing = np.zeros(len(local), dtype=bool)
    missing[::missing_every] = True
    local[missing] = 0.0
    intensity = np.clip((local[:, 2] + 2.0) / 4.0, 0.0, 1.0)
    rgb = ((np.abs(local) * [40, 50, 60]) % 256).astype(int)
    return local, missing, intensity, rgb


def _write_two_scans(path: str, newline: str = "\r\n"):
    """One room scanned twice: scan 1 stored in its scanner's frame (transform = pose) with
    intensity and colour; scan 2, from a scanner 1 m away and turned, stored registered
    (identity transform) with intensity only. Returns the poses and each scan's points in its
    scanner's frame ((0, 0, 0) where there is no return)."""
    local, missing, intensity, rgb = _scan()
    pose1 = (FAR, _tilted(30.0, 1.5))
    pose2 = (FAR + [0.8, -0.5, 0.1], _yaw(-75.0))
    m1, m2 = _matrix(*pose1), _matrix(*pose2)
    world = local @ m1[:3, :3].T + m1[:3, 3]
    local2 = (world - m2[:3, 3]) @ m2[:3, :3]
    world[missing] = 0.0
    local2[missing] = 0.0
    with open(path, "w", newline="") as f:
        write_ptx(f, local, ROWS, COLUMNS, position=m1[:3, 3], axes=m1[:3, :3], transform=m1,
                  intensity=intensity, rgb=rgb, newline=newline)
        write_ptx(f, world, ROWS, COLUMNS, position=m2[:3, 3], axes=m2[:3, :3],
                  transform=np.eye(4), intensity=intensity, newline=newline)
    return (pose1, pose2), (local, local2), missing, intensity, rgb


def _same_rotation(q1, q2) -> float:
    return float(np.abs(rotation_matrix(q1) - rotation_matrix(q2)).max())


def test_ptx_scans_come_in_their_scanners_frames(tmp_path):
    path = str(tmp_path / "site.ptx")
    poses, locals_, missing, intensity, rgb = _write_two_scans(path)
    scans = read_ptx(path)
    assert [s.scan for s in scans] == ["site-1", "site-2"]
    for s, (position, quaternion), local in zip(scans, poses, locals_):
        assert np.abs(np.asarray(s.pose.position_m) - position).max() < 1e-6
        assert _same_rotation(s.pose.quaternion_xyzw, quaternion) < 1e-8
        assert s.points.count == ROWS * COLUMNS and s.points.grid_shape == (ROWS, COLUMNS)
        cloud = s.points.read()
        err = float(np.abs(cloud.xyz_m - local).max())
        print(f"\n{s.scan}: {len(cloud)} points, {int(missing.sum())} no return; sensor-frame "
              f"error {err * 1000:.4f} mm; notes: {s.notes}")
        # The file's 6 decimals (1 µm), float64 through the transforms, then float32 (≤ 0.5 µm
        # at 8 m).
        assert err < 3e-6
        assert np.all(cloud.xyz_m[missing] == 0.0)  # "no return" stays the exact marker
        np.testing.assert_allclose(cloud.intensity, intensity, atol=6e-5)
    assert scans[0].points.as_stored and not scans[1].points.as_stored
    assert any("identity transform" in n for n in scans[1].notes)
    assert any("range grid 360 x 720" in n for n in scans[0].notes)
    cloud = scans[0].points.read()
    assert cloud.rgb is not None and scans[1].points.read().rgb is None
    srgb = rgb / 255.0
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(cloud.rgb, linear, atol=1e-6)
    # Each point's grid cell is its place in the file: column after column.
    chunks = list(scans[0].points.chunks(chunk_points=100_000))
    grid = np.concatenate([c.grid for c in chunks])
    i = np.arange(ROWS * COLUMNS)
    assert np.array_equal(grid[:, 0], i % ROWS) and np.array_equal(grid[:, 1], i // ROWS)


def test_ptx_header_variants(tmp_path):
    """A transform written for column vectors (translation in its last column) and a header
    without the scanner's position and axes (the transform alone places the scanner)."""
    local, missing, intensity, _ = _scan(missing_every=5)
    pose = ((12.5, -3.25, 1.6), _tilted(140.0, -2.0))
    m = _matrix(*pose)
    path = str(tmp_path / "variants.ptx")
    with open(path, "w") as f:
        write_ptx(f, local, ROWS, COLUMNS, position=m[:3, 3], axes=m[:3, :3], transform=m,
                  intensity=intensity, column_vectors=True)
        write_ptx(f, local[:, :3], ROWS, COLUMNS, position=(0, 0, 0), axes=np.eye(3),
                  transform=m)
    scans = read_ptx(path)
    for s in scans:
        assert np.abs(np.asarray(s.pose.position_m) - pose[0]).max() < 1e-6
        assert _same_rotation(s.pose.quaternion_xyzw, pose[1]) < 1e-8
        cloud = s.points.read()
        assert np.abs(cloud.xyz_m - local).max() < 3e-6
    assert scans[1].points.read().intensity is None  # x y z lines: no intensity
    assert any("no scanner position" in n for n in scans[1].notes)

    # A manifest's pose places the scanner of a file of one scan, in the registered frame.
    with pytest.raises(ValueError, match="a pose places one scanner, but the file holds 2"):
        read_ptx(path, pose=Pose.make(*pose))
    one = str(tmp_path / "one.ptx")
    with open(one, "w") as f:
        write_ptx(f, local, ROWS, COLUMNS, position=m[:3, 3], axes=m[:3, :3], transform=m)
    given = Pose.make((14.5, -3.25, 1.6), _yaw(10.0))
    scan, = read_ptx(one, pose=given)
    assert scan.pose == given and any("2.00 m from the file's scanner" in n for n in scan.notes)
    world = local @ m[:3, :3].T + m[:3, 3]
    expected = (world - given.position_m) @ rotation_matrix(given.quaternion_xyzw)
    expected[missing] = 0.0
    assert np.abs(scan.points.read().xyz_m - expected).max() < 3e-6


def test_ptx_coordinates_that_are_not_numbers_are_no_returns(tmp_path):
    path = tmp_path / "gaps.ptx"
    header = ["2", "2", "10 0 0", "1 0 0", "0 1 0", "0 0 1",
              "1 0 0 0", "0 1 0 0", "0 0 1 0", "10 0 0 1"]
    path.write_text("\n".join(header + ["1 2 3 0.5", "nan nan nan 0.5", "0 0 0 0.5",
                                         "4 5 6 nan"]) + "\n")
    cloud = read_ptx(str(path))[0].points.read()
    assert cloud.xyz_m.tolist() == [[1, 2, 3], [0, 0, 0], [0, 0, 0], [4, 5, 6]]
    assert cloud.intensity.tolist() == [0.5, 0.5, 0.5, 0.0]


@pytest.mark.parametrize("damage, message", [
    ("truncate", "the file ends after 7 of the scan's 12 points"),
    ("bad-line", "line 15: expected 4 numbers"),
    ("scaled", "not a rotation"),
    ("text", "not a PTX scan header"),
    ("fields", "a PTX point is x y z intensity"),
])
def test_malformed_ptx_is_refused_naming_the_place(tmp_path, damage, message):
    path = tmp_path / f"{damage}.ptx"
    header = ["4", "3", "0 0 0", "1 0 0", "0 1 0", "0 0 1",
              "1 0 0 0", "0 1 0 0", "0 0 1 0", "0 0 0 1"]
    points = [f"{1 + i} 2 3 0.5" for i in range(12)]
    if damage == "truncate":
        points = points[:7]
    elif damage == "bad-line":
        points[4] = "1 2 x 0.5"
    elif damage == "scaled":
        header[6] = "2 0 0 0"
    elif damage == "text":
        header[0] = "ply"
    elif damage == "fields":
        points = [p + " 7 7" for p in points]
    path.write_text("\n".join(header + points) + "\n")
    with pytest.raises(ValueError, match=message) as e:
        scans = read_ptx(str(path))
        scans[0].points.read()
    assert str(path) in str(e.value)


def test_ptx_ingests_and_renders_from_its_scanners(server, client, tmp_path):
    path = str(tmp_path / "site.ptx")
    poses, locals_, missing, _, _ = _write_two_scans(path)
    client.create_project("ptx", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", path, "--project", "ptx", "--quiet")
    print("\n" + r.stdout.strip())
    assert "site-1: version 1" in r.stdout and "site-2: version 2" in r.stdout
    assert "range grid 360 x 720 (PTX)" in r.stdout
    scans = {s.name: s for s in client.list_scans("ptx")}
    assert set(scans) == {"site-1", "site-2"}
    assert [s.name for s in scans["site-1"].sources] == ["lidar", "point-colour"]
    for pose, local in zip(poses, locals_):
        assert render_agreement(client, "ptx", pose, local[~missing], VOSSEL_M) >= 0.95

    # A manifest whose lidar.points names a PTX file of one scan, its pose the scanner's.
    one = tmp_path / "one.ptx"
    m = _matrix(*poses[1])
    with open(one, "w") as f:
        write_ptx(f, locals_[1], ROWS, COLUMNS, position=m[:3, 3], axes=m[:3, :3], transform=m)
    manifest = tmp_path / "one.json"
    manifest.write_text(json.dumps({
        "scan": "one", "pose": {"position": list(poses[1][0]), "quaternion": poses[1][1]},
        "lidar": {"points": "one.ptx", "divergence_rad": 0.0003}}))
    client.create_project("ptx-manifest", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", str(manifest), "--project", "ptx-manifest", "--quiet")
    assert f"one: version 1, {ROWS * COLUMNS} points" in r.stdout
    assert render_agreement(client, "ptx-manifest", poses[1], locals_[1][~missing],
                            VOSSEL_M) >= 0.95
