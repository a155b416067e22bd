"""Readers for what a capture rig leaves on disk: PLY, E57, PTX, PCD, LAS/LAZ and ASCII (PTS,
XYZ, CSV) point clouds and the scan manifest.

PLY: ASCII, binary little endian and binary big endian; the ``vertex`` element's ``x, y, z``
(float or double) and an optional ``intensity`` (any numeric type); other properties and elements
are ignored. The manifest is the JSON file ``vasl_scene`` writes (documented in README.md); its
paths are relative to the manifest file.

E57, PTX, PCD, LAS/LAZ and ASCII scans can be far larger than memory (a terrestrial scan holds up to a
few hundred million points), so their points are a `PointSource`: read chunk by chunk
(`CHUNK_POINTS` at a time) whenever they are wanted, with everything the ingest header needs (the
point count, whether there is intensity and colour, the normalisation limits) settled before the
first point is sent.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from .types import Pose, srgb_to_linear

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance")
#: PLY vertex properties that give a point's colour (the first triple found).
_COLOUR_NAMES = (("red", "green", "blue"), ("r", "g", "b"),
                 ("diffuse_red", "diffuse_green", "diffuse_blue"))
#: PLY vertex properties that give a point's row and column in the scanner's range grid.
_ROW_NAMES = ("row", "rowindex", "scalar_row")
_COLUMN_NAMES = ("column", "col", "columnindex", "scalar_column")


@dataclass
class PointCloud:
    """Points of one scan in the sensor frame."""

    xyz_m: np.ndarray  #: (N, 3) float32, metres
    intensity: Optional[np.ndarray] = None  #: (N,) float32 or None
    rgb: Optional[np.ndarray] = None  #: (N, 3) float32 linear colour, or None
    grid: Optional[np.ndarray] = None  #: (N, 2) uint32 range-grid row and column, or None

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])


#: Points a streaming reader holds at once: its buffers (a few float64 fields a point) and the
#: packed chunk stay within a few MB however large the scan.
CHUNK_POINTS = 1 << 16
#: No terrestrial scanner measures this far (the longest-range ones reach about 6 km): points that
#: lie farther from their scan's origin were not stored in that scan's own frame but in a world
#: (georeferenced) frame.
GEOREFERENCED_M = 10_000.0


class PointSource:
    """The points of one scan in the sensor frame, read chunk by chunk whenever they are wanted
    and as often (an ingest that is sent again reads them again), holding one chunk at a time.

    `count`, `has_intensity` and `has_rgb` are known before any point is read, because the
    ingest header declares them. `count` is what `chunks` yields in all, or more: a reader that
    drops a point it finds unusable only while reading it (an E57 coordinate that is not
    finite) yields fewer, and an ingest sends the difference as (0, 0, 0), the scanners'
    "no return" marker that the server skips. `notes` say what was decided on reading (limits,
    colour depth, frame conversions)."""

    path: str = ""
    count: int = 0
    has_intensity: bool = False
    has_rgb: bool = False
    #: (rows, columns) of the scan's range grid when each point has its row and column (E57
    #: rowIndex / columnIndex): the server then fills the gaps between neighbouring returns
    grid_shape: Optional[Tuple[int, int]] = None

    def __init__(self) -> None:
        self.notes: List[str] = []

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        """PointClouds of at most `chunk_points` points each, in the file's order."""
        raise NotImplementedError

    def read(self) -> PointCloud:
        """Every point at once: what a caller that wants whole arrays gets (its memory grows
        with the scan, unlike `chunks`)."""
        parts = list(self.chunks())
        if not parts:
            return PointCloud(np.zeros((0, 3), np.float32),
                              np.zeros(0, np.float32) if self.has_intensity else None,
                              np.zeros((0, 3), np.float32) if self.has_rgb else None)
        return PointCloud(
            np.ascontiguousarray(np.concatenate([p.xyz_m for p in parts]), dtype=np.float32),
            np.concatenate([p.intensity for p in parts]) if self.has_intensity else None,
            np.concatenate([p.rgb for p in parts]) if self.has_rgb else None)

    def __len__(self) -> int:
        return int(self.count)


def rotation_matrix(quaternion_xyzw) -> np.ndarray:
    """The 3x3 rotation (float64) of a quaternion (x, y, z, w), normalised first."""
    x, y, z, w = (float(v) for v in quaternion_xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def world_to_sensor(xyz_world: np.ndarray, pose: Pose) -> np.ndarray:
    """World points (N, 3) to the sensor frame of `pose` (T_world_sensor): p = Rᵀ(x − o), in
    float64, so that georeferenced coordinates (10^5-10^7 m, where float32 steps by up to a
    metre) keep their millimetres once the small sensor-frame values become float32."""
    x = np.asarray(xyz_world, dtype=np.float64) - np.asarray(pose.position_m, dtype=np.float64)
    return x @ rotation_matrix(pose.quaternion_xyzw)  # rows: (Rᵀ v)ᵀ = vᵀ R


def read_ply(path: str) -> PointCloud:
    """Reads the vertices of a PLY file: x, y, z; intensity and colour (red, green, blue) in
    [0, 1] (see `_ply_unit`), colour then linearised (sRGB); row and column as the range grid.
    ValueError for a malformed or unsupported file."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise ValueError(f"{path}: truncated PLY header")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[nl + 1:]
    fmt = None
    elements: List[Tuple[str, int, list]] = []  # (name, count, [(name, type, is_list, count_t)])
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise ValueError(f"{path}: unsupported PLY format line '{line}'")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3:
                raise ValueError(f"{path}: bad element line '{line}'")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"{path}: property before any element: '{line}'")
            if len(parts) == 5 and parts[1] == "list":
                elements[-1][2].append((parts[4], parts[3], True, parts[2]))
            elif len(parts) == 3:
                if parts[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type '{parts[1]}'")
                elements[-1][2].append((parts[2], parts[1], False, None))
            else:
                raise ValueError(f"{path}: bad property line '{line}'")
    if fmt is None:
        raise ValueError(f"{path}: PLY header has no format line")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    vi = names.index("vertex")
    _, count, props = elements[vi]
    prop_names = [p[0] for p in props]
    for axis in ("x", "y", "z"):
        if axis not in prop_names:
            raise ValueError(f"{path}: the vertex element has no '{axis}' property")
    intensity_name = next((p for p in prop_names if p.lower() in _INTENSITY_NAMES), None)

    if fmt == "ascii":
        lines = body.decode("ascii", errors="replace").splitlines()
        skip = sum(e[1] for e in elements[:vi])
        rows = lines[skip:skip + count]
        if len(rows) < count:
            raise ValueError(f"{path}: expected {count} vertex lines, found {len(rows)}")
        if any(p[2] for p in props):
            raise ValueError(f"{path}: list properties in the vertex element are not supported")
        table = np.array([r.split()[:len(props)] for r in rows], dtype=np.float64).reshape(count, len(props))
        col = {n: table[:, i] for i, n in enumerate(prop_names)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        offset = 0
        for name, n, eprops in elements[:vi]:
            if any(p[2] for p in eprops):
                raise ValueError(f"{path}: element '{name}' with list properties precedes 'vertex'")
            offset += n * sum(np.dtype(_PLY_TYPES[p[1]]).itemsize for p in eprops)
        if any(p[2] for p in props):
            raise ValueError(f"{path}: list properties in the vertex element are not supported")
        dtype = np.dtype([(p[0], endian + _PLY_TYPES[p[1]]) for p in props])
        need = offset + count * dtype.itemsize
        if len(body) < need:
            raise ValueError(f"{path}: truncated: {count} vertices need {need} bytes after the "
                             f"header, the file has {len(body)}")
        table = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
        col = {n: table[n] for n in prop_names}
    xyz = np.stack([col["x"], col["y"], col["z"]], axis=1).astype(np.float32)
    types = {p[0]: p[1] for p in props}
    intensity = (_ply_unit(col[intensity_name], types[intensity_name]).astype(np.float32)
                 if intensity_name else None)
    rgb = None
    colour_names = _ply_colour_names(prop_names)
    if colour_names:
        rgb = srgb_to_linear(np.stack([_ply_unit(col[n], types[n], colour=True)
                                       for n in colour_names], axis=1)).astype(np.float32)
    grid = None
    row_name = next((p for p in prop_names if p.lower() in _ROW_NAMES), None)
    column_name = next((p for p in prop_names if p.lower() in _COLUMN_NAMES), None)
    if row_name and column_name and count > 0:  # the scan's range grid (see PointSource)
        rc = np.stack([col[row_name], col[column_name]], axis=1).astype(np.float64)
        if not np.all(np.isfinite(rc)) or np.any(rc < 0) or np.any(rc != np.floor(rc)):
            raise ValueError(f"{path}: '{row_name}' and '{column_name}' must be whole numbers "
                             ">= 0 (a point's row and column in the scanner's grid)")
        shape = (int(rc[:, 0].max()) + 1, int(rc[:, 1].max()) + 1)
        if shape[0] * shape[1] > MAX_GRID_CELLS:
            raise ValueError(f"{path}: a {shape[0]} x {shape[1]} range grid exceeds 2^32 cells")
        grid = rc.astype(np.uint32)
    return PointCloud(xyz_m=np.ascontiguousarray(xyz), intensity=intensity, rgb=rgb, grid=grid)


def _ply_colour_names(names: Sequence[str]) -> Optional[Tuple[str, str, str]]:
    """The vertex properties holding a point's red, green and blue, if it has all three."""
    lower = {n.lower(): n for n in names}
    for r, g, b in _COLOUR_NAMES:
        if r in lower and g in lower and b in lower:
            return lower[r], lower[g], lower[b]
    return None


def intensity_scale(lo: float, hi: float) -> Tuple[float, float, str]:
    """How intensities found between `lo` and `hi` (a file that gives no limits) come into
    [0, 1], as (i − a) / b: (a, b) and what was decided. Kept in [0, 1]; Leica's −2048..2047
    as (i + 2048) / 4095; 0..255 and 0..65535 over their top; any other range by itself."""
    if lo >= 0.0 and hi <= 1.0:
        return 0.0, 1.0, "intensity in [0, 1], kept"
    if lo >= -2048.0 and hi <= 2047.0 and lo < 0.0:
        return -2048.0, 4095.0, "intensity -2048..2047 (Leica): (i + 2048) / 4095"
    if lo >= 0.0 and hi <= 255.0:
        return 0.0, 255.0, "intensity 0..255: over 255"
    if lo >= 0.0 and hi <= 65535.0:
        return 0.0, 65535.0, "intensity 0..65535: over 65535"
    return lo, (hi - lo if hi > lo else 1.0), f"intensity scaled by the data's range {lo:g}..{hi:g}"


def _ply_unit(values: np.ndarray, ply_type: str, colour: bool = False) -> np.ndarray:
    """A PLY intensity or colour channel in [0, 1] (float64): an unsigned integer type over its
    largest value (uchar 255, ushort 65535, ...); a colour of floats as they are in [0, 1], else
    over 255 or 65535 by its largest value; any other intensity by the range its values span
    (intensity_scale)."""
    v = np.asarray(values, dtype=np.float64)
    kind = np.dtype(_PLY_TYPES[ply_type])
    if kind.kind == "u":
        return np.clip(v / float(np.iinfo(kind).max), 0.0, 1.0)
    finite = v[np.isfinite(v)]
    lo = float(finite.min()) if finite.size else 0.0
    hi = float(finite.max()) if finite.size else 1.0
    if colour:
        top = 1.0 if hi <= 1.0 else 255.0 if hi <= 255.0 else 65535.0
        return np.clip(np.nan_to_num(v, nan=0.0) / top, 0.0, 1.0)
    a, b, _ = intensity_scale(lo, hi)
    return np.clip(np.nan_to_num((v - a) / b, nan=0.0), 0.0, 1.0)


PINHOLE_KEYS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2", "k4",
                "field_of_view_deg")
#: A pinhole camera's `lens`: Brown-Conrady (VASL-MODEL §2.2, k1-k3, p1, p2; the default) or a
#: fisheye (Kannala-Brandt equidistant, OpenCV's cv::fisheye and ROS's "equidistant": k1-k4).
LENSES = ("brown-conrady", "fisheye")


