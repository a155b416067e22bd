"""Plain result and input types of the vasl client (numpy in and out)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np


@dataclass(frozen=True)
class Pose:
    """Rigid pose T_world_sensor: x_world = R(quaternion) * p_sensor + position (VASL-MODEL §2)."""

    position_m: tuple = (0.0, 0.0, 0.0)  #: sensor origin in the world, metres
    quaternion_xyzw: tuple = (0.0, 0.0, 0.0, 1.0)  #: rotation sensor -> world, (x, y, z, w)

    @staticmethod
    def make(position, quaternion=(0.0, 0.0, 0.0, 1.0), *, where: str = "pose",
             check_finite: bool = True) -> "Pose":
        """Builds a pose; ValueError for wrong lengths, non-numbers or (if checked) non-finite values."""
        try:
            p = tuple(float(v) for v in position)
            q = tuple(float(v) for v in quaternion)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: position and quaternion must be numbers ({e})") from e
        if len(p) != 3:
            raise ValueError(f"{where}: position must have 3 numbers (x, y, z), got {len(p)}")
        if len(q) != 4:
            raise ValueError(f"{where}: quaternion must have 4 numbers (x, y, z, w), got {len(q)}")
        if check_finite:
            if not all(math.isfinite(v) for v in p + q):
                raise ValueError(f"{where}: position and quaternion must be finite, got {p} {q}")
            if math.sqrt(sum(v * v for v in q)) < 1e-9:
                raise ValueError(f"{where}: the quaternion must not be zero")
        return Pose(p, q)

    @staticmethod
    def parse(value, *, check_finite: bool = True) -> "Pose":
        """Accepts a Pose, a dict {"position": [..], "quaternion": [..]}, a (position,
        quaternion) pair, 3 numbers (position, identity rotation) or 7 numbers (position then
        quaternion x, y, z, w), or a string "x,y,z[,qx,qy,qz,qw]"."""
        if isinstance(value, Pose):
            return value
        if isinstance(value, dict):
            return Pose.make(value.get("position", (0, 0, 0)),
                             value.get("quaternion", (0, 0, 0, 1)), check_finite=check_finite)
        if isinstance(value, str):
            try:
                value = [float(v) for v in value.split(",")]
            except ValueError as e:
                raise ValueError(f"pose '{value}': expected x,y,z[,qx,qy,qz,qw]") from e
        try:
            seq = list(value.ravel()) if isinstance(value, np.ndarray) else list(value)
        except TypeError as e:
            raise ValueError(f"pose: expected numbers, got {value!r}") from e
        if len(seq) == 2 and not np.isscalar(seq[0]):
            return Pose.make(seq[0], seq[1], check_finite=check_finite)
        if len(seq) == 3:
            return Pose.make(seq, (0.0, 0.0, 0.0, 1.0), check_finite=check_finite)
        if len(seq) == 7:
            return Pose.make(seq[:3], seq[3:], check_finite=check_finite)
        raise ValueError(f"pose: expected 3 or 7 numbers or (position, quaternion), got {value!r}")


@dataclass
class Project:
    name: str
    description: str
    vossel_size_m: float
    head_version: int
    scan_count: int
    vossel_count: int
    record_count: int
    created_utc: str
    #: Set when the server cannot open the project (damaged): what is wrong with it.
    problem: str = ""
    #: The origin x_0 (VASL-MODEL §1), world metres; None until given at creation or fixed by
    #: the first scan (its position rounded to the kilometre). Every position is a world one.
    origin_m: Optional[Tuple[float, float, float]] = None


@dataclass
class CalibrationHealth:
    """How well a camera sits on its pose, judged against its scan's LiDAR at ingest
    (VASL-MODEL §2.3; README "Calibration health")."""

    camera: str  #: the camera source's name
    lidar_source: int  #: the LiDAR source id it was checked against
    verdict: str  #: "ok", "flagged" or "unchecked"
    points_in_view: int
    features: int  #: textured LiDAR patches tried
    matched: int  #: of those, found in the image
    cell_px: float  #: camera pixels per analysis cell: the check's resolution
    pixel_mean_px: float  #: |matched - projected|, camera pixels
    pixel_p95_px: float
    offset_mean_m: float  #: the same on the surface, metres
    offset_p95_m: float
    roundtrip_mean_m: float  #: the projection model's own round-trip error, metres
    roundtrip_p95_m: float
    rotation_deg: float  #: the rotation that best explains the residuals
    note: str  #: the verdict in words

    def summary(self) -> str:
        """One line: the verdict and its figures."""
        line = f"calibration {self.camera}: {self.verdict}"
        if self.matched:
            line += (f", {self.matched}/{self.features} patches matched, pixel residual mean "
                     f"{self.pixel_mean_px:.2f} px, p95 {self.pixel_p95_px:.2f} px (cell "
                     f"{self.cell_px:g} px; {1e3 * self.offset_p95_m:.1f} mm on the surface), "
                     f"rotation {self.rotation_deg:.2f} deg")
        return line + (f": {self.note}" if self.note else "")


@dataclass
class Source:
    id: int
    name: str
    modality: str
    pose: Pose
    blob_sha256: str
    width_px: int
    height_px: int
    divergence_rad: float
    point_count: int
    calibration: Optional[CalibrationHealth] = None  #: a camera of a scan with LiDAR
    mask_sha256: str = ""  #: a camera sent with a mask: sha256 (hex) of the stored mask image
    #: a camera's projection as stored ("equirect", "equirect window L T", "equirect cylinder
    #: …", "pinhole …", "fisheye …", "points SHA"; proto Source.projection); "" for a LiDAR
    projection: str = ""

    @property
    def kind(self) -> str:
        """What `vasl scans` calls the source's projection: "" for a whole equirect panorama,
        a LiDAR or a point-colour source, else "part of the sphere", "cylindrical",
        "pinhole" or "fisheye"."""
        words = self.projection.split()
        if words[:2] == ["equirect", "window"]:
            return "part of the sphere"
        if words[:2] == ["equirect", "cylinder"]:
            return "cylindrical"
        return words[0] if words[:1] in (["pinhole"], ["fisheye"]) else ""


@dataclass
class VisualReference:
    """A photo kept with a scan for people to look at (an E57 visual reference)."""

    name: str
    pose: Pose
    blob_sha256: str
    width_px: int
    height_px: int
    size_bytes: int


@dataclass
class ArtefactCoverage:
    """One artefact's confidence map of a camera image (VASL-MODEL §9)."""

    #: "saturation": saturation and blooming (with smear); "smear": readout smear alone
    #: (regions: its columns); "flare": veiling glare; "codec": a JPEG's
    #: blocking, ringing and chroma; "fringing": chromatic fringing, corrected before sampling
    #: (its soft pixels: those the correction moved); "lens": the rig camera's dirt and fog
    #: (a lens map applies to it)
    artefact: str
    covered_fraction: float  #: share of the image's pixels with confidence below 1
    flagged_pixels: int  #: confidence 0 (clipped; flare: invalid)
    soft_pixels: int  #: between 0 and 1 (a halo; a veil)
    regions: int  #: connected clipped regions (flare: sources with a veil)
    max_extent_px: int  #: widest soft band around one (flare: farthest pixel from its source)
    map_png: bytes = b""  #: 8-bit grey PNG of the image's size, 255 at confidence 1
    #: fringing, when found: red's (dx, dy) then blue's against green's, pixels
    channel_offsets_px: List[float] = field(default_factory=list)
    jpeg_quality: float = 0.0  #: codec: the IJG quality of a JPEG's luma table (0: not a JPEG)
    chroma_subsampled: bool = False  #: codec: its chroma was coded at a lower resolution
    lens_map: int = 0  #: lens: the id of the lens map that applies
    smear_offset: float = 0.0  #: smear: the largest column lift, a fraction of the clip level


