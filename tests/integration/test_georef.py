"""A georeferenced site through the client and a real vasld (VASL-MODEL §1): the synthetic scene
moved to UTM-like coordinates, (500000, 5000000, 100) m, in a project created with that origin,
renders as the unmoved one from the same (moved) viewpoints; scans, queries and the project
itself report world coordinates."""
from __future__ import annotations

import json
import os

import numpy as np

from conftest import E2E_PROJECT, VOSSEL_M, manifests, run_cli

SHIFT = np.array([500000.0, 5000000.0, 100.0])
PROJECT = "georef"


def _moved(pose: dict) -> dict:
    return {**pose, "position": [float(v) for v in np.asarray(pose["position"]) + SHIFT]}


def _psnr(a, b):
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def test_georeferenced_copy_renders_as_the_site(client, server, scene_dir, ingested, views,
                                                tmp_path):
    origin = ",".join(f"{v:.0f}" for v in SHIFT)
    r = run_cli(server, "project", "create", PROJECT, "--vossel-size", str(VOSSEL_M),
                "--origin", origin)
    assert "origin 500000.000,5000000.000,100.000" in r.stdout, r.stdout
    for path in manifests(scene_dir):  # the same scans, posed in the moved frame
        with open(path) as f:
            doc = json.load(f)
        doc["pose"] = _moved(doc["pose"])
        doc["lidar"]["points"] = os.path.join(scene_dir, doc["lidar"]["points"])
        for pano in doc.get("panoramas", []):
            pano["pose"] = _moved(pano["pose"])
            pano["image"] = os.path.join(scene_dir, pano["image"])
        moved = tmp_path / os.path.basename(path)
        moved.write_text(json.dumps(doc))
        client.ingest(PROJECT, str(moved))
    geo, plain = client.get_project(PROJECT), client.get_project(E2E_PROJECT)
    assert geo.origin_m == tuple(SHIFT)
    assert plain.origin_m == (0.0, 0.0, 0.0)
    assert (geo.vossel_count, geo.record_count) == (plain.vossel_count, plain.record_count)
    shown = run_cli(server, "project", "get", PROJECT).stdout
    assert "origin_m       500000.000,5000000.000,100.000" in shown, shown

    # Scans come back where they were sent.
    for scan, path in zip(client.list_scans(PROJECT), manifests(scene_dir)):
        with open(path) as f:
            sent = np.asarray(json.load(f)["pose"]["position"]) + SHIFT
        np.testing.assert_allclose(scan.pose.position_m, sent, atol=1e-6)

    # Renders from the moved viewpoints equal the site's from the unmoved ones.
    for name in ("novel-1", "novel-2"):
        view = views[name]
        pose = {"position": view["position"], "quaternion": view["quaternion"]}
        truth = np.load(os.path.join(scene_dir, "truth", view["rgb"]))
        h, w = truth.shape[:2]
        a = client.render(E2E_PROJECT, pose, w, h, formats=("exr",))
        b = client.render(PROJECT, _moved(pose), w, h, formats=("exr",))
        hit = np.isfinite(a.depth_m) & np.isfinite(b.depth_m)
        same_hits = float(np.mean(np.isfinite(a.depth_m) == np.isfinite(b.depth_m)))
        dz = np.abs(a.depth_m[hit] - b.depth_m[hit])
        psnr_a, psnr_b = _psnr(a.rgb[hit], truth[hit]), _psnr(b.rgb[hit], truth[hit])
        print(f"\n{name}: {hit.mean():.2%} of pixels hit in both, hits agree on {same_hits:.4%}; "
              f"max |Δdepth| {dz.max() * 1000:.4f} mm; PSNR vs truth {psnr_b:.3f} dB moved, "
              f"{psnr_a:.3f} dB at home")
        assert hit.mean() > 0.9 and same_hits > 0.9999
        assert dz.max() <= 1e-3
        assert abs(psnr_a - psnr_b) <= 0.1

    # A query of a world box finds the records the site has there, at world centroids.
    lo, hi = np.array([2.95, 4.95, 0.95]), np.array([3.05, 5.05, 1.05])  # on the wall y = 5
    qa = client.query_records(E2E_PROJECT, box=[*lo, *hi])
    qb = client.query_records(PROJECT, box=[*(lo + SHIFT), *(hi + SHIFT)])
    assert len(qa.records) == len(qb.records) > 0
    for x, y in zip(qa.records, qb.records):
        np.testing.assert_allclose(np.asarray(y["centroid_m"]) - SHIFT, x["centroid_m"],
                                   atol=1e-5)
    print(f"query: {len(qa.records)} records at the same places in both projects")
