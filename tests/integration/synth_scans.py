"""Synthetic scans written as real files, for the streaming, LAS/LAZ and memory tests: points
on the walls, floor and ceiling of a box room seen from a scanner inside it (so every point's
range from the scanner is known), written chunk by chunk as E57 (pye57's libe57 bindings; with
spherical images and their masks when asked) or LAS/LAZ (laspy), so that files of tens of
millions of points never sit in memory whole; and the two image helpers several tests share
(sRGB encoding, PNG bytes around raw rows)."""
from __future__ import annotations

import struct
import uuid
import zlib
from typing import Dict, Iterator, Optional, Sequence, Tuple

import numpy as np

#: Half extents of the room around the scanner, metres (x, y, then z down and up).
ROOM = (6.0, 4.5, 1.5, 1.8)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear -> sRGB-encoded (IEC 61966-2-1), in [0, 1]."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def png_bytes(width: int, height: int, raw_rows: bytes, colour_type: int = 2) -> bytes:
    """An 8-bit PNG (colour type 2: RGB) of `raw_rows`, each row its filter byte then its
    pixels. The header says width x height whatever the rows hold (a pixel bomb can lie)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + \
            struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(raw_rows, 9)) + chunk(b"IEND", b""))


def room_points(n: int, seed: int, room: Sequence[float] = ROOM) -> np.ndarray:
    """`n` points (float64, sensor frame) where rays in uniformly random directions from the
    scanner at the origin meet the room's box: -room[0] <= x <= room[0], -room[1] <= y <=
    room[1], -room[2] <= z <= room[3]."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        tx = room[0] / np.abs(d[:, 0])
        ty = room[1] / np.abs(d[:, 1])
        tz = np.where(d[:, 2] < 0, room[2], room[3]) / np.abs(d[:, 2])
    t = np.minimum(np.minimum(tx, ty), tz)
    return d * t[:, None]


