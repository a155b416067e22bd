"""The `vasl` command line: a thin layer over vasl.Client.

Exit status: 0 on success, 1 when the server reports an error (printed as CODE: message),
2 for bad arguments or unreadable input files.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from typing import List, Optional

from .client import DEFAULT_SERVER, Client, VaslError
from .readers import (is_ascii_cloud, is_las, is_pcd, is_ptx, read_ascii_cloud, read_e57,
                      read_las, read_manifest, read_pcd, read_ptx)
from .types import CONFIDENCE_FACTORS
from .types import Pose


def _print_project(p) -> None:
    print(f"project {p.name}")
    print(f"  vossel_size_m  {p.vossel_size_m:g}")
    print(f"  head_version   {p.head_version}")
    print(f"  scans          {p.scan_count}")
    print(f"  vossels        {p.vossel_count}")
    print(f"  records        {p.record_count}")
    print(f"  created_utc    {p.created_utc}")
    print("  origin_m       " + (",".join(f"{v:.3f}" for v in p.origin_m) if p.origin_m
                                 else "not fixed yet (the first scan fixes it)"))
    if p.description:
        print(f"  description    {p.description}")


def _cmd_project(client: Client, args) -> int:
    if args.project_cmd == "create":
        origin = None
        if args.origin:
            try:
                origin = [float(x) for x in args.origin.split(",")]
            except ValueError:
                origin = []
            if len(origin) != 3:
                raise ValueError(f"--origin takes X,Y,Z in world metres, got {args.origin!r}")
        p = client.create_project(args.name, vossel_size_m=args.vossel_size,
                                  description=args.description, origin_m=origin)
        print(f"created project {p.name} (vossel {p.vossel_size_m:g} m" +
              (f", origin {','.join(f'{v:.3f}' for v in p.origin_m)})" if p.origin_m else ")"))
        return 0
    if args.project_cmd == "get":
        _print_project(client.get_project(args.name))
        return 0
    projects = client.list_projects()
    if not projects:
        print("no projects")
        return 0
    print(f"{'NAME':<24} {'VOSSEL_M':>8} {'VERSION':>7} {'SCANS':>5} {'VOSSELS':>10} {'RECORDS':>11}")
    for p in projects:
        if p.problem:
            print(f"{p.name:<24} DAMAGED: {p.problem}")
            continue
        print(f"{p.name:<24} {p.vossel_size_m:>8g} {p.head_version:>7} {p.scan_count:>5} "
              f"{p.vossel_count:>10} {p.record_count:>11}")
    return 0


class _Progress:
    """tqdm bars for one change: the upload (bytes, with the points sent, MB/s and the time
    left), then each of the server's stages (percent). Bars show on a terminal only (tqdm's
    disable=None): a log gets the summary lines alone, not a stream of redrawn bars."""

    def __init__(self, label: str):
        self.label = label
        self.stage = None
        self.bar = None

    def _open(self, stage: str, **kwargs) -> None:
        from tqdm import tqdm  # imported here: only progress displays need it

        self.done()
        self.stage = stage
        self.bar = tqdm(desc=f"{self.label}: {stage}", file=sys.stderr, disable=None,
                        leave=False, mininterval=0.2, dynamic_ncols=True, **kwargs)

    def __call__(self, p: dict) -> None:
        if p["stage"] == "upload":
            if self.stage != "upload":
                self._open("upload", total=max(1, p["total_bytes"]), unit="B", unit_scale=True,
                           unit_divisor=1000)
            if "sent_points" in p:
                self.bar.set_postfix_str(f"{p['sent_points']:,}/{p['total_points']:,} points",
                                         refresh=False)
            self.bar.update(p["sent_bytes"] - self.bar.n)
            return
        if p["stage"] != self.stage:
            self._open(p["stage"], total=100,
                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}")
        self.bar.update(int(round(100 * p["fraction"])) - self.bar.n)

    def done(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.bar = None
        self.stage = None


def _ingest_summary(r, seconds: float) -> str:
    """One line per ingested scan: what was sent, how fast, and what the server made of it."""
    rate = r.sent_bytes / 1e6 / r.upload_seconds if r.upload_seconds > 0 else 0.0
    stages = ", ".join(f"{k} {v:.2f}s" for k, v in r.stages.items())
    return (f"{r.scan}: version {r.version}, {r.point_count} points, "
            f"{r.sent_bytes / 1e6:.1f} MB sent in {r.upload_seconds:.1f} s ({rate:.1f} MB/s), "
            f"{r.new_vossels} new vossels, {r.vossel_count} vossels, {r.record_count} records, "
            f"{seconds:.1f} s in all, server {r.total_seconds:.1f} s"
            + (f" ({stages})" if stages else ""))


def _cmd_ingest(client: Client, args) -> int:
    # Read and validate every input before sending any: manifests, E57 files (each of whose
    # scans is ingested with its spherical and pinhole images; images of no scan make a
    # camera-only scan), PTX files (every scan, each with its scanner's pose), PCD files (the
    # scanner at the file's VIEWPOINT, or where --pose places it), and LAS/LAZ files and ASCII
    # point clouds (world coordinates: --pose places the scanner). The points themselves are
    # read as they are sent, chunk by chunk.
    pose = Pose.parse(args.pose) if args.pose else None
    las = [p for p in args.manifest if is_las(p) or is_ascii_cloud(p) or is_pcd(p)]
    if pose is not None and len(las) > 1:
        raise ValueError(f"--pose places one scanner, but {len(las)} LAS/LAZ, PCD or ASCII "
                         "point cloud files were given: ingest them one at a time, or give "
                         "each a manifest with its pose")
    e57 = [p for p in args.manifest if p.lower().endswith(".e57")]
    if pose is not None and not las and len(e57) > 1:
        raise ValueError(f"--pose places one scanner, but {len(e57)} E57 files were given")
    pose_used = False
    jobs = []

    def points_job(name: str, points, scan_pose, rig: str):
        """The ingest of one point file's scan, run when its turn comes."""
        return (name, lambda bar: client.ingest(
            args.project, scan=name, points=points, pose=scan_pose,
            divergence_rad=args.divergence_rad, rig=rig, progress=bar,
            request_id=args.request_id))

    for path in args.manifest:
        if path.lower().endswith(".e57"):
            stored_without_pose = pose is not None and not las
            for scan in read_e57(path, pose=pose if stored_without_pose else None):
                pose_used = pose_used or stored_without_pose
                for note in scan.notes:
                    print(f"{path}: {scan.scan}: {note}")
                for im in scan.images:
                    what = f"{path}: {scan.scan}: image '{im.name}' ({im.kind})"
                    if im.problem:
                        print(f"{what}: not ingested: {im.problem}")
                    elif im.kind == "visual":
                        print(f"{what}: kept with the scan as a visual reference")
                    elif im.mask:
                        print(f"{what}: its imageMask is sent as its mask")
                    if im.notes and not im.problem:
                        print(f"{what}: {'; '.join(im.notes)}")
                cameras = [im for im in scan.ingestible_images if im.kind != "visual"]
                if scan.points is None and not cameras:
                    print(f"{path}: {scan.scan}: no points and no camera image that can be "
                          "ingested (visual references alone colour nothing); skipped")
                    continue
                jobs.append((scan.scan, lambda bar, s=scan, p=path: client.ingest_e57_scan(
                    args.project, s, divergence_rad=args.divergence_rad,
                    rig=f"e57:{os.path.basename(p)}", progress=bar,
                    request_id=args.request_id)))
        elif is_ptx(path):  # every scan of the file, each with its own scanner pose
            for scan in read_ptx(path):
                for note in scan.notes:
                    print(f"{path}: {scan.scan}: {note}")
                jobs.append(points_job(scan.scan, scan.points, scan.pose,
                                       f"ptx:{os.path.basename(path)}"))
        elif is_pcd(path):  # the scanner at its VIEWPOINT, or where --pose places it
            scan = read_pcd(path, pose)
            pose_used = pose_used or pose is not None
            for note in scan.notes:
                print(f"{path}: {note}")
            jobs.append(points_job(scan.scan, scan.points, scan.pose,
                                   f"pcd:{os.path.basename(path)}"))
        elif path.lower().endswith(".ply"):
            raise ValueError(f"{path}: a PLY file records no scanner pose: name it in a scan "
                             "manifest's lidar.points, whose pose places the scanner (README, "
                             "\"Scan manifest\")")
        elif is_las(path) or is_ascii_cloud(path):
            points = read_las(path, pose) if is_las(path) else read_ascii_cloud(path, pose)
            pose_used = True
            name = os.path.splitext(os.path.basename(path))[0]
            for note in points.notes:
                print(f"{path}: {note}")
            jobs.append(points_job(name, points, points.pose,
                                   f"{'las' if is_las(path) else 'ascii'}:"
                                   f"{os.path.basename(path)}"))
        else:
            m = read_manifest(path)
            jobs.append((m.scan, lambda bar, m=m: client.ingest(args.project, m, progress=bar,
                                                                request_id=args.request_id)))
    if pose is not None and not pose_used:
        raise ValueError("--pose is for LAS/LAZ and PCD files, ASCII point clouds and E57 "
                         "scans stored without a pose; a manifest gives its scan's pose itself")
    if args.request_id and len(jobs) != 1:
        raise ValueError(f"--request-id names one change, but {len(jobs)} scans were given")
    existing = set()
    if args.skip_existing:
        existing = {s.name for s in client.list_scans(args.project)}
    for scan, run in jobs:
        if scan in existing:
            print(f"{scan}: already in project {args.project}, skipped")
            continue
        bar = _Progress(scan) if not args.quiet else None
        t0 = time.monotonic()
        try:
            r = run(bar)
        finally:
            if bar:
                bar.done()
        if r.replayed:
            print(f"{r.scan}: already committed in version {r.version} under request "
                  f"{r.request_id}; not ingested again")
            continue
        print(_ingest_summary(r, time.monotonic() - t0), flush=True)
        for c in r.calibration:
            print(f"  {c.summary()}", flush=True)
    return 0


