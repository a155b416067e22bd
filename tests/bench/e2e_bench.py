"""e2e_bench: issue "Speed"'s figures through vasld over gRPC on loopback, as a user meets them.

A site written by `vasl_scene` (the corridor's first 6 stations; `realistic`: LiDAR 2048×1024,
RGB 4096×2048, h = 2 cm; `small`: LiDAR 512×256, RGB 1024×512, h = 5 cm) is ingested scan by
scan through the client, reweighted under a general profile, and rendered at the panorama's
size from the first novel view into EXR and PNG files, all against a real vasld started here on
a free loopback port with a temporary data directory. Printed and written to --json:

  - ingest: points/s from the call to its answer (upload, server work, commit), the server's
    own seconds and its stages, per scan;
  - reweight: seconds and records/s per run (each under a new profile revision, so each fuses
    and commits);
  - render end to end: seconds from the request to both files closed; the server's render
    seconds and, of them, the seconds its render threads spent encoding; and the ratio of the
    end to end seconds to the library's render alone of the same site, view and size (the
    march and fusion lookups, no encoding), read from vasl_bench's --json figures
    (--library-json, default build/bench-site.json, written first by deploy/bench.sh);
  - vasld's peak RSS (VmHWM, reset through /proc/PID/clear_refs before each phase) during
    ingest, reweight and render.

Usage: python tests/bench/e2e_bench.py [--site realistic|small] [--repeat N] [--json PATH]
       [--build DIR] [--work DIR] [--scene DIR] [--library-json PATH]. Run by deploy/bench.sh with the client's virtual environment.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
SITES = {  # LiDAR azimuth steps, panorama width, vossel edge (metres)
    "realistic": (2048, 4096, 0.02),
    "small": (512, 1024, 0.05),
}
STATIONS = 6


def spread(values):
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


class Vasld:
    """A vasld on a free loopback port, its peak RSS readable and resettable."""

    def __init__(self, binary: str, work: str):
        self.log_path = os.path.join(work, "vasld.log")
        port_file = os.path.join(work, "port")
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [binary, "--address", "127.0.0.1:0", "--data-dir", os.path.join(work, "data"),
             "--port-file", port_file], stdout=self._log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        while not os.path.exists(port_file) and time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        if not os.path.exists(port_file):
            self.stop()
            sys.exit(f"e2e_bench: vasld wrote no port file; its log:\n{open(self.log_path).read()}")
        with open(port_file) as f:
            self.address = f"127.0.0.1:{int(f.read().strip())}"

    def reset_peak(self) -> None:
        with open(f"/proc/{self.proc.pid}/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current RSS (Linux ≥ 4.0)

    def peak_mb(self) -> float:
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
        return float("nan")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


def library_render_s(path: str, site: str, width: int):
    """Seconds of vasl_bench's render of `site` at `width` (the median), or None."""
    try:
        with open(path) as f:
            figures = json.load(f)
    except (OSError, ValueError):
        return None
    render = figures.get("render", {})
    if figures.get("site") != site or render.get("width") != width:
        return None
    return render["width"] * render["height"] / render["rays_per_s"]["median"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--site", choices=sorted(SITES), default="realistic")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default="")
    ap.add_argument("--build", default=os.environ.get("VASL_BUILD_DIR", os.path.join(REPO, "build")))
    ap.add_argument("--work", default="", help="directory for the scene and the data (default: a "
                    "temporary one, removed at the end)")
    ap.add_argument("--scene", default="", help="the site's scans: written there by vasl_scene "
                    "unless it already holds them (scene.json), and kept (default: in --work)")
    ap.add_argument("--library-json", default=os.path.join(REPO, "build", "bench-site.json"),
                    help="vasl_bench --site figures whose render this one's end to end is set "
                    "against (skipped when absent or of another site)")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    from vasl import Client  # the client's virtual environment

    lidar_w, pano_w, h = SITES[args.site]
    owned = None if args.work else tempfile.TemporaryDirectory(prefix="vasl-e2e-bench-")
    work = args.work or owned.name
    os.makedirs(work, exist_ok=True)
    scene = args.scene or os.path.join(work, "scene")
    t0 = time.monotonic()
    if not os.path.exists(os.path.join(scene, "scene.json")):
        subprocess.run([os.path.join(args.build, "tests", "scenes", "vasl_scene"), "--out", scene,
                        "--site", "corridor", "--stations", str(STATIONS), "--pano-width",
                        str(pano_w), "--lidar-azimuth-steps", str(lidar_w),
                        "--lidar-elevation-steps", str(lidar_w // 2), "--supersample", "2",
                        "--vossel-size", str(h)], check=True, stdout=subprocess.DEVNULL)
    cores = os.cpu_count()
    print(f"\ne2e through vasld ({args.site}): corridor stations 1-{STATIONS}, LiDAR "
          f"{lidar_w}x{lidar_w // 2}, RGB {pano_w}x{pano_w // 2}, h {h} m, {cores} cores "
          f"(scene written in {time.monotonic() - t0:.0f} s)")
    out = {"site": args.site, "cores": cores, "vossel_m": h, "lidar": [lidar_w, lidar_w // 2],
           "rgb": [pano_w, pano_w // 2], "ingest": []}
    server = Vasld(os.path.join(args.build, "server", "vasld"), work)
    try:
        with Client(server.address, timeout_s=3600) as client:
            deadline = time.monotonic() + 60
            while client.health() != "SERVING":
                if time.monotonic() > deadline:
                    sys.exit("e2e_bench: vasld did not become SERVING")
                time.sleep(0.2)
            client.create_project("site", vossel_size_m=h, description="e2e_bench")

            # Ingest, scan by scan, each call timed from request to answer.
            server.reset_peak()
            for manifest in sorted(glob.glob(os.path.join(scene, "scan-*.json"))):
                t = time.monotonic()
                r = client.ingest("site", manifest)
                wall = time.monotonic() - t
                out["ingest"].append({
                    "scan": r.scan, "seconds": wall, "server_seconds": r.ingest_seconds,
                    "upload_seconds": r.upload_seconds, "points": r.point_count,
                    "points_per_s": r.point_count / wall, "records": r.record_count,
                    "stages_s": dict(r.stages)})
                print(f"{r.scan:8s} {wall:6.2f} s ({r.ingest_seconds:.2f} s in vasld, upload "
                      f"{r.upload_seconds:.2f} s) {r.point_count:9d} points "
                      f"{r.point_count / wall / 1e6:5.2f} M points/s "
                      f"({r.point_count / wall / 1e6 / cores:.2f} per core) "
                      f"{r.record_count:9d} records")
            out["ingest_peak_rss_mb"] = server.peak_mb()
            records = out["ingest"][-1]["records"]
            total_points = sum(s["points"] for s in out["ingest"])
            total_s = sum(s["seconds"] for s in out["ingest"])
            print(f"ingest over gRPC: {total_points / total_s / 1e6:.2f} M points/s over "
                  f"{len(out['ingest'])} scans, vasld peak {out['ingest_peak_rss_mb']:.0f} MB")

            # Reweight under a general profile, a new revision per run.
            server.reset_peak()
            seconds = []
            for i in range(args.repeat):
                client.create_profile("site", {"name": "bench", "alpha": 1.3, "beta": 0.7,
                                               "rho": 0.5, "proximity_m": 2.0 + 0.01 * i,
                                               "kappa": [2.5, 1.5, 0.5, 1.2, 0.8, 1.7]})
                t = time.monotonic()
                client.reweight("site", "bench")
                seconds.append(time.monotonic() - t)
            out["reweight_s"] = spread(seconds)
            out["reweight_records_per_s"] = records / out["reweight_s"]["median"]
            out["reweight_peak_rss_mb"] = server.peak_mb()
            print(f"reweight over gRPC: {out['reweight_s']['median']:.2f} s "
                  f"({out['reweight_s']['min']:.2f}-{out['reweight_s']['max']:.2f}), "
                  f"{out['reweight_records_per_s'] / 1e6:.1f} M records/s, vasld peak "
                  f"{out['reweight_peak_rss_mb']:.0f} MB")

            # Render end to end: request to files, beside the server's march.
            with open(os.path.join(scene, "truth", "views.json")) as f:
                view = {v["name"]: v for v in json.load(f)["views"]}["novel-1"]
            pose = ",".join(str(c) for c in view["position"] + view["quaternion"])
            server.reset_peak()
            walls, servers, encodes = [], [], []
            for i in range(args.repeat):
                files = {"exr": os.path.join(work, f"render-{i}.exr"),
                         "png": os.path.join(work, f"render-{i}.png")}
                t = time.monotonic()
                r = client.render("site", pose, pano_w, pano_w // 2, formats=("exr", "png"),
                                  decode=False, stream_rows=True, files=files)
                walls.append(time.monotonic() - t)
                encodes.append(r.encode_seconds)
                servers.append(r.render_seconds)
                for path in files.values():
                    if os.path.getsize(path) == 0:
                        sys.exit(f"e2e_bench: the render wrote an empty {path}")
            out["render"] = {"width": pano_w, "height": pano_w // 2, "end_to_end_s": spread(walls),
                             "server_s": spread(servers), "encode_s": spread(encodes),
                             "peak_rss_mb": server.peak_mb()}
            print(f"render {pano_w}x{pano_w // 2} end to end (request to EXR + PNG files): "
                  f"{statistics.median(walls):.2f} s ({min(walls):.2f}-{max(walls):.2f}); in "
                  f"vasld {statistics.median(servers):.2f} s, of which its render threads "
                  f"encoded {statistics.median(encodes):.2f} s; vasld peak "
                  f"{server.peak_mb():.0f} MB")
            library = library_render_s(args.library_json, args.site, pano_w)
            if library is None:
                print(f"  (no library render of this site in {args.library_json}: run "
                      f"vasl_bench --site {args.site} --json it first to compare)")
            else:
                ratio = statistics.median(walls) / library
                out["render"]["library_render_s"] = library
                out["render"]["end_to_end_over_library_render"] = ratio
                print(f"  the library's render alone of the same site, view and size: "
                      f"{library:.2f} s; end to end / library render {ratio:.2f}")
    finally:
        server.stop()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"figures written to {args.json}")
    if owned:
        owned.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
