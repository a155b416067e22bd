"""Client memory on a large scan (deploy/soak.sh): a synthetic E57 file of
VASL_SOAK_CLIENT_POINTS points (default 20 M; written chunk by chunk with pye57's libe57
bindings) ingested by the CLI into a real vasld with coarse vossels, beside a 1 M-point file.
Prints `soak: client ...` lines with each file's size and the client process's peak RSS
(VmHWM); the large ingest's peak may exceed the small one's by at most the integration test's
slack (tests/integration/test_client_memory.py)."""
from __future__ import annotations

import re

from conftest import env_int
from test_client_memory import SLACK_MB, measure_e57_ingest


def test_client_peak_memory_on_a_large_e57(server, client, tmp_path):
    big = env_int("VASL_SOAK_CLIENT_POINTS", 20_000_000)
    peaks = {}
    for n in (1_000_000, big):
        out, peak_mb, seconds, size_mb, written = measure_e57_ingest(
            server, client, tmp_path, n, f"soak-client-{n}")
        peaks[n] = peak_mb
        rate = re.search(r"\(([\d.]+) MB/s\)", out)
        print(f"\n{out.strip()}")
        print(f"soak: client ingest of {n:,} points: E57 {size_mb:.0f} MB "
              f"(written in {written:.0f} s), client peak RSS {peak_mb:.1f} MB, {seconds:.1f} s, "
              f"upload {rate.group(1) if rate else '?'} MB/s")
    growth = peaks[big] - peaks[1_000_000]
    print(f"soak: client peak RSS growth from 1,000,000 to {big:,} points: {growth:+.1f} MB "
          f"(allowed {SLACK_MB:.0f} MB; {big:,} points packed whole: {big * 16 / 1e6:.0f} MB)")
    assert growth <= SLACK_MB
