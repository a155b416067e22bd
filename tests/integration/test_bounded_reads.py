"""A server whose --max-snapshot-bytes is far below a project's size renders it and answers
records queries tile group by tile group, and gives what a server that reads the project whole
gives: the same pixels through the streamed EXR, the same rows (issue "A store that grows",
bounded memory; the engine-level claim with every render mode is tests/engine/bounded_read_test.cc)."""
from __future__ import annotations

import numpy as np

from crash_util import start_vasld
from conftest import VASLD, VOSSEL_M, manifests
from vasl import Client

BUDGET = str(2_000_000)  # bytes: a few tiles of the room's version at a time


def _serve(tmp_path, data, n, extra, work):
    proc, address, log = start_vasld(VASLD, str(tmp_path), data, n, extra)
    try:
        with Client(address, timeout_s=300) as client:
            return work(client)
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        log.close()


def _ask(client, view):
    pose = {"position": view["position"], "quaternion": view["quaternion"]}
    image = client.render("room", pose, 512, 256, formats=("exr",), stream_rows=True)
    deep = client.render("room", pose, 256, 128, formats=("exr",), eta=1.0)
    centre = np.asarray(view["position"], float)
    rows = client.query_records("room", box=[*(centre - 1.5), *(centre + 1.5)]).records
    return image, deep, rows


def test_a_bounded_server_answers_as_a_whole_one(tmp_path, scene_dir, views):
    import os
    data = str(tmp_path / "data")
    os.makedirs(data)
    view = views["novel-1"]

    def ingest_and_ask(client):
        client.create_project("room", vossel_size_m=VOSSEL_M)
        for m in manifests(scene_dir)[:2]:
            client.ingest("room", m)
        return _ask(client, view)

    whole = _serve(tmp_path, data, 0, (), ingest_and_ask)
    bounded = _serve(tmp_path, data, 1, ("--max-snapshot-bytes", BUDGET),
                     lambda client: _ask(client, view))
    for a, b in zip(whole[:2], bounded[:2]):
        print(f"{a.width_px}x{a.height_px}: whole in {a.tile_groups} group, bounded in "
              f"{b.tile_groups} reading {b.tiles_read} of {b.tiles_total} tiles; "
              f"{a.hit_pixels} hit pixels")
        assert a.tile_groups == 1 and a.tiles_total == 0
        assert b.tile_groups >= 2 and 0 < b.tiles_read <= b.tiles_total
        assert a.hit_pixels > a.width_px * a.height_px // 2
        assert b.hit_pixels == a.hit_pixels
        for name in ("rgb", "depth_m", "normal", "uncertainty", "alpha"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    assert len(whole[2]) > 100
    assert bounded[2] == whole[2]
