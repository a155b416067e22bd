"""End to end: scans written by vasl_scene go through a real vasld and come back as renders
that match the analytic ground truth (VASL-MODEL §8), from a station camera and a novel view."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import grpc
import numpy as np
import pytest

from conftest import E2E_PROJECT, VOSSEL_M, manifests
from vasl import Pose
from vasl._proto import vasl_pb2 as pb
from vasl.client import pose_to_pb


def _render_view(client, scene_dir, view):
    r = client.render(E2E_PROJECT, {"position": view["position"], "quaternion": view["quaternion"]},
                      view["width"], view["height"])
    truth_rgb = np.load(os.path.join(scene_dir, "truth", view["rgb"]))
    truth_depth = np.load(os.path.join(scene_dir, "truth", view["depth"]))
    assert r.rgb.shape == truth_rgb.shape, (r.rgb.shape, truth_rgb.shape)
    assert r.depth_m.shape == truth_depth.shape
    return r, truth_rgb, truth_depth


def _psnr(a, b):
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def test_station_view_psnr(client, ingested, scene_dir, views):
    view = views["scan-1-cam0"]
    r, truth_rgb, truth_depth = _render_view(client, scene_dir, view)
    hit = np.isfinite(r.depth_m) & np.isfinite(truth_depth)
    coverage = hit.sum() / np.isfinite(truth_depth).sum()
    psnr = _psnr(r.rgb[hit], truth_rgb[hit])
    print(f"\nstation view {view['name']} {view['width']}x{view['height']}: hit {hit.sum()} px "
          f"({100 * coverage:.1f}% of truth surface), PSNR {psnr:.2f} dB over hit pixels, "
          f"render {r.render_seconds:.2f} s")
    assert hit.sum() > 0.5 * hit.size, "the render should cover most of the panorama"
    assert psnr >= 30.0


def test_novel_view_psnr_and_depth(client, ingested, scene_dir, views):
    novel = sorted(n for n in views if n.startswith("novel-"))
    assert novel, "vasl_scene wrote no novel view"
    for name in novel:
        view = views[name]
        r, truth_rgb, truth_depth = _render_view(client, scene_dir, view)
        hit = np.isfinite(r.depth_m) & np.isfinite(truth_depth)
        psnr = _psnr(r.rgb[hit], truth_rgb[hit])
        err = np.abs(r.depth_m[hit] - truth_depth[hit])
        within = float(np.mean(err < VOSSEL_M))
        print(f"\nnovel view {name} {view['width']}x{view['height']}: hit {hit.sum()} px, "
              f"PSNR {psnr:.2f} dB, depth error median {np.median(err) * 1e3:.1f} mm, "
              f"p95 {np.percentile(err, 95) * 1e3:.1f} mm, {100 * within:.2f}% below one vossel "
              f"({VOSSEL_M} m)")
        assert hit.sum() > 0.5 * hit.size
        assert psnr >= 25.0
        assert within >= 0.95


def test_counts_after_ingest(client, ingested, scene_dir):
    names = [os.path.basename(m)[:-5] for m in manifests(scene_dir)]
    scans = client.list_scans(E2E_PROJECT)
    project = client.get_project(E2E_PROJECT)
    print(f"\nproject {project.name}: version {project.head_version}, {project.scan_count} scans, "
          f"{project.vossel_count} vossels, {project.record_count} records")
    assert sorted(s.name for s in scans) == sorted(names)
    assert project.scan_count == len(names)
    assert project.head_version == ingested[-1].version
    assert [r.version for r in ingested] == sorted(r.version for r in ingested)
    assert len({r.version for r in ingested}) == len(ingested), "one version per ingest"
    assert project.vossel_count == ingested[-1].vossel_count > 0
    assert project.record_count == ingested[-1].record_count > project.vossel_count
    assert abs(project.vossel_size_m - VOSSEL_M) < 1e-12
    for s in scans:
        modalities = sorted(src.modality for src in s.sources)
        assert modalities == ["lidar", "rgb"], modalities
        assert sum(src.point_count for src in s.sources) > 0
    assert any(p.name == E2E_PROJECT for p in client.list_projects())


def test_vdb_files_open_and_inspect_lists_attributes(client, ingested, server):
    project = client.get_project(E2E_PROJECT)
    # Tile objects are plain OpenVDB files named by their sha256 (the reach rasters beside them
    # are not .vdb files and vdb_print refuses them).
    objects = os.path.join(server.data_dir, E2E_PROJECT, "objects")
    kinds = {}
    for name in sorted(os.listdir(objects)):
        path = os.path.join(objects, name)
        with open(path, "rb") as f:
            if f.read(4) != b" BDV":  # OpenVDB's magic number, 0x56444220 little-endian
                continue
        assert subprocess.run(["vdb_print", "-l", path], capture_output=True).returncode == 0
        r = subprocess.run(["vdb_print", path], capture_output=True, text=True)  # a grid a line
        assert r.returncode == 0, r.stderr
        grids = [line.split()[0] for line in r.stdout.splitlines() if line.strip()]
        kind = "records" if "records" in grids else "geometry" if "index" in grids else "fused"
        kinds[kind] = kinds.get(kind, 0) + 1
    print(f"\nvdb_print opened tile objects: {kinds}")
    assert kinds.get("records", 0) >= 1 and kinds.get("geometry", 0) >= 1 and kinds.get("fused", 0) >= 1
    info = client.inspect_records(E2E_PROJECT)
    assert info.version == project.head_version
    assert info.record_count == project.record_count and info.tile_count >= 1
    attrs = {a.name: a for a in info.attributes}
    for a in info.attributes:
        print(f"  {a.name:<12} {a.type:<8} {a.codec:<10} stride {a.stride}")
    for needed in ("scan", "modality", "value", "range", "cos_inc", "uv", "vis", "conf", "flags",
                   "batch"):
        assert needed in attrs, f"attribute {needed} missing from {sorted(attrs)}"
    assert any(n.startswith("foot") for n in attrs)
    assert attrs["uv"].stride == 2 and attrs["value"].stride == 3 and attrs["conf"].stride == 6
    assert all(a.type and a.codec for a in info.attributes)
    # The CLI shows the same table.
    out = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "inspect",
                          "--project", E2E_PROJECT], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    for needed in ("range", "cos_inc", "conf", "batch"):
        assert needed in out.stdout
    assert "conf factors: saturation, flare, dirt, codec, smear, fog" in out.stdout, out.stdout


def test_cli_render_writes_exr_and_png(ingested, server, views, tmp_path):
    v = views["novel-1"]
    pose = ",".join(str(x) for x in list(v["position"]) + list(v["quaternion"]))
    out = tmp_path / "view.exr"
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "render",
                        "--project", E2E_PROJECT, "--pose", pose, "--width", "256", "--height",
                        "128", "-o", str(out)], capture_output=True, text=True)
    print("\n" + r.stdout)
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:4] == b"\x76\x2f\x31\x01"  # EXR magic
    assert (tmp_path / "view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from vasl import decode_exr

    channels = decode_exr(out.read_bytes())
    assert set(channels) >= {"R", "G", "B", "Z", "N.x", "N.y", "N.z", "U"}, sorted(channels)
    assert channels["Z"].shape == (128, 256)


def test_pinhole_renders_alpha_and_render_ids(ingested, client, server, views, tmp_path):
    """Pinhole renders from the CLI and the client; every render gets a new id; a hit without
    colour has alpha 0 and U = inf (never black with alpha 1)."""
    v = views["novel-1"]
    pose = ",".join(str(x) for x in list(v["position"]) + list(v["quaternion"]))
    out = tmp_path / "pin.exr"
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "render",
                        "--project", E2E_PROJECT, "--pose", pose, "--width", "160", "--height",
                        "120", "--pinhole", "100,100,80,60", "-o", str(out)],
                       capture_output=True, text=True)
    print("\n" + r.stdout)
    assert r.returncode == 0, r.stderr
    assert re.search(r"render \d+: pinhole 160x120", r.stdout), r.stdout
    from vasl import decode_exr

    channels = decode_exr(out.read_bytes())
    assert channels["A"].shape == (120, 160)
    png = (tmp_path / "pin.png").read_bytes()
    assert png[25] == 6, "the PNG is RGBA (colour type 6)"
    a = client.render(E2E_PROJECT, v, 160, 120, formats=("exr",),
                      pinhole={"fx_px": 100, "fy_px": 100, "cx_px": 80, "cy_px": 60})
    b = client.render(E2E_PROJECT, v, 64, 32, formats=("exr",))
    assert b.render_id > a.render_id > 0
    hit = np.isfinite(a.depth_m)
    colourless = hit & (a.alpha == 0)
    assert int(colourless.sum()) == a.colourless_pixels
    assert np.all(np.isinf(a.uncertainty[colourless]))
    assert np.all(a.alpha[~hit] == 0) and np.all(a.alpha[hit & ~colourless] == 1)
    print(f"pinhole 160x120: {int(hit.sum())} hit pixels, {a.colourless_pixels} without colour; "
          f"render ids {a.render_id}, {b.render_id}")
    # Impossible intrinsics: the CLI refuses them before sending (its usage error, 2), and the
    # server refuses them (and a lens it does not know) when they come all the same.
    bad = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "render",
                          "--project", E2E_PROJECT, "--pose", pose, "--pinhole", "0,100,80,60",
                          "-o", str(out)], capture_output=True, text=True)
    assert bad.returncode == 2 and "fx_px and fy_px must be > 0" in bad.stderr, bad.stderr
    for camera, message in ((pb.PinholeCamera(fx_px=0, fy_px=100, cx_px=80, cy_px=60),
                             "focal lengths must be > 0"),
                            (pb.PinholeCamera(fx_px=100, fy_px=100, cx_px=80, cy_px=60, lens=7),
                             "pinhole.lens 7 is not a lens")):
        request = pb.RenderRequest(project=E2E_PROJECT, width_px=160, height_px=120,
                                   pinhole=camera, pose=pose_to_pb(Pose.parse(pose)))
        with pytest.raises(grpc.RpcError) as e:
            list(client.stub.Render(request, timeout=30))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value
        assert message in e.value.details(), e.value.details()


def test_deep_render_from_the_cli(ingested, client, server, views, tmp_path):
    """--layers L writes a deep EXR beside the render: per pixel its successive surfaces, the
    first of which is the flat render's depth."""
    v = views["novel-1"]
    pose = ",".join(str(x) for x in list(v["position"]) + list(v["quaternion"]))
    out = tmp_path / "deep.exr"
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "render",
                        "--project", E2E_PROJECT, "--pose", pose, "--width", "128", "--height",
                        "64", "--layers", "3", "-o", str(out)], capture_output=True, text=True)
    print("\n" + r.stdout)
    assert r.returncode == 0, r.stderr
    deep = (tmp_path / "deep-deep.exr").read_bytes()
    assert deep[:4] == b"\x76\x2f\x31\x01"
    import OpenEXR

    path = tmp_path / "copy.exr"
    path.write_bytes(deep)
    f = OpenEXR.File(str(path), separate_channels=True)
    part = f.parts[0]
    assert part.header["type"] == OpenEXR.deepscanline, part.header["type"]
    z = part.channels["Z"].pixels  # (H, W) array of per-pixel sample arrays
    flat = client.render(E2E_PROJECT, v, 128, 64, formats=("exr",)).depth_m
    counts = np.array([[len(z[j][i]) if z[j][i] is not None else 0 for i in range(128)]
                       for j in range(64)])
    assert counts.max() <= 3 and counts.max() >= 2
    firsts = np.array([[z[j][i][0] if counts[j, i] else np.inf for i in range(128)]
                       for j in range(64)], dtype=np.float32)
    assert np.array_equal(firsts, flat.astype(np.float32))
    print(f"deep: {int(counts.sum())} samples, {np.bincount(counts.ravel()).tolist()} pixels with "
          f"0..3 surfaces")