@dataclass
class CameraConfidence:
    """The confidence maps of one camera of a scan."""

    source_id: int
    source: str
    width_px: int
    height_px: int
    artefacts: List[ArtefactCoverage] = field(default_factory=list)


@dataclass
class Scan:
    id: int
    name: str
    rig: str
    captured_utc: str
    pose: Pose
    batch: int
    version: int
    created_utc: str
    sources: List[Source] = field(default_factory=list)
    visual_references: List[VisualReference] = field(default_factory=list)


@dataclass
class ChangeStats:
    """What a change (ingest, rebuild, deletion) recomputed and wrote."""

    sources_computed: int = 0  #: sources computed on every tile they see
    sources_revisited: int = 0  #: older sources recomputed where the change reaches them
    pairs_revisited: int = 0  #: (older source, tile) pairs recomputed
    tiles_changed: int = 0  #: tiles whose objects the commit wrote
    bytes_written: int = 0  #: bytes the commit wrote
    blocks_revisited: int = 0  #: (older source, 16³-vossel block) pairs recomputed
    sources_refreshed: int = 0  #: of those revisited, refreshed from their records (no blob)
    vossels_revisited: int = 0  #: (older source, vossel) pairs recomputed in those blocks


@dataclass
class IngestResult:
    scan_id: int
    scan: str
    version: int
    vossel_count: int
    record_count: int
    new_vossels: int
    point_count: int
    ingest_seconds: float
    total_seconds: float
    stages: Dict[str, float] = field(default_factory=dict)  #: stage -> seconds, in order
    change: ChangeStats = field(default_factory=ChangeStats)
    request_id: str = ""  #: the id the ingest was sent under (retries under it are answered once)
    replayed: bool = False  #: the ingest had committed before; this answers a retry
    sent_bytes: int = 0  #: bytes this client sent (points and images); 0 for a replayed answer
    #: from the call's start to its last byte sent (reading the points included)
    upload_seconds: float = 0.0
    #: each camera of the scan against its LiDAR (none for camera-only scans and replays)
    calibration: List[CalibrationHealth] = field(default_factory=list)


