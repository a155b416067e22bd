"""vasl.Client: a typed facade over the vasl.v1 gRPC service (numpy in and out).

Bad arguments raise ValueError before anything is sent; errors from the server raise VaslError
carrying the gRPC status code and the server's message.
"""
from __future__ import annotations

import os
import tempfile
import threading
import time
import uuid
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import grpc
import numpy as np
from google.protobuf.timestamp_pb2 import Timestamp

from ._proto import vasl_pb2 as pb
from ._proto import vasl_pb2_grpc as pb_grpc
from .readers import (CHUNK_POINTS, E57Scan, Manifest, PointCloud, PointSource,
                      cylinder_from_json, is_ascii_cloud, is_las, is_pcd, is_ptx,
                      pinhole_from_json, read_ascii_cloud, read_e57, read_las, read_manifest,
                      read_pcd, read_ply, read_ptx, sphere_from_json)
from .types import (CONFIDENCE_FACTORS, ArtefactCoverage, CalibrationHealth, CameraConfidence,
                    ChangeResult, ChangeStats, ExportResult, Inspection, IngestResult,
                    LensEstimate, LensMap, NormaliseResult, Pose, Project, RecordAttribute, RecordsQuery, RenderResult,
                    ReweightResult, Scan, Source, Version, VisualReference)

DEFAULT_SERVER = "127.0.0.1:50051"
#: Payload bytes per streamed chunk (a multiple of 16, well below the server's 8 MiB messages).
CHUNK_BYTES = 1 << 20
#: Largest message the client accepts (render chunks are 1 MiB by default).
MAX_MESSAGE_BYTES = 64 << 20

_MODALITY_TO_PB = {"rgb": pb.MODALITY_RGB, "ir": pb.MODALITY_IR}
_MODALITY_NAMES = {pb.MODALITY_LIDAR: "lidar", pb.MODALITY_RGB: "rgb", pb.MODALITY_IR: "ir",
                   pb.MODALITY_RADAR: "radar", pb.MODALITY_DERIVED: "derived"}
_FORMATS = {"exr": pb.IMAGE_FORMAT_EXR, "png": pb.IMAGE_FORMAT_PNG,
            "deep": pb.IMAGE_FORMAT_DEEP_EXR}
_COLOUR_DETAIL = {"vossel": pb.COLOUR_DETAIL_VOSSEL, "images": pb.COLOUR_DETAIL_SOURCE_IMAGES}
#: Bits of a record's flags (RecordRow.flags): derived (back-projected), and invalidated (kept
#: with weight 0: a flare-invalid sample, or one lying mostly on masked or transparent pixels).
FLAG_DERIVED = 1
FLAG_INVALIDATED = 2



def pinhole_to_pb(pinhole: dict, where: str) -> "pb.PinholeCamera":
    """A pinhole camera's intrinsics (a dict as `pinhole_from_json` reads them: fx_px, fy_px,
    cx_px, cy_px, optional k1-k3, p1, p2, or with "lens": "fisheye" k1-k4 and optionally
    field_of_view_deg) as the proto message. ValueError naming `where` for missing or unknown
    keys and bad values."""
    k = pinhole_from_json(pinhole, where)
    lens = pb.LENS_FISHEYE if k.pop("lens") == "fisheye" else pb.LENS_BROWN_CONRADY
    return pb.PinholeCamera(lens=lens, **k)

class VaslError(Exception):
    """A failed RPC: `code` is the grpc.StatusCode, `details` the server's message."""

    def __init__(self, code: grpc.StatusCode, details: str, method: str = ""):
        self.code = code
        self.details = details or ""
        self.method = method
        super().__init__(f"{code.name}: {self.details}")


def _change_stats(c) -> ChangeStats:
    return ChangeStats(c.sources_computed, c.sources_revisited, c.pairs_revisited, c.tiles_changed,
                       c.bytes_written, c.blocks_revisited, c.sources_refreshed,
                       c.vossels_revisited)


def _change(r) -> ChangeResult:
    return ChangeResult(r.version, r.vossel_count, r.record_count, r.seconds,
                        {s.stage: s.seconds for s in r.stages}, _change_stats(r.change),
                        r.request_id, r.replayed)


def _reweight_result(r) -> ReweightResult:
    return ReweightResult(r.version, r.profile, r.revision, r.tile_count, r.record_count,
                          r.vossel_count, r.bytes_written, r.unchanged, r.seconds, r.request_id,
                          r.replayed)


_VERDICTS = {pb.CalibrationHealth.VERDICT_OK: "ok",
             pb.CalibrationHealth.VERDICT_FLAGGED: "flagged",
             pb.CalibrationHealth.VERDICT_UNCHECKED: "unchecked"}


def _calibration(c: pb.CalibrationHealth) -> CalibrationHealth:
    return CalibrationHealth(c.camera, c.lidar_source, _VERDICTS.get(c.verdict, "unchecked"),
                             c.points_in_view, c.features, c.matched, c.cell_px, c.pixel_mean_px,
                             c.pixel_p95_px, c.offset_mean_m, c.offset_p95_m, c.roundtrip_mean_m,
                             c.roundtrip_p95_m, c.rotation_deg, c.note)


def _ingest_result(r) -> IngestResult:
    result = IngestResult(r.scan_id, r.scan, r.version, r.vossel_count, r.record_count,
                          r.new_vossels, r.point_count, r.ingest_seconds, r.total_seconds,
                          {s.stage: s.seconds for s in r.stages}, _change_stats(r.change),
                          r.request_id, r.replayed)
    result.calibration = [_calibration(c) for c in r.calibration]
    return result


def _back_project_result(r) -> dict:
    return {"name": r.name, "version": r.version,
            "pixels_back_projected": r.pixels_back_projected,
            "pixels_outside": r.pixels_outside, "pixels_invalid": r.pixels_invalid,
            "record_count": r.record_count, "seconds": r.seconds,
            "request_id": r.request_id, "replayed": r.replayed}


def new_request_id() -> str:
    """A fresh request id for a change (a UUID): send a retry under the same one."""
    return uuid.uuid4().hex


# Codes after which a change may have committed without its answer reaching the client: the
# client asks GetOperation before it sends the change again.
_ANSWER_LOST = (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE,
                grpc.StatusCode.ABORTED)
_CODES = {c.value[0]: c for c in grpc.StatusCode}
# How a change that stored nothing may have failed for want of its upload (the stream was cut):
# sent again.
_UPLOAD_CUT = _ANSWER_LOST + (grpc.StatusCode.CANCELLED,)


def _wrap(method: str, err: grpc.RpcError) -> VaslError:
    code = err.code() if hasattr(err, "code") else grpc.StatusCode.UNKNOWN
    details = err.details() if hasattr(err, "details") else str(err)
    return VaslError(code, details, method)


def pose_to_pb(pose: Pose) -> pb.Pose:
    p = pb.Pose()
    p.position_m.x, p.position_m.y, p.position_m.z = pose.position_m
    q = pose.quaternion_xyzw
    p.quaternion_xyzw.x, p.quaternion_xyzw.y, p.quaternion_xyzw.z, p.quaternion_xyzw.w = q
    return p


def _pose_from_pb(p: pb.Pose) -> Pose:
    return Pose((p.position_m.x, p.position_m.y, p.position_m.z),
                (p.quaternion_xyzw.x, p.quaternion_xyzw.y, p.quaternion_xyzw.z,
                 p.quaternion_xyzw.w))


def _iso(msg, field: str) -> str:
    """A Timestamp field as RFC 3339 text ("" when unset)."""
    return getattr(msg, field).ToJsonString() if msg.HasField(field) else ""


def _timestamp(iso: str, what: str):
    """RFC 3339 text (e.g. 2026-11-22T12:00:00Z) as a Timestamp; None for ""."""
    if not iso:
        return None
    ts = Timestamp()
    try:
        ts.FromJsonString(iso)
    except ValueError:
        raise ValueError(f"{what} must be an RFC 3339 time such as 2026-11-22T12:00:00Z, "
                         f"got {iso!r}") from None
    return ts


def _project(p: pb.Project) -> Project:
    origin = (p.origin_m.x, p.origin_m.y, p.origin_m.z) if p.HasField("origin_m") else None
    return Project(p.name, p.description, p.vossel_size_m, p.head_version, p.scan_count,
                   p.vossel_count, p.record_count, _iso(p, "create_time"), p.problem, origin)


_PROFILE_NUMBERS = ("alpha", "beta", "rho", "v_min", "lambda_src", "theta_max_rad",
                    "proximity_m")
_PROFILE_KEYS = set(_PROFILE_NUMBERS) | {"name", "kappa", "mode", "scan_gain", "channel_gain",
                                         "theta_max_deg", "revision", "created_utc",
                                         "lens_maps"}


