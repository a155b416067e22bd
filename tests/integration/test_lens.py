"""Lens dirt and fog through a real vasld and the `vasl` CLI (VASL-MODEL §9): six panoramas of
one rig, taken at the scene's stations and novel views through two dirt spots at fixed pixels,
are ingested as a rig sends them (with capture times) beside the stations' LiDAR.
`vasl lens estimate --reweight` finds the spots from the stored records, stores the map and a
profile that applies it and reweights under it; `vasl lens list` shows the map; `vasl
confidence show` of the first frame, ingested before the map existed, writes its "dirt" map,
which lowers the spots' pixels and leaves the rest at 1; and a render under the new profile
gives the spots' vossels their colour back (the error against the clean truth falls)."""
from __future__ import annotations

import dataclasses
import json
import re

import grpc
import numpy as np
import pytest

from conftest import VOSSEL_M, manifests, run_cli
from synth_scans import linear_to_srgb
from test_confidence import _read_grey_png, _write_png
from vasl import decode_exr, read_manifest
from vasl._proto import vasl_pb2 as pb

PROJECT = "lens-e2e"
SPOTS = ((0.3, 0.45, 0.045, 0.45), (0.7, 0.55, 0.04, 0.55))  # u, v, radius (of W), D at the core


def _dirt(h, w):
    """The planted transmission: 1 - strength inside each spot, fading to 1 at 1.4 radii."""
    jj, ii = np.mgrid[0:h, 0:w] + 0.5
    d = np.ones((h, w))
    for u, v, r, core in SPOTS:
        rr = np.hypot(ii - u * w, jj - v * h) / (r * w)
        t = np.clip((1.4 - rr) / 0.4, 0.0, 1.0)
        d *= 1.0 - (1.0 - core) * t * t * (3.0 - 2.0 * t)
    return d