@dataclass
class ChangeResult:
    """A version made by a rebuild or a scan deletion."""

    version: int
    vossel_count: int
    record_count: int
    seconds: float
    stages: Dict[str, float] = field(default_factory=dict)
    change: ChangeStats = field(default_factory=ChangeStats)
    request_id: str = ""
    replayed: bool = False


@dataclass
class Version:
    """A kept version of a project and what made it."""

    version: int
    vossel_count: int
    record_count: int
    tile_count: int
    bytes_written: int
    bytes_total: int
    made_by: str
    pinned: bool
    created_utc: str


@dataclass
class ExportResult:
    """A version exported as one OpenVDB file."""

    version: int
    vossel_count: int
    record_count: int
    size_bytes: int
    path: str


@dataclass
class RenderResult:
    """A rendered equirectangular panorama (VASL-MODEL §8); arrays are row-major, row 0 up."""

    width_px: int
    height_px: int
    version: int
    hit_pixels: int
    render_seconds: float
    rgb: Optional[np.ndarray] = None  #: (H, W, 3) float32 linear; 0 where no hit
    depth_m: Optional[np.ndarray] = None  #: (H, W) float32 metres along the ray; +inf no hit
    normal: Optional[np.ndarray] = None  #: (H, W, 3) float32 world frame
    uncertainty: Optional[np.ndarray] = None  #: (H, W) float32
    profile: str = "default"  #: the weighting profile rendered under
    profile_revision: int = 1
    fused_on_the_fly: bool = False  #: no stored fused tiles for the profile: fused for this render
    render_id: int = 0  #: the id the project recorded this render under (cite it when editing)
    colourless_pixels: int = 0  #: hit pixels whose vossel has no colour (alpha 0, never black)
    detail_sources: int = 0  #: colour_detail="images": cameras whose image coloured some pixel
    detail_sources_skipped: int = 0  #: cameras left out, their images beyond the server's budget
    #: groups of tiles the version was rendered in, one after another, within the server's
    #: memory budget (vasld --max-snapshot-bytes); 1: the version at once
    tile_groups: int = 1
    #: of the version's tiles, those such a render read (the rest lay behind what every ray
    #: through them had hit); both 0 when the server read the version whole
    tiles_read: int = 0
    tiles_total: int = 0
    alpha: Optional[np.ndarray] = None  #: (H, W) float32 coverage: 1 where the pixel has a colour
    exr: Optional[bytes] = None  #: the encoded EXR, if requested
    png: Optional[bytes] = None  #: the encoded PNG preview, if requested
    deep_exr: Optional[bytes] = None  #: the deep EXR (successive surfaces per pixel), if requested
    #: render(files=...): the files written, by format ("exr", "png", "deep"); their bytes
    #: are not held in memory (exr, png and deep_exr stay None)
    files: Dict[str, str] = field(default_factory=dict)
    encode_seconds: float = 0.0  #: of render_seconds, the time the server spent encoding

    @property
    def hit_mask(self) -> np.ndarray:
        return np.isfinite(self.depth_m)