def profile_to_pb(profile: dict) -> pb.WeightingProfile:
    """A weighting profile from a dict (as read from JSON or TOML): name, alpha, beta, rho,
    kappa (6 numbers in CONFIDENCE_FACTORS order, or a table by factor name), v_min,
    lambda_src, theta_max_rad or
    theta_max_deg, proximity_m, mode ("blend" or "nearest"), scan_gain {source id: g},
    channel_gain {source id: [r, g, b]}, lens_maps [lens map ids]. Unset fields take the
    model's defaults."""
    if not isinstance(profile, dict):
        raise ValueError("a profile must be a table of parameters")
    unknown = set(profile) - _PROFILE_KEYS
    if unknown:
        raise ValueError(f"unknown profile parameter(s) {sorted(unknown)}; known: {sorted(_PROFILE_KEYS)}")
    out = pb.WeightingProfile(name=str(profile.get("name", "")))
    for key in _PROFILE_NUMBERS:
        if key in profile:
            setattr(out, key, float(profile[key]))
    if "theta_max_deg" in profile:
        if "theta_max_rad" in profile:
            raise ValueError("give theta_max_rad or theta_max_deg, not both")
        out.theta_max_rad = float(np.deg2rad(float(profile["theta_max_deg"])))
    kappa = profile.get("kappa")
    if isinstance(kappa, dict):
        bad = set(kappa) - set(CONFIDENCE_FACTORS)
        if bad:
            raise ValueError(f"kappa factors must be among {CONFIDENCE_FACTORS}, got {sorted(bad)}")
        kappa = [float(kappa.get(f, 1.0)) for f in CONFIDENCE_FACTORS]
    if kappa is not None:
        if len(kappa) not in (len(CONFIDENCE_FACTORS), 4):
            raise ValueError(f"kappa needs {len(CONFIDENCE_FACTORS)} values {CONFIDENCE_FACTORS} "
                             "(or the first 4), or a table by factor name")
        out.kappa.extend(float(k) for k in kappa)
    mode = profile.get("mode", "blend")
    if mode not in ("blend", "nearest"):
        raise ValueError(f"mode must be 'blend' or 'nearest', got {mode!r}")
    out.mode = pb.WeightingProfile.MODE_NEAREST if mode == "nearest" else pb.WeightingProfile.MODE_BLEND
    for source, g in (profile.get("scan_gain") or {}).items():
        out.scan_gain[int(source)] = float(g)
    for source, gains in (profile.get("channel_gain") or {}).items():
        gains = [float(g) for g in (gains if isinstance(gains, (list, tuple)) else [gains])]
        out.channel_gain.add(source=int(source), gain=gains)
    out.lens_maps.extend(int(i) for i in (profile.get("lens_maps") or []))
    return out


def profile_from_pb(p: pb.WeightingProfile) -> dict:
    """The dict form of a profile (profile_to_pb's input), with its revision and time."""
    return {"name": p.name, "revision": p.revision, "alpha": p.alpha, "beta": p.beta,
            "rho": p.rho, "kappa": dict(zip(CONFIDENCE_FACTORS, p.kappa)), "v_min": p.v_min,
            "lambda_src": p.lambda_src, "theta_max_rad": p.theta_max_rad,
            "proximity_m": p.proximity_m,
            "mode": "nearest" if p.mode == pb.WeightingProfile.MODE_NEAREST else "blend",
            "scan_gain": {int(k): v for k, v in sorted(p.scan_gain.items())},
            "channel_gain": {int(c.source): list(c.gain) for c in p.channel_gain},
            "lens_maps": list(p.lens_maps), "created_utc": _iso(p, "create_time")}


def lens_map_from_pb(m: pb.LensMap) -> LensMap:
    """A lens map as the client returns it."""
    return LensMap(m.id, m.rig, m.camera, m.period, m.image_width_px, m.image_height_px,
                   m.grid_width, m.grid_height, list(m.transmission), list(m.veil),
                   {int(g.source): list(g.gain) for g in m.source_gain}, m.dirt_share,
                   m.veil_share, _iso(m, "create_time"))


