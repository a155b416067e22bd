"""Crash soak (deploy/soak.sh): vasld is killed with SIGKILL at random moments during ingests,
reweights and back-projections, many rounds of each. After every restart:
  - the project opens (which recovers it and collects what no kept version references);
  - HEAD is a complete version: it is the newest kept version, its history is exactly the
    committed operations in order, every tile of it reads (an export of HEAD, a records
    inspection and a render succeed);
  - every operation the client was told was committed is there, and one that was not committed
    is not visible at all (no scan, no batch, no fused layer of its profile revision);
  - no object, blob or staging file outside the kept versions survives that collection, and
    the data directory holds nothing but projects.
Kills during exports (which change nothing) check the last point alone.
Rounds per kind come from VASL_SOAK_INGEST_KILLS (default 20), VASL_SOAK_REWEIGHT_KILLS (8),
VASL_SOAK_BACKPROJECT_KILLS (8) and VASL_SOAK_EXPORT_KILLS (6); VASL_SOAK_SEED seeds the kill
moments. Each test prints one `soak: ...` summary line."""
from __future__ import annotations

import os
import random
import signal
import threading
import time

import numpy as np
import pytest

from conftest import VASLD, VOSSEL_M, env_int, manifests
from crash_util import referenced, start_vasld

SEED = env_int("VASL_SOAK_SEED", 2026)
POSE = [2.0, 2.0, 1.5]
TIMEOUT_S = 300


class Vasld:
    """A vasld over one data directory that is killed and started again."""

    def __init__(self, base: str):
        self.base = base
        self.data_dir = os.path.join(base, "data")
        self.starts = 0
        self.proc = None
        self.address = ""
        self.log = None
        self.start()

    def start(self):
        self.proc, self.address, self.log = start_vasld(VASLD, self.base, self.data_dir,
                                                        self.starts)
        self.starts += 1

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=60)
        self.log.close()

    def restart(self):
        """Stops vasld gracefully (SIGTERM) and starts it again."""
        self.stop()
        self.start()

    def stop(self):
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except Exception:
                self.proc.kill()
                self.proc.wait()
        if self.log is not None:
            self.log.close()

    def client(self):
        from vasl import Client

        return Client(self.address, timeout_s=TIMEOUT_S)


def timed(fn):
    """(fn(), seconds it took)."""
    t0 = time.monotonic()
    result = fn()
    return result, time.monotonic() - t0


def kill_during(server: Vasld, op, delay_s: float):
    """Runs op(client) in a thread, kills vasld after `delay_s`; returns (outcome, during):
    outcome has "result" (the client was told it committed) or "error"; `during` says the kill
    landed before the reply (else it landed after the commit: also a crash point)."""
    from vasl import VaslError

    outcome = {}

    def run():
        t0 = time.monotonic()
        try:
            with server.client() as c:
                outcome["result"] = op(c)
        except VaslError as e:
            outcome["error"] = e
        outcome["seconds"] = time.monotonic() - t0

    t = threading.Thread(target=run)
    t.start()
    time.sleep(delay_s)
    during = t.is_alive()
    server.kill()
    t.join(timeout=TIMEOUT_S)
    assert not t.is_alive(), "the client call did not return after the kill"
    return outcome, during