def equirect_pixels(p: np.ndarray, width: int, height: int
                    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """VASL-MODEL §2.1 from the sensor: each sensor-frame point's (N, 3) column and row in a
    width × height equirect panorama, and its range: what a render from the scanner holds at
    the point's pixel."""
    p = np.asarray(p, dtype=np.float64)
    rng = np.linalg.norm(p, axis=1)
    phi = np.arctan2(p[:, 1], p[:, 0])
    psi = np.arcsin(np.clip(p[:, 2] / rng, -1.0, 1.0))
    u = np.floor(width * (0.5 - phi / (2 * np.pi))).astype(int) % width
    v = np.clip(np.floor(height * (0.5 - psi / np.pi)).astype(int), 0, height - 1)
    return u, v, rng


def render_agreement(client, project: str, pose, local: np.ndarray, vossel_m: float,
                     width: int = 2048, height: int = 1024) -> float:
    """Renders `project` from a scanner's `pose` (position, quaternion x y z w); the share of its
    returns `local` (N, 3, sensor frame) whose pixel holds their range within two vossels
    (VASL-MODEL §2.1, §8), printing the figures."""
    render = client.render(project, {"position": list(pose[0]), "quaternion": list(pose[1])},
                           width, height, formats=("exr",))
    u, v, rng = equirect_pixels(local, width, height)
    depth = render.depth_m[v, u]
    close = np.abs(depth - rng) < 2 * vossel_m
    print(f"{project}: depth within 2 vossels of the range for {close.mean():.2%} of "
          f"{len(local)} returns; median |Z - r| "
          f"{np.nanmedian(np.abs(depth - rng)) * 1000:.1f} mm")
    return float(close.mean())


def room_chunks(n: int, chunk: int = 1 << 18, seed: int = 7) -> Iterator[Dict[str, np.ndarray]]:
    """The room's points in chunks: "xyz" (sensor frame, float64), "intensity" (0..65535,
    by height), "rgb" (uint8 by wall), "invalid" (every 97th point flagged invalid, its
    coordinates left at 0)."""
    for at in range(0, n, chunk):
        m = min(chunk, n - at)
        xyz = room_points(m, seed + at // chunk)
        index = np.arange(at, at + m)
        invalid = (index % 97 == 96).astype(np.int64) * 2
        xyz[invalid != 0] = 0.0
        intensity = np.clip((xyz[:, 2] + 2.0) / 4.0 * 65535, 0, 65535).astype(np.int64)
        rgb = np.stack([(np.abs(xyz[:, 0]) * 40) % 256, (np.abs(xyz[:, 1]) * 50) % 256,
                        (np.abs(xyz[:, 2]) * 60) % 256], axis=1).astype(np.int64)
        yield {"xyz": xyz, "intensity": intensity, "rgb": rgb, "invalid": invalid}


def write_e57(path: str, n: int, chunks: Iterator[Dict[str, np.ndarray]], *,
              pose: Optional[Tuple[Sequence[float], Sequence[float]]] = None,
              scale_m: Optional[float] = 0.001, extent_m: float = 50.0,
              intensity: bool = True, colour: bool = False, invalid: bool = False,
              name: str = "synthetic", images: Sequence[dict] = ()) -> None:
    """Writes one scan of `n` points from `chunks` (room_chunks' dicts) to a new E57 file, one
    chunk at a time. Coordinates are scaled integers of `scale_m` within ±`extent_m`, or
    doubles with `scale_m` None; `pose` is (translation, quaternion w x y z) or None (no pose).
    Intensity (limits 0..65535), colour (0..255) and the invalid state are written as asked.
    `images`: spherical images taken with the scan (images2D), each a dict {name, png (bytes),
    width, height, pose (as `pose`), and optionally mask (the imageMask's bytes), pixel_rad
    (the pixels' angle; default: the whole sphere's, 2π / width by π / height) and cylinder
    ({pixel_height_m, radius_m, principal_y_px}: a cylindrical image instead)}."""
    import pye57
    from pye57 import libe57

    e57 = pye57.E57(path, mode="w")
    imf = e57.image_file
    scan = libe57.StructureNode(imf)
    guid = "{%s}" % uuid.uuid4()
    scan.set("guid", libe57.StringNode(imf, guid))
    scan.set("name", libe57.StringNode(imf, name))
    if pose is not None:
        scan.set("pose", _e57_pose(imf, pose))
    proto = libe57.StructureNode(imf)
    fields = []
    for axis in "XYZ":
        if scale_m is None:
            coord = libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, -1e300, 1e300)
        else:
            top = int(np.ceil(extent_m / scale_m))
            coord = libe57.ScaledIntegerNode(imf, 0, -top, top, scale_m, 0.0)
        proto.set(f"cartesian{axis}", coord)
        fields.append((f"cartesian{axis}", "d"))
    if intensity:
        proto.set("intensity", libe57.IntegerNode(imf, 0, 0, 65535))
        limits = libe57.StructureNode(imf)
        limits.set("intensityMinimum", libe57.IntegerNode(imf, 0))
        limits.set("intensityMaximum", libe57.IntegerNode(imf, 65535))
        scan.set("intensityLimits", limits)
        fields.append(("intensity", "u2"))
    if colour:
        limits = libe57.StructureNode(imf)
        for c in ("Red", "Green", "Blue"):
            proto.set(f"color{c}", libe57.IntegerNode(imf, 0, 0, 255))
            limits.set(f"color{c}Minimum", libe57.IntegerNode(imf, 0))
            limits.set(f"color{c}Maximum", libe57.IntegerNode(imf, 255))
            fields.append((f"color{c}", "u1"))
        scan.set("colorLimits", limits)
    if invalid:
        proto.set("cartesianInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
        fields.append(("cartesianInvalidState", "i1"))
    points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    for image in images:
        _write_e57_spherical(imf, guid, image)

    # Buffer types libe57's bindings read right: 64-bit integers are taken for 32-bit ones.
    capacity = 1 << 18
    arrays = {f: np.zeros(capacity, dtype=t) for f, t in fields}
    buffers = libe57.VectorSourceDestBuffer()
    for f, _ in fields:
        buffers.append(libe57.SourceDestBuffer(imf, f, arrays[f], capacity, True, True))
    writer = points.writer(buffers)
    written = 0
    for chunk in chunks:
        for at in range(0, len(chunk["xyz"]), capacity):
            part = slice(at, min(at + capacity, len(chunk["xyz"])))
            m = part.stop - part.start
            for k, axis in enumerate("XYZ"):
                arrays[f"cartesian{axis}"][:m] = chunk["xyz"][part, k]
            if intensity:
                arrays["intensity"][:m] = chunk["intensity"][part]
            if colour:
                for k, c in enumerate(("Red", "Green", "Blue")):
                    arrays[f"color{c}"][:m] = chunk["rgb"][part, k]
            if invalid:
                arrays["cartesianInvalidState"][:m] = chunk["invalid"][part]
            writer.write(m)
            written += m
    writer.close()
    e57.close()
    assert written == n, f"wrote {written} of {n} points"


def _e57_pose(imf, pose):
    """An E57 pose node of (translation, quaternion w x y z)."""
    from pye57 import libe57

    (tx, ty, tz), (qw, qx, qy, qz) = pose
    node = libe57.StructureNode(imf)
    rotation = libe57.StructureNode(imf)
    for key, v in zip("wxyz", (qw, qx, qy, qz)):
        rotation.set(key, libe57.FloatNode(imf, float(v)))
    translation = libe57.StructureNode(imf)
    for key, v in zip("xyz", (tx, ty, tz)):
        translation.set(key, libe57.FloatNode(imf, float(v)))
    node.set("rotation", rotation)
    node.set("translation", translation)
    return node


def _write_e57_spherical(imf, scan_guid: str, image: dict) -> None:
    """Appends one spherical image (write_e57's `images`) of the scan `scan_guid` to images2D.
    A blob's bytes can be written only once its node is in the file's tree, so they follow."""
    from pye57 import libe57

    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
    node.set("name", libe57.StringNode(imf, image["name"]))
    node.set("associatedData3DGuid", libe57.StringNode(imf, scan_guid))
    node.set("pose", _e57_pose(imf, image["pose"]))
    rep = libe57.StructureNode(imf)
    width, height = image["width"], image["height"]
    rep.set("imageWidth", libe57.IntegerNode(imf, width, 0, 1 << 30))
    rep.set("imageHeight", libe57.IntegerNode(imf, height, 0, 1 << 30))
    cylinder = image.get("cylinder")
    rep.set("pixelWidth", libe57.FloatNode(imf, image.get("pixel_rad", 2 * np.pi / width)))
    if cylinder:
        rep.set("pixelHeight", libe57.FloatNode(imf, cylinder["pixel_height_m"]))
        rep.set("radius", libe57.FloatNode(imf, cylinder["radius_m"]))
        rep.set("principalPointY", libe57.FloatNode(imf, cylinder["principal_y_px"]))
    else:
        rep.set("pixelHeight", libe57.FloatNode(imf, image.get("pixel_rad", np.pi / height)))
    blobs = []
    for key in ("pngImage", "imageMask") if image.get("mask") else ("pngImage",):
        data = image["png" if key == "pngImage" else "mask"]
        blobs.append((libe57.BlobNode(imf, len(data)), data))
        rep.set(key, blobs[-1][0])
    node.set("cylindricalRepresentation" if cylinder else "sphericalRepresentation", rep)
    imf.root()["images2D"].append(node)
    for blob, data in blobs:
        blob.write(np.frombuffer(data, dtype=np.uint8).copy(), 0, len(data))


def write_las(path: str, world_xyz: np.ndarray, *, intensity: np.ndarray,
              rgb: Optional[np.ndarray] = None, offset: Sequence[float] = (0.0, 0.0, 0.0),
              scale_m: float = 0.001) -> None:
    """Writes points (world coordinates) to a LAS file, or LAZ when `path` ends in .laz
    (laspy with lazrs): point format 3 (with 16-bit RGB) when `rgb` is given (uint16 values,
    stored as they are), else 1; coordinates as integers of `scale_m` around `offset`."""
    import laspy

    header = laspy.LasHeader(point_format=3 if rgb is not None else 1, version="1.2")
    header.offsets = np.asarray(offset, dtype=np.float64)
    header.scales = np.array([scale_m] * 3)
    with laspy.open(path, mode="w", header=header) as writer:
        step = 1 << 17
        for at in range(0, len(world_xyz), step):
            part = slice(at, min(at + step, len(world_xyz)))
            record = laspy.ScaleAwarePointRecord.zeros(part.stop - part.start, header=header)
            record.x = world_xyz[part, 0]
            record.y = world_xyz[part, 1]
            record.z = world_xyz[part, 2]
            record.intensity = intensity[part]
            if rgb is not None:
                record.red, record.green, record.blue = rgb[part, 0], rgb[part, 1], rgb[part, 2]
            writer.write_points(record)


def room_grid(rows: int, columns: int, room: Sequence[float] = ROOM) -> np.ndarray:
    """A structured scan of the room: (columns·rows, 3) sensor-frame points (float64), column
    after column as a PTX file holds them, the ray of row r and column c at azimuth
    2π·c/columns and elevation from −80° (row 0) to +80°."""
    c, r = np.meshgrid(np.arange(columns), np.arange(rows), indexing="ij")
    az = 2 * np.pi * c.ravel() / columns
    el = np.radians(-80.0 + 160.0 * r.ravel() / max(rows - 1, 1))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    with np.errstate(divide="ignore"):
        tx = room[0] / np.abs(d[:, 0])
        ty = room[1] / np.abs(d[:, 1])
        tz = np.where(d[:, 2] < 0, room[2], room[3]) / np.abs(d[:, 2])
    return d * np.minimum(np.minimum(tx, ty), tz)[:, None]


def write_ptx(f, points: np.ndarray, rows: int, columns: int, *, position, axes, transform,
              intensity: Optional[np.ndarray] = None, rgb: Optional[np.ndarray] = None,
              newline: str = "\n", column_vectors: bool = False) -> None:
    """Appends one PTX scan to the open text file `f`: its header (columns, rows, the scanner
    position, its x, y and z axes as the columns of `axes`, and the 4x4 `transform`, written
    for row vectors as PTX does, or for column vectors when asked) and `points` (N = rows ×
    columns, as stored: (0, 0, 0) for no return) with `intensity` in [0, 1] and `rgb` 0..255
    when given."""
    t = np.asarray(transform, dtype=np.float64)
    rows_out = t if column_vectors else t.T
    lines = [str(columns), str(rows), " ".join(f"{v:.6f}" for v in position)]
    lines += [" ".join(f"{v:.9f}" for v in np.asarray(axes)[:, i]) for i in range(3)]
    lines += [" ".join(f"{v:.9f}" if abs(v) < 1e3 else f"{v:.6f}" for v in row)
              for row in rows_out]
    f.write(newline.join(lines) + newline)
    cols = [np.asarray(points, dtype=np.float64)]
    fmt = ["%.6f"] * 3
    if intensity is not None:
        cols.append(np.asarray(intensity, dtype=np.float64)[:, None])
        fmt.append("%.4f")
    if rgb is not None:
        cols.append(np.asarray(rgb, dtype=np.float64))
        fmt += ["%d"] * 3
    np.savetxt(f, np.concatenate(cols, axis=1), fmt=" ".join(fmt), newline=newline)
