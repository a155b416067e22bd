#!/usr/bin/env bash
# Sets up, builds, then prints the speed figures of ingest, reweight, render and record IO on
# the synthetic room and the growth of the store over the corridor site
# (tests/bench/vasl_bench.cc), after the kernels under Google Benchmark
# (tests/bench/kernels_bench.cc: the §7 weight kernel and fusion beside a STREAM triad;
# tests/bench/visibility_bench.cc: the §5 depth panorama, dilation and visibility test, and the
# §8 render's march and its EXR and PNG encoding, on the corridor site; tests/bench/image_bench.cc:
# the PNG decode and §9 artefact detectors every camera load runs, at 4096×2048, and the §2.3
# calibration check's patch search under each instruction set;
# tests/bench/tile_io_bench.cc: encoding and reading the fullest tile's geometry, records and
# fused objects, what every commit and reweight does per tile), whose medians
# and spread over 5 runs are also written to build/bench-kernels.json.
# Then a site at realistic size (the corridor's first 6 stations, LiDAR 2048×1024 and RGB
# 4096×2048 each, h = 2 cm; about 2 minutes; BENCH_SITE=small for LiDAR 512×256, RGB 1024×512,
# h = 5 cm, under a minute) ingested, fused, reweighted against a rebuild and rendered beside
# Embree tracing the same site as triangles (the analytic boxes and the lattice's surfels,
# rtcIntersect1 and rtcIntersect8, same threads), its figures also in build/bench-site.json;
# then the same site through vasld over gRPC (build/bench-e2e.json; its scans are kept in
# build/bench-scene-<site> and written again only when that is removed), and Open3D integrating
# the same scans into its VoxelBlockGrid and ray casting it (build/bench-open3d.json).
# Arguments go to the last vasl_bench run (--panorama-width W, --repeat N, --growth-only,
# --tile-vossels T, --snapshot-budget-mb M, --revisit-cache-mb M, --growth-passes N).
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/setup.sh
# What the benchmarks alone need, from Debian's packages.
missing=""
for pkg in libbenchmark-dev libembree-dev; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" ||
    missing="$missing $pkg"
done
if [ -n "$missing" ]; then
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  # shellcheck disable=SC2086
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
fi
./deploy/build.sh
./build/tests/bench/vasl_kernels_bench --benchmark_repetitions=5 \
  --benchmark_report_aggregates_only=true --benchmark_out=build/bench-kernels.json \
  --benchmark_out_format=json
./build/tests/bench/vasl_bench --site "${BENCH_SITE:-realistic}" --repeat 3 \
  --json build/bench-site.json
# The same site through vasld over gRPC on loopback: ingest points/s, reweight, a render from
# request to files beside the march, vasld's peak RSS (tests/bench/e2e_bench.py).
site="${BENCH_SITE:-realistic}"
scene="build/bench-scene-$site"
.venv/bin/python tests/bench/e2e_bench.py --site "$site" --repeat 3 --scene "$scene" \
  --json build/bench-e2e.json
# Open3D on the same scans (tests/bench/open3d_peer.py): open3d-cpu from PyPI in a virtual
# environment of its own, so that the client's stays lean.
if [ ! -x build/open3d-venv/bin/python ] ||
   ! build/open3d-venv/bin/python -c "import open3d" 2>/dev/null; then
  python3 -m venv build/open3d-venv
  build/open3d-venv/bin/pip install -q --upgrade pip
  build/open3d-venv/bin/pip install -q "open3d-cpu==0.20.*"
fi
build/open3d-venv/bin/python tests/bench/open3d_peer.py --scene "$scene" --repeat 3 \
  --json build/bench-open3d.json
./build/tests/bench/vasl_bench "$@"