def check_store(server: Vasld, project: str, made_by: list, tmp_path) -> dict:
    """The checks every restart must pass; `made_by` is the history of committed operations
    (versions' made_by, oldest first). Returns the project."""
    with server.client() as c:
        p = c.get_project(project)  # opens the project: recovery and collection
        versions = c.list_versions(project)
        assert versions, "no kept version"
        assert versions[-1].version == p.head_version, (versions[-1].version, p.head_version)
        assert [v.made_by for v in versions] == made_by[-len(versions):], (
            [v.made_by for v in versions], made_by[-len(versions):])
        assert len(versions) <= len(made_by)
        # HEAD complete: every tile and layer of it reads.
        out = str(tmp_path / "head.vdb")
        exported = c.export(project, out)
        assert exported.version == p.head_version and os.path.getsize(out) == exported.size_bytes
        assert exported.record_count == p.record_count, (exported.record_count, p.record_count)
        os.unlink(out)
        inspection = c.inspect_records(project)
        assert inspection.version == p.head_version
        assert inspection.record_count == p.record_count, (inspection.record_count, p.record_count)
        r = c.render(project, POSE, 128, 64, formats=("exr",))
        assert r.version == p.head_version and r.hit_pixels > 0 and np.isfinite(r.depth_m).any()
    pdir = os.path.join(server.data_dir, project)
    objects, blobs = referenced(pdir)
    on_disk = set(os.listdir(os.path.join(pdir, "objects")))
    assert on_disk == objects, (sorted(on_disk - objects)[:3], sorted(objects - on_disk)[:3])
    assert set(os.listdir(os.path.join(pdir, "blobs"))) == blobs
    staging = [os.path.join(d, n) for d, dirs, files in os.walk(pdir) for n in dirs + files
               if n.startswith(".tmp-") or ".tmp-" in n]
    assert not staging, f"staging files survived the restart: {staging[:3]}"
    stray = [n for n in os.listdir(server.data_dir)
             if not os.path.isdir(os.path.join(server.data_dir, n))
             and not n.startswith("access.sqlite")]
    assert not stray, f"files in the data directory that are no project: {stray[:3]}"
    return p


class KillWindow:
    """When to kill, as a fraction of the operation's expected duration: half the kills
    anywhere in [0.02, 1.0], half in [0.75, 1.25] where the commit runs (objects, manifest,
    HEAD) and just after it (between commit and reply, or after the reply). The estimate
    follows the operations that finish and grows when kills near its end still land inside."""

    def __init__(self, rng: random.Random, estimate_s: float):
        self.rng = rng
        self.estimate_s = estimate_s

    def delay(self) -> float:
        lo, hi = (0.02, 1.0) if self.rng.random() < 0.5 else (0.75, 1.25)
        return self.rng.uniform(lo, hi) * self.estimate_s

    def observe(self, outcome: dict, during: bool, delay_s: float):
        if not during and "result" in outcome:
            self.estimate_s = 0.5 * self.estimate_s + 0.5 * outcome["seconds"]
        elif during and delay_s > 0.8 * self.estimate_s:
            self.estimate_s = max(self.estimate_s, 1.2 * delay_s)


def describe(outcome: dict, during: bool, delay: float, window: KillWindow) -> str:
    return (f"client told {'ok' if 'result' in outcome else 'error'}, kill at {delay:.2f} s of "
            f"~{window.estimate_s:.2f} s {'during' if during else 'after'}")


def kill_round(server: Vasld, op, window: KillWindow):
    delay = window.delay()
    outcome, during = kill_during(server, op, delay)
    window.observe(outcome, during, delay)
    server.start()
    return outcome, during, delay


def report(kind: str, rounds: int, during: int, committed: int, lost: int, unreplied: int,
           seconds: float):
    print(f"\nsoak: kills during {kind}: {rounds} kills ({during} before the reply, "
          f"{rounds - during} after), {rounds} restarts all whole; {committed} committed and "
          f"present ({unreplied} of them committed although the client got an error), {lost} lost "
          f"and invisible; {seconds:.0f} s")


