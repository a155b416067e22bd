"""Helpers of the crash-safety tests (tests/integration/test_crash.py, the quick case, and the
soak in tests/soak): start a vasld that can be killed and restarted on one data directory, and
read which objects and blobs a project's kept versions reference. Not a test module."""
from __future__ import annotations

import errno
import os
import sqlite3
import subprocess
import time

import pytest
from conftest import _port_file_address, _wait_serving  # tests/integration's, or the soak's


def start_vasld(vasld: str, base: str, data_dir: str, n: int, extra_args=()):
    """Starts `vasld` on a free loopback port over `data_dir` (logs and port file in `base`,
    numbered `n`) and waits until it serves; returns (proc, address, open log file). Waits for
    the binary and retries when a rebuild is replacing it (missing, "text file busy")."""
    deadline = time.monotonic() + 120  # a rebuild may be relinking it right now
    while not os.access(vasld, os.X_OK) and time.monotonic() < deadline:
        time.sleep(2)
    if not os.access(vasld, os.X_OK):
        pytest.fail(f"{vasld} is missing: build first (./deploy/build.sh, or set VASL_BUILD_DIR)",
                    pytrace=False)
    port_file = os.path.join(base, f"port-{n}")
    log_path = os.path.join(base, f"vasld-{n}.log")
    if os.path.exists(port_file):
        os.unlink(port_file)
    log = open(log_path, "w")
    for attempt in range(20):
        try:
            proc = subprocess.Popen([vasld, "--address", "127.0.0.1:0", "--data-dir", data_dir,
                                     "--port-file", port_file, *extra_args],
                                    stdout=log, stderr=subprocess.STDOUT)
            break
        except OSError as e:
            if e.errno not in (errno.ETXTBSY, errno.ENOENT) or attempt == 19:
                raise
            time.sleep(3)
    address = _port_file_address(port_file, proc, log_path)
    _wait_serving(address, proc, log_path)
    return proc, address, log


def referenced(project_dir: str):
    """Objects and blobs the kept versions of the catalog reference (read-only)."""
    db = sqlite3.connect(f"file:{os.path.join(project_dir, 'catalog.sqlite')}?mode=ro", uri=True)
    try:
        objects = {r[0] for r in db.execute(
            "SELECT object FROM manifest UNION SELECT object FROM reach")}
        blobs = {r[0] for r in db.execute(
            "SELECT DISTINCT src.blob_sha256 FROM sources src JOIN scans sc ON src.scan_id = sc.id "
            "WHERE EXISTS (SELECT 1 FROM versions v WHERE v.pruned = 0 AND sc.version <= v.version "
            "AND (sc.deleted_in IS NULL OR sc.deleted_in > v.version))")}
    finally:
        db.close()
    return objects, blobs
