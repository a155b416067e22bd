#!/usr/bin/env bash
# Builds the libFuzzer harnesses of tests/fuzz (Debian's clang 14, ASan + UBSan) into
# build-fuzz/ and runs each for SECONDS_PER_TARGET seconds (default 60) over its corpus in
# build-fuzz/fuzz/corpus/TARGET, seeded with inputs generated here (oiiotool images, ingest
# streams from vasl_fuzz_seeds). Prints per target the executions, exec/s, coverage and
# "no crash"; exits 1 if any target crashed, leaked, timed out or ran out of memory, naming the
# reproducer (build-fuzz/fuzz/artifacts/TARGET/...), whose log is build-fuzz/fuzz/logs/TARGET.log.
# Before fuzzing, each target runs once over tests/fuzz/regressions/TARGET: the inputs that
# crashed it before and were fixed (copy a new reproducer there with its fix).
#
#   deploy/fuzz.sh [SECONDS_PER_TARGET]
#   VASL_FUZZ_TARGETS="fuzz_image_decode" deploy/fuzz.sh 30   # a subset
#   VASL_FUZZ_JOBS=1 deploy/fuzz.sh                            # build with one job (default 2)
#   VASL_FUZZ_MALLOC_LIMIT_MB=2048 deploy/fuzz.sh              # see -malloc_limit_mb below
#
# Besides -rss_limit_mb=2048 the targets run with -malloc_limit_mb=512: under the harnesses'
# small limits (tests/fuzz/fuzz_limits.h) no single allocation comes near it, so one that does
# is an input that makes vasld allocate what its limits do not bound, and counts as a crash.
#
# Reproduce a crash: build-fuzz/tests/fuzz/TARGET FILE (runs that one input and prints the
# stack). Needs the Debian packages of deploy/setup.sh; installs clang, libclang-rt-14-dev
# (libFuzzer) and llvm-14 (symbolizer) when missing (as root, or through sudo).
set -euo pipefail
cd "$(dirname "$0")/.."

SECONDS_PER_TARGET="${1:-60}"
if ! [[ "$SECONDS_PER_TARGET" =~ ^[1-9][0-9]*$ ]]; then
  echo "usage: deploy/fuzz.sh [SECONDS_PER_TARGET]" >&2
  exit 2
fi
read -r -a TARGETS <<< "${VASL_FUZZ_TARGETS:-fuzz_ingest_stream fuzz_image_decode fuzz_backproject_image}"
JOBS="${VASL_FUZZ_JOBS:-2}"
MALLOC_LIMIT_MB="${VASL_FUZZ_MALLOC_LIMIT_MB:-512}"
BUILD=build-fuzz
WORK=$BUILD/fuzz

# --- clang and libFuzzer from Debian -----------------------------------------------------------
missing=()
for p in clang libclang-rt-14-dev llvm-14 openimageio-tools; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "fuzz: installing ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# --- configure and build only the harnesses ----------------------------------------------------
mkdir -p "$BUILD" "$WORK"
cmake -S . -B "$BUILD" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  "-DCMAKE_CXX_FLAGS_RELWITHDEBINFO=-O1 -gline-tables-only" -DCMAKE_CXX_COMPILER=clang++ \
  -DVASL_FUZZ=ON -DVASL_BUILD_TESTS=OFF > "$WORK/configure.log" 2>&1 || {
  cat "$WORK/configure.log"; exit 1; }
build_start=$(date +%s)
nice -n 10 cmake --build "$BUILD" -j "$JOBS" --target "${TARGETS[@]}" vasl_fuzz_seeds \
  > "$WORK/build.log" 2>&1 || { tail -n 60 "$WORK/build.log"; exit 1; }
echo "fuzz: build took $(( $(date +%s) - build_start )) s (log $WORK/build.log)"

# --- seeds, generated afresh each run (tiny images: a few hundred bytes each) -------------------
SEEDS=$WORK/seeds
rm -rf "$SEEDS"
mkdir -p "$SEEDS/images" "$SEEDS/fuzz_ingest_stream" "$SEEDS/fuzz_image_decode" \
  "$SEEDS/fuzz_backproject_image"
# make OUT SIZE CHANNELS TYPE [oiiotool options before -o]
make_image() {
  local out=$1 size=$2 channels=$3 type=$4
  shift 4
  oiiotool --nosoftwareattrib --pattern "noise:type=uniform:min=0.25:max=3:seed=7" "$size" \
    "$channels" "$@" --eraseattrib DateTime -d "$type" -o "$out"
}
I=$SEEDS/fuzz_image_decode
make_image "$I/rgb8.png" 16x8 3 uint8
make_image "$I/gray8.png" 16x8 1 uint8
make_image "$I/graya8.png" 8x4 2 uint8
make_image "$I/rgba16.png" 8x4 4 uint16
make_image "$I/rgb.jpg" 16x8 3 uint8
make_image "$I/gray.jpg" 8x4 1 uint8
make_image "$I/rgb-half-zip.exr" 8x4 3 half
make_image "$I/rgba-half-piz.exr" 8x4 4 half --compression piz
make_image "$I/rgb-float-tiled.exr" 8x4 3 float --tile 4 4
make_image "$I/rgb8.tif" 8x4 3 uint8
make_image "$I/rgb16-lzw.tif" 8x4 3 uint16 --compression lzw
make_image "$I/gray-float.tif" 8x4 1 float
P=$SEEDS/fuzz_backproject_image
make_image "$P/rgbz.exr" 8x4 4 float --chnames R,G,B,Z
make_image "$P/rgbz-normals-u-a.exr" 8x4 9 float --chnames R,G,B,A,Z,N.x,N.y,N.z,U
make_image "$P/rgbz-half-tiled.exr" 8x4 5 half --chnames R,G,B,A,Z --tile 4 4
make_image "$P/rgbz-b44.exr" 8x4 4 half --chnames R,G,B,Z --compression b44
"$BUILD/tests/fuzz/vasl_fuzz_seeds" "$SEEDS/fuzz_ingest_stream" "$I/rgb8.png" "$I/gray8.png" \
  "$I/rgb.jpg"