def _json_object(obj, keys: Sequence[str], where: str) -> dict:
    """`obj` when it is a JSON object of no other fields than `keys`; ValueError naming `where`
    otherwise."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected an object with {', '.join(keys)}")
    unknown = sorted(set(obj) - set(keys))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(unknown)}; "
                         f"expected {', '.join(keys)}")
    return obj


def pinhole_from_json(obj, where: str) -> Dict[str, object]:
    """A pinhole camera's intrinsics (VASL-MODEL §2.2: x right, y down, z forward; pixels;
    Brown-Conrady k1 k2 k3 p1 p2, default 0; or with "lens": "fisheye", Kannala-Brandt k1 k2 k3
    k4 and optionally its field_of_view_deg, a circular fisheye's image circle) from a JSON
    object: the numbers as floats and "lens". ValueError naming the field."""
    _json_object(obj, PINHOLE_KEYS + ("lens",), where)
    out: Dict[str, object] = {}
    for key in PINHOLE_KEYS:
        if key not in obj and key in ("fx_px", "fy_px", "cx_px", "cy_px"):
            raise ValueError(f"{where}: missing '{key}'")
        try:
            out[key] = float(obj.get(key, 0.0))
        except (TypeError, ValueError):
            raise ValueError(f"{where}.{key}: expected a number, got {obj.get(key)!r}") from None
        if not math.isfinite(out[key]):
            raise ValueError(f"{where}.{key}: must be finite")
    if out["fx_px"] <= 0 or out["fy_px"] <= 0:
        raise ValueError(f"{where}: fx_px and fy_px must be > 0 pixels")
    lens = obj.get("lens", "brown-conrady")
    if lens not in LENSES:
        raise ValueError(f"{where}.lens: 'brown-conrady' (the default) or 'fisheye', got "
                         f"{lens!r}")
    if lens == "fisheye" and (out["p1"] or out["p2"]):
        raise ValueError(f"{where}: a fisheye lens has k1-k4 and no tangential p1, p2")
    if lens != "fisheye" and (out["k4"] or out["field_of_view_deg"]):
        raise ValueError(f"{where}: k4 and field_of_view_deg are a fisheye's (\"lens\": "
                         "\"fisheye\"); a Brown-Conrady lens has k1-k3, p1, p2")
    if not 0.0 <= out["field_of_view_deg"] <= 360.0:
        raise ValueError(f"{where}.field_of_view_deg: degrees across, in (0, 360] (0 or absent: "
                         f"unlimited), got {out['field_of_view_deg']}")
    out["lens"] = lens
    return out


SPHERE_KEYS = ("width_px", "height_px", "left_px", "top_px")



def sphere_from_json(obj, where: str) -> Dict[str, int]:
    """Where an equirect panorama of part of the sphere lies in the whole sphere's panorama
    (at the image's pixel pitch, twice as wide as high): {width_px, height_px} of the sphere
    and {left_px, top_px} of the image's top-left pixel in it, whole numbers. ValueError naming
    the field (the server checks that the image lies within it)."""
    _json_object(obj, SPHERE_KEYS, where)
    out = {}
    for key in SPHERE_KEYS:
        value = obj.get(key, 0 if key in ("left_px", "top_px") else None)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{where}.{key}: expected a whole number >= 0, got {value!r}")
        out[key] = value
    if out["width_px"] <= 0 or out["height_px"] <= 0:
        raise ValueError(f"{where}: width_px and height_px must be > 0")
    return out


CYLINDER_KEYS = ("pixel_width_rad", "pixel_height_m", "radius_m", "principal_y_px")


def cylinder_from_json(obj, where: str) -> Dict[str, float]:
    """A cylindrical panorama's projection (an E57 cylindricalRepresentation): columns every
    pixel_width_rad of azimuth, centred on the camera's x axis; rows every pixel_height_m up a
    cylinder of radius_m, the horizon at row coordinate principal_y_px. ValueError naming the
    field."""
    _json_object(obj, CYLINDER_KEYS, where)
    out = {}
    for key in CYLINDER_KEYS:
        value = obj.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not math.isfinite(value):
            raise ValueError(f"{where}.{key}: expected a finite number, got {value!r}")
        out[key] = float(value)
    if min(out["pixel_width_rad"], out["pixel_height_m"], out["radius_m"]) <= 0:
        raise ValueError(f"{where}: pixel_width_rad, pixel_height_m and radius_m must be > 0")
    return out


@dataclass
class PanoramaEntry:
    """One image of a manifest: an equirect panorama, or a pinhole photo with `pinhole`."""

    name: str
    image_path: str  #: absolute path of the encoded image
    modality: str  #: "rgb" or "ir"
    pose: Optional[Pose]  #: None only for a visual reference (it takes the scan's pose)
    angular_resolution_rad: float = 0.0
    pinhole: Optional[Dict[str, float]] = None  #: intrinsics (PINHOLE_KEYS), None: equirect
    #: a photo kept with the scan for people to look at: no projection, colours nothing
    visual_reference: bool = False
    #: absolute path of the image's mask (the share of each pixel the camera reports); None: none
    mask_path: Optional[str] = None
    #: an equirect panorama of part of the sphere: where it lies in the whole sphere's
    #: (SPHERE_KEYS); None: the image is the whole sphere
    sphere: Optional[Dict[str, int]] = None
    #: a cylindrical panorama's projection (CYLINDER_KEYS); None: not cylindrical
    cylinder: Optional[Dict[str, float]] = None


@dataclass
class Manifest:
    """One scan as described by a manifest file (README.md, "Scan manifest")."""

    path: str
    scan: str
    rig: str
    captured_utc: str
    pose: Pose
    #: absolute path of the PLY, LAS, LAZ, PTX or ASCII file (LAS/LAZ and ASCII: world
    #: coordinates, turned into the sensor frame with `pose`; PTX: one scan, registered by its
    #: transform, then the same);
    #: None: a camera-only scan
    points_path: Optional[str]
    divergence_rad: float
    panoramas: List[PanoramaEntry] = field(default_factory=list)


def _pose_from_json(obj, where: str) -> Pose:
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected an object with 'position' and 'quaternion'")
    position = obj.get("position", [0.0, 0.0, 0.0])
    quaternion = obj.get("quaternion", [0.0, 0.0, 0.0, 1.0])
    return Pose.make(position, quaternion, where=where)


def _flag(obj: dict, key: str, where: str) -> bool:
    """An optional JSON boolean; ValueError for anything but true or false."""
    value = obj.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"{where}.{key} must be true or false, got {value!r}")
    return value


def _mask_path(panorama: dict, base: str, reference: bool, where: str) -> Optional[str]:
    """A panorama's optional `mask`: the absolute path of an image file that exists, relative
    to the manifest's folder `base`; None when not given. ValueError naming `where` for one
    that is not a path, names no file, or belongs to a visual reference (which colours
    nothing)."""
    mask = panorama.get("mask")
    if mask is None:
        return None
    if not isinstance(mask, str) or not mask:
        raise ValueError(f"{where}.mask must be the path of an image file (relative to the "
                         f"manifest), got {mask!r}")
    if reference:
        raise ValueError(f"{where} is a visual reference: it colours nothing, so it takes no "
                         "mask")
    resolved = os.path.join(base, mask)
    if not os.path.isfile(resolved):
        raise ValueError(f"{where}.mask: no such file {resolved}")
    return resolved


def _panorama_lens(p: dict, base: str, where: str) -> Optional[Dict[str, object]]:
    """A manifest panorama's lens: its `pinhole` object, or its `camera_info` (a ROS
    camera_info YAML file, relative to the manifest); None for an equirect panorama."""
    if "pinhole" in p and "camera_info" in p:
        raise ValueError(f"{where}: give the lens as pinhole or as camera_info, not both")
    if "camera_info" in p:
        if not isinstance(p["camera_info"], str):
            raise ValueError(f"{where}.camera_info: expected a path (a Kalibr camchain's camera "
                             "as path#cam1)")
        return pinhole_from_camera_info(os.path.join(base, p["camera_info"]))
    return pinhole_from_json(p["pinhole"], f"{where}.pinhole") if "pinhole" in p else None


def read_manifest(path: str) -> Manifest:
    """Reads a scan manifest (JSON). ValueError naming the field for a malformed one."""
    with open(path, "r", encoding="utf-8") as f:
        try:
            doc = json.load(f)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{path}: not a scan manifest (JSON): {e}") from e
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: not a scan manifest (a JSON object)")
    base = os.path.dirname(os.path.abspath(path))

    def need(obj, key, where):
        if not isinstance(obj, dict) or key not in obj:
            raise ValueError(f"{path}: missing '{where}{key}'")
        return obj[key]

    scan = need(doc, "scan", "")
    if not isinstance(scan, str) or not scan:
        raise ValueError(f"{path}: 'scan' must be a non-empty string")
    lidar = doc.get("lidar")  # none: a camera-only scan (its images colour known geometry)
    if lidar is None and not doc.get("panoramas"):
        raise ValueError(f"{path}: a scan needs 'lidar' (points) or 'panoramas' (images)")
    points = need(lidar, "points", "lidar.") if lidar is not None else None
    divergence = float((lidar or {}).get("divergence_rad", 0.0003))
    if not math.isfinite(divergence) or divergence <= 0:
        raise ValueError(f"{path}: 'lidar.divergence_rad' must be > 0, got {divergence}")
    panoramas = []
    names = set()
    for i, p in enumerate(doc.get("panoramas", [])):
        name = need(p, "name", f"panoramas[{i}].")
        if name in names:
            raise ValueError(f"{path}: panorama name '{name}' is used twice")
        names.add(name)
        modality = p.get("modality", "rgb").lower()
        if modality not in ("rgb", "ir"):
            raise ValueError(f"{path}: panoramas[{i}].modality must be 'rgb' or 'ir', got '{modality}'")
        reference = _flag(p, "visual_reference", f"{path}: panoramas[{i}]")
        mask = _mask_path(p, base, reference, f"{path}: panoramas[{i}] ('{name}')")
        panoramas.append(PanoramaEntry(
            name=name,
            image_path=os.path.join(base, need(p, "image", f"panoramas[{i}].")),
            modality=modality,
            pose=(None if reference and "pose" not in p else  # a reference may take the scan's
                  _pose_from_json(need(p, "pose", f"panoramas[{i}]."),
                                  f"{path}: panoramas[{i}].pose")),
            angular_resolution_rad=float(p.get("angular_resolution_rad", 0.0)),
            pinhole=_panorama_lens(p, base, f"{path}: panoramas[{i}]"),
            visual_reference=reference,
            mask_path=mask,
            sphere=(sphere_from_json(p["sphere"], f"{path}: panoramas[{i}].sphere")
                    if p.get("sphere") is not None else None),
            cylinder=(cylinder_from_json(p["cylinder"], f"{path}: panoramas[{i}].cylinder")
                      if p.get("cylinder") is not None else None),
        ))
    return Manifest(
        path=os.path.abspath(path),
        scan=scan,
        rig=str(doc.get("rig", "")),
        captured_utc=str(doc.get("captured_utc", "")),
        pose=_pose_from_json(need(doc, "pose", ""), f"{path}: pose"),
        points_path=os.path.join(base, points) if points is not None else None,
        divergence_rad=divergence,
        panoramas=panoramas,
    )


@dataclass
class E57Image:
    """One image (images2D) of an E57 file, as it will be ingested or why it will not be."""

    name: str  #: its E57 name, or "image-<n>"
    kind: str  #: "spherical", "pinhole", "cylindrical" or "visual" (visual reference)
    width: int
    height: int
    data: bytes  #: the encoded JPEG or PNG
    #: T_world_camera in VASL's frames: §2.1 for a spherical image (the E57 frame as it is),
    #: §2.2 for a pinhole one (the E57 camera frame, x right, y up, looking along -z, turned
    #: 180° about x); None when the file gives no pose.
    pose: Optional[Pose] = None
    pinhole: Optional[Dict[str, float]] = None  #: intrinsics (PINHOLE_KEYS) of a pinhole image
    scan_guid: str = ""  #: associatedData3DGuid: the scan it was taken with ("" none)
    problem: str = ""  #: why it is not ingested ("" when it is)
    notes: List[str] = field(default_factory=list)  #: what was mended on reading (pose, ...)
    #: a camera image's imageMask (a PNG: the pixels with valid data, as the share of each
    #: pixel the camera reports), sent as its mask; b"": none
    mask: bytes = b""
    #: a spherical image of part of the sphere: where it lies in the whole sphere's panorama
    #: (sphere_from_json's keys); None: the whole sphere, or not spherical
    sphere: Optional[Dict[str, int]] = None
    #: a cylindrical image's projection (cylinder_from_json's keys); None: not cylindrical
    cylinder: Optional[Dict[str, float]] = None


@dataclass
class E57Scan:
    """One scan (data3D) of an E57 file: its points in its own frame (read when wanted), its
    pose and the images taken with it; or the images of the file that belong to no scan
    (points None: a camera-only scan)."""

    scan: str  #: scan id: the file stem, "-<n>" when the file holds several scans
    pose: Pose  #: the data3D pose (sensor frame to the file's world frame)
    #: the valid points, streamed (`E57Points`); None: images only
    points: Optional["E57Points"] = None
    images: List[E57Image] = field(default_factory=list)
    _cloud: Optional[PointCloud] = field(default=None, repr=False, compare=False)

    @property
    def cloud(self) -> Optional[PointCloud]:
        """Every valid point read whole (intensity scaled to [0, 1]); None: images only. Read on
        first use and kept: an ingest streams `points` instead and never needs it."""
        if self._cloud is None and self.points is not None:
            self._cloud = self.points.read()
        return self._cloud

    @property
    def notes(self) -> List[str]:
        return self.points.notes if self.points is not None else []

    @property
    def ingestible_images(self) -> List[E57Image]:
        return [im for im in self.images if not im.problem]


_E57_XYZ = ("cartesianX", "cartesianY", "cartesianZ")
_E57_RAE = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_E57_RGB = ("colorRed", "colorGreen", "colorBlue")
_E57_GRID = ("rowIndex", "columnIndex")
#: Cells a range grid may have (the server's limit: 2^32).
MAX_GRID_CELLS = 1 << 32


class E57Points(PointSource):
    """The valid points of one scan of an E57 file, read chunk by chunk through pye57's
    libe57 bindings (a CompressedVectorReader filling fixed-size SourceDestBuffers, as
    pye57's own read_scan_raw does for a whole scan at once), so a scan of any size never
    sits in memory whole.

    Each chunk: coordinates in float64 (spherical ones converted with VASL-MODEL §2.1's axes:
    azimuth from +x toward +y, elevation up), points flagged invalid or not finite dropped,
    points stored in a world frame turned into the sensor frame (`to_sensor`) while still
    float64, then float32; intensity scaled to [0, 1] and colour scaled and linearised (sRGB) by
    the limits settled when the file was opened (`intensity_limits`, `colour_limits`; see
    read_e57 for where they come from)."""

    def __init__(self, path: str, index: int, where: str, spherical: bool,
                 invalid_field: Optional[str], records: int):
        super().__init__()
        self.path = path
        self.index = index  #: data3D index
        self.where = where
        self.spherical = spherical
        self.invalid_field = invalid_field
        self.records = records  #: the scan's record count, invalid points included
        self.count = records
        self.intensity_limits: Optional[Tuple[float, float]] = None
        self.colour_limits: Optional[List[Tuple[float, float]]] = None  #: red, green, blue
        self.to_sensor: Optional[Pose] = None  #: set: the points are stored in its world frame
        self.grid_origin: Tuple[int, int] = (0, 0)  #: rowMinimum, columnMinimum of the grid

    @property
    def coordinate_fields(self) -> Tuple[str, ...]:
        return _E57_RAE if self.spherical else _E57_XYZ

    def raw_chunks(self, fields: Sequence[str], chunk_points: int = CHUNK_POINTS
                   ) -> Iterator[Dict[str, np.ndarray]]:
        """The scan's records chunk by chunk, `fields` as float64 arrays (views into buffers
        reused for the next chunk: copy what must outlive it). ValueError naming the scan when
        libe57 cannot read them."""
        import pye57
        from pye57 import libe57

        try:
            e57 = pye57.E57(self.path)
            points = e57.data3d[self.index]["points"]
            arrays = {f: np.empty(chunk_points, dtype=np.float64) for f in fields}
            buffers = libe57.VectorSourceDestBuffer()
            for f in fields:  # doConversion: integer and scaled fields into float64 buffers
                buffers.append(libe57.SourceDestBuffer(e57.image_file, f, arrays[f],
                                                       chunk_points, True, True))
            reader = points.reader(buffers)
        except Exception as e:
            raise ValueError(f"{self.where}: cannot be read: {str(e).splitlines()[0]}") from e
        try:
            while True:
                try:
                    n = reader.read()
                except Exception as e:
                    raise ValueError(f"{self.where}: cannot be read: "
                                     f"{str(e).splitlines()[0]}") from e
                if n == 0:
                    return
                yield {f: a[:n] for f, a in arrays.items()}
        finally:
            reader.close()
            e57.close()

    def local_chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[np.ndarray]:
        """The valid points' coordinates as stored (float64, Cartesian), chunk by chunk."""
        fields = list(self.coordinate_fields) + ([self.invalid_field] if self.invalid_field
                                                 else [])
        for raw in self.raw_chunks(fields, chunk_points):
            xyz, keep = self._xyz(raw)
            yield xyz[keep]

    def _xyz(self, raw: Dict[str, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
        """Cartesian float64 coordinates of a chunk and the mask of its valid points."""
        if self.spherical:
            r, az, el = (raw[f] for f in _E57_RAE)
            xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                            r * np.sin(el)], axis=1)
        else:
            xyz = np.stack([raw[f] for f in _E57_XYZ], axis=1)
        keep = np.all(np.isfinite(xyz), axis=1)
        if self.invalid_field:
            keep &= raw[self.invalid_field] == 0
        return xyz, keep

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        fields = list(self.coordinate_fields)
        if self.invalid_field:
            fields.append(self.invalid_field)
        if self.has_intensity:
            fields.append("intensity")
        if self.has_rgb:
            fields.extend(_E57_RGB)
        if self.grid_shape:
            fields.extend(_E57_GRID)
        for raw in self.raw_chunks(fields, chunk_points):
            xyz, keep = self._xyz(raw)
            xyz = xyz[keep]
            if self.to_sensor is not None:
                xyz = world_to_sensor(xyz, self.to_sensor)
            intensity = rgb = None
            if self.has_intensity:
                intensity = _scaled(raw["intensity"][keep], self.intensity_limits)
                intensity = intensity.astype(np.float32)
            if self.has_rgb:
                rgb = np.stack([srgb_to_linear(_scaled(raw[f][keep], lim))
                                for f, lim in zip(_E57_RGB, self.colour_limits)], axis=1)
            grid = None
            if self.grid_shape:  # from the index bounds' minimum, clipped into the grid
                rc = np.stack([raw[f][keep] - lo for f, lo in zip(_E57_GRID, self.grid_origin)],
                              axis=1)
                grid = np.clip(rc, 0, np.asarray(self.grid_shape) - 1).astype(np.uint32)
            yield PointCloud(np.ascontiguousarray(xyz, dtype=np.float32), intensity, rgb, grid)