def test_kill_during_ingests(scene_dir, tmp_path):
    from vasl import read_manifest

    rounds = env_int("VASL_SOAK_INGEST_KILLS", 20)
    rng = random.Random(SEED)
    project = "soak-ingest"
    scans = manifests(scene_dir)
    t_start = time.monotonic()
    server = Vasld(str(tmp_path))
    committed, made_by = [], []
    during_n = lost = unreplied = 0
    try:
        # Two ingests that are not killed; the second, on a restarted vasld as every round
        # runs, sets the kill window.
        for i, m in enumerate(scans[:2]):
            if i:
                server.restart()
            with server.client() as c:
                if not i:
                    c.create_project(project, vossel_size_m=VOSSEL_M)
                c.get_project(project)
                _, window_s = timed(lambda: c.ingest(project, m))
            committed.append(read_manifest(m).scan)
            made_by.append(f"ingest scan {committed[-1]}")
        window = KillWindow(rng, window_s)
        for round_ in range(rounds):
            manifest = read_manifest(scans[round_ % len(scans)])
            manifest.scan = name = f"{manifest.scan}-k{round_}"
            outcome, during, delay = kill_round(server, lambda c: c.ingest(project, manifest),
                                                window)
            during_n += during
            with server.client() as c:
                c.get_project(project)
                listed = [s.name for s in c.list_scans(project)]
            if "result" in outcome or name in listed:
                if "result" not in outcome:
                    unreplied += 1
                committed.append(name)
                made_by.append(f"ingest scan {name}")
            else:
                lost += 1
            assert listed == committed, (listed, committed)
            p = check_store(server, project, made_by, tmp_path)
            assert p.scan_count == len(committed)
            print(f"ingest round {round_}: {name} {'committed' if name in listed else 'lost'} "
                  f"({describe(outcome, during, delay, window)}); HEAD {p.head_version}, "
                  f"{len(listed)} scans")
        report("ingests", rounds, during_n, len(committed) - 2, lost, unreplied,
               time.monotonic() - t_start)
        assert during_n >= min(3, rounds), "too few kills landed during an ingest"
        assert len(committed) > 2 or rounds < 5, \
            "no killed ingest ever committed: the kill window is too short"
    finally:
        server.stop()


def _project_with_scans(server: Vasld, project: str, scans, n: int) -> list:
    with server.client() as c:
        c.create_project(project, vossel_size_m=VOSSEL_M)
        for m in scans[:n]:
            c.ingest(project, m)
        return [v.made_by for v in c.list_versions(project)]


def test_kill_during_reweights(scene_dir, tmp_path):
    rounds = env_int("VASL_SOAK_REWEIGHT_KILLS", 8)
    rng = random.Random(SEED + 1)
    project = "soak-reweight"
    t_start = time.monotonic()
    server = Vasld(str(tmp_path))
    during_n = lost = unreplied = committed = 0
    try:
        made_by = _project_with_scans(server, project, manifests(scene_dir), 3)
        with server.client() as c:
            c.create_profile(project, {"name": "soak", "alpha": 1.0})
        server.restart()  # the window: a reweight on a restarted vasld, as every round runs
        with server.client() as c:
            c.get_project(project)
            first, window_s = timed(lambda: c.reweight(project, "soak"))
        made_by.append(f"reweight under profile soak revision {first.revision}")
        stored = {first.revision}  # revisions whose fused tiles HEAD must hold
        window = KillWindow(rng, window_s)
        for round_ in range(rounds):
            with server.client() as c:
                revision = c.create_profile(project, {"name": "soak", "alpha": 1.5 + 0.25 * round_,
                                                      "rho": 0.25 + 0.05 * round_})["revision"]
            outcome, during, delay = kill_round(
                server, lambda c: c.reweight(project, "soak", revision), window)
            during_n += during
            label = f"reweight under profile soak revision {revision}"
            with server.client() as c:
                c.get_project(project)
                head_made_by = c.list_versions(project)[-1].made_by
                if "result" in outcome:
                    assert outcome["result"].revision == revision
                if "result" in outcome or head_made_by == label:
                    if "result" not in outcome:
                        unreplied += 1
                    committed += 1
                    made_by.append(label)
                    stored.add(revision)
                else:
                    lost += 1
                check_store(server, project, made_by, tmp_path)
                # A committed revision renders from stored fused tiles, a lost one is fused on
                # the fly: no fused layer of it is visible. Earlier committed ones stay stored.
                for rev in (revision, max(stored)):
                    r = c.render(project, POSE, 128, 64, formats=("exr",), profile="soak",
                                 profile_revision=rev)
                    assert r.hit_pixels > 0
                    assert r.fused_on_the_fly == (rev not in stored), (rev, sorted(stored))
            print(f"reweight round {round_}: revision {revision} "
                  f"{'committed' if revision in stored else 'lost'} "
                  f"({describe(outcome, during, delay, window)})")
        report("reweights", rounds, during_n, committed, lost, unreplied,
               time.monotonic() - t_start)
        assert during_n >= min(2, rounds), "too few kills landed during a reweight"
    finally:
        server.stop()


