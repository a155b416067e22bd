"""vasl: Python client of the vasl volumetric scan-fusion server (vasld).

`Client` is the typed facade (numpy in and out); `read_ply` and `read_manifest` read what a rig
writes; the `vasl` command line (vasl.cli) is a thin layer over the client.
"""
from .client import Client, VaslError, decode_exr, pack_points
from .readers import Manifest, PanoramaEntry, PointCloud, read_manifest, read_ply
from .types import (Inspection, IngestResult, Pose, Project, RecordAttribute, RenderResult,
                    Scan, Source)

__all__ = [
    "Client", "VaslError", "decode_exr", "pack_points", "Manifest", "PanoramaEntry",
    "PointCloud", "read_manifest", "read_ply", "Inspection", "IngestResult", "Pose", "Project",
    "RecordAttribute", "RenderResult", "Scan", "Source",
]
__version__ = "0.1.0"
