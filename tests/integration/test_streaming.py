"""Streaming reads (issue "Real captures in"): an E57 scan is read chunk by chunk through
pye57's libe57 bindings and gives the same points as the whole read; points an E57 stores in a
world frame are turned into the scanner's frame in float64; and the CLI shows upload progress
(points sent, MB/s, time left) with tqdm on a terminal only, and a summary line per scan."""
from __future__ import annotations

import fcntl
import glob
import json
import math
import os
import pty
import re
import struct
import subprocess
import sys
import termios

import numpy as np
import pytest

from conftest import REPO, run_cli
from synth_scans import room_chunks, room_points, write_e57
from vasl import PointCloud, Pose
from vasl.readers import PointSource, read_e57, rotation_matrix

DATA = os.environ.get("VASL_DATA_DIR", os.path.join(REPO, "..", "shared", "data"))
E57_FILES = sorted(glob.glob(os.path.join(DATA, "e57", "tiny", "*.e57"))
                   + glob.glob(os.path.join(DATA, "e57", "real", "*.e57")))
QUATERNION = (0.0, 0.0, math.sin(math.radians(20.0)), math.cos(math.radians(20.0)))  # x y z w


def test_chunks_equal_the_whole_read():
    if not E57_FILES:
        pytest.skip(f"real data not found under {DATA}/e57 (set VASL_DATA_DIR)")
    for path in E57_FILES:
        for scan in read_e57(path):
            if scan.points is None:
                continue
            whole = scan.cloud
            parts = list(scan.points.chunks(1000))
            assert sum(len(p) for p in parts) == len(whole) == scan.points.count
            np.testing.assert_array_equal(np.concatenate([p.xyz_m for p in parts]), whole.xyz_m)
            if whole.intensity is not None:
                np.testing.assert_array_equal(np.concatenate([p.intensity for p in parts]),
                                              whole.intensity)
                assert 0.0 <= whole.intensity.min() and whole.intensity.max() <= 1.0
            if whole.rgb is not None:
                np.testing.assert_array_equal(np.concatenate([p.rgb for p in parts]), whole.rgb)
            print(f"\n{os.path.basename(path)}: {scan.points.count} points of "
                  f"{scan.points.records} records in {len(parts)} chunks of 1000; "
                  f"{'; '.join(scan.notes) or 'limits from the header'}")


def test_georeferenced_e57_points_become_the_scanners_frame(tmp_path):
    """Points stored in a world frame at survey magnitudes (x ≈ 500 km, y ≈ 5000 km): with a
    pose that places the scanner among them they are turned into its frame in float64; without
    one the file is refused unless the scanner's pose is given. Points in the scan's own frame
    under a georeferenced pose are left as they are."""
    local = room_points(20_000, seed=11)
    scanner = (500_012.345, 5_000_067.891, 101.6)
    world = local @ rotation_matrix(QUATERNION).T + np.asarray(scanner)
    wxyz = (QUATERNION[3],) + QUATERNION[:3]
    chunk = {"xyz": world, "intensity": np.zeros(len(world), np.int64)}
    posed, bare, ok = (str(tmp_path / f"{n}.e57") for n in ("posed", "bare", "local"))
    write_e57(posed, len(world), iter([chunk]), pose=(scanner, wxyz), scale_m=None)
    write_e57(bare, len(world), iter([chunk]), pose=None, scale_m=None)
    write_e57(ok, len(local), iter([dict(chunk, xyz=local)]), pose=(scanner, wxyz))

    scan = read_e57(posed)[0]
    err = float(np.abs(scan.cloud.xyz_m - local).max())
    naive = (world.astype(np.float32) - np.asarray(scanner)) @ rotation_matrix(QUATERNION)
    print(f"\nE57 at x ≈ 500 km, y ≈ 5000 km: sensor-frame error {err * 1e6:.2f} µm; "
          f"{np.abs(naive - local).max() * 1000:.0f} mm had the world coordinates been float32")
    assert err < 1e-5 and any("world frame" in n for n in scan.notes)
    np.testing.assert_allclose(scan.pose.position_m, scanner)

    with pytest.raises(ValueError, match="--pose") as refused:
        read_e57(bare)
    assert bare in str(refused.value)
    given = read_e57(bare, pose=Pose.make(scanner, QUATERNION))[0]
    assert np.abs(given.cloud.xyz_m - local).max() < 1e-5 and given.pose.position_m == scanner
    with pytest.raises(ValueError, match="own pose"):
        read_e57(posed, pose=Pose.make(scanner, QUATERNION))

    kept = read_e57(ok)[0]
    assert np.abs(kept.cloud.xyz_m - local).max() <= 0.0005 and not kept.notes