def test_cli_render_with_colour_from_the_source_images(ingested, client, server, scene_dir,
                                                       views, tmp_path):
    """§8 with ColourDetail::kSourceImages through vasld and the CLI: each novel view's colour
    comes from the cameras' images at each pixel's own point. The room's albedos are smooth, so
    one colour per vossel already resolves them: the detail render must match the truth as well
    (within 0.5 dB; tests/engine/site_render_test.cc shows its gain on sharp edges)."""
    from vasl import decode_exr

    for name in sorted(n for n in views if n.startswith("novel-")):
        v = views[name]
        pose = ",".join(str(x) for x in list(v["position"]) + list(v["quaternion"]))
        out = tmp_path / f"{name}-detail.exr"
        r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address,
                            "render", "--project", E2E_PROJECT, "--pose", pose,
                            "--width", str(v["width"]), "--height", str(v["height"]),
                            "--colour-detail", "images", "-o", str(out)],
                           capture_output=True, text=True)
        print("\n" + r.stdout)
        assert r.returncode == 0, r.stderr
        used = re.search(r"colour from (\d+) cameras' images", r.stdout)
        assert used and int(used.group(1)) >= 1, r.stdout
        ch = decode_exr(out.read_bytes())
        detail_rgb = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
        plain, truth_rgb, truth_depth = _render_view(client, scene_dir, v)
        hit = np.isfinite(plain.depth_m) & np.isfinite(truth_depth) & (plain.alpha > 0)
        assert np.array_equal(np.isfinite(ch["Z"]), np.isfinite(plain.depth_m))
        psnr_plain = _psnr(plain.rgb[hit], truth_rgb[hit])
        psnr_detail = _psnr(detail_rgb[hit], truth_rgb[hit])
        print(f"novel view {name}: PSNR {psnr_plain:.2f} dB one colour per vossel, "
              f"{psnr_detail:.2f} dB with colour from the source images")
        assert psnr_detail >= psnr_plain - 0.5
        assert psnr_detail >= 30.0


