"""Sensor artefacts as confidence through a real vasld (VASL-MODEL §9): a panorama with bright
sources planted at known pixels, with a known bloom, is ingested as a rig sends it;
`vasl confidence show` writes its saturation map, which finds the planted halos (recall) and
leaves the image away from the sources at 1, and says what it covers; a clean panorama's map
stays at 1. (Precision is printed, not asserted: around a source lying on a patch brighter
than its surround the map also lowers that patch, which the room's render has; the planted
textures of tests/ingest/artefacts_test.cc assert it.)"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import struct
import zlib

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli
from synth_scans import linear_to_srgb, png_bytes
from vasl import read_manifest

PROJECT = "confidence"


def _write_png(path, rgb8):
    """An 8-bit RGB PNG, every row unfiltered."""
    h, w, _ = rgb8.shape
    with open(path, "wb") as f:
        f.write(png_bytes(w, h, b"".join(b"\x00" + rgb8[j].tobytes() for j in range(h))))


def _ingest_panorama(server, project, tmp_path, name, image, view):
    """Writes `image` (8-bit RGB) as a PNG and ingests it through the CLI, as a rig sends it,
    as scan `name` of one panorama "pano" at the view's pose."""
    _write_png(tmp_path / f"{name}.png", image)
    pose = {"position": list(view["position"]), "quaternion": list(view["quaternion"])}
    manifest = {"scan": name, "rig": "handheld", "pose": pose,
                "panoramas": [{"name": "pano", "image": f"{name}.png", "modality": "rgb",
                               "pose": pose}]}
    (tmp_path / f"{name}.json").write_text(json.dumps(manifest))
    run_cli(server, "ingest", "--project", project, str(tmp_path / f"{name}.json"))


