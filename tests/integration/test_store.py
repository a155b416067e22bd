"""The tiled store through a real vasld and the `vasl` CLI: versions with what made each,
rebuild (the oracle: same renders), scan deletion, export of one merged .vdb that vdb_print
opens with the project's record count."""
from __future__ import annotations

import json
import os
import re
import subprocess

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli

PROJECT = "store-e2e"


def test_versions_rebuild_delete_and_export_from_the_cli(client, server, scene_dir, tmp_path):
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    scans = manifests(scene_dir)[:3]
    for m in scans:
        r = client.ingest(PROJECT, m)
        print(f"\ningested {r.scan}: v{r.version}, {r.change.sources_computed} sources computed, "
              f"{r.change.sources_revisited} revisited on {r.change.pairs_revisited} pairs, "
              f"{r.change.tiles_changed} tiles, {r.change.bytes_written / 1e6:.1f} MB written")
        assert r.change.sources_computed == 2  # the scan's LiDAR and camera
        assert r.change.bytes_written > 0
    head = client.get_project(PROJECT)
    pose = {"position": [2.0, 2.0, 1.5], "quaternion": [0, 0, 0, 1]}
    before = client.render(PROJECT, pose, 256, 128, formats=("exr",))

    out = run_cli(server, "rebuild", "--project", PROJECT).stdout
    print(out)
    assert re.search(r"rebuilt store-e2e: version 4,", out), out
    rebuilt = client.get_project(PROJECT)
    assert (rebuilt.vossel_count, rebuilt.record_count) == (head.vossel_count, head.record_count)
    after = client.render(PROJECT, pose, 256, 128, formats=("exr",))
    assert np.array_equal(before.rgb, after.rgb) and np.array_equal(before.depth_m, after.depth_m)

    listed = json.loads(run_cli(server, "versions", "--project", PROJECT, "--json").stdout)
    made_by = [v["made_by"] for v in listed]
    print("versions:", made_by)
    assert made_by == ["ingest scan scan-1", "ingest scan scan-2", "ingest scan scan-3", "rebuild"]
    assert all(v["tile_count"] >= 1 and v["bytes_total"] >= v["bytes_written"] > 0 for v in listed)

    out = run_cli(server, "scan", "delete", "scan-2", "--project", PROJECT).stdout
    print(out)
    assert [s.name for s in client.list_scans(PROJECT)] == ["scan-1", "scan-3"]
    missing = run_cli(server, "scan", "delete", "scan-2", "--project", PROJECT, check=False)
    assert missing.returncode == 1 and "NOT_FOUND" in missing.stderr, missing.stderr

    target = str(tmp_path / "site.vdb")
    out = run_cli(server, "export", "--project", PROJECT, "-o", target).stdout
    print(out)
    project = client.get_project(PROJECT)
    r = subprocess.run(["vdb_print", target], capture_output=True, text=True)  # a grid a line
    assert r.returncode == 0, r.stderr
    grids = {line.split()[0] for line in r.stdout.splitlines() if line.strip()}
    r = subprocess.run(["vdb_print", "-m", target], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert {"records", "index", "normal", "rgb.value"} <= grids, grids
    count = re.search(r"record_count: (\d+)", r.stdout)
    assert count and int(count.group(1)) == project.record_count, r.stdout[:2000]
    print(f"export: {os.path.getsize(target) / 1e6:.1f} MB, {int(count.group(1))} records, grids "
          f"{sorted(grids)}")
    bad = run_cli(server, "export", "--project", PROJECT, "--version", "99", "-o", target,
                check=False)
    assert bad.returncode == 1 and "NOT_FOUND" in bad.stderr, bad.stderr
