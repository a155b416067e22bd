"""PCD input (the Point Cloud Library's format, the one ROS, Open3D and most robotics stacks
write): ascii, binary and LZF-compressed binary data; an organised cloud (HEIGHT > 1) as the
scan's range grid; NaN cells as "no return"; PCL's packed rgb; and the header's VIEWPOINT as the
pose of the sensor in the points' frame. The reader must give the same sensor-frame points
whatever the layout, and refuse a malformed file naming it. Through vasld, a PCD in a map frame
with its VIEWPOINT, one in its sensor's frame placed by a manifest, and one at survey
coordinates placed by --pose each render from their scanner with each point's range at its
pixel (VASL-MODEL §2.1, §8) within two vossels, which holds only if the frame was read right."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import run_cli
from synth_scans import render_agreement, room_grid
from vasl.readers import lzf_decompress, quaternion_from_matrix, read_pcd, rotation_matrix

ROWS, COLUMNS = 180, 360
VOSSEL_M = 0.05
FIELDS = "x y z intensity rgb"


def lzf_compress(data: bytes) -> bytes:
    """Greedy LZF (liblzf's format): literal runs of up to 32 bytes, and back references of
    3..264 bytes up to 8192 bytes back, overlapping ones included (a run of one repeated byte
    copies from one byte back)."""
    out, literal, last = bytearray(), bytearray(), {}

    def flush():
        for k in range(0, len(literal), 32):
            part = literal[k:k + 32]
            out.append(len(part) - 1)
            out.extend(part)
        literal.clear()

    i, n = 0, len(data)
    while i < n:
        key = data[i:i + 3]
        ref = last.get(key) if len(key) == 3 else None
        if len(key) == 3:
            last[key] = i
        if ref is not None and i - ref <= 8192:
            length, most = 0, min(264, n - i)
            while length < most and data[ref + length] == data[i + length]:
                length += 1
            if length >= 3:
                flush()
                off, code = i - ref - 1, length - 2
                if code < 7:
                    out.append(code << 5 | off >> 8)
                else:
                    out.extend((7 << 5 | off >> 8, code - 7))
                out.append(off & 0xFF)
                i += length
                continue
        literal.append(data[i])
        i += 1
    flush()
    return bytes(out)


def _pose(position, yaw_deg: float, roll_deg: float = 0.0):
    a, b = math.radians(yaw_deg), math.radians(roll_deg)
    r = rotation_matrix((0, 0, math.sin(a / 2), math.cos(a / 2))) @ rotation_matrix(
        (math.sin(b / 2), 0, 0, math.cos(b / 2)))
    return np.asarray(position, dtype=np.float64), quaternion_from_matrix(r)


def _room():
    """The room scanned as an organised cloud, row after row (ROWS × COLUMNS, sensor frame),
    every 7th cell without a return; its intensity 0..255 and colour codes."""
    grid = room_grid(ROWS, COLUMNS).reshape(COLUMNS, ROWS, 3).transpose(1, 0, 2).reshape(-1, 3)
    missing = np.zeros(len(grid), dtype=bool)
    missing[::7] = True
    intensity = np.clip((grid[:, 2] + 2.0) / 4.0, 0.0, 1.0) * 255.0
    codes = ((np.abs(grid) * [40, 50, 60]) % 256).astype(np.uint32)
    return grid, missing, intensity, codes


def write_pcd(path, xyz, *, data="binary", viewpoint=None, width=COLUMNS, height=ROWS,
              intensity=None, codes=None, xyz_type="F 4", extra_header=()):
    """Writes a PCD v0.7 file: x y z (float or double), optional intensity (F 4) and packed rgb
    (F 4, PCL's 0xRRGGBB bits), the VIEWPOINT (position, quaternion x y z w) when given."""
    size = int(xyz_type.split()[1])
    cols = [("x", xyz_type), ("y", xyz_type), ("z", xyz_type)]
    if intensity is not None:
        cols.append(("intensity", "F 4"))
    if codes is not None:
        cols.append(("rgb", "F 4"))
    vp = "0 0 0 1 0 0 0"
    if viewpoint is not None:
        (t, q) = viewpoint
        vp = " ".join(f"{v:.12g}" for v in (*t, q[3], q[0], q[1], q[2]))
    header = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
              "FIELDS " + " ".join(c[0] for c in cols),
              "SIZE " + " ".join(c[1].split()[1] for c in cols),
              "TYPE " + " ".join(c[1].split()[0] for c in cols),
              "COUNT " + " ".join("1" for _ in cols), f"WIDTH {width}", f"HEIGHT {height}",
              f"VIEWPOINT {vp}", f"POINTS {width * height}", *extra_header, f"DATA {data}"]
    fdt = "<f4" if size == 4 else "<f8"
    columns = [np.asarray(xyz[:, k], dtype=fdt) for k in range(3)]
    if intensity is not None:
        columns.append(np.asarray(intensity, dtype="<f4"))
    if codes is not None:
        c = np.asarray(codes, dtype=np.uint32)
        columns.append((c[:, 0] << 16 | c[:, 1] << 8 | c[:, 2]).astype("<u4").view("<f4"))
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        if data == "ascii":
            for row in zip(*columns):
                words = [repr(float(v)) if i < 3 else f"{float(v):.9g}"
                         for i, v in enumerate(row)]
                f.write((" ".join(words) + "\n").encode())
        elif data == "binary":
            dtype = np.dtype([(f"c{i}", c.dtype) for i, c in enumerate(columns)])
            rec = np.empty(len(xyz), dtype)
            for i, c in enumerate(columns):
                rec[f"c{i}"] = c
            f.write(rec.tobytes())
        else:
            raw = b"".join(c.tobytes() for c in columns)
            packed = lzf_compress(raw)
            f.write(np.array([len(packed), len(raw)], "<u4").tobytes() + packed)


def _linear(codes):
    srgb = codes / 255.0
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def test_lzf_round_trip_and_corruption():
    rng = np.random.default_rng(3)
    data = (bytes(rng.integers(0, 4, 5000, dtype=np.uint8)) + b"\0" * 3000
            + b"abcabcabc" * 400 + bytes(rng.integers(0, 256, 2000, dtype=np.uint8)))
    packed = lzf_compress(data)
    print(f"\nLZF: {len(data)} bytes packed to {len(packed)}")
    assert len(packed) < len(data) // 2  # back references were made, overlapping ones too
    assert lzf_decompress(packed, len(data)) == data
    with pytest.raises(ValueError, match="unpacks to"):
        lzf_decompress(packed, len(data) + 1, "t")
    with pytest.raises(ValueError, match="corrupt"):
        lzf_decompress(packed[:-5], len(data), "t")
    with pytest.raises(ValueError, match="corrupt"):
        lzf_decompress(bytes([0xE0, 0x05, 0xFF]), 100, "t")  # a reference before the start


def test_pcd_layouts_give_the_scanners_points(tmp_path):
    """The room in a map frame (its VIEWPOINT the scanner's pose there) as ascii, binary and
    binary_compressed: the same sensor-frame points, "no return" cells, intensity, colour and
    range grid from each."""
    local, missing, intensity, codes = _room()
    position, quaternion = _pose([3.2, -1.7, 0.4], 40.0, 2.0)
    world = local @ rotation_matrix(quaternion).T + position
    world[missing] = np.nan
    clouds = []
    for data in ("ascii", "binary", "binary_compressed"):
        path = tmp_path / f"room-{data}.pcd"
        write_pcd(path, world, data=data, viewpoint=(position, quaternion),
                  intensity=intensity, codes=codes)
        scan = read_pcd(str(path))
        assert scan.scan == f"room-{data}"
        assert np.abs(np.asarray(scan.pose.position_m) - position).max() < 1e-9
        assert scan.points.grid_shape == (ROWS, COLUMNS)
        assert scan.points.count == ROWS * COLUMNS
        cloud = scan.points.read()
        grid = np.concatenate([c.grid for c in scan.points.chunks(chunk_points=10_000)])
        err = float(np.abs(cloud.xyz_m[~missing] - local[~missing]).max())
        print(f"{data}: {len(cloud)} points, sensor-frame error {err * 1000:.4f} mm; "
              f"notes: {scan.notes}")
        assert err < 2e-6  # float32 map coordinates (≤ 0.5 µm at 8 m), float64 to the sensor
        assert np.all(cloud.xyz_m[missing] == 0.0)
        np.testing.assert_allclose(cloud.intensity, intensity / 255.0, atol=1e-6)
        np.testing.assert_allclose(cloud.rgb, _linear(codes), atol=1e-6)
        i = np.arange(ROWS * COLUMNS)
        assert np.array_equal(grid[:, 0], i // COLUMNS) and np.array_equal(grid[:, 1], i % COLUMNS)
        assert any("intensity 0..255" in n for n in scan.notes)
        assert any("through the file's VIEWPOINT" in n for n in scan.notes)
        clouds.append(cloud)
    for other in clouds[1:]:  # binary and compressed: the same bits; ascii's 9 digits too
        assert np.array_equal(other.xyz_m, clouds[0].xyz_m)
        assert np.array_equal(other.rgb, clouds[0].rgb)


def test_pcd_unsigned_reflectivity_is_its_intensity(tmp_path):
    """An Ouster-style cloud: no intensity field, a 16-bit `reflectivity` over 65535; a
    version 0.5 header (no COUNT, VIEWPOINT or POINTS) reads with their defaults; blank lines
    among the points are skipped."""
    path = tmp_path / "ouster.pcd"
    path.write_text("VERSION .5\nFIELDS x y z reflectivity\nSIZE 4 4 4 2\nTYPE F F F U\n"
                    "WIDTH 3\nHEIGHT 1\nDATA ascii\n"
                    "1 0 0 0\n\n\n0 2 0 65535\nnan nan nan 9\n")
    scan = read_pcd(str(path))
    cloud = scan.points.read()
    # Blank lines between points are skipped, however the points are chunked.
    assert [len(c) for c in scan.points.chunks(chunk_points=1)] == [1, 1, 1]
    assert np.array_equal(cloud.xyz_m, [[1, 0, 0], [0, 2, 0], [0, 0, 0]])
    assert np.allclose(cloud.intensity, [0.0, 1.0, 9 / 65535])
    assert "reflectivity over 65535 (uint16)" in scan.notes
    assert any("no VIEWPOINT" in n for n in scan.notes)


@pytest.mark.parametrize("damage, message", [
    ("no_z", "have no z"),
    ("data", "is not ascii, binary or binary_compressed"),
    ("points", "is not WIDTH x HEIGHT"),
    ("type", "is not a PCD field"),
    ("short", "ends after"),
    ("packed_size", "unpacks to"),
    ("ascii_word", "near line"),
    ("far", "georeferenced"),
    ("not_pcd", "not a PCD"),
])
def test_malformed_pcd_is_refused_naming_the_file(tmp_path, damage, message):
    local, _, _, _ = _room()
    local = local[:COLUMNS * 2]
    path = tmp_path / "bad.pcd"
    kind = {"packed_size": "binary_compressed", "ascii_word": "ascii"}.get(damage, "binary")
    write_pcd(path, local, data=kind, width=COLUMNS, height=2)
    raw = path.read_bytes()
    head, body = raw.split(b"DATA ", 1)
    if damage == "no_z":
        raw = raw.replace(b"FIELDS x y z", b"FIELDS x y w")
    elif damage == "data":
        raw = raw.replace(b"DATA binary", b"DATA packed")
    elif damage == "points":
        raw = raw.replace(f"POINTS {COLUMNS * 2}".encode(), b"POINTS 5")
    elif damage == "type":
        raw = raw.replace(b"TYPE F F F", b"TYPE F F Q")
    elif damage == "short":
        raw = raw[:-100]
    elif damage == "packed_size":
        line, data = body.split(b"\n", 1)
        sizes = np.frombuffer(data[:8], "<u4").copy()
        sizes[1] += 4
        raw = head + b"DATA " + line + b"\n" + sizes.tobytes() + data[8:]
    elif damage == "ascii_word":
        raw = raw[:-30] + b" oops\n"
    elif damage == "far":
        write_pcd(path, local + [500_000.0, 5_000_000.0, 0.0], width=COLUMNS, height=2,
                  xyz_type="F 8")
        raw = path.read_bytes()
    elif damage == "not_pcd":
        raw = b"ply\nformat ascii 1.0\n"
    path.write_bytes(raw)
    with pytest.raises(ValueError, match=message) as e:
        read_pcd(str(path)).points.read()
    assert str(path) in str(e.value)


def test_pcd_ingests_and_renders_from_its_scanner(server, client, tmp_path):
    local, missing, intensity, codes = _room()
    valid = ~missing

    # A map-frame PCD: its VIEWPOINT places the scanner.
    pose = _pose([3.2, -1.7, 0.4], 40.0, 2.0)
    world = local @ rotation_matrix(pose[1]).T + pose[0]
    world[missing] = np.nan
    path = tmp_path / "map.pcd"
    write_pcd(path, world, data="binary_compressed", viewpoint=pose, intensity=intensity,
              codes=codes)
    client.create_project("pcd", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", str(path), "--project", "pcd", "--quiet")
    print("\n" + r.stdout.strip())
    assert f"map: version 1, {ROWS * COLUMNS} points" in r.stdout
    assert "organised 180 x 360" in r.stdout and "VIEWPOINT" in r.stdout
    scans = {s.name: s for s in client.list_scans("pcd")}
    assert [s.name for s in scans["map"].sources] == ["lidar", "point-colour"]
    assert render_agreement(client, "pcd", pose, local[valid], VOSSEL_M) >= 0.95

    # A sensor-frame PCD (identity VIEWPOINT) placed by a manifest's pose.
    pose2 = _pose([-2.5, 4.0, 1.1], -120.0)
    sensor = local.copy()
    sensor[missing] = np.nan
    write_pcd(tmp_path / "raw.pcd", sensor, data="binary", intensity=intensity)
    manifest = tmp_path / "raw.json"
    manifest.write_text(json.dumps({
        "scan": "raw", "pose": {"position": list(pose2[0]), "quaternion": pose2[1]},
        "lidar": {"points": "raw.pcd", "divergence_rad": 0.0003}}))
    client.create_project("pcd-manifest", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", str(manifest), "--project", "pcd-manifest", "--quiet")
    assert f"raw: version 1, {ROWS * COLUMNS} points" in r.stdout
    assert render_agreement(client, "pcd-manifest", pose2, local[valid], VOSSEL_M) >= 0.95

    # Survey coordinates in doubles (identity VIEWPOINT): --pose places the scanner in them.
    pose3 = _pose([500_012.345, 5_000_067.891, 101.6], 75.0)
    survey = local @ rotation_matrix(pose3[1]).T + pose3[0]
    survey[missing] = np.nan
    write_pcd(tmp_path / "survey.pcd", survey, data="ascii", xyz_type="F 8")
    client.create_project("pcd-survey", vossel_size_m=VOSSEL_M)
    given = ",".join(f"{v:.6f}" for v in (*pose3[0], *pose3[1]))
    r = run_cli(server, "ingest", str(tmp_path / "survey.pcd"), "--project", "pcd-survey",
                "--pose", given, "--quiet")
    assert "in a world frame" in r.stdout
    assert render_agreement(client, "pcd-survey", pose3, local[valid], VOSSEL_M) >= 0.95
