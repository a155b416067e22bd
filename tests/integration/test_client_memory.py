"""Bounded client memory (issue "Real captures in"): ingesting an E57 file streams its points
chunk by chunk (read, packed, sent), so the client's peak memory does not grow with the scan.
The CLI ingests a synthetic 1 M-point and a 4 M-point E57 file into a real vasld; the peak RSS
of the client process (VmHWM) may grow by at most SLACK_MB from the first to the second, far
below the 48 MB the 3 M extra points would take packed whole (16 bytes a point), let alone as
the float64 arrays they are read into (24 bytes a point and more)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time

from synth_scans import room_chunks, write_e57

SIZES = (1_000_000, 4_000_000)
#: Allowed growth of the client's peak RSS from the 1 M to the 4 M run: allocator and gRPC
#: buffer noise; a quarter of what the extra points would take packed whole.
SLACK_MB = 12.0
VOSSEL_M = 0.25  # coarse: the server's share of the time stays small


# The CLI, then its own peak RSS from /proc/self/status. VmHWM belongs to the process's memory
# since its exec: a child's rusage (ru_maxrss, from wait4) would also count the RSS of the
# process that forked it (here pytest, hundreds of MB), which Linux carries across exec.
_MEASURED_CLI = """import sys
from vasl.cli import main
code = main(sys.argv[1:])
with open("/proc/self/status") as f:
    sys.stderr.write(next(line for line in f if line.startswith("VmHWM:")))
sys.exit(code)
"""


def client_ingest(address: str, path: str, project: str):
    """Runs `vasl ingest PATH --project PROJECT --quiet` in a process of its own; (stdout, its
    peak RSS in MB, seconds)."""
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", _MEASURED_CLI, "--server", address, "ingest", path,
                        "--project", project, "--quiet"], capture_output=True, text=True,
                       timeout=900)
    seconds = time.monotonic() - t0
    assert r.returncode == 0, f"{r.stdout}\n{r.stderr}"
    hwm = re.search(r"VmHWM:\s+(\d+) kB", r.stderr)
    assert hwm, r.stderr
    return r.stdout, int(hwm.group(1)) / 1024.0, seconds


def measure_e57_ingest(server, client, tmp_path, n: int, project: str):
    """Writes a synthetic E57 of `n` points, ingests it with the CLI into a new project with
    coarse vossels; (CLI output, peak RSS MB, seconds, file size MB, seconds writing it). The
    file is removed afterwards."""
    path = str(tmp_path / f"{project}.e57")
    t0 = time.monotonic()
    write_e57(path, n, room_chunks(n), invalid=True)
    written = time.monotonic() - t0
    client.create_project(project, vossel_size_m=VOSSEL_M)
    out, peak_mb, seconds = client_ingest(server.address, path, project)
    size_mb = os.path.getsize(path) / 1e6
    os.unlink(path)
    return out, peak_mb, seconds, size_mb, written


def test_client_peak_memory_does_not_grow_with_the_scan(server, client, tmp_path):
    peaks = []
    for n in SIZES:
        out, peak_mb, seconds, size_mb, written = measure_e57_ingest(
            server, client, tmp_path, n, f"memory-{n // 1_000_000}m")
        peaks.append(peak_mb)
        print(f"\n{out.strip()}\nclient ingest of {n:,} points ({size_mb:.1f} MB E57, written "
              f"in {written:.1f} s): peak RSS {peak_mb:.1f} MB, {seconds:.1f} s")
    growth = peaks[1] - peaks[0]
    whole = (SIZES[1] - SIZES[0]) * 16 / 1e6
    print(f"client peak RSS growth from {SIZES[0]:,} to {SIZES[1]:,} points: {growth:+.1f} MB "
          f"(allowed {SLACK_MB:.0f} MB; the extra points packed whole: {whole:.0f} MB)")
    assert growth <= SLACK_MB