def test_kill_during_back_projections(scene_dir, tmp_path):
    rounds = env_int("VASL_SOAK_BACKPROJECT_KILLS", 8)
    rng = random.Random(SEED + 2)
    project = "soak-backproject"
    t_start = time.monotonic()
    server = Vasld(str(tmp_path))
    during_n = lost = unreplied = 0
    try:
        made_by = _project_with_scans(server, project, manifests(scene_dir), 2)
        scans = ["scan-1", "scan-2"]
        with server.client() as c:
            view = c.render(project, POSE, 1024, 512, formats=("exr",))
        server.restart()  # the window: a back-projection on a restarted vasld, as rounds run
        with server.client() as c:
            c.get_project(project)
            _, window_s = timed(lambda: c.back_project(project, view.exr, POSE, name="bp-first",
                                                       render_id=view.render_id))
        made_by.append("back-project bp-first")
        batches = ["bp-first"]
        window = KillWindow(rng, window_s)
        for round_ in range(rounds):
            name = f"bp-k{round_}"
            outcome, during, delay = kill_round(
                server, lambda c: c.back_project(project, view.exr, POSE, name=name,
                                                 render_id=view.render_id), window)
            during_n += during
            with server.client() as c:
                c.get_project(project)
                listed = [s.name for s in c.list_scans(project)]
                derived = [s.name for s in c.list_scans(project)
                           if any(src.modality == "derived" for src in s.sources)]
            if "result" in outcome or name in listed:
                if "result" not in outcome:
                    unreplied += 1
                batches.append(name)
                made_by.append(f"back-project {name}")
            else:
                lost += 1
            assert derived == batches, (derived, batches)
            assert listed == scans + batches, (listed, scans + batches)
            check_store(server, project, made_by, tmp_path)
            print(f"back-projection round {round_}: {name} "
                  f"{'committed' if name in batches else 'lost'} "
                  f"({describe(outcome, during, delay, window)})")
        report("back-projections", rounds, during_n, len(batches) - 1, lost, unreplied,
               time.monotonic() - t_start)
        assert during_n >= min(2, rounds), "too few kills landed during a back-projection"
    finally:
        server.stop()


def test_kill_during_exports(scene_dir, tmp_path):
    rounds = env_int("VASL_SOAK_EXPORT_KILLS", 6)
    rng = random.Random(SEED + 3)
    project = "soak-export"
    t_start = time.monotonic()
    server = Vasld(str(tmp_path))
    during_n = 0
    stray_rounds = 0
    try:
        made_by = _project_with_scans(server, project, manifests(scene_dir), 3)
        server.restart()
        out = str(tmp_path / "export.vdb")
        with server.client() as c:
            c.get_project(project)
            _, window_s = timed(lambda: c.export(project, out))
        window = KillWindow(rng, window_s)
        for round_ in range(rounds):
            # Exports write their file near their end: kill in the second half and just after.
            delay = rng.uniform(0.4, 1.2) * window.estimate_s
            outcome, during = kill_during(server, lambda c: c.export(project, out), delay)
            server.start()
            during_n += during
            stray = sorted(n for n in os.listdir(server.data_dir) if n.startswith(".tmp-export"))
            stray_rounds += bool(stray)
            assert not os.path.exists(out + ".part"), "the client left its .part file"
            print(f"export round {round_}: kill at {delay:.2f} s of ~{window.estimate_s:.2f} s "
                  f"{'during' if during else 'after'}; left in the data directory: "
                  f"{stray or 'nothing'}")
            if "result" in outcome:
                os.unlink(out)
        print(f"\nsoak: kills during exports: {rounds} kills, {during_n} before the reply; "
              f"{stray_rounds} restarts found export staging files left in the data directory; "
              f"{time.monotonic() - t_start:.0f} s")
        check_store(server, project, made_by, tmp_path)
    finally:
        server.stop()