# --- run ---------------------------------------------------------------------------------------
SYMBOLIZER=/usr/lib/llvm-14/bin/llvm-symbolizer
[ -x "$SYMBOLIZER" ] && export ASAN_SYMBOLIZER_PATH="$SYMBOLIZER"
# Known leaks inside Debian's libraries are suppressed (tests/fuzz/lsan.supp says which and
# why); matching them needs allocation stacks through those libraries, which have no frame
# pointers: hence the slow unwinder, over a short stack.
export ASAN_OPTIONS="${ASAN_OPTIONS:-detect_leaks=1:symbolize=1:fast_unwind_on_malloc=0:malloc_context_size=12}"
export LSAN_OPTIONS="${LSAN_OPTIONS:-suppressions=$PWD/tests/fuzz/lsan.supp:print_suppressions=0}"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}"
# final_stat NAME LOG: libFuzzer's -print_final_stats value.
final_stat() { sed -n "s/^stat::$1: *//p" "$2" | tail -n 1; }
failed=0
for t in "${TARGETS[@]}"; do
  corpus=$WORK/corpus/$t artifacts=$WORK/artifacts/$t log=$WORK/logs/$t.log
  mkdir -p "$corpus" "$artifacts" "$WORK/logs"
  # Every input that once crashed a harness (tests/fuzz/regressions/TARGET) runs first, once.
  regressions=tests/fuzz/regressions/$t
  if [ -d "$regressions" ] && [ -n "$(ls -A "$regressions")" ]; then
    rc=0
    "$BUILD/tests/fuzz/$t" -rss_limit_mb=2048 -malloc_limit_mb="$MALLOC_LIMIT_MB" -timeout=10 \
      "$regressions"/* > "$WORK/logs/$t.regressions.log" 2>&1 || rc=$?
    if [ "$rc" -ne 0 ]; then
      failed=1
      echo "fuzz: $t: FAILED (exit $rc) on a regression input of $regressions:"
      grep -E "^(==[0-9]+==ERROR|SUMMARY)|Running: " "$WORK/logs/$t.regressions.log" | tail -n 3 \
        | sed 's/^/fuzz:   /' || true
      continue
    fi
    echo "fuzz: $t: $(ls "$regressions" | wc -l) regression inputs pass"
  fi
  echo "fuzz: $t for ${SECONDS_PER_TARGET} s (corpus $corpus, log $log)"
  rc=0
  nice -n 10 "$BUILD/tests/fuzz/$t" -max_total_time="$SECONDS_PER_TARGET" -rss_limit_mb=2048 \
    -malloc_limit_mb="$MALLOC_LIMIT_MB" -timeout=10 -print_final_stats=1 -artifact_prefix="$artifacts/" \
    "$corpus" "$SEEDS/$t" > "$log" 2>&1 || rc=$?
  last=$(grep -E '^#[0-9]+.*(cov|ft):' "$log" | tail -n 1 || true)
  cov=$(sed -n 's/.* cov: \([0-9]*\).*/\1/p' <<< "$last")
  ft=$(sed -n 's/.* ft: \([0-9]*\).*/\1/p' <<< "$last")
  corp=$(sed -n 's/.* corp: \([^ ]*\) .*/\1/p' <<< "$last")
  summary="$(final_stat number_of_executed_units "$log") execs, $(final_stat average_exec_per_sec "$log") exec/s, cov ${cov:-?}, ft ${ft:-?}, corpus ${corp:-?}, $(final_stat new_units_added "$log") new units, peak RSS $(final_stat peak_rss_mb "$log") MB"
  if [ "$rc" -eq 0 ]; then
    echo "fuzz: $t: $summary: no crash"
  else
    failed=1
    echo "fuzz: $t: FAILED (exit $rc): $summary"
    grep -E "^(==[0-9]+==ERROR|SUMMARY|vasl fuzz check failed)|runtime error|ERROR: libFuzzer" "$log" \
      | head -n 5 | sed 's/^/fuzz:   /' || true
    grep -E "^ +#[0-9]+ " "$log" | grep -vE "fuzzer::|__sanitizer|__asan|__lsan|__ubsan|operator new" \
      | head -n 12 | sed 's/^/fuzz:   /' || true
    artifact=$(sed -n 's/.*Test unit written to \(.*\)$/\1/p' "$log" | tail -n 1)
    echo "fuzz:   reproducer: ${artifact:-(none written; see $log)}"
    echo "fuzz:   reproduce: $BUILD/tests/fuzz/$t ${artifact:-FILE}"
  fi
done
if [ "$failed" -ne 0 ]; then
  echo "fuzz: FAILED: a harness crashed (see above)"
  exit 1
fi
echo "fuzz: done, ${#TARGETS[@]} targets x ${SECONDS_PER_TARGET} s, no crash"
