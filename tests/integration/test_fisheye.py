"""Fisheye cameras (Kannala-Brandt's equidistant lens, as OpenCV's cv::fisheye and ROS's
"equidistant" calibrate it; lattice/geometry/pinhole.h) through the proto, the client and the
CLI on a real vasld. A fisheye render looks where an independent numpy implementation of the
lens says each pixel looks, beyond 90 degrees from its axis too: it agrees with the equirect
render from the same pose. A fisheye photo sent in a manifest (`pinhole.lens: "fisheye"`)
colours the geometry that LiDAR-only scans left colourless, and a fisheye render from its pose
gives the photo back; so does one whose lens comes as ROS's camera_info YAML."""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli
from synth_scans import equirect_pixels, linear_to_srgb, png_bytes
from vasl import read_manifest

SIZE = 480
LENS = {"lens": "fisheye", "fx_px": 100.0, "fy_px": 100.5, "cx_px": 240.5, "cy_px": 239.0,
        "k1": 0.021, "k2": -0.0048, "k3": 0.0011, "k4": 0.00005}


def fisheye_rays(lens: dict, width: int, height: int) -> np.ndarray:
    """(height, width, 3) unit camera-frame rays (x right, y down, z forward) through the pixel
    centres: θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸) inverted by Newton's method."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u - lens["cx_px"]) / lens["fx_px"]
    y = (v - lens["cy_px"]) / lens["fy_px"]
    rd = np.hypot(x, y)
    k = [lens["k1"], lens["k2"], lens["k3"], lens["k4"]]
    theta = rd.copy()
    for _ in range(30):
        t2 = theta * theta
        f = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - rd
        df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        theta -= f / df
    s = np.where(rd > 0, np.sin(theta) / np.maximum(rd, 1e-300), 0.0)
    return np.stack([s * x, s * y, np.cos(theta)], axis=-1)


def _pose(views, name: str) -> dict:
    """A view of the scene (truth/views.json) as a pose."""
    v = views[name]
    return {"position": v["position"], "quaternion": v["quaternion"]}


def test_fisheye_render_looks_where_the_lens_says(client, ingested, views):
    pose = _pose(views, "novel-1")
    fish = client.render("e2e", pose, SIZE, SIZE, formats=("exr",), pinhole=LENS)
    pano = client.render("e2e", pose, 4096, 2048, formats=("exr",))
    rays = fisheye_rays(LENS, SIZE, SIZE).reshape(-1, 3)
    u, v, _ = equirect_pixels(rays, 4096, 2048)
    depth_f = fish.depth_m.reshape(-1)
    depth_p = pano.depth_m[v, u]
    hit = np.isfinite(depth_f) & np.isfinite(depth_p)
    behind = rays[:, 2] < 0.0
    with np.errstate(invalid="ignore"):  # inf - inf where neither hit: not compared
        close = np.abs(depth_f - depth_p) < 2 * VOSSEL_M
    rgb_f = fish.rgb.reshape(-1, 3)
    rgb_p = pano.rgb[v, u]
    colour = np.abs(rgb_f - rgb_p).max(axis=1)
    print(f"\nfisheye {SIZE}x{SIZE} vs equirect 4096x2048 from the same pose: {hit.mean():.1%} "
          f"of pixels hit in both; depth within 2 vossels for {close[hit].mean():.2%} "
          f"({close[hit & behind].mean():.2%} of the {int((hit & behind).sum())} beyond 90 "
          f"degrees); colour median |d| {np.median(colour[hit]):.4f}")
    assert hit.mean() > 0.7 and (hit & behind).sum() > 5000
    assert close[hit].mean() >= 0.97
    assert close[hit & behind].mean() >= 0.97
    assert np.median(colour[hit]) < 0.02

    # With a 180-degree field of view (a circular fisheye), the pixels beyond its image circle
    # stay empty and those within it are the same render's.
    circle = client.render("e2e", pose, SIZE, SIZE, formats=("exr",),
                           pinhole=dict(LENS, field_of_view_deg=180.0))
    inside = (rays[:, 2] >= 0.0).reshape(SIZE, SIZE)
    rim = np.abs(rays[:, 2]).reshape(SIZE, SIZE) < 1e-3  # on the circle: either side
    print(f"field of view 180: {int((~inside).sum())} pixels beyond the image circle, "
          f"{int(np.isfinite(circle.depth_m[~inside & ~rim]).sum())} of them hit")
    assert not np.isfinite(circle.depth_m[~inside & ~rim]).any()
    assert np.all(circle.alpha[~inside & ~rim] == 0)
    assert np.array_equal(circle.depth_m[inside & ~rim], fish.depth_m[inside & ~rim])


def test_cli_renders_through_a_fisheye(server, ingested, views, tmp_path):
    """`vasl render --fisheye fx,fy,cx,cy,k1,k2,k3,k4,fov`: the file of a fisheye render, its
    pixels beyond the field empty (alpha 0); --pinhole with it is refused."""
    import OpenEXR

    pose = _pose(views, "novel-1")
    given = ",".join(str(v) for v in (*pose["position"], *pose["quaternion"]))
    lens = ",".join(str(LENS[k]) for k in ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3",
                                           "k4")) + ",180"
    out = tmp_path / "fish.exr"
    r = run_cli(server, "render", "--project", "e2e", "--pose", given, "--width", str(SIZE),
                "--height", str(SIZE), "--fisheye", lens, "-o", str(out))
    print("\n" + r.stdout.strip())
    assert f"fisheye {SIZE}x{SIZE}" in r.stdout
    alpha = np.asarray(OpenEXR.File(str(out), separate_channels=True).channels()["A"].pixels)
    rays = fisheye_rays(LENS, SIZE, SIZE)
    beyond = rays[..., 2] < -1e-3
    assert beyond.sum() > 100_000 and np.all(alpha[beyond] == 0)
    assert (alpha[rays[..., 2] > 1e-3] == 1).mean() > 0.9
    r = run_cli(server, "render", "--project", "e2e", "--pose", given, "--width", "64",
                "--height", "64", "--fisheye", lens, "--pinhole", "100,100,32,32", "-o",
                str(out), check=False)
    assert r.returncode == 2 and "--pinhole and --fisheye" in r.stderr, r.stderr


def test_fisheye_photo_colours_the_lidar_geometry(client, server, scene_dir, ingested, views,
                                                   tmp_path):
    pose = _pose(views, "novel-2")
    # The photo: a fisheye render of the coloured project, as its camera would have taken it.
    truth = client.render("e2e", pose, SIZE, SIZE, formats=("exr",), pinhole=LENS)
    srgb = np.round(linear_to_srgb(truth.rgb) * 255).astype(np.uint8)
    rows = b"".join(b"\0" + srgb[j].tobytes() for j in range(SIZE))
    (tmp_path / "fisheye.png").write_bytes(png_bytes(SIZE, SIZE, rows))
    # Its calibration as ROS's camera_calibration writes it (camera_info YAML, equidistant).
    (tmp_path / "fisheye.yaml").write_text(
        f"image_width: {SIZE}\nimage_height: {SIZE}\ncamera_name: fisheye\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n"
        f"  data: [{LENS['fx_px']}, 0, {LENS['cx_px']}, 0, {LENS['fy_px']}, {LENS['cy_px']}, "
        "0, 0, 1]\ndistortion_model: equidistant\ndistortion_coefficients:\n  rows: 1\n"
        f"  cols: 4\n  data: [{LENS['k1']}, {LENS['k2']}, {LENS['k3']}, {LENS['k4']}]\n")
    manifest = tmp_path / "fisheye.json"
    manifest.write_text(json.dumps({
        "scan": "fisheye", "pose": pose,
        "panoramas": [{"name": "fisheye", "image": "fisheye.png", "pose": pose,
                       "modality": "rgb", "camera_info": "fisheye.yaml"}]}))

    project = "fisheye-photo"
    client.create_project(project, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir):
        client.ingest(project, dataclasses.replace(read_manifest(m), panoramas=[]))
    r = run_cli(server, "ingest", "--project", project, str(manifest))
    print("\n" + r.stdout)
    r = run_cli(server, "scans", "--project", project)
    assert "fisheye(rgb, fisheye)" in r.stdout, r.stdout
    scan = next(s for s in client.list_scans(project) if s.name == "fisheye")
    assert scan.sources[0].kind == "fisheye" and scan.sources[0].projection.startswith(
        "fisheye 100 100.5 240.5 239 ")

    lit = client.render(project, pose, SIZE, SIZE, formats=("exr",), pinhole=LENS)
    seen = np.isfinite(truth.depth_m) & (truth.alpha > 0)
    coloured = seen & np.isfinite(lit.depth_m) & (lit.alpha > 0)
    a = np.clip(lit.rgb[coloured], 0, 1)
    b = np.clip(truth.rgb[coloured], 0, 1)
    psnr = 10.0 * np.log10(1.0 / float(np.mean((a - b) ** 2)))
    print(f"fisheye photo: {coloured.sum() / seen.sum():.2%} of the pixels it saw coloured, "
          f"PSNR {psnr:.2f} dB against it")
    assert coloured.sum() / seen.sum() > 0.9
    assert psnr >= 28.0

    # A lens that mixes the models is refused, naming the field; the project stays as it was.
    bad = dict(LENS, p1=0.001)
    manifest.write_text(json.dumps({
        "scan": "bad", "pose": pose,
        "panoramas": [{"name": "fisheye", "image": "fisheye.png", "pose": pose,
                       "modality": "rgb", "pinhole": bad}]}))
    head = client.get_project(project).head_version
    r = run_cli(server, "ingest", "--project", project, str(manifest), check=False)
    assert r.returncode != 0 and "no tangential p1, p2" in r.stderr, r.stderr
    assert client.get_project(project).head_version == head
