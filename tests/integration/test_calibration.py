"""Calibration health through the client and a real vasld (VASL-MODEL §2.3): every ingest of a
scan with LiDAR and cameras reports each camera's figures (the CLI prints them under the scan's
summary), and `vasl scans` shows them again from the catalog. The synthetic scene's scan-1 is
ingested as written (its camera on its pose: ok) and scan-2 with its camera's pose turned by
1.5° (4.2 px at the scene's 1024-pixel panoramas: flagged). The 0.5° claim at 2048 px is
tests/ingest/calibration_test.cc's; this test is about what reaches the user."""
from __future__ import annotations

import json
import math
import os

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli

PROJECT = "calibration"
TURN_DEG = 1.5


def _turned(quaternion_xyzw, deg: float):
    """The quaternion (x, y, z, w) composed with a turn of `deg` about an oblique axis."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    half = math.radians(deg) / 2
    bx, by, bz = axis * math.sin(half)
    bw = math.cos(half)
    ax, ay, az, aw = quaternion_xyzw
    return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz]


def test_ingest_reports_and_the_catalog_keeps_calibration(server, client, scene_dir, tmp_path):
    run_cli(server, "project", "create", PROJECT, "--vossel-size", str(VOSSEL_M))
    first, second = manifests(scene_dir)[:2]
    with open(second) as f:
        doc = json.load(f)
    doc["lidar"]["points"] = os.path.join(scene_dir, doc["lidar"]["points"])
    for pano in doc["panoramas"]:
        pano["image"] = os.path.join(scene_dir, pano["image"])
        pano["pose"]["quaternion"] = _turned(pano["pose"]["quaternion"], TURN_DEG)
    turned = tmp_path / "scan-2-turned.json"
    turned.write_text(json.dumps(doc))

    out = run_cli(server, "ingest", first, str(turned), "--project", PROJECT, "--quiet").stdout
    print("\n" + out)
    lines = [line.strip() for line in out.splitlines() if "calibration cam0" in line]
    assert len(lines) == 2, out
    assert lines[0].startswith("calibration cam0: ok, "), lines[0]
    assert lines[1].startswith("calibration cam0: flagged, "), lines[1]
    assert "check the camera's pose" in lines[1]

    scans = {s.name: s for s in client.list_scans(PROJECT)}
    good = next(src.calibration for src in scans["scan-1"].sources if src.name == "cam0")
    off = next(src.calibration for src in scans["scan-2"].sources if src.name == "cam0")
    lidar = next(src for src in scans["scan-1"].sources if src.name == "lidar")
    assert all(src.calibration is None for s in scans.values() for src in s.sources
               if src.name != "cam0")
    print(f"scan-1: {good.summary()}\nscan-2: {off.summary()}")
    assert good.verdict == "ok" and good.lidar_source == lidar.id
    assert good.pixel_mean_px <= 1.0 and good.matched >= 20
    assert good.roundtrip_p95_m <= 1e-5
    assert off.verdict == "flagged" and off.pixel_p95_px > 2.0
    assert abs(off.rotation_deg - TURN_DEG) <= 0.2 * TURN_DEG

    shown = run_cli(server, "scans", "--project", PROJECT).stdout
    assert shown.count("calibration cam0: ") == 2, shown
    listed = json.loads(run_cli(server, "scans", "--project", PROJECT, "--json").stdout)
    verdicts = {s["name"]: [c["verdict"] for c in s["calibration"]] for s in listed}
    assert verdicts == {"scan-1": ["ok"], "scan-2": ["flagged"]}
