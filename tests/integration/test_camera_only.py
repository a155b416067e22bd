"""Camera-only and pinhole captures through the manifest, the client and the CLI on a real
vasld (VASL-MODEL §2.2, §5): a pinhole photo taken where no LiDAR stood colours the geometry
that LiDAR-only scans left colourless, and a render from the photo's own pose gives the photo
back."""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli
from vasl import VaslError, read_manifest

PROJECT = "camera-only"


def _psnr(a, b):
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def test_pinhole_photo_without_lidar_colours_the_lidar_geometry(client, server, scene_dir):
    photo_manifest = os.path.join(scene_dir, "photo-1.json")
    with open(photo_manifest) as f:
        doc = json.load(f)
    photo = doc["panoramas"][0]
    pinhole = photo["pinhole"]
    truth = np.load(os.path.join(scene_dir, "truth", "photo-1-rgb.npy"))
    height, width = truth.shape[:2]

    # Refused while the project has no geometry: nothing to colour yet; nothing stored.
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    try:
        client.ingest(PROJECT, photo_manifest)
        raise AssertionError("a camera-only scan into an empty project was accepted")
    except VaslError as e:
        assert e.code.name == "FAILED_PRECONDITION" and "no geometry" in e.details, e
    assert client.get_project(PROJECT).head_version == 0

    # LiDAR only: geometry without colour.
    for m in manifests(scene_dir):
        client.ingest(PROJECT, dataclasses.replace(read_manifest(m), panoramas=[]))
    before = client.get_project(PROJECT)
    pose = photo["pose"]
    dark = client.render(PROJECT, pose, width, height, formats=("exr",), pinhole=pinhole)
    hit = np.isfinite(dark.depth_m)
    assert hit.mean() > 0.9
    assert dark.colourless_pixels == int(hit.sum()), "LiDAR-only scans gave colour"

    # The photo through the CLI, as a rig operator sends it.
    r = run_cli(server, "ingest", "--project", PROJECT, photo_manifest)
    print("\n" + r.stdout)
    after = client.get_project(PROJECT)
    assert after.vossel_count == before.vossel_count, "a camera-only scan changed the geometry"
    assert after.record_count > before.record_count
    scan = next(s for s in client.list_scans(PROJECT) if s.name == "photo-1")
    assert [(s.name, s.width_px, s.height_px, s.point_count) for s in scan.sources] == \
        [("photo", width, height, 0)]

    lit = client.render(PROJECT, pose, width, height, formats=("exr",), pinhole=pinhole)
    coloured = np.isfinite(lit.depth_m) & (lit.alpha > 0)
    psnr = _psnr(lit.rgb[coloured], truth[coloured])
    print(f"render from the photo's pose: {coloured.mean() * 100:.2f}% of pixels coloured "
          f"(before: 0), PSNR {psnr:.2f} dB against the photo's analytic truth")
    assert coloured.mean() > 0.85
    assert psnr >= 30.0