@dataclass
class RecordAttribute:
    name: str
    type: str
    codec: str
    stride: int


@dataclass
class Inspection:
    project: str
    version: int
    tile_count: int
    record_count: int
    attributes: List[RecordAttribute] = field(default_factory=list)


#: Confidence factors of a record, in the order of `kappa` and `conf` (VASL-MODEL §9).
CONFIDENCE_FACTORS = ("saturation", "flare", "dirt", "codec", "smear", "fog")


@dataclass
class ReweightResult:
    """A version whose tiles hold fused values under a profile (VASL-MODEL §7)."""

    version: int
    profile: str
    revision: int
    tile_count: int
    record_count: int
    vossel_count: int
    bytes_written: int
    unchanged: bool  #: HEAD already held the profile's fused tiles: no new version
    seconds: float
    request_id: str = ""
    replayed: bool = False  #: a retry answered from the reweight that committed under its id


@dataclass
class NormaliseResult:
    """Gains a_{m,c} stored as a new profile revision, with what the solve achieved."""

    profile: dict
    vossels_used: int
    pairs_used: int
    cost_before: List[float]
    cost_after: List[float]
    unlinked_sources: List[int]


@dataclass
class LensMap:
    """A rig camera's lens dirt and fog (VASL-MODEL §9): D and v per grid cell and channel."""

    id: int
    rig: str
    camera: str
    period: str  #: the frames and capture times it was found from
    image_width_px: int
    image_height_px: int
    grid_width: int
    grid_height: int
    #: D per cell and channel, row-major (grid_height x grid_width x 3); 1: clean
    transmission: List[float]
    veil: List[float]  #: v per cell and channel, linear; 0: no veil
    source_gain: Dict[int, List[float]]  #: the frames it applies to: source id -> g_m per channel
    dirt_share: float  #: share of the cells with dirt
    veil_share: float  #: share of the cells with a veil
    created_utc: str = ""


@dataclass
class LensEstimate:
    """A lens map found from a rig's frames, and the profile revision that applies it."""

    profile: dict
    map: LensMap
    samples: int  #: records compared with their vossels' other records
    cells: int
    cells_fitted: int  #: cells with enough samples
    cell_px: float
    residual_before: float  #: RMS log ratio of the frames' records to their references, before
    residual_after: float  #: ... and under the map and the frames' gains
    replaced_map: int  #: the base profile's map of the same rig and camera, now replaced; 0: none


@dataclass
class RecordsQuery:
    """Records of the vossels in a box, with their weights under a profile."""

    version: int
    profile: str
    revision: int
    vossel_count: int
    truncated: bool
    records: List[dict] = field(default_factory=list)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """The sRGB EOTF (IEC 61966-2-1): encoded values in [0, 1] -> linear, float32."""
    c = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)