def test_large_render_streams_rows_as_they_finish(ingested, client, server, views, tmp_path):
    """§8 outputs, streamed (RenderRequest.stream_rows): the server sends each format's bytes as
    bands of rows finish, so the client writes the files while the rest is still rendered.
    The streamed files equal the gathered ones byte for byte; the EXR grows on disk from one
    progress message to the next, the first arriving while most of it is still to come; the CLI
    streams too, with progress; a client that stops reading mid-stream leaves the server
    serving."""
    import grpc
    from vasl import Pose
    from vasl._proto import vasl_pb2 as pb
    from vasl.client import pose_to_pb

    v = views["novel-1"]
    w, h = 1024, 512
    whole = client.render(E2E_PROJECT, v, w, h, formats=("exr", "png", "deep"), layers=2,
                          decode=False)
    files = {f: str(tmp_path / f"streamed-{f}.bin") for f in ("exr", "png", "deep")}
    seen = []  # (rows_done, bytes of the EXR on disk so far)

    def progress(done, total):
        assert total == h
        part = files["exr"] + ".part"
        seen.append((done, os.path.getsize(part) if os.path.exists(part) else 0))

    streamed = client.render(E2E_PROJECT, v, w, h, formats=("exr", "png", "deep"), layers=2,
                             decode=False, stream_rows=True, files=files, on_progress=progress)
    assert streamed.exr is None and streamed.render_id > whole.render_id > 0
    for fmt, data in (("exr", whole.exr), ("png", whole.png), ("deep", whole.deep_exr)):
        assert open(files[fmt], "rb").read() == data, f"the streamed {fmt} differs"
    assert not any(os.path.exists(p + ".part") for p in files.values())
    done = [d for d, _ in seen]
    # At least 3 messages: how many depends on the machine, since the bands that finish while
    # one is encoded are handed on together; the EXR's 512 rows go out 64 at a time on 2 cores
    # (32 rows per thread of OpenEXR's pool), and 4 runs of this test there gave 4 or 5 messages.
    # That the first comes while most of the file is still to come is asserted below.
    assert done == sorted(done) and done[-1] == h and len(done) >= 3, done
    sizes = [size for _, size in seen]
    print(f"\nstreamed {w}x{h} (exr {len(whole.exr)} B, png {len(whole.png)} B, deep "
          f"{len(whole.deep_exr)} B): progress at rows {done}, EXR on disk then "
          f"{[round(100.0 * s / len(whole.exr)) for s in sizes]}%; render "
          f"{streamed.render_seconds:.2f} s, of it encoding {streamed.encode_seconds:.2f} s; "
          f"same bytes as gathered")
    assert all(a < b for a, b in zip(sizes, sizes[1:])), sizes
    assert sizes[0] < 0.5 * len(whole.exr)

    pose = ",".join(str(x) for x in list(v["position"]) + list(v["quaternion"]))
    out = tmp_path / "cli.exr"
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "render",
                        "--project", E2E_PROJECT, "--pose", pose, "--width", str(w), "--height",
                        str(h), "--progress", "-o", str(out)], capture_output=True, text=True)
    print(r.stdout + r.stderr)
    assert r.returncode == 0, r.stderr
    rows = [int(m) for m in re.findall(r"rows (\d+)/%d rendered and sent" % h, r.stderr)]
    assert len(rows) >= 3 and rows[-1] == h, r.stderr
    assert out.read_bytes() == whole.exr and (tmp_path / "cli.png").read_bytes() == whole.png

    request = pb.RenderRequest(project=E2E_PROJECT, width_px=2048, height_px=1024,
                               pose=pose_to_pb(Pose.parse(v)), stream_rows=True,
                               formats=[pb.IMAGE_FORMAT_EXR])
    call = client.stub.Render(request, timeout=60)
    first = [next(call) for _ in range(3)]
    assert first[0].HasField("metadata") and first[0].metadata.width_px == 2048
    call.cancel()
    with pytest.raises(grpc.RpcError):
        for _ in call:
            pass
    again = client.render(E2E_PROJECT, v, 64, 32, formats=("exr",))
    assert again.depth_m.shape == (32, 64)
