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
from typing import Dict, List, Optional, Sequence, Tuple

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


PINHOLE_KEYS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")


def pinhole_from_json(obj, where: str) -> Dict[str, float]:
    """A pinhole camera's intrinsics (VASL-MODEL §2.2: x right, y down, z forward; pixels;
    Brown-Conrady k1 k2 k3 p1 p2, default 0) from a JSON object. ValueError naming the field."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected an object with fx_px, fy_px, cx_px, cy_px")
    unknown = sorted(set(obj) - set(PINHOLE_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(unknown)}; "
                         f"expected {', '.join(PINHOLE_KEYS)}")
    out = {}
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
    return out


@dataclass
class PanoramaEntry:
    """One image of a manifest: an equirect panorama, or a pinhole photo with `pinhole`."""

    name: str
    image_path: str  #: absolute path of the encoded image
    modality: str  #: "rgb" or "ir"
    pose: Pose
    angular_resolution_rad: float = 0.0
    pinhole: Optional[Dict[str, float]] = None  #: intrinsics (PINHOLE_KEYS), None: equirect


@dataclass
class Manifest:
    """One scan as described by a manifest file (README.md, "Scan manifest")."""

    path: str
    scan: str
    rig: str
    captured_utc: str
    pose: Pose
    points_path: Optional[str]  #: absolute path of the PLY file; None: a camera-only scan
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
        panoramas.append(PanoramaEntry(
            name=name,
            image_path=os.path.join(base, need(p, "image", f"panoramas[{i}].")),
            modality=modality,
            pose=_pose_from_json(need(p, "pose", f"panoramas[{i}]."), f"{path}: panoramas[{i}].pose"),
            angular_resolution_rad=float(p.get("angular_resolution_rad", 0.0)),
            pinhole=(pinhole_from_json(p["pinhole"], f"{path}: panoramas[{i}].pinhole")
                     if "pinhole" in p else None),
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


@dataclass
class E57Scan:
    """One scan (data3D) of an E57 file: points in its own frame, its pose and the images
    taken with it; or the images of the file that belong to no scan (cloud None: a
    camera-only scan)."""

    scan: str  #: scan id: the file stem, "-<n>" when the file holds several scans
    pose: Pose  #: the data3D pose (sensor frame to the file's world frame)
    cloud: Optional[PointCloud]  #: valid points only; intensity scaled to [0, 1]; None: images only
    images: List[E57Image] = field(default_factory=list)

    @property
    def ingestible_images(self) -> List[E57Image]:
        return [im for im in self.images if not im.problem]


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
    images = _read_e57_images(e57, path)
    if count == 0 and not images:
        raise ValueError(f"{path}: the E57 file holds no scan (no data3D) and no image (images2D)")
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
        try:
            guid = str(e57.image_file.root()["data3D"][i]["guid"].value())
        except Exception:
            guid = ""
        scans.append(E57Scan(scan=name, pose=pose, cloud=PointCloud(
            xyz_m=np.ascontiguousarray(xyz[keep], dtype=np.float32), intensity=intensity,
            rgb=None if rgb is None else np.ascontiguousarray(rgb, dtype=np.float32)),
            images=[im for im in images if guid and im.scan_guid == guid]))
    # Images of no scan of the file (no or an unknown associatedData3DGuid): with one scan,
    # taken as its; otherwise a camera-only scan of their own.
    attached = {id(im) for sc in scans for im in sc.images}
    loose = [im for im in images if id(im) not in attached]
    if loose and len(scans) == 1:
        scans[0].images.extend(loose)
    elif loose:
        first = next((im.pose for im in loose if im.pose is not None), Pose.make([0, 0, 0]))
        scans.append(E57Scan(scan=f"{stem}-images" if scans else stem, pose=first, cloud=None,
                             images=loose))
    return scans


def _e57_pose(node, where: str, notes: List[str]) -> Optional[Pose]:
    """A pose node (rotation w x y z, translation) as a Pose; a quaternion that is not of unit
    length is normalised (noted), a zero or non-finite one refused (ValueError)."""
    try:
        w, x, y, z = (float(node["rotation"][c].value()) for c in "wxyz")
        t = [float(node["translation"][c].value()) for c in "xyz"]
    except Exception:
        return None
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"{where}: the pose's rotation is not a quaternion ({w}, {x}, {y}, {z})")
    if abs(norm - 1.0) > 1e-6:
        notes.append(f"rotation quaternion of length {norm:.4g} normalised")
    return Pose.make(t, [x / norm, y / norm, z / norm, w / norm], where=where)


_IMAGE_KINDS = (("pinholeRepresentation", "pinhole"), ("sphericalRepresentation", "spherical"),
                ("cylindricalRepresentation", "cylindrical"),
                ("visualReferenceRepresentation", "visual"))


def _read_e57_images(e57, path: str) -> List[E57Image]:
    """Every image of an E57 file (images2D), each with the reason it cannot be ingested when
    it cannot: a visual reference (no projection) or cylindrical image, a spherical image that
    is not a whole 360° x 180° panorama, or bytes that are neither JPEG nor PNG."""
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
        data = b""
        if blob is not None:
            buf = np.zeros(blob.byteCount(), dtype=np.uint8)
            blob.read(buf, 0, blob.byteCount())
            data = buf.tobytes()
        notes: List[str] = []
        pose = _e57_pose(node["pose"], where, notes) if node.isDefined("pose") else None
        image = E57Image(name=name, kind=kind, width=int(number("imageWidth")),
                         height=int(number("imageHeight")), data=data, pose=pose,
                         scan_guid=(str(node["associatedData3DGuid"].value())
                                    if node.isDefined("associatedData3DGuid") else ""))
        problems = []
        if kind == "visual":
            problems.append("a visual reference image has no projection (kept in the file only)")
        elif kind == "cylindrical":
            problems.append("cylindrical images are not supported (only spherical and pinhole)")
        elif kind == "spherical":
            span_w = image.width * number("pixelWidth")
            span_h = image.height * number("pixelHeight")
            if abs(span_w - 2 * math.pi) > 0.02 * 2 * math.pi or abs(span_h - math.pi) > 0.02 * math.pi:
                problems.append(f"the spherical image spans {math.degrees(span_w):.0f}° x "
                                f"{math.degrees(span_h):.0f}°; only whole 360° x 180° panoramas "
                                "are supported")
        elif kind == "pinhole":
            f, pw, ph = number("focalLength"), number("pixelWidth"), number("pixelHeight")
            if f > 0 and pw > 0 and ph > 0:
                image.pinhole = {"fx_px": f / pw, "fy_px": f / ph,
                                 "cx_px": number("principalPointX"),
                                 "cy_px": number("principalPointY"),
                                 "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0}
                if image.pose is not None:  # E57 camera: y up, looking along -z (see E57Image)
                    q = image.pose.quaternion_xyzw
                    turned = _quat_mul((q[0], q[1], q[2], q[3]), (1.0, 0.0, 0.0, 0.0))
                    image.pose = Pose.make(image.pose.position_m, turned, where=where)
            else:
                problems.append("focalLength, pixelWidth and pixelHeight must be > 0")
        if kind in ("spherical", "pinhole") and not problems:
            if not (data.startswith(b"\x89PNG\r\n\x1a\n") or data.startswith(b"\xff\xd8")):
                problems.append("its bytes are neither a JPEG nor a PNG image")
            elif image.pose is None:
                problems.append("it has no pose")
        image.problem = "; ".join(problems)
        image.notes = notes
        out.append(image)
    return out


def _quat_mul(a, b):
    """Hamilton product of two (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


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