def _scaled(values: np.ndarray, limits: Tuple[float, float]) -> np.ndarray:
    """Values scaled to [0, 1] by (min, max) limits; all ones when the limits span nothing."""
    lo, hi = limits
    return (values - lo) / (hi - lo) if hi > lo else np.ones_like(values)


def _e57_number(node) -> Optional[float]:
    """A numeric node's value (a scaled integer's scaled value), None for anything else."""
    for attr in ("scaledValue", "value"):
        if hasattr(node, attr):
            try:
                return float(getattr(node, attr)())
            except (TypeError, ValueError):
                return None
    return None


def _e57_limits(node, lo_key: str, hi_key: str) -> Optional[Tuple[float, float]]:
    """(min, max) from a limits structure (intensityLimits, colorLimits), None without both."""
    try:
        if node.isDefined(lo_key) and node.isDefined(hi_key):
            lo, hi = _e57_number(node[lo_key]), _e57_number(node[hi_key])
            if lo is not None and hi is not None and math.isfinite(lo) and math.isfinite(hi):
                return lo, hi
    except Exception:
        pass
    return None


def _e57_field_limits(prototype, name: str) -> Optional[Tuple[float, float]]:
    """The value range a point field's prototype declares: an integer's or scaled integer's
    bounds; a float's only when it states bounds (libe57's default is the float type's whole
    range, which says nothing)."""
    node = prototype[name]
    for lo_attr, hi_attr in (("scaledMinimum", "scaledMaximum"), ("minimum", "maximum")):
        if hasattr(node, lo_attr):
            lo, hi = float(getattr(node, lo_attr)()), float(getattr(node, hi_attr)())
            if hasattr(node, "precision") and not (abs(lo) < 1e30 and abs(hi) < 1e30):
                return None
            return lo, hi
    return None


def _e57_open_scan(e57, i: int, path: str, where: str, stem: str, count: int
                   ) -> Tuple[str, Pose, bool, "E57Points"]:
    """A data3D's name, pose, whether it states a pose, and its points with the ingest header's
    facts settled: valid point count, intensity and colour limits. ValueError for a scan
    without coordinates or without any valid point."""
    from pye57 import libe57

    node = e57.data3d[i]
    cv = node["points"]
    prototype = libe57.StructureNode(cv.prototype())
    names = [prototype.get(j).elementName() for j in range(prototype.childCount())]
    if all(f in names for f in _E57_XYZ):
        spherical, invalid = False, "cartesianInvalidState"
    elif all(f in names for f in _E57_RAE):
        spherical, invalid = True, "sphericalInvalidState"
    else:
        raise ValueError(f"{where}: has neither Cartesian nor spherical coordinates")
    records = int(cv.childCount())
    if records == 0:
        raise ValueError(f"{where}: holds no valid point (it has no record)")
    points = E57Points(path, i, where, spherical, invalid if invalid in names else None,
                       records)
    points.has_intensity = "intensity" in names
    points.has_rgb = all(f in names for f in _E57_RGB)
    survey = []  # what only a first pass over the data can tell
    if points.invalid_field and _e57_field_limits(prototype, invalid) != (0.0, 0.0):
        survey.append(invalid)
    if points.has_intensity:
        points.intensity_limits = (
            (_e57_limits(node["intensityLimits"], "intensityMinimum", "intensityMaximum")
             if node.isDefined("intensityLimits") else None)
            or _e57_field_limits(prototype, "intensity"))
        if points.intensity_limits is None:
            survey.append("intensity")
    if points.has_rgb:
        header = node["colorLimits"] if node.isDefined("colorLimits") else None
        limits = [(_e57_limits(header, f"{f}Minimum", f"{f}Maximum") if header is not None
                   else None) or _e57_field_limits(prototype, f) for f in _E57_RGB]
        if all(lim is not None for lim in limits):
            points.colour_limits = limits
        else:
            survey.extend(_E57_RGB)
    if survey:
        _e57_survey(points, survey)
    if points.count == 0:
        raise ValueError(f"{where}: holds no valid point")
    if all(f in names for f in _E57_GRID):
        _e57_grid(points, node, prototype)
    has_pose = node.isDefined("pose")
    notes: List[str] = []
    pose = ((_e57_pose(node["pose"], where, notes, partial=True) if has_pose else None)
            or Pose.make([0, 0, 0]))
    points.notes.extend(notes)
    if has_pose and pose == Pose.make([0, 0, 0]):
        has_pose = False
    name = stem if count == 1 else f"{stem}-{i + 1}"
    return name, pose, has_pose, points


def _e57_grid(points: E57Points, node, prototype) -> None:
    """The scan's range grid from its rowIndex / columnIndex fields: bounds from the scan's
    indexBounds, else the fields' declared ranges. A grid without bounds, or too large, is left
    out (and said so): the scan is then ingested as unordered points."""
    bounds = None
    if node.isDefined("indexBounds"):
        b = node["indexBounds"]
        rows = _e57_limits(b, "rowMinimum", "rowMaximum")
        cols = _e57_limits(b, "columnMinimum", "columnMaximum")
        if rows and cols:
            bounds = rows, cols
    if bounds is None:
        rows, cols = (_e57_field_limits(prototype, f) for f in _E57_GRID)
        if rows and cols:
            bounds = rows, cols
    if bounds is None:
        points.notes.append("rowIndex / columnIndex without bounds: the range grid is not used")
        return
    (r0, r1), (c0, c1) = bounds
    shape = (int(r1 - r0) + 1, int(c1 - c0) + 1)
    if min(shape) < 1 or shape[0] * shape[1] > MAX_GRID_CELLS:
        points.notes.append(f"a {shape[0]}x{shape[1]} range grid is out of bounds: not used")
        return
    points.grid_shape = shape
    points.grid_origin = (int(r0), int(c0))
    points.notes.append(f"range grid {shape[0]} x {shape[1]} (rowIndex, columnIndex): the "
                        "server fills the gaps between neighbouring returns on one surface")


def _e57_survey(points: E57Points, fields: List[str]) -> None:
    """A first pass over the fields the header leaves open, one chunk at a time: the number of
    valid points (when an invalid-state field may flag some), and the data's own intensity
    range and colour depth (when neither the scan's limits nor its prototype give them, as
    the whole-file reader did before: intensity min..max of the valid points; colour 0..255,
    or 0..65535 when a value exceeds 255)."""
    count, lo, hi = 0, math.inf, -math.inf
    top = [0.0, 0.0, 0.0]
    for raw in points.raw_chunks(fields):
        keep = (raw[points.invalid_field] == 0 if points.invalid_field in raw
                else np.ones(len(next(iter(raw.values()))), dtype=bool))
        count += int(keep.sum())
        if "intensity" in raw and keep.any():
            lo = min(lo, float(raw["intensity"][keep].min()))
            hi = max(hi, float(raw["intensity"][keep].max()))
        for c, f in enumerate(_E57_RGB):
            if f in raw and keep.any():
                top[c] = max(top[c], float(raw[f][keep].max()))
    if points.invalid_field in fields:
        points.count = count
    if "intensity" in fields:
        points.intensity_limits = (lo, hi) if hi >= lo else (0.0, 1.0)
        points.notes.append(f"no intensity limits in the file: scaled by the data's range "
                            f"{points.intensity_limits[0]:g}..{points.intensity_limits[1]:g}")
    if _E57_RGB[0] in fields:
        depth = 255.0 if max(top) <= 255 else 65535.0
        points.colour_limits = [(0.0, depth)] * 3
        points.notes.append(f"no colour limits in the file: scaled by 0..{depth:g}")


def _e57_frame(points: E57Points, pose: Pose, has_pose: bool, given: Optional[Pose]
               ) -> Optional[Pose]:
    """Where the scan's points are stored, from its first valid points: None when they lie in
    the scan's own frame; otherwise (points farther than GEOREFERENCED_M from its origin,
    stored in a world frame) the scanner pose to turn them into the sensor frame: the scan's
    pose when it places the scanner among them, else `given`. ValueError when the scanner's
    position is unknown."""
    chunks = points.local_chunks()
    try:
        first = next((c for c in chunks if len(c)), None)
    finally:
        chunks.close()
    if first is None:
        raise ValueError(f"{points.where}: holds no valid point")
    centre = np.median(first, axis=0)
    if given is not None:
        if has_pose:
            raise ValueError(f"{points.where}: the scan has its own pose; a scanner pose is "
                             "only for scans stored without one")
        return given
    if np.linalg.norm(centre) <= GEOREFERENCED_M:
        return None
    if np.linalg.norm(centre - np.asarray(pose.position_m)) <= GEOREFERENCED_M:
        return pose
    raise ValueError(
        f"{points.where}: its points lie {np.linalg.norm(centre) / 1000:.0f} km from the scan's "
        "origin (stored georeferenced) and the scan's pose does not place the scanner among "
        "them: the scanner position is unknown, and visibility needs the origin of the rays. "
        "Give the scanner's pose in the points' frame (vasl ingest --pose x,y,z[,qx,qy,qz,qw])")


