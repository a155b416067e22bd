"""open3d_peer: issue "Speed"'s Open3D figures, on the scans vasl ingests in the same run.

Open3D (open3d-cpu from PyPI, in its own virtual environment: deploy/bench.sh makes it) is what a
user would otherwise reach for to fuse range scans into a sparse volume and ray cast it. Its
VoxelBlockGrid integrates depth images from pinhole cameras, so each station's LiDAR points (the
very PLY files `vasl_scene` wrote and vasl ingests) become six 90° cube-face depth images whose
pixel is the LiDAR's pitch (the nearest point per pixel, in the LiDAR's frame), integrated as
TSDF with voxels of the site's vossel edge h (scene.json's) and a truncation of 4 h. The grid is
then ray cast from the first novel view as six cube faces whose pixels together number those of
a render at the panoramas' size (W × W/2), on Open3D's own CPU threads. Printed and written to --json: frames/s and LiDAR points/s of the
integration (the projection to faces not counted), rays/s of the ray cast, and the share of its
rays that hit within 2 h of the site's analytic depth of the same pixel.

Usage: open3d_peer.py --scene DIR [--repeat N] [--json PATH]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import sys
import time

import numpy as np

def _face(forward, down) -> np.ndarray:
    """A camera's axes in the sensor frame as columns: x right = down × forward, y down, z
    forward (right-handed, Open3D's camera convention)."""
    z, y = np.array(forward, float), np.array(down, float)
    return np.column_stack([np.cross(y, z), y, z])


# The six 90° cube faces round a sensor, sensor up (+z) drawn up on the side faces.
FACES = {
    "+x": _face((1, 0, 0), (0, 0, -1)),
    "-x": _face((-1, 0, 0), (0, 0, -1)),
    "+y": _face((0, 1, 0), (0, 0, -1)),
    "-y": _face((0, -1, 0), (0, 0, -1)),
    "+z": _face((0, 0, 1), (-1, 0, 0)),
    "-z": _face((0, 0, -1), (1, 0, 0)),
}


def read_ply_xyz(path: str) -> np.ndarray:
    """The x, y, z of a binary little-endian PLY of float vertex properties."""
    with open(path, "rb") as f:
        names, count = [], 0
        while True:
            line = f.readline().decode("ascii").strip()
            if line.startswith("element vertex"):
                count = int(line.split()[2])
            elif line.startswith("property float"):
                names.append(line.split()[2])
            elif line.startswith("property"):
                sys.exit(f"open3d_peer: {path}: only float properties are read, got {line!r}")
            elif line == "end_header":
                break
        data = np.fromfile(f, dtype="<f4", count=count * len(names)).reshape(count, len(names))
    return data[:, [names.index("x"), names.index("y"), names.index("z")]].astype(np.float64)


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def face_camera(n: int):
    """A 90° pinhole of n × n pixels: intrinsic matrix."""
    f = n / 2.0
    return np.array([[f, 0, n / 2.0], [0, f, n / 2.0], [0, 0, 1]])


def face_depths(points_sensor: np.ndarray, n: int):
    """Per cube face the z-buffered depth image (0: no point) of the sensor-frame points."""
    out = {}
    for name, r in FACES.items():
        p = points_sensor @ r  # camera coordinates (r's columns are the camera axes)
        z = p[:, 2]
        keep = z > 1e-6
        u = p[keep, 0] / z[keep] * (n / 2.0) + n / 2.0
        v = p[keep, 1] / z[keep] * (n / 2.0) + n / 2.0
        zk = z[keep]
        inside = (u >= 0) & (u < n) & (v >= 0) & (v < n)
        idx = v[inside].astype(np.int64) * n + u[inside].astype(np.int64)
        depth = np.full(n * n, np.inf)
        np.minimum.at(depth, idx, zk[inside])
        depth[~np.isfinite(depth)] = 0.0
        out[name] = depth.reshape(n, n).astype(np.float32)
    return out


def world_to_camera(r_world_sensor, o_world, r_sensor_camera) -> np.ndarray:
    r = r_world_sensor @ r_sensor_camera
    e = np.eye(4)
    e[:3, :3] = r.T
    e[:3, 3] = -r.T @ o_world
    return e


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", required=True, help="a directory vasl_scene wrote")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    import open3d as o3d
    import open3d.core as o3c

    # Sizes as the scene was written: the render is of its panoramas' width, a face pixel's
    # angle the LiDAR's pitch (90° of a face = a quarter of its azimuth steps).
    with open(os.path.join(args.scene, "scene.json")) as f:
        described = json.load(f)
    h = described["recommended_vossel_size_m"]
    args.render_width = described["panorama"]["width"]
    args.face_px = described["lidar"]["azimuth_steps"] // 4
    threads = os.cpu_count()
    manifests = sorted(glob.glob(os.path.join(args.scene, "scan-*.json")),
                       key=lambda p: int(p.rsplit("-", 1)[1].split(".")[0]))
    frames, points = [], 0
    for m in manifests:
        with open(m) as f:
            manifest = json.load(f)
        xyz = read_ply_xyz(os.path.join(args.scene, manifest["lidar"]["points"]))
        points += len(xyz)
        r = quat_matrix(manifest["pose"]["quaternion"])
        o = np.array(manifest["pose"]["position"], float)
        for name, depth in face_depths(xyz, args.face_px).items():
            frames.append((depth, world_to_camera(r, o, FACES[name])))
    intrinsic = o3c.Tensor(face_camera(args.face_px), o3c.float64)
    depth_max = 100.0
    print(f"\nopen3d {o3d.__version__} ({threads} threads): {len(manifests)} stations' LiDAR as "
          f"{len(frames)} cube-face depth frames of {args.face_px}x{args.face_px}, {points} "
          f"points, TSDF voxels of {h} m")

    rates, vbg, blocks = [], None, None
    for _ in range(args.repeat):
        vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)), voxel_size=h, block_resolution=16, block_count=200000,
            device=o3c.Device("CPU:0"))
        images = [(o3d.t.geometry.Image(o3c.Tensor(d)), o3c.Tensor(e, o3c.float64))
                  for d, e in frames]
        t = time.monotonic()
        for depth, extrinsic in images:
            coords = vbg.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0,
                                                          depth_max, trunc_voxel_multiplier=4.0)
            vbg.integrate(coords, depth, intrinsic, extrinsic, 1.0, depth_max,
                          trunc_voxel_multiplier=4.0)
        rates.append(time.monotonic() - t)
    seconds = statistics.median(rates)
    hashmap = vbg.hashmap()
    blocks = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]
    out = {"open3d": o3d.__version__, "threads": threads, "frames": len(frames),
           "face_px": args.face_px, "points": points, "vossel_m": h,
           "integrate_s": {"median": seconds, "min": min(rates), "max": max(rates)},
           "frames_per_s": len(frames) / seconds, "points_per_s": points / seconds,
           "blocks": int(blocks.shape[0])}
    print(f"integrate: {seconds:.2f} s ({min(rates):.2f}-{max(rates):.2f}), "
          f"{len(frames) / seconds:.1f} frames/s, {points / seconds / 1e6:.2f} M LiDAR points/s, "
          f"{blocks.shape[0]} blocks of 16^3")

    # Ray cast from the first novel view: six faces with as many rays as the render.
    with open(os.path.join(args.scene, "truth", "views.json")) as f:
        view = {v["name"]: v for v in json.load(f)["views"]}["novel-1"]
    r = quat_matrix(view["quaternion"])
    o = np.array(view["position"], float)
    # A face's blocks: those whose bounding sphere meets its 90° frustum (what Open3D's own
    # pipeline takes from a frame's depth; given all blocks, behind the camera too, its range
    # map overflows and the cast slows by orders of magnitude).
    block_m = 16 * h
    coords = blocks.numpy().astype(np.float64)
    centres = (coords + 0.5) * block_m
    radius = block_m * np.sqrt(3.0) / 2.0

    def frustum_blocks(extrinsic):
        c = centres @ extrinsic[:3, :3].T + extrinsic[:3, 3]
        slack = radius * np.sqrt(2.0)  # a sphere's reach past a 45° side plane, generously
        keep = (c[:, 2] > -radius) & (np.abs(c[:, 0]) <= c[:, 2] + slack) & \
               (np.abs(c[:, 1]) <= c[:, 2] + slack)
        return o3c.Tensor(blocks.numpy()[keep])

    rays = args.render_width * (args.render_width // 2)
    n = int(round((rays / 6) ** 0.5))
    cast_intrinsic = o3c.Tensor(face_camera(n), o3c.float64)
    times, hit = [], 0
    for _ in range(args.repeat):
        t = time.monotonic()
        depths = []
        for name, rc in FACES.items():
            extrinsic = world_to_camera(r, o, rc)
            result = vbg.ray_cast(block_coords=frustum_blocks(extrinsic), intrinsic=cast_intrinsic,
                                  extrinsic=o3c.Tensor(extrinsic, o3c.float64),
                                  width=n, height=n, render_attributes=["depth"],
                                  depth_scale=1.0, depth_min=0.05, depth_max=depth_max,
                                  weight_threshold=1.0, range_map_down_factor=8)
            depths.append(result["depth"].numpy())
        times.append(time.monotonic() - t)
        hit = sum(int(np.count_nonzero(d > 0)) for d in depths)
    cast = statistics.median(times)
    out.update({"raycast_faces_px": n, "raycast_rays": 6 * n * n,
                "raycast_s": {"median": cast, "min": min(times), "max": max(times)},
                "raycast_rays_per_s": 6 * n * n / cast, "raycast_hit_fraction": hit / (6 * n * n)})
    print(f"ray cast from novel-1: 6 faces of {n}x{n} ({6 * n * n} rays, as many as a "
          f"{args.render_width}x{args.render_width // 2} render): {cast:.2f} s "
          f"({min(times):.2f}-{max(times):.2f}), {6 * n * n / cast / 1e6:.2f} M rays/s, "
          f"{100.0 * hit / (6 * n * n):.1f}% hit")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"figures written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
