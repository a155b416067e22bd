"""Crash safety of the tiled store: vasld is killed with SIGKILL at random moments during
ingests; after each restart the project opens, HEAD is a complete version, every scan the client
was told was committed is there, and no object, blob or staging file outside the kept versions
survives (the store collects them when it opens the project)."""
from __future__ import annotations

import os
import random
import signal
import threading
import time

import numpy as np
import pytest

from conftest import VASLD, VOSSEL_M, _require, manifests
from crash_util import referenced as _referenced, start_vasld

PROJECT = "crash"


def _start(base: str, data_dir: str, n: int):
    return start_vasld(_require(VASLD), base, data_dir, n)


def test_kill_during_ingests_loses_nothing_committed(scene_dir, tmp_path):
    from vasl import Client, VaslError, read_manifest

    base = str(tmp_path)
    data_dir = os.path.join(base, "data")
    scans = manifests(scene_dir)
    rng = random.Random(5)
    committed: list[str] = []
    kills = 0
    restarts = 0
    proc, address, log = _start(base, data_dir, restarts)
    try:
        with Client(address, timeout_s=120) as c:
            c.create_project(PROJECT, vossel_size_m=VOSSEL_M)
        # A full ingest's duration sets the kill window; each round ingests a new scan id (the
        # scene's scans in turn, renamed), so rounds never run out. A scan of geometry the
        # project already holds ingests faster than the first (no older source is revisited):
        # a round whose ingest finished before the kill shortens the window to its duration.
        t0 = time.monotonic()
        with Client(address, timeout_s=120) as c:
            c.ingest(PROJECT, scans[0])
        committed.append(read_manifest(scans[0]).scan)
        window_s = time.monotonic() - t0
        for round_ in range(10):
            manifest = read_manifest(scans[(round_ + 1) % len(scans)])
            manifest.scan = f"{manifest.scan}-r{round_}"
            name = manifest.scan
            outcome = {}

            def run():
                started = time.monotonic()
                try:
                    with Client(address, timeout_s=120) as c:
                        outcome["result"] = c.ingest(PROJECT, manifest)
                    outcome["seconds"] = time.monotonic() - started
                except VaslError as e:
                    outcome["error"] = e

            t = threading.Thread(target=run)
            t.start()
            time.sleep(rng.uniform(0.1, 1.5) * window_s)
            during = t.is_alive()  # else the kill lands after the commit: also a crash point
            proc.send_signal(signal.SIGKILL)
            kills += 1 if during else 0
            t.join(timeout=120)
            proc.wait(timeout=30)
            log.close()
            if "result" in outcome:
                committed.append(name)
                window_s = min(window_s, outcome["seconds"])
            restarts += 1
            proc, address, log = _start(base, data_dir, restarts)
            with Client(address, timeout_s=120) as c:
                project = c.get_project(PROJECT)  # opens the project: recovery and collection
                listed = [s.name for s in c.list_scans(PROJECT)]
                versions = c.list_versions(PROJECT)
                if name in listed and name not in committed:
                    committed.append(name)  # committed, but killed before the reply reached us
                print(f"\nround {round_}: {name} {'committed' if name in listed else 'lost'} "
                      f"(client told {'ok' if 'result' in outcome else 'error'}); HEAD "
                      f"{project.head_version}, scans {listed}")
                assert listed == committed, (listed, committed)
                assert project.scan_count == len(committed)
                assert [v.version for v in versions][-1] == project.head_version
                assert [v.made_by for v in versions] == [f"ingest scan {s}" for s in committed][
                    -len(versions):]
                if project.head_version:
                    r = c.render(PROJECT, [2.0, 2.0, 1.5], 128, 64, formats=("exr",))
                    assert r.hit_pixels > 0 and np.isfinite(r.depth_m).any()
            pdir = os.path.join(data_dir, PROJECT)
            objects, blobs = _referenced(pdir)
            on_disk = set(os.listdir(os.path.join(pdir, "objects")))
            assert on_disk == objects, (sorted(on_disk - objects)[:3], sorted(objects - on_disk)[:3])
            assert set(os.listdir(os.path.join(pdir, "blobs"))) == blobs
        print(f"\ncrash safety: {kills} kills during ingests, {restarts} restarts, {len(committed)} scans "
              f"committed and all present; no orphan object, blob or staging file")
        assert kills >= 3, "fewer than 3 kills landed during an ingest"
        assert committed, "no ingest survived: the kill window is too short"
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        log.close()