def read_e57(path: str, pose=None) -> List[E57Scan]:
    """Reads every scan of an E57 file with pye57: its pose, images, and points as a streaming
    `E57Points` (read chunk by chunk when wanted; `E57Scan.cloud` reads them whole). Points
    flagged invalid are dropped, extension fields (normals, ...) skipped.

    What the ingest header needs is settled here, from the header where it can be:
    - the point count: the scan's record count, less the points an invalid-state field flags
      (a first pass over that field alone when its declared range allows any);
    - intensity scaled to [0, 1] by the scan's ``intensityLimits``, else the intensity field's
      declared range (an integer or scaled integer), else the data's own range (the first pass
      reads it);
    - colour scaled by ``colorLimits``, else the colour fields' declared ranges, else 0..255 or
      0..65535 by the data's largest value; then linearised (E57 colour is display-referred,
      taken as sRGB).
    Points stored in a world frame (farther than GEOREFERENCED_M from the scan's origin) are
    turned into the scanner's frame in float64 before they become float32: with the scan's pose
    when it places the scanner among them, else with `pose` (the scanner's T_world_sensor in the
    points' frame, for a file of one scan stored without a pose; it then becomes the scan's
    pose). ValueError naming the file for one that is not readable E57, holds no scan, a scan
    without valid points, or georeferenced points without a scanner position."""
    try:
        import pye57  # imported here: only E57 users need it
    except ImportError as e:  # pragma: no cover - setup.sh installs it
        raise ValueError("reading E57 needs the pye57 package (deploy/setup.sh installs it)") from e
    given = None if pose is None else Pose.parse(pose)
    stem = os.path.splitext(os.path.basename(path))[0]
    try:
        e57 = pye57.E57(path)
        count = e57.scan_count
    except Exception as e:  # pye57 raises its own exception types
        raise ValueError(f"{path}: not a readable E57 file: {str(e).splitlines()[0]}") from e
    try:
        images = _read_e57_images(e57, path)
        if count == 0 and not images:
            raise ValueError(f"{path}: the E57 file holds no scan (no data3D) and no image "
                             "(images2D)")
        if given is not None and count != 1:
            raise ValueError(f"{path}: a scanner pose names one scan's position, but the file "
                             f"holds {count} scans")
        scans = []
        for i in range(count):
            where = f"{path}: scan {i}"
            try:
                name, scan_pose, has_pose, points = _e57_open_scan(e57, i, path, where, stem,
                                                                   count)
            except ValueError:
                raise
            except Exception as e:
                raise ValueError(f"{where}: cannot be read: {str(e).splitlines()[0]}") from e
            frame = _e57_frame(points, scan_pose, has_pose, given)
            if frame is not None:
                points.to_sensor = frame
                scan_pose = frame
                points.notes.append(
                    "points stored in a world frame: turned into the scanner's frame (float64) "
                    f"with the scanner at {', '.join(f'{v:.3f}' for v in frame.position_m)}")
            try:
                guid = str(e57.data3d[i]["guid"].value())
            except Exception:
                guid = ""
            scans.append(E57Scan(scan=name, pose=scan_pose, points=points,
                                 images=[im for im in images if guid and im.scan_guid == guid]))
    finally:
        e57.close()
    # Images of no scan of the file (no or an unknown associatedData3DGuid): with one scan,
    # taken as its; otherwise a camera-only scan of their own.
    attached = {id(im) for sc in scans for im in sc.images}
    loose = [im for im in images if id(im) not in attached]
    if loose and len(scans) == 1:
        scans[0].images.extend(loose)
    elif loose:
        first = next((im.pose for im in loose if im.pose is not None), Pose.make([0, 0, 0]))
        scans.append(E57Scan(scan=f"{stem}-images" if scans else stem, pose=first, points=None,
                             images=loose))
    return scans


def _e57_pose(node, where: str, notes: List[str], partial: bool = False) -> Optional[Pose]:
    """A pose node (rotation w x y z, translation) as a Pose; a quaternion that is not of unit
    length is normalised (noted), a zero or non-finite one refused (ValueError). None when a
    part is missing, or with `partial` (a scan's pose) a missing part is the identity's."""
    def part(key: str, components: str, default: List[float]) -> List[float]:
        if partial and not node.isDefined(key):
            return default
        values = [_e57_number(node[key][c]) for c in components]
        if any(v is None for v in values):
            raise ValueError(f"{where}: the pose's {key} is not numeric")
        return values

    try:
        w, x, y, z = part("rotation", "wxyz", [1.0, 0.0, 0.0, 0.0])
        t = part("translation", "xyz", [0.0, 0.0, 0.0])
    except Exception:
        return None
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"{where}: the pose's rotation is not a quaternion ({w}, {x}, {y}, {z})")
    if abs(norm - 1.0) > 1e-6:
        notes.append(f"rotation quaternion of length {norm:.4g} normalised")
    return Pose.make(t, [x / norm, y / norm, z / norm, w / norm], where=where)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IMAGE_KINDS = (("pinholeRepresentation", "pinhole"), ("sphericalRepresentation", "spherical"),
                ("cylindricalRepresentation", "cylindrical"),
                ("visualReferenceRepresentation", "visual"))