def _pty_run(args):
    """Runs the CLI with stderr on a pseudo-terminal (as a user's shell has it); its exit
    code, stdout and what the terminal showed."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))  # rows, columns
    proc = subprocess.Popen([sys.executable, "-m", "vasl.cli", *args], stdout=subprocess.PIPE,
                            stderr=slave)
    os.close(slave)
    shown = b""
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        shown += data
    out = proc.stdout.read().decode()
    proc.wait(timeout=300)
    os.close(master)
    return proc.returncode, out, shown.decode(errors="replace")


def test_cli_progress_on_a_terminal_and_a_summary_line(server, client, tmp_path):
    n = 1_500_000
    path = str(tmp_path / "room.e57")
    write_e57(path, n, room_chunks(n), colour=True, invalid=True)
    client.create_project("progress", vossel_size_m=0.25)
    code, out, shown = _pty_run(["--server", server.address, "ingest", path,
                                 "--project", "progress"])
    print(f"\n{out.strip()}")
    assert code == 0, shown
    # tqdm's upload bar: bytes with MB/s, the time left, and the points sent.
    bars = [line for line in re.split(r"[\r\n]", shown) if "room: upload" in line]
    print(f"terminal, last upload bar: {bars[-1].strip() if bars else None!r}")
    assert any(re.search(r"MB/s", b) for b in bars), shown
    assert any(re.search(r"<\d\d:\d\d", b) for b in bars), shown
    assert any(re.search(r"[\d,]+/[\d,]+ points", b) for b in bars), shown
    valid = n - (n + 1) // 97
    summary = re.search(rf"room: version 1, {valid} points, ([\d.]+) MB sent in ([\d.]+) s "
                        rf"\(([\d.]+) MB/s\), .* vossels, \d+ records", out)
    assert summary, out
    assert abs(float(summary.group(1)) - valid * 28 / 1e6) < 0.1

    # --quiet on a terminal: no bar; and no bar when stderr is not a terminal (a log).
    client.create_project("progress-quiet", vossel_size_m=0.25)
    code, out, shown = _pty_run(["--server", server.address, "ingest", path,
                                 "--project", "progress-quiet", "--quiet"])
    assert code == 0 and "upload" not in shown and "room: version 1" in out, shown
    client.create_project("progress-log", vossel_size_m=0.25)
    r = run_cli(server, "ingest", path, "--project", "progress-log")
    assert r.stderr == "" and "room: version 1" in r.stdout, r.stderr


class _Source(PointSource):
    """A PointSource of the room that declares `count` points, yields `yields` of them, and
    raises after `fail_after` chunks (None: never)."""

    def __init__(self, count: int, yields: int, fail_after=None):
        super().__init__()
        self.path = "fake-source"
        self.count, self.yields, self.fail_after = count, yields, fail_after
        self.has_intensity = True

    def chunks(self, chunk_points=1000):
        chunk_points = 1000  # whatever is asked: the failure comes mid-way
        xyz = room_points(self.yields, seed=21).astype(np.float32)
        for i, at in enumerate(range(0, self.yields, chunk_points)):
            if self.fail_after is not None and i == self.fail_after:
                raise ValueError("fake-source: chunk 2 cannot be read")
            part = xyz[at:at + chunk_points]
            yield PointCloud(part, np.full(len(part), 0.5, np.float32), None)


def test_a_reading_error_mid_upload_stores_nothing_and_short_sources_are_padded(client):
    """A source that fails while it is being sent ends the upload: the server refuses the short
    stream and stores nothing, and the caller gets the reader's error. A source that yields
    fewer points than it declared (points found unusable while reading) is made up with
    (0, 0, 0) "no return" points, so the header's count holds."""
    client.create_project("stream-errors", vossel_size_m=0.1)
    with pytest.raises(ValueError, match="chunk 2 cannot be read"):
        client.ingest("stream-errors", scan="broken", points=_Source(5000, 5000, fail_after=2),
                      pose=[0, 0, 0])
    assert client.get_project("stream-errors").head_version == 0
    r = client.ingest("stream-errors", scan="short", points=_Source(5000, 4990), pose=[0, 0, 0])
    print(f"\nshort source: {r.point_count} points declared and sent (10 of them no-return "
          f"padding), {r.vossel_count} vossels, {r.sent_bytes} bytes")
    assert r.version == 1 and r.point_count == 5000 and r.sent_bytes == 5000 * 16


