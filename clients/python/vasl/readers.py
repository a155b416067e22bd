"""Readers for what a capture rig leaves on disk: PLY point clouds and the scan manifest.

PLY: ASCII, binary little endian and binary big endian; the ``vertex`` element's ``x, y, z``
(float or double) and an optional ``intensity`` (any numeric type); other properties and elements
are ignored. The manifest is the JSON file ``vasl_scene`` writes (documented in README.md); its
paths are relative to the manifest file.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np

from .types import Pose, srgb_to_linear

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance")


@dataclass
class PointCloud:
    """Points of one scan in the sensor frame."""

    xyz_m: np.ndarray  #: (N, 3) float32, metres
    intensity: Optional[np.ndarray] = None  #: (N,) float32 or None
    rgb: Optional[np.ndarray] = None  #: (N, 3) float32 linear colour, or None

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])


def read_ply(path: str) -> PointCloud:
    """Reads the vertices of a PLY file. ValueError for a malformed or unsupported file."""
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
    intensity = col[intensity_name].astype(np.float32) if intensity_name else None
    return PointCloud(xyz_m=np.ascontiguousarray(xyz), intensity=intensity)


@dataclass
class PanoramaEntry:
    """One panorama of a manifest."""

    name: str
    image_path: str  #: absolute path of the encoded image
    modality: str  #: "rgb" or "ir"
    pose: Pose
    angular_resolution_rad: float = 0.0


@dataclass
class Manifest:
    """One scan as described by a manifest file (README.md, "Scan manifest")."""

    path: str
    scan: str
    rig: str
    captured_utc: str
    pose: Pose
    points_path: str  #: absolute path of the PLY file
    divergence_rad: float
    panoramas: List[PanoramaEntry] = field(default_factory=list)


def _pose_from_json(obj, where: str) -> Pose:
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected an object with 'position' and 'quaternion'")
    position = obj.get("position", [0.0, 0.0, 0.0])
    quaternion = obj.get("quaternion", [0.0, 0.0, 0.0, 1.0])
    return Pose.make(position, quaternion, where=where)


def read_manifest(path: str) -> Manifest:
    """Reads a scan manifest (JSON). ValueError naming the field for a malformed one."""
    with open(path, "r", encoding="utf-8") as f:
        try:
            doc = json.load(f)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON: {e}") from e
    base = os.path.dirname(os.path.abspath(path))

    def need(obj, key, where):
        if not isinstance(obj, dict) or key not in obj:
            raise ValueError(f"{path}: missing '{where}{key}'")
        return obj[key]

    scan = need(doc, "scan", "")
    if not isinstance(scan, str) or not scan:
        raise ValueError(f"{path}: 'scan' must be a non-empty string")
    lidar = need(doc, "lidar", "")
    points = need(lidar, "points", "lidar.")
    divergence = float(lidar.get("divergence_rad", 0.0003))
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
        panoramas.append(PanoramaEntry(
            name=name,
            image_path=os.path.join(base, need(p, "image", f"panoramas[{i}].")),
            modality=modality,
            pose=_pose_from_json(need(p, "pose", f"panoramas[{i}]."), f"{path}: panoramas[{i}].pose"),
            angular_resolution_rad=float(p.get("angular_resolution_rad", 0.0)),
        ))
    return Manifest(
        path=os.path.abspath(path),
        scan=scan,
        rig=str(doc.get("rig", "")),
        captured_utc=str(doc.get("captured_utc", "")),
        pose=_pose_from_json(need(doc, "pose", ""), f"{path}: pose"),
        points_path=os.path.join(base, points),
        divergence_rad=divergence,
        panoramas=panoramas,
    )


@dataclass
class E57Scan:
    """One scan (data3D) of an E57 file: points in its own frame and its pose."""

    scan: str  #: scan id: the file stem, with "-<n>" when the file holds several scans
    pose: Pose  #: the data3D pose (sensor frame to the file's world frame)
    cloud: PointCloud  #: valid points only; intensity scaled to [0, 1] by the file's limits


def read_e57(path: str) -> List[E57Scan]:
    """Reads every scan of an E57 file with pye57: Cartesian or spherical coordinates (spherical
    ones converted with VASL-MODEL §2.1's axes: azimuth from +x toward +y, elevation up),
    points flagged invalid dropped, intensity scaled to [0, 1] by ``intensityLimits``, colour
    scaled by ``colorLimits`` and linearised (sRGB), extension fields (normals, ...) skipped.
    ValueError with the file's name for a file that is not readable E57, holds no scan, or a
    scan without valid points."""
    try:
        import pye57  # imported here: only E57 users need it
    except ImportError as e:  # pragma: no cover - setup.sh installs it
        raise ValueError("reading E57 needs the pye57 package (deploy/setup.sh installs it)") from e
    stem = os.path.splitext(os.path.basename(path))[0]
    try:
        e57 = pye57.E57(path)
        count = e57.scan_count
    except Exception as e:  # pye57 raises its own exception types
        raise ValueError(f"{path}: not a readable E57 file: {str(e).splitlines()[0]}") from e
    if count == 0:
        raise ValueError(f"{path}: the E57 file holds no scan (no data3D)")
    scans = []
    for i in range(count):
        where = f"{path}: scan {i}"
        try:
            header = e57.get_header(i)
            # Extension fields (normals, ...) are skipped, never a reason to lose the file.
            raw = e57.read_scan_raw(i, ignore_unsupported_fields=True)
        except Exception as e:
            raise ValueError(f"{where}: cannot be read: {str(e).splitlines()[0]}") from e
        if "cartesianX" in raw:
            xyz = np.stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]], axis=1)
            invalid = raw.get("cartesianInvalidState")
        elif "sphericalRange" in raw:
            r, az, el = raw["sphericalRange"], raw["sphericalAzimuth"], raw["sphericalElevation"]
            xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                            r * np.sin(el)], axis=1)
            invalid = raw.get("sphericalInvalidState")
        else:
            raise ValueError(f"{where}: has neither Cartesian nor spherical coordinates")
        keep = np.all(np.isfinite(xyz), axis=1)
        if invalid is not None:
            keep &= np.asarray(invalid) == 0
        if not np.any(keep):
            raise ValueError(f"{where}: holds no valid point")
        intensity = None
        if "intensity" in raw:
            intensity = np.asarray(raw["intensity"], dtype=np.float64)[keep]
            lo, hi = _e57_intensity_limits(header, intensity)
            intensity = ((intensity - lo) / (hi - lo) if hi > lo else np.ones_like(intensity))
            intensity = intensity.astype(np.float32)
        rgb = None
        if all(f"color{c}" in raw for c in ("Red", "Green", "Blue")):
            rgb = np.stack([_e57_colour(header, raw[f"color{c}"], c)[keep]
                            for c in ("Red", "Green", "Blue")], axis=1)
        w, x, y, z = (float(v) for v in header.rotation)
        pose = Pose.make([float(v) for v in header.translation], [x, y, z, w], where=where)
        name = stem if count == 1 else f"{stem}-{i + 1}"
        scans.append(E57Scan(scan=name, pose=pose, cloud=PointCloud(
            xyz_m=np.ascontiguousarray(xyz[keep], dtype=np.float32), intensity=intensity,
            rgb=None if rgb is None else np.ascontiguousarray(rgb, dtype=np.float32))))
    return scans


def _e57_colour(header, values: np.ndarray, channel: str) -> np.ndarray:
    """One colour channel scaled to [0, 1] by the file's colorLimits (the data's integer range
    when it gives none) and linearised: E57 colours are display-referred, taken as sRGB."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = 0.0, 255.0 if v.size == 0 or v.max() <= 255 else 65535.0
    try:
        limits = header.node["colorLimits"]
        lo = float(limits[f"color{channel}Minimum"].value())
        hi = float(limits[f"color{channel}Maximum"].value())
    except Exception:
        pass
    scaled = (v - lo) / (hi - lo) if hi > lo else np.ones_like(v)
    return srgb_to_linear(scaled)


def _e57_intensity_limits(header, values: np.ndarray) -> Tuple[float, float]:
    """The file's intensityLimits, or the data's own range when the file gives none."""
    try:
        return float(header.intensityMinimum), float(header.intensityMaximum)
    except Exception:
        return float(values.min()), float(values.max())