def test_lens_estimate_finds_planted_dirt_and_a_reweight_applies_it(client, server, scene_dir,
                                                                    views, tmp_path):
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir):  # the geometry: the stations' LiDAR
        client.ingest(PROJECT, dataclasses.replace(read_manifest(m), panoramas=[]))
    names = sorted(n for n in views if n.endswith("cam0") or n.startswith("novel"))
    assert len(names) >= 5, sorted(views)
    frames = []
    for i, name in enumerate(names):
        v = views[name]
        surface = np.load(f"{scene_dir}/truth/{v['rgb']}").astype(np.float64)
        h, w = surface.shape[:2]
        image = np.round(linear_to_srgb(surface * _dirt(h, w)[..., None]) * 255.0)
        _write_png(tmp_path / f"dusty-{i}.png", image.astype(np.uint8))
        pose = {"position": list(v["position"]), "quaternion": list(v["quaternion"])}
        manifest = {"scan": f"dusty-{i}", "rig": "dusty", "pose": pose,
                    "captured_utc": f"2026-11-{10 + i}T09:00:00Z",
                    "panoramas": [{"name": "pano", "image": f"dusty-{i}.png", "modality": "rgb",
                                   "pose": pose}]}
        (tmp_path / f"dusty-{i}.json").write_text(json.dumps(manifest))
        run_cli(server, "ingest", "--project", PROJECT, str(tmp_path / f"dusty-{i}.json"))
        frames.append((v, surface))

    r = run_cli(server, "lens", "estimate", "--project", PROJECT, "--rig", "dusty",
                "--until", "2026-11-30", "--reweight", "--quiet")
    print("\n" + r.stdout)
    found = re.search(r"lens map (\d+) of rig dusty, camera pano: (\d+) frames", r.stdout)
    assert found and int(found.group(2)) == len(names), r.stdout
    assert "profile lens revision 1 applies lens maps [" in r.stdout
    assert "reweighted lens-e2e under lens revision 1" in r.stdout
    listed = run_cli(server, "lens", "list", "--project", PROJECT).stdout
    assert f"lens map {found.group(1)}: rig dusty, camera pano" in listed, listed
    maps = client.list_lens_maps(PROJECT)
    assert len(maps) == 1 and 0.0 < maps[0].dirt_share < 0.2
    # ListLensMaps pages as every List RPC does.
    assert [m.id for m in client.list_lens_maps(PROJECT, True, page_size=1)] == [maps[0].id]
    page = client.stub.ListLensMaps(pb.ListLensMapsRequest(project=PROJECT, summary=True,
                                                           page_size=1))
    assert len(page.maps) == 1 and page.next_page_token == ""
    with pytest.raises(grpc.RpcError) as bad:
        client.stub.ListLensMaps(pb.ListLensMapsRequest(project=PROJECT, page_token="x"))
    assert bad.value.code() == grpc.StatusCode.INVALID_ARGUMENT

    # The first frame's lens map, as confidence show writes it.
    out = tmp_path / "maps"
    shown = run_cli(server, "confidence", "show", "--project", PROJECT, "--scan", "dusty-0",
                    "-o", str(out)).stdout
    print(shown)
    assert re.search(r"pano \(\d+x\d+\) dirt: dirt of lens map \d+: [\d.]+% of the "
                     r"image lowered", shown), shown
    assert re.search(r"pano \(\d+x\d+\) fog: veil of lens map \d+: ", shown), shown
    grey = _read_grey_png((out / "pano-dirt.png").read_bytes())
    h, w = grey.shape
    jj, ii = np.mgrid[0:h, 0:w] + 0.5
    core = np.zeros((h, w), bool)
    far = np.ones((h, w), bool)
    for u, v, rad, _ in SPOTS:
        dist = np.hypot(ii - u * w, jj - v * h) / (rad * w)
        core |= dist <= 1.0
        far &= dist > 2.5
    recall = (grey[core] < 230).mean()
    clean = (grey[far] == 255).mean()
    print(f"lens map of the first frame: {100.0 * recall:.1f}% of the spots' cores lowered "
          f"below 0.9, {100.0 * clean:.2f}% of the pixels away from them at 1")
    assert recall >= 0.9
    assert clean >= 0.99

    # A render at the first frame's pose under the new profile against the default's: the
    # spots' pixels come closer to the clean truth.
    v, surface = frames[0]
    pose = f"{','.join(map(str, v['position']))},{','.join(map(str, v['quaternion']))}"
    errs = {}
    # Fused colours, the view blend of the records, and the sources' images read again at each
    # pixel's point (§8 colour detail): each corrects the dusty frames as fusion does.
    modes = (("0", "vossel"), ("2", "vossel"), ("0", "images"))
    for profile in ("default", "lens"):
        for eta, detail in modes:
            exr = tmp_path / f"render-{profile}-{eta}-{detail}.exr"
            shown = run_cli(server, "render", "--project", PROJECT, "--pose", pose, "--width",
                            str(w), "--height", str(h), "--profile", profile, "--eta", eta,
                            "--colour-detail", detail, "-o", str(exr)).stdout
            if detail == "images":
                assert re.search(r"colour from \d+ cameras' images", shown), shown
            img = decode_exr(exr.read_bytes())
            rgb = np.stack([img["R"], img["G"], img["B"]], axis=-1)
            ok = core & np.isfinite(rgb).all(axis=-1) & (img["A"] > 0)
            errs[profile, eta, detail] = float(np.abs(rgb[ok] - surface[ok]).mean())
    for mode in modes:
        print(f"render at dusty-0's pose, eta {mode[0]}, colour detail {mode[1]}, mean |error| "
              f"on the spots against the truth: {errs[('default',) + mode]:.4f} under the "
              f"default profile, {errs[('lens',) + mode]:.4f} under 'lens'")
        # Measured: 0.13-0.10 of the default's error; reading the images without the lens
        # correction (only the dusty frames' lower weights) leaves 0.68 of it.
        assert errs[("lens",) + mode] < 0.3 * errs[("default",) + mode]