class _GridWall(PointSource):
    """A wall 4 m in front of the scanner sampled on a 1° grid of azimuth (columns) and
    elevation (rows): 7 cm between returns, coarser than 2 cm vossels. With `grid` each point
    carries its row and column; `bad` puts one column beyond the grid."""

    def __init__(self, grid: bool, bad: bool = False):
        super().__init__()
        self.path = "grid-wall"
        az, el = np.meshgrid(np.radians(np.arange(-30, 31)), np.radians(np.arange(20, -21, -1)))
        self.rc = np.stack(np.meshgrid(np.arange(61), np.arange(41))[::-1], axis=-1).reshape(-1, 2)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
        self.xyz = (4.0 / d[..., :1] * d).reshape(-1, 3).astype(np.float32)
        self.count, self.has_intensity = len(self.xyz), True
        self.grid_shape = (41, 61) if grid else None
        if bad:
            self.rc[5, 1] = 61

    def chunks(self, chunk_points=1000):
        for at in range(0, self.count, chunk_points):
            rc = self.rc[at:at + chunk_points].astype(np.uint32) if self.grid_shape else None
            part = self.xyz[at:at + chunk_points]
            yield PointCloud(part, np.full(len(part), 0.5, np.float32), None, rc)


def test_a_range_grid_travels_with_the_points_and_closes_the_gaps(client, tmp_path):
    """LidarModel.grid: each point's row and column reach the server, which fills the gaps of
    a surface sampled more coarsely than the lattice (from a PointSource, and from a manifest's
    PLY with row and column properties); a column beyond the grid is refused and nothing is
    stored."""
    for name in ("wall-bare", "wall-grid"):
        client.create_project(name, vossel_size_m=0.02)
    bare = client.ingest("wall-bare", scan="wall", points=_GridWall(False), pose=[0, 0, 0])
    grid = client.ingest("wall-grid", scan="wall", points=_GridWall(True), pose=[0, 0, 0])
    # The wall spans 2·4·tan 30° × 2·4·tan 20° = 4.62 m × 2.91 m: 33,600 vossels of 2 cm.
    print(f"\n1° wall at 4 m, 2 cm vossels: {bare.vossel_count} vossels from its "
          f"{bare.point_count} returns, {grid.vossel_count} with its range grid "
          f"({grid.sent_bytes} bytes sent, {bare.sent_bytes} without)")
    assert bare.vossel_count <= bare.point_count
    assert grid.vossel_count >= 0.95 * 4.62 * 2.91 / 0.02 ** 2
    assert grid.sent_bytes == bare.sent_bytes + 8 * bare.point_count
    # The same scan as a manifest's PLY with row and column properties: the same lattice.
    wall = _GridWall(True)
    ply = tmp_path / "wall.ply"
    rows = np.zeros(wall.count, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("intensity", "<f4"), ("row", "<u4"), ("column", "<u4")])
    for k, axis in enumerate("xyz"):
        rows[axis] = wall.xyz[:, k]
    rows["intensity"], rows["row"], rows["column"] = 0.5, wall.rc[:, 0], wall.rc[:, 1]
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % wall.count
                    + b"".join(b"property %s %s\n" % (t, n) for t, n in (
                        (b"float", b"x"), (b"float", b"y"), (b"float", b"z"),
                        (b"float", b"intensity"), (b"uint", b"row"), (b"uint", b"column")))
                    + b"end_header\n" + rows.tobytes())
    (tmp_path / "wall.json").write_text(json.dumps({
        "scan": "wall", "pose": {"position": [0, 0, 0], "quaternion": [0, 0, 0, 1]},
        "lidar": {"points": "wall.ply", "divergence_rad": 0.0003}}))
    client.create_project("wall-ply", vossel_size_m=0.02)
    from_ply = client.ingest("wall-ply", str(tmp_path / "wall.json"))
    assert from_ply.vossel_count == grid.vossel_count

    client.create_project("wall-bad", vossel_size_m=0.02)
    with pytest.raises(Exception, match="outside the 41x61 range grid"):
        client.ingest("wall-bad", scan="wall", points=_GridWall(True, bad=True), pose=[0, 0, 0])
    assert client.get_project("wall-bad").head_version == 0