def _read_e57_images(e57, path: str) -> List[E57Image]:
    """Every image of an E57 file (images2D), each with the reason it cannot be ingested when
    it cannot: a cylinder that is not one, a partial sphere of pixels that are not square,
    bytes that are neither JPEG nor PNG, or an imageMask that is not a PNG (the server would
    refuse the whole scan for it). A camera image's imageMask (the pixels with valid data) is
    read with it and sent as its mask; a visual reference (no projection) is kept with its scan
    as a photo for people to look at."""
    root = e57.image_file.root()
    if not root.isDefined("images2D"):
        return []
    out = []
    nodes = root["images2D"]
    for i in range(nodes.childCount()):
        node = nodes[i]
        where = f"{path}: image {i}"
        name = str(node["name"].value()) if node.isDefined("name") else f"image-{i + 1}"
        kind, rep = next(((k, node[key]) for key, k in _IMAGE_KINDS if node.isDefined(key)),
                         (None, None))
        if rep is None:
            out.append(E57Image(name, "unknown", 0, 0, b"", problem="no image representation"))
            continue

        def number(key, default=0.0):
            return float(rep[key].value()) if rep.isDefined(key) else default

        blob = next((rep[b] for b in ("jpegImage", "pngImage") if rep.isDefined(b)), None)
        data = _e57_blob(blob) if blob is not None else b""
        notes: List[str] = []
        pose = _e57_pose(node["pose"], where, notes) if node.isDefined("pose") else None
        image = E57Image(name=name, kind=kind, width=int(number("imageWidth")),
                         height=int(number("imageHeight")), data=data, pose=pose,
                         scan_guid=(str(node["associatedData3DGuid"].value())
                                    if node.isDefined("associatedData3DGuid") else ""),
                         mask=(_e57_blob(rep["imageMask"])
                               if kind != "visual" and rep.isDefined("imageMask") else b""))
        problems = []
        if kind == "cylindrical":
            try:
                image.cylinder = cylinder_from_json(
                    {"pixel_width_rad": number("pixelWidth"),
                     "pixel_height_m": number("pixelHeight"), "radius_m": number("radius"),
                     "principal_y_px": number("principalPointY")}, where)
            except ValueError as e:
                problems.append(f"its cylinder is not one: {str(e).split(': ', 2)[-1]}")
            else:
                if image.width * image.cylinder["pixel_width_rad"] > 2 * math.pi * 1.02:
                    problems.append("the cylindrical image spans more than 360°")
                    image.cylinder = None
                else:
                    notes.append("cylindrical: resampled by the server into the part of the "
                                 "sphere it covers")
        elif kind == "spherical":
            place = _e57_sphere(image.width, image.height, number("pixelWidth"),
                                number("pixelHeight"))
            if isinstance(place, str):
                problems.append(place)
            elif place is not None:
                image.sphere = place
                notes.append(
                    f"spans {math.degrees(image.width * number('pixelWidth')):.0f}° x "
                    f"{math.degrees(image.height * number('pixelHeight')):.0f}°: sent as that "
                    f"part of a {place['width_px']}x{place['height_px']} panorama of the "
                    "sphere, centred on the camera's x axis, the rest uncovered")
        elif kind == "pinhole":
            f, pw, ph = number("focalLength"), number("pixelWidth"), number("pixelHeight")
            nominal = None
            if f > 0 and pw > 0 and ph > 0:
                nominal = {"fx_px": f / pw, "fy_px": f / ph,
                           "cx_px": number("principalPointX"),
                           "cy_px": number("principalPointY"),
                           "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0}
            lens = _leica_distortion(e57, node, image, nominal, notes)
            if isinstance(lens, str):
                problems.append(lens)
            elif lens is not None or nominal is not None:
                image.pinhole = lens or nominal
                if image.pose is not None:  # E57 camera: y up, looking along -z (see E57Image)
                    q = image.pose.quaternion_xyzw
                    turned = _quat_mul((q[0], q[1], q[2], q[3]), (1.0, 0.0, 0.0, 0.0))
                    image.pose = Pose.make(image.pose.position_m, turned, where=where)
            else:
                problems.append("focalLength, pixelWidth and pixelHeight must be > 0")
        if kind in ("spherical", "cylindrical", "pinhole", "visual") and not problems:
            if not (data.startswith(_PNG_SIGNATURE) or data.startswith(b"\xff\xd8")):
                problems.append("its bytes are neither a JPEG nor a PNG image")
            elif image.mask and not image.mask.startswith(_PNG_SIGNATURE):
                problems.append("its imageMask is not a PNG image")
            elif image.pose is None and kind != "visual":  # a reference takes its scan's
                problems.append("it has no pose")
        image.problem = "; ".join(problems)
        image.notes = notes
        out.append(image)
    return out


#: The E57 extension Leica's software writes a pinhole image's calibrated lens in (OpenCV's
#: model: fx, fy, cx, cy in pixels of a CV_WIDTH x CV_HEIGHT image, k1-k6, p1, p2).
LEICA_DISTORTION_URI = "http://www.libe57.org/E57_LEICA_Camera_Distortion.txt"
#: The largest error, in pixels, allowed where a rational lens (k4-k6) is refitted as k1-k3.
RATIONAL_FIT_MAX_PX = 0.25


def _leica_distortion(e57, node, image: "E57Image", nominal: Optional[Dict[str, float]],
                      notes: List[str]):
    """A pinhole image's intrinsics from Leica's distortion extension when the image has it
    (None when not, or when it gives no fx, fy and `nominal`, the E57 pinhole's own, is None;
    a string: why the image cannot be used). OpenCV's model in the image's
    pixel axes, which are §2.2's (the E57 camera frame turned 180° about x). Its fx, fy, cx, cy
    (when given, scaled from CV_WIDTH x CV_HEIGHT to the image's size) replace the nominal
    focalLength / pixel size; k1-k3, p1, p2 are §2.2's. A rational model (k4-k6 not zero:
    radial factor (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)) is refitted as
    §2.2's polynomial over the image's radii by least squares, and used when it stays within
    RATIONAL_FIT_MAX_PX of it everywhere (noted), otherwise refused."""
    imf = e57.image_file
    prefix = next((imf.extensionsPrefix(i) for i in range(imf.extensionsCount())
                   if imf.extensionsUri(i) == LEICA_DISTORTION_URI), None)
    if prefix is None or not node.isDefined(f"{prefix}:distortion"):
        return None
    d = node[f"{prefix}:distortion"]

    def cv(key: str) -> float:
        name = f"{prefix}:CV_{key}"
        v = _e57_number(d[name]) if d.isDefined(name) else None
        return float(v) if v is not None and math.isfinite(v) else 0.0

    if not (cv("FX") > 0 and cv("FY") > 0) and nominal is None:
        return None
    lens = dict(nominal or {})
    if cv("FX") > 0 and cv("FY") > 0:
        sx = image.width / cv("WIDTH") if cv("WIDTH") > 0 else 1.0
        sy = image.height / cv("HEIGHT") if cv("HEIGHT") > 0 else 1.0
        lens.update(fx_px=cv("FX") * sx, fy_px=cv("FY") * sy, cx_px=cv("CX") * sx,
                    cy_px=cv("CY") * sy)
    lens.update(k1=cv("K1"), k2=cv("K2"), k3=cv("K3"), p1=cv("P1"), p2=cv("P2"))
    what = "Leica distortion extension: calibrated intrinsics and k1-k3, p1, p2"
    k456 = (cv("K4"), cv("K5"), cv("K6"))
    if any(k456):
        worst = _refit_rational(lens, k456, image.width, image.height)
        if not worst <= RATIONAL_FIT_MAX_PX:
            return (f"its Leica lens is rational (k4-k6) and §2.2's k1-k3 fit it only within "
                    f"{worst:.2g} px (at most {RATIONAL_FIT_MAX_PX} px)")
        what += f"; its rational k4-k6 refitted as k1-k3 within {worst:.2g} px"
    notes.append(what)
    return lens


def _refit_rational(lens: Dict[str, float], k456, width: int, height: int) -> float:
    """OpenCV's rational radial distortion (k1-k3 over k4-k6) refitted as §2.2's k1-k3 by least
    squares over the radii of a width x height image: `lens`'s k1-k3 replaced when the fit
    holds within RATIONAL_FIT_MAX_PX; returns its worst error in pixels."""
    corners = [((u - lens["cx_px"]) / lens["fx_px"], (v - lens["cy_px"]) / lens["fy_px"])
               for u in (0, width) for v in (0, height)]
    r = np.linspace(0.0, max(math.hypot(*c) for c in corners), 256)[1:]
    r2 = r * r
    rational = (1 + lens["k1"] * r2 + lens["k2"] * r2 ** 2 + lens["k3"] * r2 ** 3) / \
        (1 + k456[0] * r2 + k456[1] * r2 ** 2 + k456[2] * r2 ** 3)
    basis = np.stack([r * r2, r * r2 ** 2, r * r2 ** 3], axis=1)
    k, *_ = np.linalg.lstsq(basis, r * (rational - 1), rcond=None)
    worst = float(np.abs(basis @ k - r * (rational - 1)).max()) * max(lens["fx_px"],
                                                                         lens["fy_px"])
    if worst <= RATIONAL_FIT_MAX_PX:
        lens.update(k1=float(k[0]), k2=float(k[1]), k3=float(k[2]))
    return worst


def pinhole_from_camera_info(path: str) -> Dict[str, object]:
    """A camera's intrinsics from a ROS camera_info YAML file (what camera_calibration writes:
    image_width, image_height, camera_matrix.data [fx 0 cx 0 fy cy 0 0 1], distortion_model
    and distortion_coefficients.data), as `pinhole_from_json` gives them: "plumb_bob" /
    "radtan" ([k1, k2, p1, p2[, k3]], OpenCV's order) as Brown-Conrady, "equidistant" /
    "fisheye" ([k1, k2, k3, k4]) as a fisheye, "rational_polynomial" ([k1, k2, p1, p2, k3, k4,
    k5, k6]) refitted as k1-k3 when that holds within RATIONAL_FIT_MAX_PX. Or one camera of a
    Kalibr camchain YAML (`path#cam1`; the file's only camera without a fragment): its
    camera_model pinhole, intrinsics [fu, fv, pu, pv], distortion_model radtan or equidistant
    and distortion_coeffs, resolution [w, h]. The intrinsics are the image's as it is sent.
    ValueError naming the file and the key."""
    path, _, camera = path.partition("#")
    try:
        import yaml  # imported here: only camera_info users need it
    except ImportError as e:  # pragma: no cover - setup.sh installs it
        raise ValueError("reading camera_info needs PyYAML (pip install pyyaml; deploy/setup.sh "
                         "installs it)") from e
    try:
        with open(path, "rb") as f:
            doc = yaml.safe_load(f)
    except OSError as e:
        raise ValueError(f"{path}: cannot be read: {e.strerror}") from e
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not a YAML file ({str(e).splitlines()[0]})") from None

    if isinstance(doc, dict) and "camera_matrix" not in doc:  # a Kalibr camchain?
        cams = {k: v for k, v in doc.items() if isinstance(v, dict) and "intrinsics" in v}
        if camera and camera not in cams:
            raise ValueError(f"{path}: no camera {camera!r} (it holds "
                             f"{', '.join(sorted(cams)) or 'none'})")
        if not camera and len(cams) != 1:
            raise ValueError(f"{path}: not a ROS camera_info file (no camera_matrix)" if not cams
                             else f"{path}: a camchain of {len(cams)} cameras "
                             f"({', '.join(sorted(cams))}): name one, {path}#cam0")
        cam = cams[camera or next(iter(cams))]
        if cam.get("camera_model", "pinhole") != "pinhole":
            raise ValueError(f"{path}: camera_model {cam.get('camera_model')!r} is not one vasl "
                             "reads (pinhole, with radtan or equidistant distortion)")
        resolution = cam.get("resolution") or [0, 0]
        f = cam["intrinsics"]  # [fu, fv, pu, pv]
        matrix = ([f[0], 0, f[2], 0, f[1], f[3], 0, 0, 1]
                  if isinstance(f, list) and len(f) == 4 else None)
        doc = {"camera_matrix": {"data": matrix},
               "distortion_model": cam.get("distortion_model", "radtan"),
               "distortion_coefficients": {"data": cam.get("distortion_coeffs")},
               "image_width": resolution[0], "image_height": resolution[1]}
    elif camera:
        raise ValueError(f"{path}: a camera_info file holds one camera; #{camera} names one of a "
                         "Kalibr camchain")

    def numbers(key: str, counts) -> List[float]:
        node = doc.get(key) if isinstance(doc, dict) else None
        data = node.get("data") if isinstance(node, dict) else None
        if not isinstance(data, list) or len(data) not in counts:
            raise ValueError(f"{path}: not a ROS camera_info file: {key}.data must hold "
                             f"{' or '.join(str(c) for c in counts)} numbers")
        try:
            out = [float(v) for v in data]
        except (TypeError, ValueError):
            raise ValueError(f"{path}: {key}.data holds something that is not a number") from None
        if not all(math.isfinite(v) for v in out):
            raise ValueError(f"{path}: {key}.data must be finite")
        return out

    k = numbers("camera_matrix", (9,))
    model = str(doc.get("distortion_model", "plumb_bob")).lower()
    lens: Dict[str, object] = {"fx_px": k[0], "fy_px": k[4], "cx_px": k[2], "cy_px": k[5]}
    if abs(k[1]) > 1e-9 * k[0]:
        raise ValueError(f"{path}: camera_matrix has a skew ({k[1]:g}), which the pinhole "
                         "model does not hold")
    if model in ("plumb_bob", "radtan"):
        d = numbers("distortion_coefficients", (4, 5)) + [0.0]
        lens.update(k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
    elif model in ("equidistant", "fisheye"):
        d = numbers("distortion_coefficients", (4,))
        lens.update(lens="fisheye", k1=d[0], k2=d[1], k3=d[2], k4=d[3])
    elif model == "rational_polynomial":
        d = numbers("distortion_coefficients", (8,))
        lens.update(k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
        if any(d[5:]):
            try:
                width, height = int(doc["image_width"]), int(doc["image_height"])
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"{path}: a rational_polynomial lens needs image_width and "
                                 "image_height to be refitted") from None
            worst = _refit_rational(lens, d[5:], width, height)
            if not worst <= RATIONAL_FIT_MAX_PX:
                raise ValueError(f"{path}: its rational lens (k4-k6) fits §2.2's k1-k3 only "
                                 f"within {worst:.2g} px (at most {RATIONAL_FIT_MAX_PX} px)")
    else:
        raise ValueError(f"{path}: distortion_model {model!r} is not one vasl reads "
                         "(plumb_bob, radtan, equidistant, fisheye, rational_polynomial)")
    return pinhole_from_json(lens, path)


def _e57_sphere(width: int, height: int, pixel_width: float, pixel_height: float):
    """Where an E57 spherical image lies in the whole sphere's panorama: None when it is the
    whole sphere (360° x 180° within 2%); else the sphere at its pixel pitch (π / pixelHeight
    rows, twice as many columns, which must match 2π / pixelWidth within 2%) with the image
    centred in it (E57 gives a spherical image no offset: its centre is the camera's x axis,
    azimuth and elevation 0, as in a whole one; §2.1); a string saying why it cannot be."""
    if not (pixel_width > 0 and pixel_height > 0 and width > 0 and height > 0):
        return "pixelWidth and pixelHeight must be > 0"
    span_w, span_h = width * pixel_width, height * pixel_height
    if abs(span_w - 2 * math.pi) <= 0.02 * 2 * math.pi and \
            abs(span_h - math.pi) <= 0.02 * math.pi:
        if not 1.95 <= width / height <= 2.05:  # the server's rule: it would refuse the scan
            return (f"a whole sphere of {width}x{height} pixels: an equirect panorama needs "
                    "square pixels, twice as wide as high")
        return None
    if math.pi / pixel_height > (1 << 20):
        return (f"its pixels of {pixel_height:g} rad make a sphere of more than 2^20 rows")
    rows = int(round(math.pi / pixel_height))
    columns = 2 * rows
    if abs(columns * pixel_width - 2 * math.pi) > 0.02 * 2 * math.pi:
        return (f"its pixels are {math.degrees(pixel_width) * 3600:.0f}\" wide and "
                f"{math.degrees(pixel_height) * 3600:.0f}\" high: an equirect panorama of part "
                "of the sphere needs square pixels")
    if width > columns or height > rows:
        return (f"the spherical image spans {math.degrees(span_w):.0f}° x "
                f"{math.degrees(span_h):.0f}°, more than the sphere")
    return {"width_px": columns, "height_px": rows, "left_px": (columns - width) // 2,
            "top_px": (rows - height) // 2}


def _e57_blob(blob) -> bytes:
    """The bytes of an E57 blob node, read whole."""
    buf = np.zeros(blob.byteCount(), dtype=np.uint8)
    blob.read(buf, 0, blob.byteCount())
    return buf.tobytes()


def _quat_mul(a, b):
    """Hamilton product of two (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


class LasPoints(PointSource):
    """The points of a LAS or LAZ file (laspy; LAZ through its lazrs backend), read chunk by
    chunk with laspy's chunk iterator.

    LAS stores world coordinates (scaled integers plus an offset, often UTM: 10^5-10^7 m) and
    no scanner position, so a scan needs the scanner's pose `pose` (T_world_sensor, in the
    file's coordinates): each chunk's coordinates are turned into the sensor frame,
    p = Rᵀ(x − o), in float64 before they become float32. Intensity is the 16-bit intensity
    field over 65535. Colour, when the point format has red, green and blue, is 16-bit as the
    specification says, or 8-bit values stored in 16 bits when no value in the file exceeds 255
    (`colour_bits`; the check stops at the first larger value, usually within the first
    chunk); scaled to [0, 1] and linearised (sRGB)."""

    def __init__(self, path: str, pose: Pose):
        super().__init__()
        try:
            import laspy  # imported here: only LAS users need it
        except ImportError as e:  # pragma: no cover - setup.sh installs it
            raise ValueError("reading LAS/LAZ needs the laspy package with lazrs "
                             "(pip install 'laspy[lazrs]'; deploy/setup.sh installs it)") from e
        self.path = path
        self.pose = pose
        try:
            with laspy.open(path) as f:
                header = f.header
                self.count = int(header.point_count)
                dims = set(header.point_format.dimension_names)
                self.point_format = int(header.point_format.id)
        except Exception as e:  # laspy raises its own errors (and OSError)
            raise ValueError(f"{path}: not a readable LAS/LAZ file: "
                             f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from e
        if self.count == 0:
            raise ValueError(f"{path}: the LAS file holds no point")
        self.has_intensity = "intensity" in dims
        self.has_rgb = {"red", "green", "blue"} <= dims
        self.colour_bits = 0
        if self.has_rgb:
            self.colour_bits = self._colour_bits()
            self.notes.append(
                f"point format {self.point_format}: RGB "
                + ("16-bit" if self.colour_bits == 16
                   else "8-bit values stored in 16 bits (no value above 255)"))

    def _las_chunks(self, chunk_points: int):
        import laspy

        try:
            with laspy.open(self.path) as f:
                for chunk in f.chunk_iterator(chunk_points):
                    yield chunk
        except Exception as e:
            raise ValueError(f"{self.path}: cannot be read: "
                             f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from e

    def _colour_bits(self) -> int:
        for chunk in self._las_chunks(CHUNK_POINTS):
            if any(int(np.max(chunk[c], initial=0)) > 255 for c in ("red", "green", "blue")):
                return 16
        return 8

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        full = 65535.0 if self.colour_bits == 16 else 255.0
        for chunk in self._las_chunks(chunk_points):
            world = np.stack([np.asarray(chunk.x, dtype=np.float64),
                              np.asarray(chunk.y, dtype=np.float64),
                              np.asarray(chunk.z, dtype=np.float64)], axis=1)
            xyz = world_to_sensor(world, self.pose).astype(np.float32)
            intensity = (np.asarray(chunk.intensity, dtype=np.float32) / np.float32(65535.0)
                         if self.has_intensity else None)
            rgb = None
            if self.has_rgb:
                rgb = np.stack([srgb_to_linear(np.asarray(chunk[c], dtype=np.float64) / full)
                                for c in ("red", "green", "blue")], axis=1)
            yield PointCloud(np.ascontiguousarray(xyz), intensity, rgb)


def read_las(path: str, pose=None) -> LasPoints:
    """A LAS or LAZ file's points as a streaming `LasPoints` in the sensor frame of `pose`
    (the scanner's T_world_sensor in the file's coordinates; see Pose.parse). ValueError naming
    the file for one without a pose (LAS records no scanner position, and visibility needs the
    origin of the rays), one that is not readable LAS/LAZ, or one without points."""
    if pose is None:
        raise ValueError(f"{path}: a LAS/LAZ file records no scanner position, and visibility "
                         "needs the origin of the rays: give the scanner's pose in the file's "
                         "coordinates (vasl ingest --pose x,y,z[,qx,qy,qz,qw], or a manifest "
                         "whose lidar.points names the file)")
    return LasPoints(path, Pose.parse(pose))


def is_las(path: str) -> bool:
    """Whether a path names a LAS or LAZ file (by its extension)."""
    return path.lower().endswith((".las", ".laz"))


def quaternion_from_matrix(r: np.ndarray) -> Tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a 3x3 rotation (Shepperd's method: the largest of
    w, x, y, z found first, so that no division is by a small number)."""
    r = np.asarray(r, dtype=np.float64)
    t = float(np.trace(r))
    if t > max(r[0, 0], r[1, 1], r[2, 2]):
        w = math.sqrt(1.0 + t) / 2
        q = ((r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
             (r[1, 0] - r[0, 1]) / (4 * w), w)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 0.0)) * 2  # 4 |q_i|
        v = [0.0, 0.0, 0.0]
        v[i] = s / 4
        v[j] = (r[j, i] + r[i, j]) / s
        v[k] = (r[k, i] + r[i, k]) / s
        q = (v[0], v[1], v[2], (r[k, j] - r[j, k]) / s)
    n = math.sqrt(sum(c * c for c in q))
    return tuple(float(c / n) for c in q)


#: The fields of a PTX point line, as many as it has (3, 4 or 7).
_PTX_FIELDS = ("x", "y", "z", "intensity", "r", "g", "b")
#: How far from a rotation a PTX header's 3x3 may be (|RᵀR − I|, |det R − 1|): the files print
#: six or so decimals.
_PTX_RIGID_TOL = 1e-3
#: Bytes read at a time while skipping a PTX scan's lines to find the next one.
_PTX_SKIP_BLOCK = 1 << 23


@dataclass
class PtxScan:
    """One scan of a PTX file: its scanner pose in the file's registered frame and its points
    (a streaming `PtxPoints` in the scanner's frame)."""

    scan: str  #: scan id: the file stem, "-<n>" when the file holds several scans
    pose: Pose  #: T_world_scanner in the file's registered frame
    points: "PtxPoints"

    @property
    def notes(self) -> List[str]:
        return self.points.notes


class PtxPoints(PointSource):
    """The points of one scan of a PTX file (Leica's structured ASCII format, also written by
    FARO SCENE, Trimble RealWorks and CloudCompare), read chunk by chunk.

    A PTX scan is a full range grid: `columns` × `rows` lines, column after column, each
    ``x y z intensity [r g b]``; a cell without a return is ``0 0 0`` (or, from some writers, a
    coordinate that is not a number), which is sent as the scanners' "no return" marker (the
    server skips it), so the point count is the grid's and each point's row and column are its
    place in the file. Coordinates are read in float64 and
    taken through `to_world` (the file's 4x4 transform: x_world = R p + t) and then into the
    sensor frame of `pose` (p_sensor = Rᵀ(x_world − o)), before they become float32; where the
    two are one (the usual file), the points are already in the sensor frame and are kept as
    they are. Intensity is the format's [0, 1] (clipped into it); colour 0..255, linearised
    (sRGB)."""

    def __init__(self, path: str, where: str, offset: int, first_line: int, rows: int,
                 columns: int, fields: int, to_world: np.ndarray, pose: Pose):
        super().__init__()
        self.path = path
        self.where = where
        self.offset = offset  #: byte offset of the scan's first point line
        self.first_line = first_line  #: its line number (1-based), for errors
        self.rows, self.columns, self.fields = rows, columns, fields
        self.count = rows * columns
        self.has_intensity = fields >= 4
        self.has_rgb = fields == 7
        self.grid_shape = (rows, columns)
        self.to_world = to_world
        self.pose = pose
        sensor = np.eye(4)
        sensor[:3, :3] = rotation_matrix(pose.quaternion_xyzw)
        sensor[:3, 3] = pose.position_m
        # The points' frame is the sensor's when the file's transform is the pose: no arithmetic.
        self.as_stored = bool(np.allclose(to_world, sensor, rtol=0.0, atol=1e-9))

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        import itertools

        r_world, t_world = self.to_world[:3, :3], self.to_world[:3, 3]
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            done = 0
            while done < self.count:
                n = min(chunk_points, self.count - done)
                lines = list(itertools.islice(f, n))
                values, bad = _number_table(lines, self.fields)
                if values is None and bad < len(lines):
                    line = lines[bad].decode("latin-1").strip()[:80]
                    raise ValueError(f"{self.where}: line {self.first_line + done + bad}: "
                                     f"expected {self.fields} numbers "
                                     f"({' '.join(_PTX_FIELDS[:self.fields])}), got {line!r}")
                if values is None or len(lines) < n:
                    raise ValueError(f"{self.where}: the file ends after {done + len(lines)} of "
                                     f"the scan's {self.count} points ({self.columns} columns x "
                                     f"{self.rows} rows)")
                xyz = values[:, :3]
                # No return: 0 0 0, or a coordinate that is not a number (kept as the marker).
                missing = np.all(xyz == 0.0, axis=1) | ~np.all(np.isfinite(xyz), axis=1)
                if not self.as_stored:
                    xyz = world_to_sensor(xyz @ r_world.T + t_world, self.pose)
                xyz[missing] = 0.0
                intensity = rgb = None
                if self.has_intensity:
                    intensity = np.clip(np.nan_to_num(values[:, 3]), 0.0, 1.0).astype(np.float32)
                if self.has_rgb:
                    rgb = srgb_to_linear(np.clip(np.nan_to_num(values[:, 4:7]), 0.0, 255.0) / 255.0)
                cell = np.arange(done, done + n, dtype=np.int64)
                grid = np.stack([cell % self.rows, cell // self.rows], axis=1).astype(np.uint32)
                done += n
                yield PointCloud(np.ascontiguousarray(xyz, dtype=np.float32), intensity,
                                 None if rgb is None else rgb.astype(np.float32), grid)


def _parse_numbers(text: bytes) -> Optional[np.ndarray]:
    """The whitespace-separated numbers of `text` as float64 (numpy's C parser); None when a
    word is not a number."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy < 2.3 warns where later ones raise
        try:
            return np.fromstring(text, sep=" ")
        except (ValueError, DeprecationWarning):
            return None


def _number_table(lines: List[bytes], fields: int) -> Tuple[Optional[np.ndarray], int]:
    """The lines' numbers as a (len(lines), fields) float64 table and -1; or None and the index
    of the first line that does not hold `fields` numbers (len(lines) when each does alone but
    not together, which whitespace inside a number cannot make: kept for safety)."""
    values = _parse_numbers(b" ".join(lines))
    if values is not None and values.size == len(lines) * fields:
        return values.reshape(len(lines), fields), -1
    for i, line in enumerate(lines):
        got = _parse_numbers(line)
        if got is None or got.size != fields:
            return None, i
    return None, len(lines)


def _ptx_numbers(line: bytes, count: int, what: str, where: str) -> List[float]:
    words = line.split()
    try:
        values = [float(w) for w in words]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{where}: expected {what} ({count} numbers), got "
                         f"{line.decode('latin-1').strip()[:80]!r}")
    return values


def _ptx_rigid(r: np.ndarray) -> bool:
    return (float(np.abs(r.T @ r - np.eye(3)).max()) <= _PTX_RIGID_TOL
            and abs(float(np.linalg.det(r)) - 1.0) <= _PTX_RIGID_TOL)


def _ptx_transform(rows: List[List[float]], where: str) -> np.ndarray:
    """The 4x4 of a PTX header as x_world = M[:3, :3] p + M[:3, 3]. PTX writes it for row
    vectors (x_world = p M: the translation is the last row, the last column 0 0 0 1); a file
    written the other way (the translation in the last column) is read as written."""
    m = np.asarray(rows, dtype=np.float64)
    last_column, last_row = m[:, 3], m[3, :]
    if np.allclose(last_column, [0, 0, 0, 1], atol=1e-9):
        m = m.T
    elif not np.allclose(last_row, [0, 0, 0, 1], atol=1e-9):
        raise ValueError(f"{where}: the 4x4 transform has neither 0 0 0 1 as its last column "
                         "nor as its last row: not a rigid transform")
    if not _ptx_rigid(m[:3, :3]):
        raise ValueError(f"{where}: the 4x4 transform's rotation is not a rotation (scaled, "
                         "sheared or mirrored)")
    return m


def _skip_lines(f, n: int) -> int:
    """Moves `f` past `n` lines (to the start of the next); the lines skipped (fewer at the end
    of the file, where a last line without its newline counts)."""
    skipped, open_line = 0, False  # open_line: text after the last newline seen
    while skipped < n:
        at = f.tell()
        block = f.read(_PTX_SKIP_BLOCK)
        if not block:
            return skipped + int(open_line)
        newlines = np.flatnonzero(np.frombuffer(block, dtype=np.uint8) == 10)
        if skipped + len(newlines) >= n:
            f.seek(at + int(newlines[n - skipped - 1]) + 1)
            return n
        skipped += len(newlines)
        tail = block[int(newlines[-1]) + 1:] if len(newlines) else block
        open_line = bool(tail.strip()) or (open_line and not len(newlines))
    return skipped


def read_ptx(path: str, pose=None) -> List[PtxScan]:
    """Reads every scan of a PTX file: its header and where its points start (the points are
    streamed from the file when wanted, `PtxPoints`).

    Each scan's header is ten lines: columns, rows, the scanner's registered position, its
    registered x, y and z axes, and a 4x4 transform of the points into the registered frame.
    The scanner's pose is the position and axes (where the rays start: visibility needs it);
    the points are taken through the transform into the registered frame and from there into
    the scanner's. The usual file has the two equal (points in the scanner's own frame); a file
    exported with its points already registered has an identity transform; a header whose
    position and axes are the identity while its transform is not is one that left them out,
    and the transform is the scanner's pose. `pose` (a manifest's, for a file of one scan)
    places the scanner instead, in the registered frame. ValueError naming the file and line
    for a file that is not PTX, a header that is not a rigid pose, a point line without 3, 4 or
    7 numbers, or a scan with fewer point lines than its grid has cells."""
    stem = os.path.splitext(os.path.basename(path))[0]
    given = None if pose is None else Pose.parse(pose)
    found = []
    try:
        f = open(path, "rb")
    except OSError as e:
        raise ValueError(f"{path}: cannot be read: {e.strerror}") from e
    with f:
        line_no = 0
        while True:
            header, at_line = [], line_no + 1
            while len(header) < 10:
                line = f.readline()
                if not line:
                    break
                line_no += 1
                if line.strip() or header:  # blank lines between scans are skipped
                    header.append(line)
            if not header:
                break
            where = f"{path}: scan {len(found)} (line {at_line})"
            if len(header) < 10:
                raise ValueError(f"{where}: the file ends inside a scan's 10-line header")
            try:
                columns, rows = (int(header[i].strip()) for i in (0, 1))
            except ValueError:
                raise ValueError(f"{where}: not a PTX scan header (its first two lines are "
                                 "the column and row counts)") from None
            if columns < 1 or rows < 1 or columns * rows > MAX_GRID_CELLS:
                raise ValueError(f"{where}: a {columns} x {rows} grid is out of bounds")
            position = _ptx_numbers(header[2], 3, "the scanner position", where)
            axes = np.array([_ptx_numbers(header[3 + i], 3, f"the scanner's {'xyz'[i]} axis",
                                          where) for i in range(3)]).T  # columns: the axes
            to_world = _ptx_transform([_ptx_numbers(header[6 + i], 4, "a row of the 4x4 "
                                                    "transform", where) for i in range(4)],
                                      where)
            if not _ptx_rigid(axes):
                raise ValueError(f"{where}: the scanner's axes are not a rotation")
            notes = []
            if np.allclose(axes, np.eye(3), atol=1e-9) and not any(position) \
                    and not np.allclose(to_world, np.eye(4), atol=1e-9):
                pose_r, pose_t = to_world[:3, :3], to_world[:3, 3]
                notes.append("no scanner position in the header: the scanner is where the "
                             "4x4 transform puts the points' origin")
            else:
                pose_r, pose_t = axes, np.asarray(position)
            pose = Pose.make(pose_t, quaternion_from_matrix(pose_r), where=where)
            if given is not None:
                moved = float(np.linalg.norm(np.asarray(given.position_m) - pose_t))
                if moved > 0.01:
                    notes.append(f"the scanner placed by the given pose, {moved:.2f} m from "
                                 "the file's scanner position")
                pose = given
            offset, first_line = f.tell(), line_no + 1
            first = f.readline()
            fields = len(first.split())
            if fields not in (3, 4, 7):
                raise ValueError(f"{where}: line {first_line}: a PTX point is x y z intensity "
                                 f"[r g b], got {first.decode('latin-1').strip()[:80]!r}")
            f.seek(offset)
            got = _skip_lines(f, columns * rows)
            if got < columns * rows:
                raise ValueError(f"{where}: the file ends after {got} of the scan's "
                                 f"{columns * rows} points ({columns} columns x {rows} rows)")
            line_no += got
            points = PtxPoints(path, where, offset, first_line, rows, columns, fields,
                               to_world, pose)
            if not points.as_stored:
                if np.allclose(to_world, np.eye(4), atol=1e-9):
                    notes.append("points stored registered (an identity transform): turned "
                                 "into the scanner's frame (float64)")
                else:
                    notes.append("the 4x4 transform is not the scanner's pose: points taken "
                                 "through it, then into the scanner's frame (float64)")
            notes.append(f"range grid {rows} x {columns} (PTX): the server fills the gaps "
                         "between neighbouring returns on one surface")
            points.notes.extend(notes)
            found.append((points, pose))
    if not found:
        raise ValueError(f"{path}: holds no PTX scan")
    if given is not None and len(found) != 1:
        raise ValueError(f"{path}: a pose places one scanner, but the file holds {len(found)} "
                         "scans")
    return [PtxScan(scan=stem if len(found) == 1 else f"{stem}-{i + 1}", pose=pose,
                    points=points) for i, (points, pose) in enumerate(found)]


def is_ptx(path: str) -> bool:
    """Whether a path names a PTX file (by its extension)."""
    return path.lower().endswith(".ptx")


#: Extensions of the ASCII point clouds `read_ascii_cloud` reads (one point per line).
ASCII_CLOUD_EXTENSIONS = (".pts", ".xyz", ".txt", ".asc", ".csv")


class AsciiPoints(PointSource):
    """The points of an ASCII point cloud (Leica PTS, XYZ, CSV: one point a line, x y z then
    optionally intensity and/or r g b, separated by spaces, tabs, commas or semicolons), read
    chunk by chunk. Such a file holds world coordinates and no scanner position, so a scan
    needs the scanner's pose `pose`, as a LAS file does: each chunk's coordinates go into the
    sensor frame, p = Rᵀ(x − o), in float64 before they become float32.

    Columns: 3 (x y z), 4 (x y z intensity), 6 (x y z r g b) or 7 (x y z intensity r g b), the
    same on every line. A line that holds one whole number alone is a count (PTS writes one
    before each block of points) and is skipped, as is a first line that is not numbers (a
    CSV header); a point whose coordinate is not a number (nan) is sent as a "no return".
    Intensity is scaled into [0, 1] by the range the file's first pass finds (intensity_scale:
    Leica PTS's −2048..2047 among the ranges it knows; noted). Colour 0..255, or 0..1 when no
    value exceeds 1, taken as sRGB and linearised."""

    def __init__(self, path: str, pose: Pose):
        super().__init__()
        self.path = path
        self.pose = pose
        self.fields = 0
        self._survey()

    def _lines(self, chunk_points: int) -> Iterator[Tuple[int, List[bytes]]]:
        """(line number of the first, lines) of points, `chunk_points` at a time, counts and
        a header skipped."""
        import itertools

        with open(self.path, "rb") as f:
            line_no = 0
            first = True
            while True:
                raw = list(itertools.islice(f, chunk_points))
                if not raw:
                    return
                start = line_no + 1
                line_no += len(raw)
                kept = []
                for i, line in enumerate(raw):
                    words = line.replace(b",", b" ").replace(b";", b" ").split()
                    if not words:
                        continue
                    if len(words) == 1 and words[0].isdigit():
                        continue  # a PTS count line
                    if first:
                        first = False
                        if _parse_numbers(b" ".join(words)) is None:
                            continue  # a header line (X,Y,Z,...)
                    kept.append(line.replace(b",", b" ").replace(b";", b" "))
                if kept:
                    yield start, kept

    def _table(self, start: int, lines: List[bytes]) -> np.ndarray:
        values, bad = _number_table(lines, self.fields)
        if values is not None:
            return values
        if bad == len(lines):
            raise ValueError(f"{self.path}: near line {start}: lines of different lengths")
        got = _parse_numbers(lines[bad])
        raise ValueError(f"{self.path}: a line holds "
                         f"{'words that are not numbers' if got is None else got.size}"
                         f" where the first point line has {self.fields} numbers: "
                         f"{lines[bad].decode('latin-1').strip()[:80]!r}")

    def _survey(self) -> None:
        """One pass over the file: the column count, the point count and the ranges that
        settle the scaling."""
        count, lo, hi, top = 0, math.inf, -math.inf, 0.0
        for start, lines in self._lines(CHUNK_POINTS):
            if not self.fields:
                self.fields = len(lines[0].split())
                if self.fields not in (3, 4, 6, 7):
                    raise ValueError(f"{self.path}: a point line has {self.fields} numbers; "
                                     "expected x y z [intensity] [r g b] (3, 4, 6 or 7)")
            t = self._table(start, lines)
            count += len(t)
            if self.fields in (4, 7) and np.isfinite(t[:, 3]).any():
                lo = min(lo, float(np.nanmin(t[:, 3])))
                hi = max(hi, float(np.nanmax(t[:, 3])))
            if self.fields in (6, 7) and np.isfinite(t[:, -3:]).any():
                top = max(top, float(np.nanmax(t[:, -3:])))
        if count == 0:
            raise ValueError(f"{self.path}: holds no point")
        self.count = count
        self.has_intensity = self.fields in (4, 7)
        self.has_rgb = self.fields in (6, 7)
        self.intensity_scale = (0.0, 1.0)  # i → (i − a) / b
        if self.has_intensity:
            a, b, what = intensity_scale(lo, hi)
            self.intensity_scale = (a, b)
            self.notes.append(what)
        self.colour_full = 1.0 if top <= 1.0 else 255.0
        if self.has_rgb:
            self.notes.append("colour " + ("0..1" if top <= 1.0 else "0..255") + ", as sRGB")
        self.notes.append(f"{count} points, x y z{' intensity' if self.has_intensity else ''}"
                          f"{' r g b' if self.has_rgb else ''}")

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        a, b = self.intensity_scale
        for start, lines in self._lines(chunk_points):
            t = self._table(start, lines)
            xyz = world_to_sensor(t[:, :3], self.pose).astype(np.float32)
            xyz[~np.all(np.isfinite(t[:, :3]), axis=1)] = 0.0  # not a number: no return
            intensity = (np.clip(np.nan_to_num((t[:, 3] - a) / b), 0.0, 1.0).astype(np.float32)
                         if self.has_intensity else None)
            rgb = (srgb_to_linear(np.clip(np.nan_to_num(t[:, -3:] / self.colour_full), 0.0, 1.0))
                   .astype(np.float32) if self.has_rgb else None)
            yield PointCloud(np.ascontiguousarray(xyz), intensity, rgb)


def read_ascii_cloud(path: str, pose=None) -> AsciiPoints:
    """An ASCII point cloud (PTS, XYZ, CSV; see AsciiPoints) as a streaming `AsciiPoints` in
    the sensor frame of `pose` (the scanner's T_world_sensor in the file's coordinates).
    ValueError naming the file for one without a pose, with lines that are not points, or
    without points."""
    if pose is None:
        raise ValueError(f"{path}: an ASCII point cloud records no scanner position, and "
                         "visibility needs the origin of the rays: give the scanner's pose in "
                         "the file's coordinates (vasl ingest --pose x,y,z[,qx,qy,qz,qw], or a "
                         "manifest whose lidar.points names the file)")
    try:
        return AsciiPoints(path, Pose.parse(pose))
    except OSError as e:
        raise ValueError(f"{path}: cannot be read: {e.strerror}") from e


def is_ascii_cloud(path: str) -> bool:
    """Whether a path names an ASCII point cloud (by its extension)."""
    return path.lower().endswith(ASCII_CLOUD_EXTENSIONS)


#: PCD field types (TYPE letter, SIZE bytes) as numpy reads them; the data is little endian.
_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2",
              ("I", 4): "<i4", ("I", 8): "<i8", ("U", 1): "u1", ("U", 2): "<u2",
              ("U", 4): "<u4", ("U", 8): "<u8"}
#: PCD fields that give a point's intensity, the first found (Ouster's calibrated reflectivity
#: after the usual intensity).
_PCD_INTENSITY_NAMES = ("intensity", "reflectivity", "reflectance")
#: PCD header lines a file may hold before DATA (comments aside), and the bytes read for it.
_PCD_HEADER_BYTES = 1 << 16


@dataclass
class PcdField:
    """One field of a PCD file: its name, numpy type and count (values per point)."""

    name: str
    dtype: str
    count: int


class PcdScan:
    """A PCD file's scan: its scanner pose and its points (a streaming `PcdPoints` in the
    scanner's frame)."""

    scan: str  #: scan id: the file stem
    pose: Pose  #: T_world_scanner
    points: "PcdPoints"

    def __init__(self, scan: str, pose: Pose, points: "PcdPoints"):
        self.scan, self.pose, self.points = scan, pose, points

    @property
    def notes(self) -> List[str]:
        return self.points.notes


class PcdPoints(PointSource):
    """The points of a PCD file (the Point Cloud Library's format, read and written by ROS,
    Open3D, CloudCompare and most robotics stacks), read chunk by chunk.

    The header's FIELDS, SIZE, TYPE and COUNT lay out a point; WIDTH × HEIGHT points (HEIGHT
    > 1: an organised cloud, a grid of rows × columns, which is sent as the scan's range grid);
    VIEWPOINT ``tx ty tz qw qx qy qz`` the pose of the sensor that acquired them in the
    points' frame. DATA ``ascii`` (a point a line), ``binary`` (points packed one after the
    other) or ``binary_compressed`` (LZF-compressed, field after field: decompressed whole, so
    its memory is the points' bytes). Coordinates ``x y z`` (float or double) go into the
    sensor frame through the viewpoint, p = Rᵀ(x − t), in float64 before they become float32
    (kept as they are under the identity viewpoint, the usual file); a point whose coordinate
    is not a number (an organised cloud's empty cell) is sent as the scanners' "no return".
    ``intensity`` (or ``reflectivity``, ``reflectance``) an unsigned integer type over its
    largest value, else by the range its values span (intensity_scale); ``rgb`` or ``rgba`` (a
    float or unsigned 32-bit field holding 0xRRGGBB, PCL's packing) as sRGB, linearised. Other fields (normals, labels,
    curvature, padding ``_``) are skipped."""

    def __init__(self, path: str, fields: List[PcdField], width: int, height: int,
                 data: str, offset: int, first_line: int, viewpoint: Pose):
        super().__init__()
        self.path = path
        self.first_line = first_line  #: the data's first line number (ascii), for errors
        self.fields = fields
        self.width, self.height = width, height
        self.count = width * height
        self.data = data
        self.offset = offset  #: byte offset of the data (after the DATA line)
        #: the pose through which the points go into the sensor frame: the VIEWPOINT, or the
        #: scanner's pose for points stored in a world frame (read_pcd)
        self.to_sensor = viewpoint
        names = [f.name for f in fields]
        for axis in "xyz":
            if axis not in names:
                raise ValueError(f"{path}: the PCD fields ({' '.join(names)}) have no {axis}")
            f = fields[names.index(axis)]
            if f.count != 1 or not f.dtype.lstrip("<").startswith("f"):
                raise ValueError(f"{path}: PCD field {axis} must be one float or double")
        self._intensity = next((f for name in _PCD_INTENSITY_NAMES for f in fields
                                if f.name == name and f.count == 1), None)
        self._rgb = next((f for f in fields if f.name in ("rgb", "rgba") and f.count == 1
                          and f.dtype.lstrip("<") in ("f4", "u4")), None)
        self.has_intensity = self._intensity is not None
        self.has_rgb = self._rgb is not None
        self.grid_shape = (height, width) if height > 1 else None
        self.intensity_scale = (0.0, 1.0)  # i → (i − a) / b
        self._columns: Optional[Dict[str, np.ndarray]] = None  # binary_compressed, decoded
        self._ascii_fields = sum(f.count for f in fields)
        self._survey()

    @property
    def as_stored(self) -> bool:
        """Whether the points are in the sensor frame as stored (an identity `to_sensor`)."""
        return (not any(self.to_sensor.position_m)
                and np.allclose(rotation_matrix(self.to_sensor.quaternion_xyzw), np.eye(3),
                                rtol=0.0, atol=1e-12))

    @staticmethod
    def _xyz(table: Dict[str, np.ndarray]) -> np.ndarray:
        """A chunk's coordinates, (N, 3) float64 (not a number where a cell has none)."""
        return np.concatenate([table[axis].astype(np.float64) for axis in "xyz"], axis=1)

    def first_xyz(self) -> np.ndarray:
        """The first chunk's coordinates (_xyz), the file closed again."""
        tables = self._tables(CHUNK_POINTS)
        try:
            return self._xyz(next(tables))
        finally:
            tables.close()

    def _record_dtype(self) -> np.dtype:
        return np.dtype([(f"f{i}", f.dtype, (f.count,)) for i, f in enumerate(self.fields)])

    def _decompressed(self) -> Dict[str, np.ndarray]:
        """binary_compressed: every field's values (points × count), decompressed once."""
        if self._columns is None:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                sizes = f.read(8)
                if len(sizes) < 8:
                    raise ValueError(f"{self.path}: the PCD file ends before its compressed "
                                     "data's sizes")
                packed, unpacked = (int(v) for v in np.frombuffer(sizes, "<u4"))
                need = sum(np.dtype(fl.dtype).itemsize * fl.count for fl in self.fields)
                if unpacked != need * self.count:
                    raise ValueError(f"{self.path}: the compressed data unpacks to {unpacked} "
                                     f"bytes, but {self.count} points of {need} bytes take "
                                     f"{need * self.count}")
                data = f.read(packed)
                if len(data) < packed:
                    raise ValueError(f"{self.path}: the PCD file ends inside its compressed "
                                     f"data ({len(data)} of {packed} bytes)")
            raw = lzf_decompress(data, unpacked, self.path)
            columns, at = {}, 0
            for fl in self.fields:
                size = np.dtype(fl.dtype).itemsize * fl.count * self.count
                columns[fl.name] = np.frombuffer(raw, fl.dtype, fl.count * self.count, at) \
                    .reshape(self.count, fl.count)
                at += size
            self._columns = columns
        return self._columns

    def _tables(self, chunk_points: int) -> Iterator[Dict[str, np.ndarray]]:
        """Per chunk of points in the file's order: each field's values (points × count)."""
        if self.data == "binary_compressed":
            columns = self._decompressed()
            for at in range(0, self.count, chunk_points):
                yield {name: v[at:at + chunk_points] for name, v in columns.items()}
            return
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            done = 0
            if self.data == "binary":
                dtype = self._record_dtype()
                while done < self.count:
                    n = min(chunk_points, self.count - done)
                    raw = f.read(n * dtype.itemsize)
                    if len(raw) < n * dtype.itemsize:
                        raise ValueError(f"{self.path}: the PCD file ends after "
                                         f"{done + len(raw) // dtype.itemsize} of its "
                                         f"{self.count} points")
                    rec = np.frombuffer(raw, dtype, n)
                    done += n
                    yield {fl.name: rec[f"f{i}"] for i, fl in enumerate(self.fields)}
                return
            import itertools
            line_no = self.first_line
            while done < self.count:
                n = min(chunk_points, self.count - done)
                lines: List[bytes] = []
                while len(lines) < n:  # blank lines skipped: read on for the rest
                    raw = list(itertools.islice(f, n - len(lines)))
                    if not raw:
                        raise ValueError(f"{self.path}: the PCD file ends after "
                                         f"{done + len(lines)} of its {self.count} points")
                    lines += [ln for ln in raw if ln.strip()]
                values, bad = _number_table(lines, self._ascii_fields)
                if values is None:
                    at = min(bad, len(lines) - 1)
                    raise ValueError(f"{self.path}: near line {line_no + at}: a point has "
                                     f"{self._ascii_fields} numbers "
                                     f"({' '.join(fl.name for fl in self.fields)}), got "
                                     f"{lines[at].decode('latin-1').strip()[:80]!r}")
                out, col = {}, 0
                for fl in self.fields:
                    v = values[:, col:col + fl.count]
                    kind = fl.dtype.lstrip("<")
                    if fl.name in ("rgb", "rgba") and kind == "f4":
                        # ascii writes the packed colour's float: its bits are the colour.
                        v = v.astype(np.float32)
                    elif kind[0] in "iu":
                        v = np.nan_to_num(v).astype(kind)
                    out[fl.name] = v
                    col += fl.count
                done += n
                line_no += n
                yield out

    def _survey(self) -> None:
        """The intensity's range, when its type does not settle the scale (one pass)."""
        names = " ".join(f.name for f in self.fields)
        notes = [f"{self.count} points ({self.data}), fields {names}"]
        if self.has_intensity:
            kind = np.dtype(self._intensity.dtype)
            if kind.kind == "u":
                self.intensity_scale = (0.0, float(np.iinfo(kind).max))
                notes.append(f"{self._intensity.name} over {np.iinfo(kind).max} ({kind.name})")
            else:
                lo, hi = math.inf, -math.inf
                for t in self._tables(CHUNK_POINTS):
                    v = t[self._intensity.name].astype(np.float64).ravel()
                    v = v[np.isfinite(v)]
                    if v.size:
                        lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
                a, b, what = intensity_scale(lo if lo <= hi else 0.0, hi if lo <= hi else 1.0)
                self.intensity_scale = (a, b)
                notes.append(what)
        if self.has_rgb:
            notes.append(f"colour from {self._rgb.name} (0xRRGGBB), as sRGB")
        if self.grid_shape is not None:
            notes.append(f"organised {self.height} x {self.width}: sent as the scan's range "
                         "grid (the server fills the gaps between neighbouring returns on one "
                         "surface)")
        self.notes.extend(notes)

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        a, b = self.intensity_scale
        done = 0
        for t in self._tables(chunk_points):
            xyz = self._xyz(t)
            n = len(xyz)
            missing = ~np.all(np.isfinite(xyz), axis=1)
            if not self.as_stored:
                xyz = world_to_sensor(xyz, self.to_sensor)
            xyz[missing] = 0.0
            intensity = rgb = grid = None
            if self.has_intensity:
                i = t[self._intensity.name].astype(np.float64).ravel()
                intensity = np.clip(np.nan_to_num((i - a) / b), 0.0, 1.0).astype(np.float32)
            if self.has_rgb:
                packed = np.ascontiguousarray(t[self._rgb.name].ravel()).view(np.uint32)
                codes = np.stack([(packed >> s) & 0xFF for s in (16, 8, 0)], axis=1)
                rgb = srgb_to_linear(codes.astype(np.float64) / 255.0).astype(np.float32)
            if self.grid_shape is not None:
                cell = np.arange(done, done + n, dtype=np.int64)
                grid = np.stack([cell // self.width, cell % self.width],
                                axis=1).astype(np.uint32)
            done += n
            yield PointCloud(np.ascontiguousarray(xyz, dtype=np.float32), intensity, rgb, grid)


def lzf_decompress(data: bytes, size: int, where: str = "LZF data") -> bytes:
    """LZF (liblzf, the compression of PCD's binary_compressed data) decompressed to exactly
    `size` bytes. A control byte below 32 starts a run of that many plus one literal bytes;
    any other copies (its top 3 bits, 7 meaning one more length byte follows) + 2 bytes from
    ((its low 5 bits) << 8 | next byte) + 1 bytes back. ValueError naming `where` for data
    that runs past either end."""
    out = bytearray(size)
    src = memoryview(data)
    ip, op, n = 0, 0, len(data)
    try:
        while ip < n:
            ctrl = src[ip]
            ip += 1
            if ctrl < 32:
                run = ctrl + 1
                if ip + run > n or op + run > size:
                    raise IndexError
                out[op:op + run] = src[ip:ip + run]
                ip += run
                op += run
                continue
            length = ctrl >> 5
            if length == 7:
                length += src[ip]
                ip += 1
            back = ((ctrl & 0x1F) << 8 | src[ip]) + 1
            ip += 1
            length += 2
            ref = op - back
            if ref < 0 or op + length > size:
                raise IndexError
            if back >= length:
                out[op:op + length] = out[ref:ref + length]
            else:  # the copy overlaps what it writes: the last `back` bytes, repeated
                pattern = bytes(out[ref:op])
                out[op:op + length] = (pattern * (length // back + 1))[:length]
            op += length
    except IndexError:
        raise ValueError(f"{where}: the LZF data is corrupt (it runs past its "
                         f"{'input' if ip >= n else 'output'} at byte {ip})") from None
    if op != size:
        raise ValueError(f"{where}: the LZF data unpacks to {op} bytes, not {size}")
    return bytes(out)


def _pcd_header(path: str) -> Tuple[Dict[str, List[str]], int, int]:
    """A PCD file's header lines by keyword, the data's byte offset and its first line
    number. ValueError for a file that is not PCD or ends before DATA."""
    try:
        with open(path, "rb") as f:
            head = f.read(_PCD_HEADER_BYTES)
    except OSError as e:
        raise ValueError(f"{path}: cannot be read: {e.strerror}") from e
    keys: Dict[str, List[str]] = {}
    at, line_no = 0, 0
    while True:
        end = head.find(b"\n", at)
        if end < 0:
            raise ValueError(f"{path}: not a PCD file (no DATA line in its first "
                             f"{_PCD_HEADER_BYTES} bytes)" if keys else
                             f"{path}: not a PCD file" + ("" if head else " (it is empty)"))
        line = head[at:end].decode("latin-1").strip()
        at, line_no = end + 1, line_no + 1
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH",
                       "HEIGHT", "VIEWPOINT", "POINTS", "DATA"):
            raise ValueError(f"{path}: line {line_no}: not a PCD header line: {line[:80]!r}")
        keys["FIELDS" if key == "COLUMNS" else key] = words[1:]
        if key == "DATA":
            return keys, at, line_no + 1


def read_pcd(path: str, pose=None) -> PcdScan:
    """A PCD file's scan (see PcdPoints): its points streamed in the scanner's frame, which the
    file's VIEWPOINT gives (the sensor's pose in the points' frame; the identity when the
    header has none). The scan's pose is `pose` when given (a manifest's or --pose: where
    that sensor stood in the project, the points following it), else the VIEWPOINT, so that
    the points keep the file's coordinates. ValueError naming the file for one that is not
    PCD, a header whose lines disagree, a type PCD does not have, or data that ends early."""
    keys, offset, first_line = _pcd_header(path)

    def need(key: str) -> List[str]:
        if key not in keys:
            raise ValueError(f"{path}: the PCD header has no {key} line")
        return keys[key]

    def whole(key: str, words: List[str]) -> List[int]:
        try:
            return [int(w) for w in words]
        except ValueError:
            raise ValueError(f"{path}: PCD {key} must be whole numbers, got "
                             f"{' '.join(words)[:80]!r}") from None

    names = need("FIELDS")
    sizes = whole("SIZE", need("SIZE"))
    types = [t.upper() for t in need("TYPE")]
    counts = whole("COUNT", keys["COUNT"]) if "COUNT" in keys else [1] * len(names)
    if not (len(names) == len(sizes) == len(types) == len(counts)) or not names:
        raise ValueError(f"{path}: the PCD header's FIELDS, SIZE, TYPE and COUNT disagree "
                         f"({len(names)}, {len(sizes)}, {len(types)}, {len(counts)} entries)")
    fields = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        dtype = _PCD_TYPES.get((kind, size))
        if dtype is None or count < 1:
            raise ValueError(f"{path}: PCD field {name}: TYPE {kind} SIZE {size} COUNT {count} "
                             "is not a PCD field (F 4/8, I or U 1/2/4/8, a positive count)")
        if name != "_" and any(f.name == name for f in fields):
            raise ValueError(f"{path}: PCD field {name} is named twice")
        fields.append(PcdField(name, dtype, count))
    width_words = whole("WIDTH", need("WIDTH"))
    height_words = whole("HEIGHT", keys.get("HEIGHT", ["1"]))
    if len(width_words) != 1 or len(height_words) != 1:
        raise ValueError(f"{path}: PCD WIDTH and HEIGHT are one number each")
    width, height = width_words[0], height_words[0]
    if width < 0 or height < 1 or width * height > MAX_GRID_CELLS:
        raise ValueError(f"{path}: a PCD of {width} x {height} points is out of bounds")
    if "POINTS" in keys and whole("POINTS", keys["POINTS"]) != [width * height]:
        raise ValueError(f"{path}: PCD POINTS {' '.join(keys['POINTS'])} is not WIDTH x HEIGHT "
                         f"= {width * height}")
    if width * height == 0:
        raise ValueError(f"{path}: the PCD file holds no point")
    data = " ".join(keys["DATA"]).lower()
    if data not in ("ascii", "binary", "binary_compressed"):
        raise ValueError(f"{path}: PCD DATA {data!r} is not ascii, binary or binary_compressed")
    notes = []
    viewpoint = Pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    if "VIEWPOINT" in keys:
        try:
            v = [float(w) for w in keys["VIEWPOINT"]]
        except ValueError:
            v = []
        if len(v) != 7:
            raise ValueError(f"{path}: PCD VIEWPOINT is tx ty tz qw qx qy qz, got "
                             f"{' '.join(keys['VIEWPOINT'])[:80]!r}")
        viewpoint = Pose.make(v[:3], (v[4], v[5], v[6], v[3]), where=f"{path}: VIEWPOINT")
    points = PcdPoints(path, fields, width, height, data, offset, first_line, viewpoint)
    # Points farther from the viewpoint than any scanner measures are stored in a world
    # (georeferenced) frame, and the viewpoint is not where they were measured from.
    xyz = points.first_xyz()
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    far = float(np.median(np.linalg.norm(xyz - np.asarray(viewpoint.position_m), axis=1))) \
        if len(xyz) else 0.0
    if far > GEOREFERENCED_M:
        if pose is None:
            raise ValueError(f"{path}: the points lie {far / 1000:.0f} km from the file's "
                             "VIEWPOINT: they are stored in a world (georeferenced) frame "
                             "without the scanner's position, which visibility needs: give the "
                             "scanner's pose in the file's coordinates (vasl ingest --pose "
                             "x,y,z[,qx,qy,qz,qw], or a manifest whose lidar.points names the "
                             "file)")
        points.to_sensor = pose = Pose.parse(pose)
        notes.append(f"points {far / 1000:.0f} km from the VIEWPOINT, in a world frame: turned "
                     "into the scanner's frame with the given pose (float64)")
    elif pose is not None:
        pose = Pose.parse(pose)
        notes.append("the scanner placed by the given pose (the points follow it)")
    else:
        pose = viewpoint
        notes.append("the scanner's pose is the file's VIEWPOINT" if "VIEWPOINT" in keys else
                     "no VIEWPOINT in the header: the scanner at the file's origin")
    if not points.as_stored and points.to_sensor is viewpoint:
        notes.append("points turned into the scanner's frame through the file's VIEWPOINT "
                     "(float64)")
    points.notes.extend(notes)
    return PcdScan(os.path.splitext(os.path.basename(path))[0], pose, points)


def is_pcd(path: str) -> bool:
    """Whether a path names a PCD file (by its extension)."""
    return path.lower().endswith(".pcd")
