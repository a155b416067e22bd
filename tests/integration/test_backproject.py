"""Back-projection (VASL-MODEL §10) through a real vasld and the `vasl` CLI: a render comes
back as a derived batch that cites it, renders again to itself, is listed and rolled back;
bad images are refused with a message and change nothing."""
from __future__ import annotations

import json
import re

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli

PROJECT = "backproject-e2e"
POSE = "2.0,2.0,1.5,0,0,0,1"


def test_backproject_a_render_list_and_roll_back(client, server, scene_dir, tmp_path):
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir)[:2]:
        client.ingest(PROJECT, m)
    exr = str(tmp_path / "view.exr")
    out = run_cli(server, "render", "--project", PROJECT, "--pose", POSE, "--width", "512",
                "--height", "256", "-o", exr).stdout
    render_id = int(re.search(r"render (\d+):", out).group(1))
    before = client.render(PROJECT, POSE, 512, 256, formats=("exr",))
    out = run_cli(server, "backproject", exr, "--project", PROJECT, "--pose", POSE, "--render",
                str(render_id), "--name", "retouch-1").stdout
    print(out)
    m = re.search(r"as batch retouch-1: version 3, (\d+) pixels -> derived records", out)
    assert m and int(m.group(1)) > 100000, out
    after = client.render(PROJECT, POSE, 512, 256, formats=("exr",))
    both = (before.alpha > 0) & (after.alpha > 0)
    mse = float(np.mean((before.rgb[both] - after.rgb[both]) ** 2))
    psnr = 10 * np.log10(1.0 / max(mse, 1e-30))
    print(f"render again after back-projection: PSNR {psnr:.1f} dB over {int(both.sum())} pixels")
    assert psnr >= 40.0
    listed = json.loads(run_cli(server, "batch", "list", "--project", PROJECT, "--json").stdout)
    assert [b["name"] for b in listed] == ["retouch-1"]
    scans = {s.name: s for s in client.list_scans(PROJECT)}
    assert scans["retouch-1"].sources[0].modality == "derived"
    dup = run_cli(server, "backproject", exr, "--project", PROJECT, "--pose", POSE, "--name",
                "retouch-1", check=False)
    assert dup.returncode == 1 and "ALREADY_EXISTS" in dup.stderr, dup.stderr
    png = str(tmp_path / "view.png")
    bad = run_cli(server, "backproject", png, "--project", PROJECT, "--pose", POSE, check=False)
    assert bad.returncode == 1 and "INVALID_ARGUMENT" in bad.stderr, bad.stderr
    missing = run_cli(server, "backproject", exr, "--project", PROJECT, "--pose", POSE, "--render",
                    "9999", check=False)
    assert missing.returncode == 1 and "NOT_FOUND" in missing.stderr, missing.stderr
    assert client.get_project(PROJECT).head_version == 3, "refused images change nothing"

    out = run_cli(server, "batch", "rollback", "retouch-1", "--project", PROJECT).stdout
    print(out)
    assert "rolled back batch retouch-1" in out
    back = client.render(PROJECT, POSE, 512, 256, formats=("exr",))
    assert np.array_equal(back.rgb, before.rgb)
    assert "no derived batches" in run_cli(server, "batch", "list", "--project", PROJECT).stdout


def test_backproject_a_deep_render_from_the_cli(client, server, scene_dir, tmp_path):
    """A deep render (`--layers 3`, out-deep.exr) comes back through the CLI: every layer is
    back-projected, so more samples become derived records than the flat render's pixels."""
    project = PROJECT + "-deep"
    client.create_project(project, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir)[:2]:
        client.ingest(project, m)
    exr = str(tmp_path / "view.exr")
    out = run_cli(server, "render", "--project", project, "--pose", POSE, "--width", "512",
                  "--height", "256", "--layers", "3", "-o", exr).stdout
    render_id = int(re.search(r"render (\d+):", out).group(1))
    flat = run_cli(server, "backproject", exr, "--project", project, "--pose", POSE,
                   "--name", "flat").stdout
    deep = run_cli(server, "backproject", str(tmp_path / "view-deep.exr"), "--project", project,
                   "--pose", POSE, "--render", str(render_id), "--name", "deep").stdout
    print(flat + deep)
    used = [int(re.search(r"(\d+) pixels -> derived records", o).group(1)) for o in (flat, deep)]
    assert used[1] > used[0] > 100000, (flat, deep)
    listed = json.loads(run_cli(server, "batch", "list", "--project", project, "--json").stdout)
    assert sorted(b["name"] for b in listed) == ["deep", "flat"]