def _check_points(xyz_m: np.ndarray, intensity, rgb) -> np.ndarray:
    """Validates point arrays as pack_points takes them; the points as an array."""
    arr = np.asarray(xyz_m)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise ValueError(f"points must be an (N, 3) or (N, 4) array, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError("points: the scan has no point")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"points must be numeric, got dtype {arr.dtype}")
    if intensity is not None and np.asarray(intensity).size != arr.shape[0]:
        raise ValueError(f"intensity has {np.asarray(intensity).size} values for "
                         f"{arr.shape[0]} points")
    if rgb is not None:
        colour = np.asarray(rgb)
        if colour.shape != (arr.shape[0], 3):
            raise ValueError(f"rgb must be an (N, 3) array for {arr.shape[0]} points, "
                             f"got shape {colour.shape}")
        if not np.all(np.isfinite(colour)) or np.any(colour < 0):
            raise ValueError("rgb: colours must be finite and >= 0 (linear)")
    return arr


def pack_points(xyz_m: np.ndarray, intensity: Optional[np.ndarray] = None,
                rgb: Optional[np.ndarray] = None, grid: Optional[np.ndarray] = None) -> bytes:
    """(N, 3) or (N, 4) points [+ (N,) intensity] [+ (N, 3) linear colour] [+ (N, 2) range-grid
    row and column] -> packed little-endian float32 (x, y, z, i), or (x, y, z, i, r, g, b) with
    colour (28 bytes a point, POINT_FORMAT_XYZIRGB_F32LE), each followed by uint32 row, column
    with a grid (LidarModel.grid)."""
    arr = _check_points(xyz_m, intensity, rgb)
    floats = 4 if rgb is None else 7
    fields = [("f", "<f4", (floats,))] + ([("rc", "<u4", (2,))] if grid is not None else [])
    packed = np.zeros(arr.shape[0], dtype=np.dtype(fields))
    packed["f"][:, :arr.shape[1]] = arr
    if intensity is not None:
        packed["f"][:, 3] = np.asarray(intensity).ravel()
    if rgb is not None:
        packed["f"][:, 4:] = np.asarray(rgb)
    if grid is not None:
        packed["rc"] = np.asarray(grid)
    return packed.tobytes()


class ArrayPoints(PointSource):
    """Points already in memory (arrays as `pack_points` takes them) as a PointSource, so that
    they are packed and sent chunk by chunk like a file's: the packed copy never exists
    whole. Validated when made, before anything is sent."""

    def __init__(self, xyz_m, intensity=None, rgb=None, grid=None):
        super().__init__()
        self.xyz_m = _check_points(xyz_m, intensity, rgb)
        self.intensity = None if intensity is None else np.asarray(intensity).ravel()
        self.rgb = None if rgb is None else np.asarray(rgb)
        self.count = int(self.xyz_m.shape[0])
        self.has_intensity = intensity is not None or self.xyz_m.shape[1] == 4
        self.has_rgb = rgb is not None
        self.grid = None
        if grid is not None:  # (N, 2) row, column in the scanner's range grid
            rc = np.asarray(grid)
            if rc.shape != (self.count, 2) or np.any(rc < 0):
                raise ValueError(f"grid must be an ({self.count}, 2) array of rows and columns "
                                 f">= 0, got shape {rc.shape}")
            self.grid = rc.astype(np.uint32)
            self.grid_shape = (int(self.grid[:, 0].max()) + 1, int(self.grid[:, 1].max()) + 1)

    def chunks(self, chunk_points: int = CHUNK_POINTS) -> Iterator[PointCloud]:
        for at in range(0, self.count, chunk_points):
            end = at + chunk_points
            yield PointCloud(self.xyz_m[at:end],
                             None if self.intensity is None else self.intensity[at:end],
                             None if self.rgb is None else self.rgb[at:end],
                             None if self.grid is None else self.grid[at:end])


def point_stride(source: PointSource) -> int:
    """Bytes a point of `source` takes on the wire: 28 with colour, else 16; 8 more with a range
    grid (its row and column)."""
    return (28 if source.has_rgb else 16) + (8 if source.grid_shape else 0)


def packed_chunks(source: PointSource, chunk_points: int = CHUNK_POINTS) -> Iterator[bytes]:
    """A PointSource packed chunk by chunk (pack_points' layout), exactly `source.count` points
    in all: points a reader dropped while reading are made up with (0, 0, 0) points, the
    scanners' "no return" marker that the server skips. ValueError for a source that yields
    more points than it declared."""
    sent = 0
    for chunk in source.chunks(chunk_points):
        n = len(chunk)
        if n == 0:
            continue
        if sent + n > source.count:
            raise ValueError(f"{source.path or 'points'}: yields more points than the "
                             f"{source.count} it declared")
        yield pack_points(chunk.xyz_m, chunk.intensity if source.has_intensity else None,
                          chunk.rgb if source.has_rgb else None,
                          chunk.grid if source.grid_shape else None)
        sent += n
    stride = point_stride(source)
    while sent < source.count:
        n = min(chunk_points, source.count - sent)
        yield bytes(n * stride)
        sent += n


def _image_bytes(image, where: str) -> bytes:
    """An encoded image given as bytes or as a file path, read whole; ValueError naming `where`
    for anything else or an empty one."""
    if isinstance(image, (str, os.PathLike)):
        with open(image, "rb") as f:
            image = f.read()
    if not isinstance(image, (bytes, bytearray)) or not image:
        raise ValueError(f"{where} must be non-empty bytes or a file path")
    return bytes(image)


def _wire_stride(header: pb.ScanHeader) -> int:
    """Bytes a point takes in the stream `header` announces."""
    return ((28 if header.lidar.point_format == pb.POINT_FORMAT_XYZIRGB_F32LE else 16)
            + (8 if header.lidar.HasField("grid") else 0))


def ingest_requests(header: pb.ScanHeader, point_bytes: Union[bytes, Iterable[bytes]],
                    images: Sequence[bytes] = (), chunk_bytes: int = CHUNK_BYTES,
                    on_sent: Optional[Callable[[int], None]] = None,
                    masks: Sequence[bytes] = ()) -> Iterator[pb.IngestScanRequest]:
    """The IngestScan stream: header, points chunks (whole points: multiples of 16 bytes, or
    28 for coloured points), then per panorama its image's chunks and, right after them, its
    mask's (`masks[i]`; empty or absent: no mask). `point_bytes` is the packed points whole, or
    an iterable of packed pieces (each whole points) taken one at a time, so that only one
    piece is in memory. No validation: a test may send anything this way."""
    yield pb.IngestScanRequest(header=header)
    sent = 0
    stride = _wire_stride(header)
    step = max(stride, chunk_bytes - chunk_bytes % stride)
    whole = isinstance(point_bytes, (bytes, bytearray, memoryview))
    pieces = [point_bytes] if whole else point_bytes
    for piece in pieces:
        view = memoryview(piece)
        for i in range(0, len(view), step):
            data = bytes(view[i:i + step])
            yield pb.IngestScanRequest(points=pb.PointsChunk(data=data))
            sent += len(data)
            if on_sent:
                on_sent(sent)
    for index, image in enumerate(images):
        mask = masks[index] if index < len(masks) else b""
        for payload, is_mask in ((image, False), (mask, True)):
            for i in range(0, len(payload), chunk_bytes):
                data = payload[i:i + chunk_bytes]
                yield pb.IngestScanRequest(image=pb.ImageChunk(panorama_index=index, data=data,
                                                               mask=is_mask))
                sent += len(data)
                if on_sent:
                    on_sent(sent)


def decode_exr(data: bytes) -> Dict[str, np.ndarray]:
    """EXR bytes -> {channel name: (H, W) float32} with the OpenEXR module."""
    import OpenEXR  # imported lazily: only renders need it

    fd, path = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        exr = OpenEXR.File(path, separate_channels=True)
        return {name: np.asarray(ch.pixels, dtype=np.float32)
                for name, ch in exr.channels().items()}
    finally:
        os.unlink(path)


def _token_from_env() -> Optional[str]:
    token = os.environ.get("VASL_TOKEN", "").strip()
    if token:
        return token
    path = os.environ.get("VASL_TOKEN_FILE")
    if path:
        with open(path) as f:
            token = f.readline().strip()
        if not token:
            raise ValueError(f"VASL_TOKEN_FILE {path} is empty")
        return token
    return None


class _BearerToken(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor,
                   grpc.StreamUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    """Adds `authorization: Bearer <token>` to every call of the channel."""

    def __init__(self, token: str):
        self._header = ("authorization", f"Bearer {token}")

    def _details(self, d):
        metadata = list(d.metadata or []) + [self._header]
        return d._replace(metadata=metadata) if hasattr(d, "_replace") else _Details(d, metadata)

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._details(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._details(details), request)

    def intercept_stream_unary(self, continuation, details, request_iterator):
        return continuation(self._details(details), request_iterator)

    def intercept_stream_stream(self, continuation, details, request_iterator):
        return continuation(self._details(details), request_iterator)


class _Details(grpc.ClientCallDetails):
    def __init__(self, d, metadata):
        self.method, self.timeout, self.credentials = d.method, d.timeout, d.credentials
        self.wait_for_ready = getattr(d, "wait_for_ready", None)
        self.compression = getattr(d, "compression", None)
        self.metadata = metadata


class Client:
    """Connection to one vasld. Usable as a context manager.

    >>> with Client("127.0.0.1:50051") as c:
    ...     c.create_project("site", vossel_size_m=0.05)
    """

    def __init__(self, server: str = DEFAULT_SERVER, *, timeout_s: Optional[float] = None,
                 chunk_bytes: int = CHUNK_BYTES, token: Optional[str] = None,
                 tls_ca: Optional[str] = None, tls_cert: Optional[str] = None,
                 tls_key: Optional[str] = None):
        """`token`: the bearer token of a server with access control; default $VASL_TOKEN, or
        the first line of the file $VASL_TOKEN_FILE. `tls_ca`: PEM file of the CA that signed
        the server's certificate (TLS; default $VASL_TLS_CA); `tls_cert`/`tls_key`: this
        client's certificate and key for mutual TLS (default $VASL_TLS_CERT/$VASL_TLS_KEY)."""
        if not server or ":" not in server:
            raise ValueError(f"server must be HOST:PORT, got {server!r}")
        if chunk_bytes < 16:
            raise ValueError("chunk_bytes must be >= 16")
        self.server = server
        self.timeout_s = timeout_s
        self.chunk_bytes = chunk_bytes
        options = [("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
                   ("grpc.max_send_message_length", MAX_MESSAGE_BYTES)]
        tls_ca = tls_ca if tls_ca is not None else os.environ.get("VASL_TLS_CA")
        tls_cert = tls_cert if tls_cert is not None else os.environ.get("VASL_TLS_CERT")
        tls_key = tls_key if tls_key is not None else os.environ.get("VASL_TLS_KEY")
        if bool(tls_cert) != bool(tls_key):
            raise ValueError("a client certificate needs its key: give both tls_cert and tls_key")
        if tls_ca or tls_cert:
            read = lambda path: open(path, "rb").read() if path else None  # noqa: E731
            creds = grpc.ssl_channel_credentials(read(tls_ca), read(tls_key), read(tls_cert))
            channel = grpc.secure_channel(server, creds, options=options)
        else:
            channel = grpc.insecure_channel(server, options=options)
        token = token if token is not None else _token_from_env()
        self.channel = (grpc.intercept_channel(channel, _BearerToken(token)) if token
                        else channel)
        self._raw_channel = channel
        #: The raw generated stub (vasl.v1.VaslService), for callers that need every field.
        self.stub = pb_grpc.VaslServiceStub(self.channel)

    def close(self) -> None:
        self._raw_channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _call(self, method: str, request):
        try:
            return getattr(self.stub, method)(request, timeout=self.timeout_s)
        except grpc.RpcError as e:
            raise _wrap(method, e) from None

    @staticmethod
    def _check_name(name: str, what: str = "project") -> None:
        if not isinstance(name, str) or not name:
            raise ValueError(f"{what} must be a non-empty string")

    # -- health --------------------------------------------------------------------------
    def health(self, timeout_s: float = 5.0) -> str:
        """The server's overall health status name, e.g. "SERVING"."""
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        stub = health_pb2_grpc.HealthStub(self.channel)
        try:
            resp = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=timeout_s)
        except grpc.RpcError as e:
            raise _wrap("Health.Check", e) from None
        return health_pb2.HealthCheckResponse.ServingStatus.Name(resp.status)

    # -- projects ------------------------------------------------------------------------
    def create_project(self, name: str, vossel_size_m: float = 0.02, description: str = "",
                       keep_versions: int = 0,
                       origin_m: Optional[Sequence[float]] = None) -> Project:
        """`origin_m`: the project's origin (x, y, z) in world metres, e.g. a point of a
        georeferenced site in its UTM frame; None lets the first scan fix it (its position
        rounded to the kilometre). The lattice holds positions within ±(2^20 - 1)·vossel_size_m
        of it on each axis (±21 km at 2 cm)."""
        self._check_name(name)
        if not (vossel_size_m > 0 and np.isfinite(vossel_size_m)):
            raise ValueError(f"vossel_size_m must be > 0 metres, got {vossel_size_m}")
        request = pb.CreateProjectRequest(name=name, vossel_size_m=vossel_size_m,
                                          description=description, keep_versions=keep_versions)
        if origin_m is not None:
            o = np.asarray(origin_m, dtype=np.float64)
            if o.shape != (3,) or not np.all(np.isfinite(o)):
                raise ValueError(f"origin_m must be 3 finite numbers (metres), got {origin_m!r}")
            request.origin_m.x, request.origin_m.y, request.origin_m.z = (float(v) for v in o)
        return _project(self._call("CreateProject", request))

    def get_project(self, name: str) -> Project:
        self._check_name(name)
        return _project(self._call("GetProject", pb.GetProjectRequest(project=name)))

    def _pages(self, method: str, request, items: str, page_size: int = 0):
        """Every item of a paged List call, page after page."""
        request.page_size = page_size
        out = []
        while True:
            resp = self._call(method, request)
            out.extend(getattr(resp, items))
            if not resp.next_page_token:
                return out, resp
            request.page_token = resp.next_page_token

    def list_projects(self, *, page_size: int = 0) -> List[Project]:
        projects, _ = self._pages("ListProjects", pb.ListProjectsRequest(), "projects", page_size)
        return [_project(p) for p in projects]

    def list_scans(self, project: str, *, page_size: int = 0) -> List[Scan]:
        self._check_name(project)
        listed, _ = self._pages("ListScans", pb.ListScansRequest(project=project), "scans",
                                page_size)
        scans = []
        for s in listed:
            sources = [Source(x.id, x.name, _MODALITY_NAMES.get(x.modality, "unspecified"),
                              _pose_from_pb(x.pose), x.blob_sha256, x.width_px, x.height_px,
                              x.divergence_rad, x.point_count,
                              _calibration(x.calibration) if x.HasField("calibration") else None,
                              x.mask_sha256, x.projection)
                       for x in s.sources]
            refs = [VisualReference(r.name, _pose_from_pb(r.pose), r.blob_sha256, r.width_px,
                                    r.height_px, r.size_bytes) for r in s.visual_references]
            scans.append(Scan(s.id, s.name, s.rig, _iso(s, "capture_time"), _pose_from_pb(s.pose),
                              s.batch, s.version, _iso(s, "create_time"), sources, refs))
        return scans

    def get_visual_reference(self, project: str, scan: str,
                             name: str) -> Tuple[VisualReference, bytes]:
        """A scan's visual reference photo and its bytes, as they were sent."""
        self._check_name(project)
        ref, parts = None, []
        try:
            for r in self.stub.GetVisualReference(
                    pb.GetVisualReferenceRequest(project=project, scan=scan, name=name),
                    timeout=self.timeout_s):
                if r.HasField("reference"):
                    x = r.reference
                    ref = VisualReference(x.name, _pose_from_pb(x.pose), x.blob_sha256,
                                          x.width_px, x.height_px, x.size_bytes)
                else:
                    parts.append(r.chunk.data)
        except grpc.RpcError as e:
            raise _wrap("GetVisualReference", e) from None
        data = b"".join(parts)
        if ref is None or len(data) != ref.size_bytes:
            raise VaslError(grpc.StatusCode.DATA_LOSS,
                            f"the stream ended after {len(data)} bytes of "
                            f"{ref.size_bytes if ref else '?'}", "GetVisualReference")
        return ref, data

    def scan_confidence(self, project: str, scan: str) -> List[CameraConfidence]:
        """The confidence maps of a scan's cameras (VASL-MODEL §9): per camera, each artefact
        found, how much of the image it covers, and its map as a grey PNG."""
        self._check_name(project)
        summary, parts = None, {}
        try:
            for r in self.stub.GetConfidence(pb.GetConfidenceRequest(project=project, scan=scan),
                                             timeout=self.timeout_s):
                if r.HasField("summary"):
                    summary = r.summary
                else:
                    c = r.chunk
                    buf = parts.setdefault((c.camera_index, c.artefact_index), bytearray())
                    if c.offset_bytes != len(buf):
                        raise VaslError(grpc.StatusCode.DATA_LOSS,
                                        "confidence map chunks arrived out of order",
                                        "GetConfidence")
                    buf.extend(c.data)
        except grpc.RpcError as e:
            raise _wrap("GetConfidence", e) from None
        if summary is None:
            raise VaslError(grpc.StatusCode.DATA_LOSS, "the stream had no summary", "GetConfidence")
        cameras = []
        for i, cam in enumerate(summary.cameras):
            artefacts = []
            for j, a in enumerate(cam.artefacts):
                data = bytes(parts.get((i, j), b""))
                if len(data) != a.map_size_bytes:
                    raise VaslError(grpc.StatusCode.DATA_LOSS,
                                    f"{cam.source} {a.artefact}: got {len(data)} of "
                                    f"{a.map_size_bytes} bytes", "GetConfidence")
                artefacts.append(ArtefactCoverage(a.artefact, a.covered_fraction,
                                                  a.flagged_pixels, a.soft_pixels, a.regions,
                                                  a.max_extent_px, data,
                                                  list(a.channel_offsets_px), a.jpeg_quality,
                                                  a.chroma_subsampled, a.lens_map,
                                                  a.smear_offset))
            cameras.append(CameraConfidence(cam.source_id, cam.source, cam.width_px,
                                            cam.height_px, artefacts))
        return cameras

    # -- ingest --------------------------------------------------------------------------
    def ingest_progress(self, project: str) -> pb.IngestProgress:
        self._check_name(project)
        return self._call("GetIngestProgress", pb.GetIngestProgressRequest(project=project))

    def ingest(self, project: str, manifest: Union[str, Manifest, None] = None, *,
               scan: Optional[str] = None, points=None, intensity=None, rgb=None, pose=None,
               divergence_rad: float = 0.0003, panoramas: Sequence[dict] = (),
               rig: str = "", captured_utc: str = "",
               progress: Optional[Callable[[dict], None]] = None,
               poll_s: float = 0.5, request_id: Optional[str] = None,
               retries: int = 2) -> IngestResult:
        """Ingests one scan, from a manifest (path or Manifest) or from arrays.

        Every ingest is sent under a request id (`request_id`, or a fresh UUID): when a call
        ends without an answer (deadline, lost connection, server restart) the client asks
        the server what became of it (GetOperation), waits while it runs, and sends it again
        (at most `retries` times) only when it did not commit, so a scan is never ingested
        twice and never lost silently.

        Arrays: `points` (N, 3) or (N, 4) sensor-frame metres [+ `intensity` (N,)] [+ `rgb`
        (N, 3) linear per-point colour, which becomes a "point-colour" source], or a
        PointSource (a file's points read chunk by chunk: `read_e57(...)[i].points`,
        `read_ptx(path)[i].points`, `read_pcd(path).points`, `read_las(path, pose)`,
        `read_ascii_cloud(path, pose)`),
        `pose` (see Pose.parse), `panoramas` as dicts {name, image
        (bytes or path), pose, modality "rgb"|"ir", angular_resolution_rad, pinhole, mask,
        sphere, cylinder}
        (`pinhole`: a pinhole photo's intrinsics {fx_px, fy_px, cx_px, cy_px[, k1, k2, k3, p1,
        p2]}, or a fisheye's {"lens": "fisheye", fx_px, fy_px, cx_px, cy_px[, k1, k2, k3, k4,
        field_of_view_deg]}; absent: an equirect panorama; `mask`: bytes or path of an image of the image's
        size whose first channel, over its largest value, is the share of each pixel the
        camera reports, 0 where a tripod, rig or operator is masked out; absent: none;
        `sphere`: for an equirect panorama of part of the sphere, {width_px, height_px} of the
        whole sphere's panorama at the image's pixel pitch and {left_px, top_px} of the image
        in it; absent: the image is the whole sphere; `cylinder`: a cylindrical panorama's
        {pixel_width_rad, pixel_height_m, radius_m, principal_y_px}, resampled by the server
        into the part of the sphere it covers). Points
        are packed and sent chunk by chunk as the upload proceeds, so a file's scan is never in
        memory whole. Without `points` (and with panoramas) the scan is camera-only: its images
        colour the geometry the project already has. `progress(dict)` is called with keys
        stage, fraction, sent_bytes, total_bytes (and sent_points, total_points while
        uploading) while uploading and while the server works.
        """
        self._check_name(project)
        if manifest is not None:
            m = read_manifest(manifest) if isinstance(manifest, (str, os.PathLike)) else manifest
            scan = m.scan
            points, intensity = None, None
            if m.points_path is not None and is_las(m.points_path):  # world coordinates
                points = read_las(m.points_path, m.pose)
            elif m.points_path is not None and is_ascii_cloud(m.points_path):
                points = read_ascii_cloud(m.points_path, m.pose)
            elif m.points_path is not None and is_ptx(m.points_path):
                points = read_ptx(m.points_path, pose=m.pose)[0].points
            elif m.points_path is not None and is_pcd(m.points_path):
                points = read_pcd(m.points_path, pose=m.pose).points
            elif m.points_path is not None:
                cloud = read_ply(m.points_path)
                points, intensity = cloud.xyz_m, cloud.intensity
                if cloud.grid is not None or cloud.rgb is not None:  # range grid, colour
                    points, intensity = ArrayPoints(cloud.xyz_m, cloud.intensity, rgb=cloud.rgb,
                                                    grid=cloud.grid), None
            pose, divergence_rad, rig, captured_utc = m.pose, m.divergence_rad, m.rig, m.captured_utc
            panoramas = [{"name": p.name, "image": p.image_path, "pose": p.pose,
                          "modality": p.modality,
                          "angular_resolution_rad": p.angular_resolution_rad,
                          "pinhole": p.pinhole, "visual_reference": p.visual_reference,
                          "mask": p.mask_path, "sphere": p.sphere, "cylinder": p.cylinder}
                         for p in m.panoramas]
        if not scan:
            raise ValueError("scan: give the scan an id (or pass a manifest)")
        if pose is None:
            raise ValueError("pose is required (or pass a manifest)")
        if points is None and not panoramas:
            raise ValueError("a scan needs points or panoramas (or pass a manifest)")
        if points is not None and not (divergence_rad > 0 and np.isfinite(divergence_rad)):
            raise ValueError(f"divergence_rad must be > 0, got {divergence_rad}")
        source = None
        if isinstance(points, PointSource):
            if intensity is not None or rgb is not None:
                raise ValueError("intensity and rgb come with a PointSource's points: "
                                 "give them only with point arrays")
            source = points
        elif points is not None:
            source = ArrayPoints(points, intensity, rgb)
        header = pb.ScanHeader(project=project, scan=scan, rig=rig,
                               pose=pose_to_pb(Pose.parse(pose)))
        captured = _timestamp(captured_utc, "captured_utc")
        if captured is not None:
            header.capture_time.CopyFrom(captured)
        if source is not None:  # none: a camera-only scan (header.lidar unset)
            header.lidar.divergence_rad = divergence_rad
            header.lidar.point_format = (pb.POINT_FORMAT_XYZIRGB_F32LE if source.has_rgb
                                         else pb.POINT_FORMAT_XYZI_F32LE)
            header.lidar.point_count = source.count
            if source.grid_shape:  # each point carries its row and column
                header.lidar.grid.rows, header.lidar.grid.columns = source.grid_shape
        images, masks = [], []
        for i, p in enumerate(panoramas):
            reference = bool(p.get("visual_reference", False))
            if "name" not in p or "image" not in p or (p.get("pose") is None and not reference):
                raise ValueError(f"panoramas[{i}] needs name, image and pose")
            image = _image_bytes(p["image"], f"panoramas[{i}].image")
            mask = b""
            if p.get("mask") is not None:
                if reference:
                    raise ValueError(f"panoramas[{i}] ('{p['name']}') is a visual reference: "
                                     "it colours nothing, so it takes no mask")
                mask = _image_bytes(p["mask"], f"panoramas[{i}].mask")
            modality = str(p.get("modality", "rgb")).lower()
            if modality not in _MODALITY_TO_PB:
                raise ValueError(f"panoramas[{i}].modality must be 'rgb' or 'ir', got {modality!r}")
            desc = header.panoramas.add(
                name=p["name"], modality=_MODALITY_TO_PB[modality],
                pose=pose_to_pb(Pose.parse(p["pose"] if p.get("pose") is not None else pose)),
                angular_resolution_rad=float(p.get("angular_resolution_rad", 0.0)),
                encoded_size_bytes=len(image), visual_reference=reference,
                mask_size_bytes=len(mask))
            if p.get("pinhole") is not None and not reference:  # a pinhole photo (VASL-MODEL §2.2)
                desc.pinhole.CopyFrom(pinhole_to_pb(p["pinhole"], f"panoramas[{i}].pinhole"))
            if p.get("sphere") is not None and not reference:  # a part of the sphere
                desc.sphere.CopyFrom(pb.SphereWindow(
                    **sphere_from_json(p["sphere"], f"panoramas[{i}].sphere")))
            if p.get("cylinder") is not None and not reference:  # a cylindrical panorama
                desc.cylinder.CopyFrom(pb.CylinderImage(
                    **cylinder_from_json(p["cylinder"], f"panoramas[{i}].cylinder")))
            images.append(image)
            masks.append(mask)
        point_total = 0 if source is None else source.count * point_stride(source)
        total = point_total + sum(len(b) for b in images) + sum(len(b) for b in masks)
        header.request_id = request_id or new_request_id()
        return self.ingest_stream(header, (lambda: packed_chunks(source)) if source else b"",
                                  images, masks=masks, total_bytes=total, progress=progress,
                                  poll_s=poll_s, retries=retries)

    def ingest_e57_scan(self, project: str, scan: E57Scan, *, divergence_rad: float = 0.0003,
                        rig: str = "", progress: Optional[Callable[[dict], None]] = None,
                        request_id: Optional[str] = None) -> IngestResult:
        """Ingests one scan read by `read_e57`: its points (streamed from the file chunk by
        chunk), intensity, per-point colour (as a "point-colour" source) and pose, and its
        spherical and pinhole images (as panoramas and pinhole photos with their poses; visual
        references kept with the scan, posed as the scan when the file gives them no pose;
        `scan.images` says why any other is left out), a camera image's imageMask sent as its
        mask. A scan of images only is a camera-only scan."""
        panoramas = [{"name": im.name, "image": im.data, "pose": im.pose, "modality": "rgb",
                      "pinhole": im.pinhole, "visual_reference": im.kind == "visual",
                      "mask": im.mask or None, "sphere": im.sphere, "cylinder": im.cylinder}
                     for im in scan.ingestible_images]
        names = [p["name"] for p in panoramas]
        for i, p in enumerate(panoramas):  # E57 names need not be unique
            if names.count(p["name"]) > 1:
                p["name"] = f"{p['name']}-{i + 1}"
        return self.ingest(project, scan=scan.scan, points=scan.points, pose=scan.pose,
                           divergence_rad=divergence_rad, panoramas=panoramas, rig=rig,
                           progress=progress, request_id=request_id)

    def ingest_stream(self, header: pb.ScanHeader,
                      point_bytes: Union[bytes, Callable[[], Iterable[bytes]]],
                      images: Sequence[bytes], *, masks: Sequence[bytes] = (),
                      total_bytes: int = 0, progress=None, poll_s: float = 0.5,
                      retries: int = 0) -> IngestResult:
        """Sends a prepared header and payloads (no client-side validation); with
        `header.request_id` set, a call whose answer is lost is resolved as in `ingest`.
        `point_bytes`: the packed points, or a function giving them as an iterable of packed
        pieces (called again for each attempt, so a retry reads them again). `masks`: each
        panorama's mask bytes, by panorama like `images` (empty: none)."""
        return self._with_retries(
            header.project, header.request_id, retries, "IngestScan", "ingest",
            lambda: self._ingest_once(header, point_bytes, images, masks, total_bytes, progress,
                                      poll_s))

    def _with_retries(self, project: str, request_id: str, retries: int, method: str, answer: str,
                      send: Callable[[], object]):
        """Runs `send` (a change under `request_id`); when its answer is lost, asks the
        server: a committed change is answered from GetOperation, a failed or unknown one is
        sent again (at most `retries` times)."""
        attempt = 0
        while True:
            try:
                return send()
            except VaslError as e:
                if not request_id or e.code not in _ANSWER_LOST:
                    raise
                try:
                    op = self.wait_operation(project, request_id, missing_ok=True)
                except VaslError as asked:
                    if asked.code != grpc.StatusCode.UNAVAILABLE:
                        raise
                    # The server is down: its answer is unknown. The caller resolves it later
                    # (get_operation, `vasl operation`) or retries under the same id.
                    raise e from None
                if op is not None and op["state"] == "succeeded" and op.get(answer) is not None:
                    result = op[answer]
                    if isinstance(result, dict):
                        result["replayed"] = True
                    else:
                        result.replayed = True
                    return result
                code = _CODES.get(op["error_code"]) if op is not None else None
                if op is not None and op["state"] == "failed" and code not in _UPLOAD_CUT:
                    # It ran and failed for a reason of its own: sending it again would too.
                    raise VaslError(code or grpc.StatusCode.UNKNOWN, op["error_message"],
                                    method) from None
                if attempt >= retries:
                    raise
                attempt += 1

    def _ingest_once(self, header, point_bytes, images, masks, total_bytes, progress, poll_s):
        state = {"sent": 0, "error": None, "t0": time.monotonic(), "t1": None}
        stride = _wire_stride(header)
        total_points = header.lidar.point_count

        def on_sent(n):
            state["sent"] = n
            if progress:
                points = min(n // stride, total_points)
                progress({"stage": "upload", "fraction": n / max(1, total_bytes),
                          "sent_bytes": n, "total_bytes": total_bytes,
                          "sent_points": points, "total_points": total_points})

        def requests():
            # Reading the points happens here, on gRPC's sending thread, as the upload proceeds.
            # An error there (an unreadable chunk of a file) ends the stream early, so the
            # server refuses it (byte counts short of the header's) and stores nothing; the
            # error itself is raised to the caller below.
            try:
                pieces = point_bytes() if callable(point_bytes) else point_bytes
                yield from ingest_requests(header, pieces, images, self.chunk_bytes, on_sent,
                                           masks)
            except Exception as e:  # noqa: BLE001 - re-raised by _ingest_once
                state["error"] = e
            state["t1"] = time.monotonic()

        future = self.stub.IngestScan.future(requests(), timeout=self.timeout_s)
        if progress:
            last = None
            while not future.done():
                time.sleep(poll_s)
                if future.done() or state["t1"] is None:
                    continue
                try:
                    p = self.stub.GetIngestProgress(
                        pb.GetIngestProgressRequest(project=header.project), timeout=5)
                except grpc.RpcError:
                    continue
                if p.state == pb.IngestProgress.STATE_PROCESSING and p.scan == header.scan:
                    key = (p.stage, round(p.fraction, 2))
                    if key != last:
                        last = key
                        progress({"stage": p.stage, "fraction": p.fraction,
                                  "sent_bytes": total_bytes, "total_bytes": total_bytes})
        try:
            r = future.result()
        except grpc.RpcError as e:
            if state["error"] is not None:
                raise state["error"] from None
            raise _wrap("IngestScan", e) from None
        if state["error"] is not None:  # pragma: no cover - the server refuses a short stream
            raise state["error"]
        result = _ingest_result(r)
        result.sent_bytes = state["sent"]
        result.upload_seconds = ((state["t1"] or time.monotonic()) - state["t0"])
        return result

    _OPERATION_STATES = {pb.Operation.STATE_RUNNING: "running",
                         pb.Operation.STATE_SUCCEEDED: "succeeded",
                         pb.Operation.STATE_FAILED: "failed"}

    def get_operation(self, project: str, request_id: str) -> dict:
        """What became of a change sent under `request_id`: a dict with state ("running",
        "succeeded", "failed"), kind, subject, stage, fraction, elapsed_s, version,
        error_code/error_message (failed) and its answer under "ingest" (IngestResult),
        "back_project" (dict), "change" (ChangeResult) or "reweight" (ReweightResult). VaslError NOT_FOUND for an id the
        project does not know."""
        self._check_name(project)
        op = self._call("GetOperation", pb.GetOperationRequest(project=project,
                                                               request_id=request_id))
        out = {"project": op.project, "request_id": op.request_id, "kind": op.kind,
               "subject": op.subject, "state": self._OPERATION_STATES.get(op.state, "unknown"),
               "stage": op.stage, "fraction": op.fraction, "elapsed_s": op.elapsed_s,
               "version": op.version, "error_code": op.error_code,
               "error_message": op.error_message}
        which = op.WhichOneof("answer")
        if which == "ingest":
            out["ingest"] = _ingest_result(op.ingest)
        elif which == "back_project":
            out["back_project"] = _back_project_result(op.back_project)
        elif which == "change":
            out["change"] = _change(op.change)
        elif which == "reweight":
            out["reweight"] = _reweight_result(op.reweight)
        return out

    def wait_operation(self, project: str, request_id: str, *, timeout_s: float = 3600.0,
                       poll_s: float = 0.5, missing_ok: bool = False,
                       unavailable_s: float = 5.0) -> Optional[dict]:
        """get_operation until the change is no longer running (at most `timeout_s`; then
        the last state). With `missing_ok`, None for an id the project does not know.
        VaslError UNAVAILABLE when the server cannot be reached for `unavailable_s`."""
        deadline = time.monotonic() + timeout_s
        unreachable_since = None
        while True:
            try:
                op = self.get_operation(project, request_id)
                unreachable_since = None
            except VaslError as e:
                if missing_ok and e.code == grpc.StatusCode.NOT_FOUND:
                    return None
                if e.code != grpc.StatusCode.UNAVAILABLE:
                    raise
                now = time.monotonic()
                unreachable_since = unreachable_since or now
                if now - unreachable_since > unavailable_s or now > deadline:
                    raise
                time.sleep(poll_s)
                continue
            if op["state"] != "running" or time.monotonic() > deadline:
                return op
            time.sleep(poll_s)

    def _poll_progress(self, project: str, future, progress, poll_s: float = 0.5) -> None:
        """Reports the server's progress of a long call in `project` until `future` is done."""
        last = None
        while progress and not future.done():
            time.sleep(poll_s)
            try:
                p = self.stub.GetIngestProgress(pb.GetIngestProgressRequest(project=project),
                                                timeout=5)
            except grpc.RpcError:
                continue
            key = (p.stage, round(p.fraction, 2))
            if p.state == pb.IngestProgress.STATE_PROCESSING and key != last:
                last = key
                progress({"stage": p.stage, "fraction": p.fraction})

    # -- store: rebuild, deletion, versions, export ------------------------------------------
    def rebuild(self, project: str, *, request_id: Optional[str] = None,
                retries: int = 1) -> ChangeResult:
        """Recomputes the whole project from its raw blobs as a new version (under a request
        id, resolved as in `ingest` when the answer is lost)."""
        self._check_name(project)
        rid = request_id or new_request_id()
        return self._with_retries(project, rid, retries, "Rebuild", "change", lambda: _change(
            self._call("Rebuild", pb.RebuildRequest(project=project, request_id=rid))))

    def delete_scan(self, project: str, scan: str, *, request_id: Optional[str] = None,
                    retries: int = 1) -> ChangeResult:
        """A new version without `scan` (its blobs go when retention drops the last version
        that has it); under a request id as `rebuild`."""
        self._check_name(project)
        if not scan:
            raise ValueError("scan must be a non-empty scan id")
        rid = request_id or new_request_id()
        return self._with_retries(project, rid, retries, "DeleteScan", "change", lambda: _change(
            self._call("DeleteScan", pb.DeleteScanRequest(project=project, scan=scan,
                                                          request_id=rid))))

    def list_versions(self, project: str, *, page_size: int = 0) -> List[Version]:
        self._check_name(project)
        versions, _ = self._pages("ListVersions", pb.ListVersionsRequest(project=project),
                                  "versions", page_size)
        return [Version(v.version, v.vossel_count, v.record_count, v.tile_count, v.bytes_written,
                        v.bytes_total, v.made_by, v.pinned, _iso(v, "commit_time")) for v in versions]

    def export(self, project: str, path: str, version: int = 0) -> ExportResult:
        """Writes version `version` (0: HEAD) as one merged OpenVDB file at `path` (streamed;
        written to `path`.part, then renamed)."""
        self._check_name(project)
        if version < 0:
            raise ValueError(f"version must be >= 0 (0: HEAD), got {version}")
        meta = None
        part = path + ".part"
        written = 0
        try:
            with open(part, "wb") as out:
                for msg in self.stub.Export(pb.ExportRequest(project=project, version=version),
                                            timeout=self.timeout_s):
                    if msg.HasField("metadata"):
                        meta = msg.metadata
                    elif msg.HasField("chunk"):
                        if msg.chunk.offset_bytes != written:
                            raise VaslError(grpc.StatusCode.DATA_LOSS,
                                            f"export chunk at {msg.chunk.offset_bytes}, expected {written}",
                                            "Export")
                        out.write(msg.chunk.data)
                        written += len(msg.chunk.data)
        except grpc.RpcError as e:
            os.unlink(part)
            raise _wrap("Export", e) from None
        except BaseException:
            if os.path.exists(part):
                os.unlink(part)
            raise
        if meta is None or written != meta.size_bytes:
            os.unlink(part)
            raise VaslError(grpc.StatusCode.DATA_LOSS,
                            f"export stream ended after {written} bytes", "Export")
        os.replace(part, path)
        return ExportResult(meta.version, meta.vossel_count, meta.record_count, meta.size_bytes, path)

    def rollback(self, project: str, version: int) -> ChangeResult:
        """A new version that gives back kept version `version`: its tiles, fused layers and
        scans."""
        self._check_name(project)
        if version <= 0:
            raise ValueError(f"version must be > 0, got {version}")
        return _change(self._call("Rollback", pb.RollbackRequest(project=project, version=version)))

    def back_project(self, project: str, image: Union[bytes, str], pose, *, name: str = "",
                     pinhole: Optional[dict] = None, render_id: int = 0,
                     request_id: Optional[str] = None, retries: int = 1) -> dict:
        """Sends an RGBZ image (OpenEXR bytes or a path; channels R, G, B, Z and optionally
        N.x, N.y, N.z, U, A) back as derived data (VASL-MODEL §10): its pixels become derived
        records in a new batch `name`. `pose` is the image's camera pose; `pinhole` as for
        render (unset: equirectangular); `render_id` cites the render it came from."""
        self._check_name(project)
        if isinstance(image, (str, os.PathLike)):
            with open(image, "rb") as f:
                image = f.read()
        if not image:
            raise ValueError("the image is empty")
        header = pb.BackProjectHeader(project=project, name=name, pose=pose_to_pb(Pose.parse(pose)),
                                      render_id=int(render_id), image_size_bytes=len(image),
                                      request_id=request_id or new_request_id())
        if pinhole is not None:
            header.pinhole.CopyFrom(pinhole_to_pb(pinhole, "pinhole"))

        def requests():
            yield pb.BackProjectRequest(header=header)
            for at in range(0, len(image), self.chunk_bytes):
                yield pb.BackProjectRequest(image_chunk=image[at:at + self.chunk_bytes])

        def send():
            try:
                return _back_project_result(self.stub.BackProject(requests(),
                                                                  timeout=self.timeout_s))
            except grpc.RpcError as e:
                raise _wrap("BackProject", e) from None

        return self._with_retries(project, header.request_id, retries, "BackProject",
                                  "back_project", send)

    # -- access control ------------------------------------------------------------------
    _ROLES = {"read": pb.ROLE_READ, "write": pb.ROLE_WRITE, "admin": pb.ROLE_ADMIN}

    @staticmethod
    def _token_dict(t: pb.AccessToken) -> dict:
        names = {v: k for k, v in Client._ROLES.items()}
        return {"id": t.id, "project": t.project, "role": names.get(t.role, "none"),
                "label": t.label, "created_by": t.created_by,
                "created_utc": _iso(t, "create_time"), "revoked_utc": _iso(t, "revoke_time")}

    def create_token(self, project: str, role: str, label: str = "") -> dict:
        """A new bearer token with `role` ("read", "write", "admin") on `project` ("*": every
        project). The dict's "token" is the secret, shown this once."""
        if role not in self._ROLES:
            raise ValueError(f"role must be one of {sorted(self._ROLES)}, got {role!r}")
        self._check_name(project)
        t = self._call("CreateToken", pb.CreateTokenRequest(project=project, role=self._ROLES[role],
                                                            label=label))
        return dict(self._token_dict(t), token=t.token)

    def list_tokens(self, project: str = "") -> List[dict]:
        r = self._call("ListTokens", pb.ListTokensRequest(project=project))
        return [self._token_dict(t) for t in r.tokens]

    def revoke_token(self, token_id: str) -> dict:
        self._check_name(token_id, "token id")
        return self._token_dict(self._call("RevokeToken", pb.RevokeTokenRequest(id=token_id)))

    def pin_version(self, project: str, version: int, pinned: bool = True) -> Version:
        """Pins (or unpins) a kept version: pinned versions survive retention."""
        self._check_name(project)
        if version <= 0:
            raise ValueError(f"version must be > 0, got {version}")
        v = self._call("PinVersion", pb.PinVersionRequest(project=project, version=version,
                                                          pinned=pinned))
        return Version(v.version, v.vossel_count, v.record_count, v.tile_count, v.bytes_written,
                       v.bytes_total, v.made_by, v.pinned, _iso(v, "commit_time"))

    # -- weighting profiles and reweighting (VASL-MODEL §7) ------------------------------
    def create_profile(self, project: str, profile: Union[dict, pb.WeightingProfile], *,
                       activate: bool = False) -> dict:
        """Stores a new revision of profile `profile["name"]` (1 for a new name)."""
        self._check_name(project)
        p = profile if isinstance(profile, pb.WeightingProfile) else profile_to_pb(profile)
        if not p.name:
            raise ValueError("a profile needs a name")
        return profile_from_pb(self._call("CreateProfile", pb.CreateProfileRequest(
            project=project, profile=p, activate=activate)))

    def get_profile(self, project: str, name: str = "", revision: int = 0) -> dict:
        """Profile `name` (empty: the active one) at `revision` (0: the latest)."""
        self._check_name(project)
        return profile_from_pb(self._call("GetProfile", pb.GetProfileRequest(
            project=project, name=name, revision=revision)))

    def list_profiles(self, project: str, *, page_size: int = 0):
        """(profiles, active name): the built-in default, then the latest revision of each."""
        self._check_name(project)
        profiles, last = self._pages("ListProfiles", pb.ListProfilesRequest(project=project),
                                     "profiles", page_size)
        return [profile_from_pb(p) for p in profiles], last.active

    def set_active_profile(self, project: str, name: str) -> dict:
        self._check_name(project)
        return profile_from_pb(self._call("SetActiveProfile", pb.SetActiveProfileRequest(
            project=project, name=name)))

    def reweight(self, project: str, profile: str = "", revision: int = 0, *,
                 progress: Optional[Callable[[dict], None]] = None,
                 request_id: Optional[str] = None, retries: int = 1) -> ReweightResult:
        """A new version whose tiles hold fused values under `profile` (default: the active
        one), from the stored records alone. `progress` gets {"stage", "fraction"} dicts.
        Under a request id, resolved as in `ingest` when the answer is lost."""
        self._check_name(project)
        if revision < 0:
            raise ValueError("revision must be >= 0 (0: the latest)")
        rid = request_id or new_request_id()
        request = pb.ReweightRequest(project=project, profile=profile, revision=revision,
                                     request_id=rid)

        def send() -> ReweightResult:
            future = self.stub.Reweight.future(request, timeout=self.timeout_s)
            self._poll_progress(project, future, progress)
            try:
                return _reweight_result(future.result())
            except grpc.RpcError as e:
                raise _wrap("Reweight", e) from None

        return self._with_retries(project, rid, retries, "Reweight", "reweight", send)

    def normalise(self, project: str, base_profile: str = "", name: str = "") -> NormaliseResult:
        """Solves per-source per-channel gains on HEAD's RGB records (weighed under
        `base_profile`) and stores them as a new revision of profile `name`."""
        self._check_name(project)
        r = self._call("Normalise", pb.NormaliseRequest(project=project,
                                                        base_profile=base_profile, name=name))
        return NormaliseResult(profile_from_pb(r.profile), r.vossels_used, r.pairs_used,
                               list(r.cost_before), list(r.cost_after), list(r.unlinked_sources))

    def estimate_lens(self, project: str, rig: str, *, camera: str = "", from_utc: str = "",
                      to_utc: str = "", base_profile: str = "", name: str = "",
                      cell_px: int = 0) -> LensEstimate:
        """Finds the lens dirt and fog map of `rig`'s camera from its frames in HEAD captured
        between `from_utc` and `to_utc` (ISO 8601; empty: open) and stores a new revision of
        profile `name` that applies it; reweight under that profile to apply it."""
        self._check_name(project)
        r = self._call("EstimateLens", pb.EstimateLensRequest(
            project=project, rig=rig, camera=camera, from_utc=from_utc, to_utc=to_utc,
            base_profile=base_profile, name=name, cell_px=cell_px))
        return LensEstimate(profile_from_pb(r.profile), lens_map_from_pb(r.map), r.samples,
                            r.cells, r.cells_fitted, r.cell_px, r.residual_before,
                            r.residual_after, r.replaced_map)

    def list_lens_maps(self, project: str, summary: bool = False, *,
                       page_size: int = 0) -> List[LensMap]:
        """The project's lens maps, oldest first (`summary`: without their cells), every page."""
        self._check_name(project)
        maps, _ = self._pages("ListLensMaps",
                              pb.ListLensMapsRequest(project=project, summary=summary),
                              "maps", page_size)
        return [lens_map_from_pb(m) for m in maps]

    def query_records(self, project: str, *, at=None, box=None, profile: str = "",
                      version: int = 0, limit: int = 0) -> RecordsQuery:
        """Provenance: the records of the vossel at world point `at` (x, y, z), or of every
        vossel meeting `box` (x0, y0, z0, x1, y1, z1), with their weights under `profile`."""
        self._check_name(project)
        if (at is None) == (box is None):
            raise ValueError("give exactly one of at=(x, y, z) or box=(x0, y0, z0, x1, y1, z1)")
        corners = [float(v) for v in (at if at is not None else box)]
        if len(corners) != (3 if at is not None else 6) or not np.all(np.isfinite(corners)):
            raise ValueError("at needs 3 finite numbers, box 6")
        lo = pb.Vec3(x=corners[0], y=corners[1], z=corners[2])
        hi = lo if at is not None else pb.Vec3(x=corners[3], y=corners[4], z=corners[5])
        r = self._call("QueryRecords", pb.QueryRecordsRequest(
            project=project, version=version, min_m=lo, max_m=hi, profile=profile, limit=limit))
        rows = [{"vossel": x.vossel, "k": [x.kx, x.ky, x.kz],
                 "centroid_m": [x.centroid_m.x, x.centroid_m.y, x.centroid_m.z],
                 "scan": x.scan, "scan_id": x.scan_id, "source": x.source,
                 "source_name": x.source_name, "modality": _MODALITY_NAMES.get(x.modality, "?"),
                 "value": list(x.value), "range_m": x.range_m, "cos_inc": x.cos_inc,
                 "foot_major_m": x.foot_major_m, "foot_minor_m": x.foot_minor_m, "vis": x.vis,
                 "uv_px": [x.u_px, x.v_px], "conf": dict(zip(CONFIDENCE_FACTORS, x.conf)),
                 "flags": x.flags, "derived": bool(x.flags & FLAG_DERIVED),
                 "invalidated": bool(x.flags & FLAG_INVALIDATED), "batch": x.batch,
                 "weight": x.weight} for x in r.records]
        return RecordsQuery(r.version, r.profile, r.revision, r.vossel_count, r.truncated, rows)

    # -- render --------------------------------------------------------------------------
    def render(self, project: str, pose, width_px: int = 2048, height_px: int = 1024, *,
               version: int = 0, formats: Sequence[str] = ("exr", "png"), eta: float = 0.0,
               max_range_m: float = 0.0, decode: bool = True, profile: str = "",
               profile_revision: int = 0, pinhole: Optional[dict] = None,
               layers: int = 1, colour_detail: str = "vossel", stream_rows: bool = False,
               files: Optional[Dict[str, str]] = None,
               on_progress: Optional[Callable[[int, int], None]] = None) -> RenderResult:
        """Renders an equirectangular panorama from `pose` (VASL-MODEL §8). With "exr" among
        `formats` and `decode`, the EXR is decoded into rgb / depth_m / normal / uncertainty.
        `profile` names the weighting profile (default: the project's active one). `pinhole`
        ({"fx_px", "fy_px", "cx_px", "cy_px"} and optional "k1", "k2", "k3", "p1", "p2") makes a
        pinhole render of width_px × height_px in the camera frame x right, y down, z forward;
        with "lens": "fisheye" (and optional "k1"-"k4", "field_of_view_deg") a fisheye render,
        its pixels beyond the field of view empty.
        `colour_detail` "vossel" shows one colour per vossel; "images" reads each colour record
        again where the pixel's own point projects into its camera's image (sharper, slower).
        `stream_rows` has the server send each format's bytes as bands of rows finish, with
        `on_progress(rows_done, rows_total)` after each band; `files` ({format: path}) writes
        each format straight into its file as its bytes arrive (through PATH.part, renamed
        once complete, removed on failure) instead of holding them in memory: together they
        render images of any size."""
        self._check_name(project)
        if colour_detail not in _COLOUR_DETAIL:
            raise ValueError(f"colour_detail must be one of {sorted(_COLOUR_DETAIL)}, got {colour_detail!r}")
        if int(width_px) <= 0 or int(height_px) <= 0:
            raise ValueError(f"width_px and height_px must be > 0, got {width_px}x{height_px}")
        unknown = [f for f in formats if f not in _FORMATS]
        if unknown or not formats:
            raise ValueError(f"formats must be a non-empty subset of {sorted(_FORMATS)}, got {formats}")
        if version < 0 or eta < 0 or max_range_m < 0:
            raise ValueError("version, eta and max_range_m must be >= 0")
        request = pb.RenderRequest(project=project, pose=pose_to_pb(Pose.parse(pose)),
                                   width_px=int(width_px), height_px=int(height_px),
                                   version=version, formats=[_FORMATS[f] for f in formats],
                                   eta=eta, max_range_m=max_range_m, profile=profile,
                                   profile_revision=int(profile_revision), layers=int(layers),
                                   colour_detail=_COLOUR_DETAIL[colour_detail])
        if pinhole is not None:
            request.pinhole.CopyFrom(pinhole_to_pb(pinhole, "pinhole"))
        request.stream_rows = bool(stream_rows)
        files = dict(files or {})
        unknown = set(files) - set(formats)
        if unknown:
            raise ValueError(f"files names formats not requested: {sorted(unknown)}")
        names = {code: name for name, code in _FORMATS.items()}
        meta = None
        parts: Dict[int, bytearray] = {}
        sizes: Dict[int, int] = {}  # bytes written per format, up to the furthest offset
        out: Dict[int, object] = {}
        try:
            for name, path in files.items():
                os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
                out[_FORMATS[name]] = open(path + ".part", "wb")
            for msg in self.stub.Render(request, timeout=self.timeout_s):
                if msg.HasField("metadata"):
                    meta = msg.metadata
                elif msg.HasField("progress"):
                    if on_progress is not None:
                        on_progress(msg.progress.rows_done, msg.progress.rows_total)
                elif msg.HasField("chunk"):
                    fmt, offset, data = msg.chunk.format, msg.chunk.offset_bytes, msg.chunk.data
                    end = sizes.get(fmt, 0)
                    # Unstreamed, a format's chunks are contiguous; streamed, a chunk may go back
                    # (an EXR's offset table is written last) but never leaves a gap.
                    if offset > end or (offset != end and not stream_rows):
                        raise VaslError(grpc.StatusCode.DATA_LOSS,
                                        "render chunks arrived out of order", "Render")
                    if fmt in out:
                        out[fmt].seek(offset)
                        out[fmt].write(data)
                    else:
                        parts.setdefault(fmt, bytearray())[offset:offset + len(data)] = data
                    sizes[fmt] = max(end, offset + len(data))
            if meta is None:
                raise VaslError(grpc.StatusCode.DATA_LOSS, "the render stream had no metadata",
                                "Render")
            if len(meta.size_bytes) != len(meta.formats):
                raise VaslError(grpc.StatusCode.DATA_LOSS,
                                "the render stream ended before its last metadata", "Render")
            for fmt, size in zip(meta.formats, meta.size_bytes):
                if sizes.get(fmt, 0) != size:
                    raise VaslError(grpc.StatusCode.DATA_LOSS,
                                    f"render format {fmt}: got {sizes.get(fmt, 0)} of {size} bytes",
                                    "Render")
            for fmt, f in out.items():
                f.close()
                os.replace(files[names[fmt]] + ".part", files[names[fmt]])
        except grpc.RpcError as e:
            raise _wrap("Render", e) from None
        finally:
            for fmt, f in out.items():
                f.close()
                if os.path.exists(files[names[fmt]] + ".part"):
                    os.remove(files[names[fmt]] + ".part")
        result = RenderResult(meta.width_px, meta.height_px, meta.version, meta.hit_pixels,
                              meta.render_seconds, profile=meta.profile,
                              profile_revision=meta.profile_revision,
                              fused_on_the_fly=meta.fused_on_the_fly, render_id=meta.render_id,
                              colourless_pixels=meta.colourless_pixels,
                              detail_sources=meta.detail_sources,
                              detail_sources_skipped=meta.detail_sources_skipped,
                              tile_groups=meta.tile_groups or 1, tiles_read=meta.tiles_read,
                              tiles_total=meta.tiles_total,
                              files=files, encode_seconds=meta.encode_seconds)
        if pb.IMAGE_FORMAT_EXR in parts:
            result.exr = bytes(parts[pb.IMAGE_FORMAT_EXR])
        if pb.IMAGE_FORMAT_PNG in parts:
            result.png = bytes(parts[pb.IMAGE_FORMAT_PNG])
        if pb.IMAGE_FORMAT_DEEP_EXR in parts:
            result.deep_exr = bytes(parts[pb.IMAGE_FORMAT_DEEP_EXR])
        exr = result.exr
        if decode and exr is None and "exr" in files:
            with open(files["exr"], "rb") as f:
                exr = f.read()
        if decode and exr is not None:
            ch = decode_exr(exr)
            result.rgb = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
            result.depth_m = ch["Z"]
            if "N.x" in ch:
                result.normal = np.stack([ch["N.x"], ch["N.y"], ch["N.z"]], axis=-1)
            result.uncertainty = ch.get("U")
            result.alpha = ch.get("A")
        return result

    # -- inspection ----------------------------------------------------------------------
    def inspect_records(self, project: str, version: int = 0) -> Inspection:
        self._check_name(project)
        if version < 0:
            raise ValueError(f"version must be >= 0 (0: HEAD), got {version}")
        r = self._call("InspectRecords", pb.InspectRecordsRequest(project=project, version=version))
        return Inspection(r.project, r.version, r.tile_count, r.record_count,
                          [RecordAttribute(a.name, a.type, a.codec, a.stride) for a in r.attributes])
