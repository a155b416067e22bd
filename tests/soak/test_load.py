"""Load on loopback (deploy/soak.sh): while scans are being ingested, many small renders run
concurrently (VASL_SOAK_LOAD_THREADS threads, default 8, each VASL_SOAK_LOAD_RENDERS renders,
default 40, of 128×64 from poses around the room). Bounded: a fixed number of renders and a
deadline (VASL_SOAK_LOAD_DEADLINE_S, default 600). The ingests run one after another (the last
scan, then renamed copies) while the renders last, at most VASL_SOAK_LOAD_MAX_INGESTS (6).
Every render must succeed and show a committed version; prints `soak: load ...` lines with the
count, errors, latency p50 / p99 / max (and a one-client baseline), throughput, how many renders
overlapped an ingest, and vasld's peak RSS (VmHWM) before and after."""
from __future__ import annotations

import os
import random
import threading
import time

import numpy as np

from conftest import VASLD, VOSSEL_M, env_int, manifests
from crash_util import start_vasld

PROJECT = "soak-load"


def vm_kib(pid: int, field: str) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return -1


def test_concurrent_renders_during_an_ingest(scene_dir, tmp_path):
    from vasl import Client, VaslError

    threads_n = env_int("VASL_SOAK_LOAD_THREADS", 8)
    per_thread = env_int("VASL_SOAK_LOAD_RENDERS", 40)
    deadline_s = env_int("VASL_SOAK_LOAD_DEADLINE_S", 600)
    scans = manifests(scene_dir)
    base = str(tmp_path)
    proc, address, log = start_vasld(VASLD, base, os.path.join(base, "data"), 0)
    try:
        with Client(address, timeout_s=300) as c:
            c.create_project(PROJECT, vossel_size_m=VOSSEL_M)
            for m in scans[:-1]:
                c.ingest(PROJECT, m)
            before = c.get_project(PROJECT).head_version
            idle = []
            for i in range(20):  # one client, nothing else running: the baseline
                t0 = time.monotonic()
                c.render(PROJECT, [1.5 + 0.05 * i, 2.0, 1.5], 128, 64, formats=("exr",))
                idle.append(time.monotonic() - t0)
        hwm_before = vm_kib(proc.pid, "VmHWM")

        # Ingests (the last scan, then renamed copies) one after another for as long as the
        # renders run, at most max_ingests of them: every render overlaps an ingest.
        max_ingests = env_int("VASL_SOAK_LOAD_MAX_INGESTS", 6)
        ingest = {"results": [], "seconds": []}
        ingest_done = threading.Event()
        renders_done = threading.Event()

        def run_ingest():
            from vasl import read_manifest

            try:
                with Client(address, timeout_s=600) as c:
                    for i in range(max_ingests):
                        if i and renders_done.is_set():
                            break
                        m = read_manifest(scans[(len(scans) - 1 + i) % len(scans)])
                        if i:
                            m.scan = f"{m.scan}-load{i}"
                        t0 = time.monotonic()
                        ingest["results"].append(c.ingest(PROJECT, m))
                        ingest["seconds"].append(time.monotonic() - t0)
            except VaslError as e:
                ingest["error"] = e
            ingest_done.set()

        lock = threading.Lock()
        latencies, overlapped, errors, versions = [], [0], [], set()
        stop_at = time.monotonic() + deadline_s

        def run_renders(seed: int):
            rng = random.Random(seed)
            with Client(address, timeout_s=120) as c:
                for _ in range(per_thread):
                    if time.monotonic() > stop_at:
                        break
                    pose = [rng.uniform(1.0, 3.0), rng.uniform(1.0, 3.0), rng.uniform(1.0, 2.0)]
                    during = not ingest_done.is_set()
                    t0 = time.monotonic()
                    try:
                        r = c.render(PROJECT, pose, 128, 64, formats=("exr",))
                        ok = (r.width_px, r.height_px, r.depth_m.shape) == (128, 64, (64, 128))
                        err = None if ok else f"bad render {r.width_px}x{r.height_px}"
                    except VaslError as e:
                        r, err = None, str(e)
                    dt = time.monotonic() - t0
                    with lock:
                        latencies.append(dt)
                        if err:
                            errors.append(err)
                        else:
                            versions.add(r.version)
                        if during and not ingest_done.is_set():
                            overlapped[0] += 1

        ti = threading.Thread(target=run_ingest)
        workers = [threading.Thread(target=run_renders, args=(i,)) for i in range(threads_n)]
        peak_rss = 0
        ti.start()
        time.sleep(0.2)  # the upload under way
        t0 = time.monotonic()
        for w in workers:
            w.start()
        while any(w.is_alive() for w in workers):
            peak_rss = max(peak_rss, vm_kib(proc.pid, "VmRSS"))
            time.sleep(0.05)
        wall = time.monotonic() - t0
        renders_done.set()
        while ti.is_alive():
            peak_rss = max(peak_rss, vm_kib(proc.pid, "VmRSS"))
            time.sleep(0.05)
        for w in workers:
            w.join()
        ti.join()
        hwm_after = vm_kib(proc.pid, "VmHWM")

        lat = np.array(latencies) * 1e3
        n = len(latencies)
        p50, p99, worst = ((np.percentile(lat, 50), np.percentile(lat, 99), lat.max()) if n
                           else (0, 0, 0))
        print(f"\nsoak: load renders: {n} renders of 128x64 from {threads_n} threads, "
              f"{len(errors)} errors, {n / wall:.1f} renders/s over {wall:.1f} s, "
              f"{overlapped[0]} of them during an ingest")
        idle_ms = np.array(idle) * 1e3
        print(f"soak: load latency: p50 {p50:.0f} ms, p99 {p99:.0f} ms, max {worst:.0f} ms "
              f"(one client alone before: p50 {np.percentile(idle_ms, 50):.0f} ms, "
              f"max {idle_ms.max():.0f} ms)")
        secs = ", ".join(f"{x:.1f}" for x in ingest["seconds"])
        print(f"soak: load ingests: {len(ingest['results'])} committed under the render load "
              f"({secs} s){', FAILED: ' + str(ingest['error']) if 'error' in ingest else ''}; "
              f"renders saw versions {sorted(versions)}")
        print(f"soak: load vasld memory: peak RSS (VmHWM) {hwm_before / 1024:.0f} MiB before the "
              f"load, {hwm_after / 1024:.0f} MiB after; highest sampled VmRSS "
              f"{peak_rss / 1024:.0f} MiB")
        assert not errors, errors[:5]
        assert "error" not in ingest, ingest["error"]
        assert n == threads_n * per_thread, f"only {n} renders before the deadline"
        committed = {before} | {r.version for r in ingest["results"]}
        assert versions <= committed, (versions, committed)
        with Client(address, timeout_s=60) as c:
            assert c.health() == "SERVING"
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=60)
        log.close()