def _read_grey_png(data):
    """An 8-bit grey PNG's pixels (any of the five row filters)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat = 8, b""
    w = h = 0
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
            assert (depth, colour) == (8, 0), (depth, colour)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw = zlib.decompress(idat)
    out = np.zeros((h, w), np.int32)
    prev = np.zeros(w, np.int32)
    for j in range(h):
        f, row = raw[j * (w + 1)], np.frombuffer(raw[j * (w + 1) + 1:(j + 1) * (w + 1)], np.uint8)
        row = row.astype(np.int32)
        if f in (0, 1, 2):  # none, sub (a running sum), up
            cur = (np.cumsum(row) if f == 1 else row + (prev if f == 2 else 0)) & 0xFF
            out[j], prev = cur, cur
            continue
        cur = np.zeros(w, np.int32)
        for i in range(w):
            a = cur[i - 1] if i else 0
            b, c = prev[i], (prev[i - 1] if i else 0)
            if f == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[i] = (row[i] + pred) & 0xFF
        out[j], prev = cur, cur
    return out


def test_confidence_maps_find_planted_blooming(client, server, scene_dir, views, tmp_path):
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    for i, m in enumerate(manifests(scene_dir)):  # the first station with its clean panorama
        scan = read_manifest(m)
        client.ingest(PROJECT, scan if i == 0 else dataclasses.replace(scan, panoramas=[]))
    first = read_manifest(manifests(scene_dir)[0]).scan

    v = views["novel-1"]
    surface = np.load(os.path.join(scene_dir, "truth", v["rgb"])).astype(np.float64)
    h, w = surface.shape[:2]
    sources = [(0.12 * w, 0.45 * h, 4, 2.0, 3.0), (0.35 * w, 0.5 * h, 6, 8.0, 3.0),
               (0.6 * w, 0.42 * h, 5, 16.0, 3.5), (0.85 * w, 0.55 * h, 7, 32.0, 3.0)]
    jj, ii = np.mgrid[0:h, 0:w] + 0.5
    bloom = np.zeros((h, w))
    for u, vv, r, brightness, lam in sources:
        d = np.hypot(ii - u, jj - vv) - r
        bloom += np.where(d <= 0, brightness, brightness * np.exp(-np.maximum(d, 0) / lam))
    image = np.round(linear_to_srgb(surface + bloom[..., None]) * 255.0).astype(np.uint8)
    _ingest_panorama(server, PROJECT, tmp_path, "bloomed", image, v)

    out = tmp_path / "maps"
    r = run_cli(server, "confidence", "show", "--project", PROJECT, "--scan", "bloomed",
                "-o", str(out))
    print("\n" + r.stdout)
    found = re.search(r"pano \((\d+)x(\d+)\) saturation: (\d+) regions, ([\d.]+)% of the image",
                      r.stdout)
    assert found and (int(found.group(1)), int(found.group(2))) == (w, h), r.stdout
    assert int(found.group(3)) == len(sources)
    grey = _read_grey_png((out / "pano-saturation.png").read_bytes())
    assert grey.shape == (h, w)

    # The planted halos, on the pixels the PNG did not clip: bloom adding more than a tenth of
    # the surface's light (and more than 2.5 codes).
    clipped = (image >= 255).any(axis=-1)
    level = surface.max(axis=-1)
    truth = (bloom > 0.1 * level) & (bloom > 0.01) & ~clipped
    said = (grey < 255) & ~clipped
    precision = (truth & said).sum() / max(1, said.sum())
    recall = (truth & said).sum() / max(1, truth.sum())
    far = np.ones((h, w), bool)
    for u, vv, rad, _, lam in sources:
        far &= np.hypot(ii - u, jj - vv) - rad > 15 * lam
    print(f"planted halo {int(truth.sum())} px, found {int(said.sum())}: precision "
          f"{precision:.3f}, recall {recall:.3f}; clipped {int(clipped.sum())} px, all at 0: "
          f"{bool((grey[clipped] == 0).all())}; far from the sources at 1: "
          f"{100.0 * (grey[far] == 255).mean():.3f}%")
    assert truth.sum() > 500
    assert recall >= 0.85
    assert (grey[clipped] == 0).all()
    assert (grey[far] == 255).mean() >= 0.999

    cameras = client.scan_confidence(PROJECT, first)
    assert len(cameras) == 1
    assert [a.artefact for a in cameras[0].artefacts] == ["saturation", "smear", "flare", "codec",
                                                          "fringing"]
    for clean in cameras[0].artefacts:
        print(f"clean panorama of {first}, {clean.artefact}: "
              f"{100.0 * clean.covered_fraction:.3f}% below 1")
        assert clean.covered_fraction <= 0.01
        assert (_read_grey_png(clean.map_png) == 255).mean() >= 0.99


def test_confidence_maps_find_planted_flare(client, server, scene_dir, views, tmp_path):
    """A panorama with bright sources, each with a broad veil of glare (VASL-MODEL §9 flare),
    ingested as a rig sends it: `vasl confidence show` writes its flare map, which finds the
    pixels the planted glare adds more than a fifth to (recall) and leaves the image far from
    the sources at 1, and the CLI says how many sources carry a veil. (The panorama shows a
    sharp checker rather than the room's smooth albedo, under which one image cannot tell a
    veil from the scene: the project holds geometry only, so it is the one camera.)"""
    project = "confidence-flare"
    client.create_project(project, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir):
        client.ingest(project, dataclasses.replace(read_manifest(m), panoramas=[]))

    v = views["novel-1"]
    h, w = np.load(os.path.join(scene_dir, "truth", v["rgb"])).shape[:2]
    jj, ii = np.mgrid[0:h, 0:w]
    tone = np.where(((ii // 9) + (jj // 7)) % 2 == 0, 0.2, 0.35)
    surface = np.repeat(tone[..., None], 3, axis=-1) * np.array([1.0, 0.9, 0.8])
    # (u, v, radius, glare at the centre, core alpha, fall beta), in pixels of this view.
    sources = [(0.2 * w, 0.48 * h, 4, 0.4, 0.025 * w, 1.1),
               (0.55 * w, 0.45 * h, 5, 0.5, 0.03 * w, 1.2),
               (0.85 * w, 0.52 * h, 4, 0.3, 0.02 * w, 1.0)]
    jj, ii = np.mgrid[0:h, 0:w] + 0.5
    glare = np.zeros((h, w))
    disc = np.zeros((h, w), bool)
    nearest = np.full((h, w), np.inf)
    for u, vv, r, g, alpha, beta in sources:
        dx = np.minimum(np.abs(ii - u), w - np.abs(ii - u))  # columns wrap
        d = np.hypot(dx, jj - vv)
        glare += g * (1.0 + (d / alpha) ** 2) ** -beta
        disc |= d <= r
        nearest = np.minimum(nearest, d)
    linear = np.where(disc[..., None], 1.0, surface + glare[..., None])
    image = np.round(linear_to_srgb(np.clip(linear, 0.0, 1.0)) * 255.0).astype(np.uint8)
    _ingest_panorama(server, project, tmp_path, "flared", image, v)

    out = tmp_path / "maps"
    r = run_cli(server, "confidence", "show", "--project", project, "--scan", "flared",
                "-o", str(out))
    print("\n" + r.stdout)
    found = re.search(r"pano \((\d+)x(\d+)\) flare: (\d+) sources with a veil", r.stdout)
    assert found and (int(found.group(1)), int(found.group(2))) == (w, h), r.stdout
    assert int(found.group(3)) == len(sources)
    grey = _read_grey_png((out / "pano-flare.png").read_bytes())
    assert grey.shape == (h, w)
    clipped = (image >= 255).any(axis=-1)
    level = surface.max(axis=-1)
    truth = (glare > 0.2 * level) & (glare > 0.02) & ~clipped
    said = grey < 255
    recall = (truth & said).sum() / max(1, truth.sum())
    far = nearest > 0.25 * w
    print(f"planted glare over a fifth of the own light on {int(truth.sum())} px, flare map "
          f"below 1 on {int(said.sum())} px: recall {recall:.3f}; far from the sources at 1: "
          f"{100.0 * (grey[far] == 255).mean():.3f}%")
    assert truth.sum() > 2000
    assert recall >= 0.85
    assert (grey[far] == 255).mean() >= 0.999