def _cmd_operation(client: Client, args) -> int:
    op = (client.wait_operation(args.project, args.request_id) if args.wait
          else client.get_operation(args.project, args.request_id))
    if args.json:
        def plain(v):
            return v.__dict__ if hasattr(v, "__dict__") else v
        print(json.dumps({k: plain(v) for k, v in op.items()}, indent=2, default=plain))
        return 0
    what = f"{op['kind']} {op['subject']}".strip()
    if op["state"] == "running":
        print(f"{args.request_id}: {what} running, stage {op['stage']} "
              f"({op['fraction'] * 100:.0f}%), {op['elapsed_s']:.1f} s")
    elif op["state"] == "succeeded":
        print(f"{args.request_id}: {what} committed in version {op['version']}")
    else:
        print(f"{args.request_id}: {what} failed: {op['error_message']} (nothing was stored; "
              f"send it again)")
    return 0 if op["state"] != "failed" else 1


def _cmd_render(client: Client, args) -> int:
    pose = Pose.parse(args.pose)
    out = args.output
    if not out.lower().endswith(".exr"):
        raise ValueError(f"-o must name an .exr file, got {out}")
    pinhole = _parse_pinhole(args.pinhole, args.fisheye)
    png = out[:-4] + ".png"
    deep = out[:-4] + "-deep.exr"
    files = {"exr": out, "png": png}
    if args.layers > 1:
        files["deep"] = deep
    shown = [0]

    def progress(done: int, total: int) -> None:  # about every tenth of the rows
        if done == total or done - shown[0] >= max(1, total // 10):
            shown[0] = done
            print(f"rows {done}/{total} rendered and sent", file=sys.stderr, flush=True)

    # The files stream in as bands of rows finish: no render size is held in memory here.
    r = client.render(args.project, pose, args.width, args.height, version=args.version,
                      formats=tuple(files), eta=args.eta, decode=False, profile=args.profile,
                      pinhole=pinhole, layers=args.layers, colour_detail=args.colour_detail,
                      stream_rows=True, files=files,
                      on_progress=progress if args.progress else None)
    if "deep" in files:
        print(f"wrote {deep} (deep: up to {args.layers} surfaces per pixel, R,G,B,A,Z)")
    total = r.width_px * r.height_px
    projection = ("equirect" if pinhole is None
                  else "fisheye" if pinhole.get("lens") == "fisheye" else "pinhole")
    print(f"render {r.render_id}: {projection} "
          f"{r.width_px}x{r.height_px} from version {r.version}: "
          f"{r.hit_pixels}/{total} pixels hit ({100.0 * r.hit_pixels / max(1, total):.1f}%), "
          f"{r.render_seconds:.2f} s ({r.encode_seconds:.2f} s of it encoding), "
          f"profile {r.profile} revision {r.profile_revision}"
          + (" (fused for this render: run vasl reweight to store it)" if r.fused_on_the_fly else "")
          + (f"; read {r.tiles_read} of {r.tiles_total} tiles in {r.tile_groups} groups (the "
             f"version exceeds the server's --max-snapshot-bytes)" if r.tiles_total else ""))
    if args.colour_detail == "images":
        print(f"colour from {r.detail_sources} cameras' images"
              + (f"; {r.detail_sources_skipped} more left out (their images exceed the server's "
                 f"budget) keep their records' colour" if r.detail_sources_skipped else ""))
    if r.colourless_pixels:
        print(f"{r.colourless_pixels} hit pixels show vossels without colour: alpha 0 and U = inf "
              f"in the EXR, transparent grey in the PNG")
    print(f"wrote {out} (R,G,B,Z,N.x,N.y,N.z,U,A float) and {png} (RGBA)")
    return 0


def _cmd_scans(client: Client, args) -> int:
    scans = client.list_scans(args.project)
    if args.json:
        print(json.dumps([{"id": s.id, "name": s.name, "rig": s.rig, "version": s.version,
                           "captured_utc": s.captured_utc,
                           "position_m": list(s.pose.position_m),
                           "sources": [src.name for src in s.sources],
                           "masks": {src.name: src.mask_sha256 for src in s.sources
                                     if src.mask_sha256},
                           "calibration": [src.calibration.__dict__ for src in s.sources
                                           if src.calibration],
                           "visual_references": [
                               {"name": r.name, "width_px": r.width_px,
                                "height_px": r.height_px, "size_bytes": r.size_bytes,
                                "blob_sha256": r.blob_sha256,
                                "position_m": list(r.pose.position_m)}
                               for r in s.visual_references]} for s in scans], indent=2))
        return 0
    if not scans:
        print(f"no scans in project {args.project}")
        return 0
    print(f"{'ID':>4} {'NAME':<20} {'VERSION':>7} {'POINTS':>10}  {'POSITION_M':<26} SOURCES")
    for s in scans:
        points = sum(src.point_count for src in s.sources)
        pos = ",".join(f"{v:.3f}" for v in s.pose.position_m)
        sources = " ".join(
            src.name + "(" + ", ".join([src.modality] + ([src.kind] if src.kind else [])
                                       + (["masked"] if src.mask_sha256 else [])) + ")"
            for src in s.sources)
        print(f"{s.id:>4} {s.name:<20} {s.version:>7} {points:>10}  {pos:<26} {sources}")
        for src in s.sources:
            if src.calibration:
                print(f"       {src.calibration.summary()}")
        for ref in s.visual_references:
            print(f"       visual reference '{ref.name}': {ref.width_px}x{ref.height_px}, "
                  f"{ref.size_bytes} bytes (vasl reference --project {args.project} "
                  f"--scan {s.name} --name '{ref.name}' -o FILE)")
    return 0


def _cmd_reference(client: Client, args) -> int:
    ref, data = client.get_visual_reference(args.project, args.scan, args.name)
    with open(args.output, "wb") as f:
        f.write(data)
    print(f"wrote {args.output}: visual reference '{ref.name}' of scan {args.scan}, "
          f"{ref.width_px}x{ref.height_px}, {len(data)} bytes")
    return 0


def _cmd_confidence(client: Client, args) -> int:
    cameras = client.scan_confidence(args.project, args.scan)
    os.makedirs(args.output, exist_ok=True)
    if not cameras:
        print(f"scan {args.scan} has no camera: no confidence maps")
    for cam in cameras:
        for a in cam.artefacts:
            path = os.path.join(args.output, f"{cam.source}-{a.artefact}.png")
            with open(path, "wb") as f:
                f.write(a.map_png)
            if a.artefact == "codec":
                found = ("not a JPEG" if not a.jpeg_quality else
                         f"JPEG quality {a.jpeg_quality:.0f}"
                         + (", chroma subsampled" if a.chroma_subsampled else "")
                         + f"; {a.soft_pixels} pixels lowered "
                         f"({100.0 * a.covered_fraction:.3f}% of the image)")
            elif a.artefact == "fringing":
                found = ("none found" if not a.channel_offsets_px else
                         "red offset ({:+.2f}, {:+.2f}) px, blue ({:+.2f}, {:+.2f}) px against "
                         "green, corrected; ".format(*a.channel_offsets_px)
                         + f"{a.soft_pixels} pixels moved by over a tenth "
                         f"({100.0 * a.covered_fraction:.3f}% of the image)")
            elif a.artefact == "smear":
                found = (f"{a.regions} columns lifted by up to {a.smear_offset:.3f} of the clip, "
                         f"{a.soft_pixels} pixels lowered "
                         f"({100.0 * a.covered_fraction:.3f}% of the image)"
                         if a.regions else "none found")
            elif a.artefact in ("dirt", "fog"):
                found = (f"{'dirt' if a.artefact == 'dirt' else 'veil'} of lens map {a.lens_map}: "
                         f"{100.0 * a.covered_fraction:.3f}% of the image lowered "
                         f"({a.flagged_pixels} pixels at 0)")
            else:
                what = "sources with a veil" if a.artefact == "flare" else "regions"
                reach = "farthest" if a.artefact == "flare" else "widest band"
                found = (f"{a.regions} {what}, {100.0 * a.covered_fraction:.3f}% of the image "
                         f"({a.flagged_pixels} pixels at 0, {a.soft_pixels} lowered, {reach} "
                         f"{a.max_extent_px} px)") if a.covered_fraction > 0 else "none found"
            print(f"{cam.source} ({cam.width_px}x{cam.height_px}) {a.artefact}: {found}; "
                  f"wrote {path}")
    return 0


def _cmd_inspect(client: Client, args) -> int:
    r = client.inspect_records(args.project, args.version)
    if args.json:
        print(json.dumps({"project": r.project, "version": r.version, "tile_count": r.tile_count,
                          "record_count": r.record_count,
                          "attributes": [a.__dict__ for a in r.attributes]}, indent=2))
        return 0
    print(f"project {r.project} version {r.version}: {r.record_count} records in {r.tile_count} tiles")
    print(f"{'ATTRIBUTE':<16} {'TYPE':<10} {'CODEC':<14} {'STRIDE':>6}")
    for a in r.attributes:
        print(f"{a.name:<16} {a.type:<10} {a.codec:<14} {a.stride:>6}")
    for a in r.attributes:
        if a.name == "conf":  # the factors, in the order the proto gives them (VASL-MODEL §9)
            known = CONFIDENCE_FACTORS[:a.stride]
            print(f"conf factors: {', '.join(known)}"
                  + ("" if a.stride >= len(CONFIDENCE_FACTORS) else
                     f" (written before {', '.join(CONFIDENCE_FACTORS[a.stride:])} had factors "
                     "of their own: they read as 1)"))
    return 0


def _print_change(what: str, r) -> None:
    c = r.change
    print(f"{what}: version {r.version}, {r.vossel_count} vossels, {r.record_count} records, "
          f"{r.seconds:.2f} s; {c.sources_computed} sources computed, {c.sources_revisited} "
          f"revisited on {c.pairs_revisited} (source, tile) pairs, {c.vossels_revisited} "
          f"(source, vossel) pairs ({c.sources_refreshed} refreshed from their own records); "
          f"{c.tiles_changed} tiles, "
          f"{c.bytes_written / 1e6:.1f} MB written")


def _cmd_rebuild(client: Client, args) -> int:
    _print_change(f"rebuilt {args.project}", client.rebuild(args.project))
    return 0


def _cmd_scan(client: Client, args) -> int:
    _print_change(f"deleted scan {args.scan} from {args.project}",
                  client.delete_scan(args.project, args.scan))
    return 0


def _cmd_versions(client: Client, args) -> int:
    versions = client.list_versions(args.project)
    if args.json:
        print(json.dumps([v.__dict__ for v in versions], indent=2))
        return 0
    print(f"{'VERSION':>7} {'TILES':>5} {'VOSSELS':>9} {'RECORDS':>10} {'WRITTEN_MB':>10} "
          f"{'TOTAL_MB':>9} {'PIN':>3}  MADE_BY")
    for v in versions:
        print(f"{v.version:>7} {v.tile_count:>5} {v.vossel_count:>9} {v.record_count:>10} "
              f"{v.bytes_written / 1e6:>10.1f} {v.bytes_total / 1e6:>9.1f} "
              f"{'yes' if v.pinned else '':>3}  {v.made_by}")
    return 0


def _cmd_export(client: Client, args) -> int:
    r = client.export(args.project, args.output, args.version)
    print(f"exported {args.project} version {r.version}: {r.record_count} records, "
          f"{r.vossel_count} vossels, {r.size_bytes / 1e6:.1f} MB -> {r.path}")
    return 0


def _read_profile_file(path: str) -> dict:
    """A profile from a .json or .toml file (a table of parameters, VASL-MODEL §7)."""
    with open(path, "rb") as f:
        data = f.read()
    if path.lower().endswith(".toml"):
        import tomllib
        try:
            return tomllib.loads(data.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{path}: not a TOML profile: {e}") from None
    try:
        return json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a JSON profile: {e}") from None


def _parse_setting(text: str):
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise ValueError(f"--set takes KEY=VALUE, got {text!r}")
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value.strip()


def _print_profile(p: dict, active: bool = False) -> None:
    print(f"profile {p['name']} revision {p['revision']}" + ("  (active)" if active else ""))
    for key in ("alpha", "beta", "rho", "v_min", "lambda_src", "theta_max_rad", "proximity_m", "mode"):
        print(f"  {key:<14} {p[key]}")
    print("  kappa          " + ", ".join(f"{k} {v:g}" for k, v in p["kappa"].items()))
    for source, g in p["scan_gain"].items():
        print(f"  scan_gain      source {source}: {g:g}")
    for source, gains in p["channel_gain"].items():
        print(f"  channel_gain   source {source}: " + ", ".join(f"{g:.4f}" for g in gains))
    if p["created_utc"]:
        print(f"  created_utc    {p['created_utc']}")


def _cmd_profile(client: Client, args) -> int:
    if args.profile_cmd == "create":
        profile = _read_profile_file(args.file) if args.file else {}
        for text in args.set or []:
            key, value = _parse_setting(text)
            profile[key] = value
        if "name" in profile and profile["name"] != args.name:
            raise ValueError(f"the file names profile {profile['name']!r}, the command {args.name!r}")
        profile["name"] = args.name
        p = client.create_profile(args.project, profile, activate=args.activate)
        print(f"created profile {p['name']} revision {p['revision']}"
              + (" (active)" if args.activate else ""))
        return 0
    if args.profile_cmd == "activate":
        p = client.set_active_profile(args.project, args.name)
        print(f"active profile of {args.project}: {p['name']} (revision {p['revision']})")
        return 0
    if args.profile_cmd == "show":
        p = client.get_profile(args.project, args.name or "", args.revision)
        if args.json:
            print(json.dumps(p, indent=2))
        else:
            _print_profile(p)
        return 0
    profiles, active = client.list_profiles(args.project)
    if args.json:
        print(json.dumps({"active": active, "profiles": profiles}, indent=2))
        return 0
    print(f"{'NAME':<24} {'REV':>4} {'ALPHA':>6} {'BETA':>6} {'RHO':>6} {'V_MIN':>6} {'MODE':<8} "
          f"{'GAINS':>5}  CREATED")
    for p in profiles:
        mark = "*" if p["name"] == active else " "
        print(f"{mark}{p['name']:<23} {p['revision']:>4} {p['alpha']:>6g} {p['beta']:>6g} "
              f"{p['rho']:>6g} {p['v_min']:>6g} {p['mode']:<8} {len(p['channel_gain']):>5}  "
              f"{p['created_utc']}")
    return 0


def _cmd_reweight(client: Client, args) -> int:
    bar = _Progress(f"reweight {args.project}") if not args.quiet else None
    try:
        r = client.reweight(args.project, args.profile or "", args.revision, progress=bar,
                            request_id=args.request_id)
    finally:
        if bar:
            bar.done()
    if r.replayed:
        print(f"{args.project}: version {r.version} was made under request id {r.request_id}; "
              "not done again")
        return 0
    if r.unchanged:
        print(f"{args.project}: version {r.version} already holds fused tiles under "
              f"{r.profile} revision {r.revision}")
        return 0
    rate = r.record_count / r.seconds / 1e6 if r.seconds > 0 else 0.0
    print(f"reweighted {args.project} under {r.profile} revision {r.revision}: version "
          f"{r.version}, {r.record_count} records in {r.tile_count} tiles, {r.seconds:.2f} s "
          f"({rate:.1f} M records/s), {r.bytes_written / 1e6:.1f} MB written")
    return 0


def _cmd_lens(client: Client, args) -> int:
    if args.lens_cmd == "list":
        maps = client.list_lens_maps(args.project, summary=not args.json)
        if args.json:
            print(json.dumps([dataclasses.asdict(m) for m in maps], indent=2))
            return 0
        if not maps:
            print(f"project {args.project} has no lens map yet: vasl lens estimate --project "
                  f"{args.project} --rig RIG")
        for m in maps:
            print(f"lens map {m.id}: rig {m.rig}, camera {m.camera} ({m.image_width_px}x"
                  f"{m.image_height_px}, {m.grid_width}x{m.grid_height} cells), {m.period}; "
                  f"dirt on {100.0 * m.dirt_share:.2f}% of the cells, veil on "
                  f"{100.0 * m.veil_share:.2f}%; sources {sorted(m.source_gain)}; "
                  f"made {m.created_utc}")
        return 0
    r = client.estimate_lens(args.project, args.rig, camera=args.camera, from_utc=args.since,
                             to_utc=args.until, base_profile=args.profile, name=args.name,
                             cell_px=args.cell_px)
    m, p = r.map, r.profile
    print(f"lens map {m.id} of rig {m.rig}, camera {m.camera}: {m.period}; {r.samples} records "
          f"compared, {r.cells_fitted} of {r.cells} cells of {r.cell_px:.1f} px fitted")
    print(f"  dirt on {100.0 * m.dirt_share:.2f}% of the cells, veil on "
          f"{100.0 * m.veil_share:.2f}%; RMS log residual {r.residual_before:.4f} -> "
          f"{r.residual_after:.4f}")
    for source, g in sorted(m.source_gain.items()):
        print(f"  source {source}: exposure gain " + ", ".join(f"{x:.4f}" for x in g))
    if r.replaced_map:
        print(f"  replaces lens map {r.replaced_map} in the profile")
    print(f"profile {p['name']} revision {p['revision']} applies lens maps {p['lens_maps']}")
    if not args.reweight:
        print(f"apply it: vasl reweight --project {args.project} --profile {p['name']}")
        return 0
    args.revision = p["revision"]
    args.profile = p["name"]
    args.request_id = None
    return _cmd_reweight(client, args)


def _cmd_normalise(client: Client, args) -> int:
    r = client.normalise(args.project, args.profile or "", args.name or "")
    p = r.profile
    print(f"normalised {args.project}: profile {p['name']} revision {p['revision']} holds gains "
          f"of {len(p['channel_gain'])} sources ({r.vossels_used} shared vossels)")
    for c, name in enumerate("RGB"):
        print(f"  {name}: disagreement {r.cost_before[c]:.4g} -> {r.cost_after[c]:.4g}")
    for source, gains in p["channel_gain"].items():
        print(f"  source {source}: " + ", ".join(f"{g:.4f}" for g in gains))
    if r.unlinked_sources:
        print(f"  sources sharing too little with the others (gain 1): {r.unlinked_sources}")
    print(f"apply it: vasl reweight --project {args.project} --profile {p['name']}")
    return 0


def _cmd_records(client: Client, args) -> int:
    def numbers(text, n, what):
        try:
            v = [float(x) for x in text.split(",")]
        except ValueError:
            v = []
        if len(v) != n:
            raise ValueError(f"--{what} takes {n} comma-separated numbers, got {text!r}")
        return v
    at = numbers(args.at, 3, "at") if args.at else None
    box = numbers(args.box, 6, "box") if args.box else None
    r = client.query_records(args.project, at=at, box=box, profile=args.profile or "",
                             version=args.version, limit=args.limit)
    if args.json:
        print(json.dumps(r.__dict__, indent=2))
        return 0
    print(f"{len(r.records)} records on {r.vossel_count} vossels, weights under {r.profile} "
          f"revision {r.revision}" + (" (truncated: raise --limit)" if r.truncated else ""))
    print(f"{'K':<16} {'SCAN':<14} {'SOURCE':<12} {'MOD':<7} {'VALUE':<20} {'RANGE':>7} {'COS':>5} "
          f"{'VIS':>5} {'BATCH':>5} {'FLAGS':>5} {'WEIGHT':>9}")
    for x in r.records:
        value = ",".join(f"{v:.3f}" for v in x["value"])
        print(f"{','.join(map(str, x['k'])):<16} {x['scan']:<14} {x['source_name']:<12} "
              f"{x['modality']:<7} {value:<20} {x['range_m']:>7.3f} {x['cos_inc']:>5.2f} "
              f"{x['vis']:>5.2f} {x['batch']:>5} {x['flags']:>5} {x['weight']:>9.4g}")
    return 0


def _cmd_rollback(client: Client, args) -> int:
    _print_change(f"rolled {args.project} back to version {args.version}",
                  client.rollback(args.project, args.version))
    return 0


def _parse_pinhole(text, fisheye=None):
    """--pinhole fx,fy,cx,cy[,k1,k2,k3,p1,p2] or --fisheye fx,fy,cx,cy[,k1,k2,k3,k4[,fov]] as
    the client's pinhole dict; None for neither."""
    if text and fisheye:
        raise ValueError("--pinhole and --fisheye name one camera: give one of them")
    if not text and not fisheye:
        return None
    try:
        v = [float(x) for x in (text or fisheye).split(",")]
    except ValueError:
        v = []
    if len(v) not in ((4, 8, 9) if fisheye else (4, 9)):
        raise ValueError("--fisheye takes fx,fy,cx,cy, fx,fy,cx,cy,k1,k2,k3,k4 or those and the "
                         "field of view in degrees (pixels)" if fisheye else
                         "--pinhole takes fx,fy,cx,cy or fx,fy,cx,cy,k1,k2,k3,p1,p2 (pixels)")
    if fisheye:
        return {"lens": "fisheye", **dict(zip(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2",
                                               "k3", "k4", "field_of_view_deg"), v))}
    return dict(zip(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2"), v))


def _cmd_backproject(client: Client, args) -> int:
    r = client.back_project(args.project, args.image, Pose.parse(args.pose), name=args.name,
                            pinhole=_parse_pinhole(args.pinhole, args.fisheye),
                            render_id=args.render)
    print(f"back-projected {args.image} as batch {r['name']}: version {r['version']}, "
          f"{r['pixels_back_projected']} pixels -> derived records, {r['pixels_outside']} "
          f"pixels outside the lattice, {r['record_count']} records, {r['seconds']:.2f} s")
    if r["pixels_invalid"]:
        print(f"warning: {r['pixels_invalid']} pixels with a depth have a NaN or infinite colour "
              "and were left out", file=sys.stderr)
    return 0


def _cmd_batch(client: Client, args) -> int:
    if args.batch_cmd == "rollback":
        _print_change(f"rolled back batch {args.name} of {args.project}",
                      client.delete_scan(args.project, args.name))
        return 0
    batches = [s for s in client.list_scans(args.project)
               if any(src.modality == "derived" for src in s.sources)]
    if args.json:
        print(json.dumps([{"name": s.name, "batch": s.batch, "version": s.version,
                           "created_utc": s.created_utc} for s in batches], indent=2))
        return 0
    if not batches:
        print(f"no derived batches in project {args.project}")
        return 0
    print(f"{'NAME':<24} {'BATCH':>5} {'VERSION':>7}  CREATED")
    for s in batches:
        print(f"{s.name:<24} {s.batch:>5} {s.version:>7}  {s.created_utc}")
    return 0


def _cmd_pin(client: Client, args) -> int:
    v = client.pin_version(args.project, args.version, not args.unpin)
    print(f"version {v.version} of {args.project} is {'pinned' if v.pinned else 'not pinned'}")
    return 0


def _cmd_token(client: Client, args) -> int:
    if args.token_cmd == "create":
        t = client.create_token(args.project, args.role, args.label)
        if args.output:
            fd = os.open(args.output, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(t["token"] + "\n")
            print(f"token {t['id']} ({t['role']} on {t['project']}) written to {args.output}")
        else:
            print(f"token {t['id']} ({t['role']} on {t['project']}); keep it secret, it is not "
                  f"shown again:\n{t['token']}")
        return 0
    if args.token_cmd == "revoke":
        t = client.revoke_token(args.id)
        print(f"token {t['id']} ({t['role']} on {t['project']}) revoked at {t['revoked_utc']}")
        return 0
    tokens = client.list_tokens(args.project)
    if args.json:
        print(json.dumps(tokens, indent=2))
        return 0
    if not tokens:
        print("no tokens")
        return 0
    print(f"{'ID':<13} {'PROJECT':<20} {'ROLE':<6} {'CREATED':<21} {'REVOKED':<21} LABEL")
    for t in tokens:
        print(f"{t['id']:<13} {t['project']:<20} {t['role']:<6} {t['created_utc']:<21} "
              f"{t['revoked_utc'] or '-':<21} {t['label']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vasl", description="Client of the vasld server.")
    parser.add_argument("--server", default=os.environ.get("VASL_SERVER", DEFAULT_SERVER),
                        help="HOST:PORT of vasld (default: $VASL_SERVER or %(default)s)")
    parser.add_argument("--timeout", type=float, default=None, help="RPC deadline, seconds")
    parser.add_argument("--token-file", default=None,
                        help="file whose first line is the bearer token (default: $VASL_TOKEN, "
                             "or the file $VASL_TOKEN_FILE)")
    parser.add_argument("--tls-ca", default=None,
                        help="PEM CA of the server's certificate: connect with TLS "
                             "(default: $VASL_TLS_CA)")
    parser.add_argument("--tls-cert", default=None,
                        help="PEM client certificate for mutual TLS (default: $VASL_TLS_CERT)")
    parser.add_argument("--tls-key", default=None,
                        help="PEM key of --tls-cert (default: $VASL_TLS_KEY)")
    sub = parser.add_subparsers(dest="cmd", required=True)

    token = sub.add_parser("token", help="access tokens: create, list, revoke")
    tsub = token.add_subparsers(dest="token_cmd", required=True)
    tcreate = tsub.add_parser("create", help="a new token; its secret is printed once")
    tcreate.add_argument("--project", required=True, help="project name, or '*' for every one")
    tcreate.add_argument("--role", required=True, choices=["read", "write", "admin"])
    tcreate.add_argument("--label", default="", help="who holds it, what for")
    tcreate.add_argument("-o", "--output", default=None, metavar="FILE",
                         help="write the token to FILE (mode 600) instead of printing it")
    tlist = tsub.add_parser("list", help="list the tokens you administer")
    tlist.add_argument("--project", default="", help="only this project's tokens")
    tlist.add_argument("--json", action="store_true")
    trevoke = tsub.add_parser("revoke", help="revoke a token at once")
    trevoke.add_argument("id", help="the token's id (see `vasl token list`)")

    project = sub.add_parser("project", help="create, list or show projects")
    psub = project.add_subparsers(dest="project_cmd", required=True)
    create = psub.add_parser("create", help="create an empty project")
    create.add_argument("name")
    create.add_argument("--vossel-size", type=float, default=0.02, metavar="M",
                        help="vossel edge in metres (default 0.02)")
    create.add_argument("--description", default="")
    create.add_argument("--origin", metavar="X,Y,Z",
                        help="the project's origin in world metres (a georeferenced site's "
                             "frame, e.g. UTM); default: the first scan's position rounded to "
                             "the kilometre")
    psub.add_parser("list", help="list projects")
    get = psub.add_parser("get", help="show a project")
    get.add_argument("name")

    ingest = sub.add_parser("ingest", help="ingest scans: manifest, E57, PTX, PCD, LAS/LAZ or "
                                           "ASCII point cloud files")
    ingest.add_argument("manifest", nargs="+",
                        metavar="MANIFEST.json|SCAN.e57|SCAN.ptx|SCAN.pcd|SCAN.las|SCAN.laz|"
                                "SCAN.pts",
                        help="scan manifest JSON file(s), E57 and PTX files (every scan of the "
                             "file is ingested as a LiDAR scan named after the file, -<n> when "
                             "it holds several), PCD files (one scan named after the file, its "
                             "scanner at the file's VIEWPOINT) and/or a LAS/LAZ file or an "
                             "ASCII point cloud (.pts, .xyz, .txt, .asc, .csv: x y z "
                             "[intensity] [r g b] a line) in world coordinates (one scan named "
                             "after the file, placed by --pose)")
    ingest.add_argument("--pose", metavar="x,y,z[,qx,qy,qz,qw]",
                        help="the scanner's pose in the points' world coordinates: required for "
                             "a LAS/LAZ file or an ASCII point cloud (neither records a scanner "
                             "position), for a PCD file stored in world coordinates, and for an "
                             "E57 file of one scan stored in world coordinates without a pose; "
                             "for a PCD file in its sensor's frame, where that sensor stood in "
                             "the project (default: the file's VIEWPOINT)")
    ingest.add_argument("--divergence-rad", type=float, default=0.0003,
                        help="LiDAR beam divergence for E57, PTX, PCD, LAS/LAZ and ASCII scans "
                             "(none of them records it)")
    ingest.add_argument("--project", required=True)
    ingest.add_argument("--skip-existing", action="store_true",
                        help="skip scans whose id is already in the project")
    ingest.add_argument("--quiet", action="store_true", help="no progress display")
    ingest.add_argument("--request-id", metavar="ID",
                        help="send the (one) scan under this id, e.g. to retry an ingest whose "
                             "answer was lost: a committed one is not ingested twice "
                             "(default: a fresh UUID per scan)")

    operation = sub.add_parser("operation", help="what became of a change sent under a request id")
    operation.add_argument("--project", required=True)
    operation.add_argument("--request-id", required=True, metavar="ID")
    operation.add_argument("--wait", action="store_true", help="wait while it runs")
    operation.add_argument("--json", action="store_true")

    render = sub.add_parser("render", help="render an equirectangular panorama to EXR + PNG")
    render.add_argument("--project", required=True)
    render.add_argument("--pose", required=True, metavar="x,y,z[,qx,qy,qz,qw]",
                        help="viewpoint position (m) and optional quaternion (x,y,z,w)")
    render.add_argument("--width", type=int, default=2048)
    render.add_argument("--height", type=int, default=1024)
    render.add_argument("--version", type=int, default=0, help="version (0: HEAD)")
    render.add_argument("--eta", type=float, default=0.0, help="view term (VASL-MODEL §8)")
    render.add_argument("--pinhole", metavar="fx,fy,cx,cy[,k1,k2,k3,p1,p2]",
                        help="a pinhole render (pixels; camera x right, y down, z forward) "
                             "instead of an equirectangular panorama")
    render.add_argument("--fisheye", metavar="fx,fy,cx,cy[,k1,k2,k3,k4[,fov]]",
                        help="a fisheye render (Kannala-Brandt, as OpenCV's cv::fisheye; "
                             "pixels, the pinhole's camera frame; fov: its field of view in "
                             "degrees, pixels beyond it empty)")
    render.add_argument("--layers", type=int, default=1, metavar="L",
                        help="also write OUT-deep.exr with up to L successive surfaces per pixel")
    render.add_argument("--colour-detail", choices=("vossel", "images"), default="vossel",
                        help="vossel: one colour per vossel; images: read each camera's image "
                             "where the pixel's own point lands (sharper, slower)")
    render.add_argument("--profile", default="",
                        help="weighting profile (default: the project's active one)")
    render.add_argument("-o", "--output", required=True, metavar="OUT.exr",
                        help="EXR output; the PNG preview is written beside it (the files "
                             "stream in as bands of rows finish)")
    render.add_argument("--progress", action="store_true",
                        help="print the rows rendered and sent as they stream in")

    scans = sub.add_parser("scans", help="list the scans of a project")
    scans.add_argument("--project", required=True)
    scans.add_argument("--json", action="store_true")

    reference = sub.add_parser("reference", help="write a scan's visual reference photo to a file")
    reference.add_argument("--project", required=True)
    reference.add_argument("--scan", required=True)
    reference.add_argument("--name", required=True, help="the reference's name (vasl scans)")
    reference.add_argument("-o", "--output", required=True, metavar="FILE")

    inspect = sub.add_parser("inspect", help="list record attributes (type, codec, stride)")
    inspect.add_argument("--project", required=True)
    inspect.add_argument("--version", type=int, default=0, help="version (0: HEAD)")
    inspect.add_argument("--json", action="store_true")

    rebuild = sub.add_parser("rebuild", help="recompute a project from its raw scans (new version)")
    rebuild.add_argument("--project", required=True)

    scan = sub.add_parser("scan", help="act on one scan of a project")
    ssub = scan.add_subparsers(dest="scan_cmd", required=True)
    delete = ssub.add_parser("delete", help="make a new version without the scan")
    delete.add_argument("scan", help="the scan id")
    delete.add_argument("--project", required=True)

    versions = sub.add_parser("versions", help="list the kept versions of a project")
    versions.add_argument("--project", required=True)
    versions.add_argument("--json", action="store_true")

    profile = sub.add_parser("profile", help="weighting profiles (VASL-MODEL §7)")
    prsub = profile.add_subparsers(dest="profile_cmd", required=True)
    pcreate = prsub.add_parser("create", help="store a new revision of a profile")
    pcreate.add_argument("name")
    pcreate.add_argument("--project", required=True)
    pcreate.add_argument("--file", metavar="PROFILE.json|.toml",
                         help="parameters: alpha, beta, rho, kappa, v_min, lambda_src, "
                              "theta_max_deg, proximity_m, mode, scan_gain, channel_gain")
    pcreate.add_argument("--set", action="append", metavar="KEY=VALUE",
                         help="one parameter (JSON value), after the file's; repeatable")
    pcreate.add_argument("--activate", action="store_true", help="make it the active profile")
    plist = prsub.add_parser("list", help="list profiles (* marks the active one)")
    plist.add_argument("--project", required=True)
    plist.add_argument("--json", action="store_true")
    pshow = prsub.add_parser("show", help="show a profile revision")
    pshow.add_argument("name", nargs="?", help="default: the active profile")
    pshow.add_argument("--project", required=True)
    pshow.add_argument("--revision", type=int, default=0, help="0: the latest")
    pshow.add_argument("--json", action="store_true")
    pact = prsub.add_parser("activate", help="make a profile the one renders and queries use")
    pact.add_argument("name")
    pact.add_argument("--project", required=True)

    reweight = sub.add_parser("reweight", help="fuse a project under a profile (new version)")
    reweight.add_argument("--project", required=True)
    reweight.add_argument("--profile", default="", help="default: the active profile")
    reweight.add_argument("--revision", type=int, default=0, help="0: the latest")
    reweight.add_argument("--quiet", action="store_true", help="no progress display")
    reweight.add_argument("--request-id", metavar="ID",
                          help="id of this change (default: a fresh UUID); a retry under the "
                               "same id is answered from the reweight that committed")

    normalise = sub.add_parser("normalise", help="solve per-scan colour gains into a profile")
    normalise.add_argument("--project", required=True)
    normalise.add_argument("--profile", default="", help="profile whose weights the solve uses")
    normalise.add_argument("--name", default="", help="profile to store the gains in")

    lens = sub.add_parser("lens", help="lens dirt and fog of a rig's camera (§9)")
    lens_sub = lens.add_subparsers(dest="lens_cmd", required=True)
    estimate = lens_sub.add_parser(
        "estimate", help="find a rig camera's dirt and fog from its frames into a profile")
    estimate.add_argument("--project", required=True)
    estimate.add_argument("--rig", required=True, help="the rig, as its scans name it")
    estimate.add_argument("--camera", default="", help="camera name (default: the rig's only one)")
    estimate.add_argument("--since", default="", metavar="ISO8601",
                          help="frames captured at or after this time")
    estimate.add_argument("--until", default="", metavar="ISO8601",
                          help="frames captured at or before (a date takes the whole day)")
    estimate.add_argument("--profile", default="",
                          help="profile whose weights the estimate uses and the new one extends")
    estimate.add_argument("--name", default="", help="profile to store (default: the base's, "
                                                      "'lens' for the default)")
    estimate.add_argument("--cell-px", type=int, default=0,
                          help="grid cell edge, pixels (0: from the samples)")
    estimate.add_argument("--reweight", action="store_true",
                          help="reweight under the new profile at once")
    estimate.add_argument("--quiet", action="store_true", help="no progress display (--reweight)")
    listing = lens_sub.add_parser("list", help="the project's lens maps")
    listing.add_argument("--project", required=True)
    listing.add_argument("--json", action="store_true", help="every map with its cells")

    recs = sub.add_parser("records", help="the records of a vossel or a box, with weights")
    recs.add_argument("--project", required=True)
    where = recs.add_mutually_exclusive_group(required=True)
    where.add_argument("--at", metavar="x,y,z", help="the vossel holding this world point")
    where.add_argument("--box", metavar="x0,y0,z0,x1,y1,z1", help="every vossel meeting the box")
    recs.add_argument("--profile", default="", help="weights under this profile (default: active)")
    recs.add_argument("--version", type=int, default=0, help="version (0: HEAD)")
    recs.add_argument("--limit", type=int, default=0, help="most records to list (0: 10000)")
    recs.add_argument("--json", action="store_true")

    bp = sub.add_parser("backproject", help="send an RGBZ EXR back as derived data (§10)")
    bp.add_argument("image", metavar="IMAGE.exr", help="channels R, G, B, Z [, N.x, N.y, N.z, U, A]")
    bp.add_argument("--project", required=True)
    bp.add_argument("--pose", required=True, metavar="x,y,z[,qx,qy,qz,qw]",
                    help="the image's camera pose (a render's pose)")
    bp.add_argument("--pinhole", metavar="fx,fy,cx,cy[,k1,k2,k3,p1,p2]",
                    help="a pinhole image (default: equirectangular)")
    bp.add_argument("--fisheye", metavar="fx,fy,cx,cy[,k1,k2,k3,k4[,fov]]",
                    help="a fisheye image (Kannala-Brandt, as a --fisheye render's)")
    bp.add_argument("--render", type=int, default=0, metavar="ID", help="the render it came from")
    bp.add_argument("--name", default="", help="the batch's name (default backproject-<batch>)")

    confidence = sub.add_parser("confidence", help="sensor artefacts as confidence (§9)")
    csub = confidence.add_subparsers(dest="confidence_cmd", required=True)
    cshow = csub.add_parser("show", help="write a scan's cameras' confidence maps as images "
                                         "and say what each artefact covers")
    cshow.add_argument("--project", required=True)
    cshow.add_argument("--scan", required=True)
    cshow.add_argument("-o", "--output", required=True, metavar="DIR",
                       help="directory for CAMERA-ARTEFACT.png (grey: white is confidence 1)")

    batch = sub.add_parser("batch", help="derived batches: list, roll back")
    bsub = batch.add_subparsers(dest="batch_cmd", required=True)
    blist = bsub.add_parser("list", help="list derived batches")
    blist.add_argument("--project", required=True)
    blist.add_argument("--json", action="store_true")
    brb = bsub.add_parser("rollback", help="a new version without a derived batch")
    brb.add_argument("name")
    brb.add_argument("--project", required=True)

    rollback = sub.add_parser("rollback", help="a new version that gives back an earlier one")
    rollback.add_argument("version", type=int)
    rollback.add_argument("--project", required=True)

    pin = sub.add_parser("pin", help="pin a version against retention")
    pin.add_argument("version", type=int)
    pin.add_argument("--project", required=True)
    pin.add_argument("--unpin", action="store_true")

    export = sub.add_parser("export", help="write a version as one OpenVDB file")
    export.add_argument("--project", required=True)
    export.add_argument("--version", type=int, default=0, help="version (0: HEAD)")
    export.add_argument("-o", "--output", required=True, metavar="SITE.vdb")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    handlers = {"project": _cmd_project, "ingest": _cmd_ingest, "render": _cmd_render,
                "scans": _cmd_scans, "reference": _cmd_reference, "inspect": _cmd_inspect, "rebuild": _cmd_rebuild,
                "scan": _cmd_scan, "versions": _cmd_versions, "export": _cmd_export,
                "profile": _cmd_profile, "reweight": _cmd_reweight, "normalise": _cmd_normalise,
                "lens": _cmd_lens,
                "records": _cmd_records, "pin": _cmd_pin, "rollback": _cmd_rollback,
                "backproject": _cmd_backproject, "batch": _cmd_batch, "token": _cmd_token,
                "operation": _cmd_operation, "confidence": _cmd_confidence}
    try:
        token = None
        if args.token_file:
            with open(args.token_file) as f:
                token = f.readline().strip()
        with Client(args.server, timeout_s=args.timeout, token=token, tls_ca=args.tls_ca,
                    tls_cert=args.tls_cert, tls_key=args.tls_key) as client:
            return handlers[args.cmd](client, args)
    except VaslError as e:
        hint = ""
        if e.code.name == "UNAVAILABLE":
            hint = f" (is vasld running at {args.server}?)"
        elif e.code.name == "UNAUTHENTICATED":
            hint = " (give a token: --token-file, $VASL_TOKEN or $VASL_TOKEN_FILE)"
        print(f"vasl: error: {e.code.name}: {e.details}{hint}", file=sys.stderr)
        return 1
    except (ValueError, OSError) as e:
        print(f"vasl: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("vasl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
