"""Reweighting stored projects through a real vasld and the `vasl` CLI (VASL-MODEL §7):
profiles from TOML and JSON files with revisions, renders under a profile (fused on the fly,
then from stored tiles after `vasl reweight`, bit for bit the same), provenance queries with
weights, normalisation into a profile, pinning."""
from __future__ import annotations

import json
import re

import numpy as np

from conftest import VOSSEL_M, manifests, run_cli

PROJECT = "reweight-e2e"
POSE = {"position": [2.0, 2.0, 1.5], "quaternion": [0, 0, 0, 1]}


def test_profiles_reweight_records_normalise_and_pin_from_the_cli(client, server, scene_dir,
                                                                  tmp_path):
    client.create_project(PROJECT, vossel_size_m=VOSSEL_M)
    for m in manifests(scene_dir)[:2]:
        client.ingest(PROJECT, m)

    toml = tmp_path / "steep.toml"
    toml.write_text('alpha = 4.0\nbeta = 0.5\ntheta_max_deg = 75\nmode = "blend"\n'
                    '[kappa]\nsaturation = 2.0\n')
    out = run_cli(server, "profile", "create", "steep", "--project", PROJECT, "--file", str(toml)).stdout
    assert "created profile steep revision 1" in out, out
    js = tmp_path / "steep.json"
    js.write_text(json.dumps({"alpha": 2.0, "v_min": 0.25, "scan_gain": {"2": 0.5}}))
    out = run_cli(server, "profile", "create", "steep", "--project", PROJECT, "--file", str(js),
                "--set", "rho=0.5").stdout
    assert "created profile steep revision 2" in out, out
    listed = json.loads(run_cli(server, "profile", "list", "--project", PROJECT, "--json").stdout)
    assert listed["active"] == "default"
    by_name = {p["name"]: p for p in listed["profiles"]}
    assert by_name["steep"]["revision"] == 2 and by_name["steep"]["rho"] == 0.5
    first = json.loads(run_cli(server, "profile", "show", "steep", "--project", PROJECT,
                             "--revision", "1", "--json").stdout)
    assert first["alpha"] == 4.0 and abs(first["theta_max_rad"] - np.deg2rad(75)) < 1e-12
    assert first["kappa"]["saturation"] == 2.0 and first["kappa"]["flare"] == 1.0

    bad = run_cli(server, "profile", "create", "broken", "--project", PROJECT, "--set", "v_min=2",
                check=False)
    assert bad.returncode == 1 and "INVALID_ARGUMENT" in bad.stderr, bad.stderr
    bad = run_cli(server, "profile", "create", "broken", "--project", PROJECT, "--set", "alhpa=2",
                check=False)
    assert bad.returncode == 2 and "unknown profile parameter" in bad.stderr, bad.stderr

    exr = str(tmp_path / "steep.exr")
    out = run_cli(server, "render", "--project", PROJECT, "--pose", "2,2,1.5", "--width", "256",
                "--height", "128", "--profile", "steep", "-o", exr).stdout
    assert "fused for this render" in out, out
    fly = client.render(PROJECT, POSE, 256, 128, formats=("exr",), profile="steep")
    assert fly.fused_on_the_fly and fly.profile_revision == 2

    out = run_cli(server, "reweight", "--project", PROJECT, "--profile", "steep").stdout
    print(out)
    m = re.search(r"reweighted reweight-e2e under steep revision 2: version 3, (\d+) records", out)
    assert m, out
    assert int(m.group(1)) == client.get_project(PROJECT).record_count
    stored = client.render(PROJECT, POSE, 256, 128, formats=("exr",), profile="steep")
    assert not stored.fused_on_the_fly
    assert np.array_equal(stored.rgb, fly.rgb) and np.array_equal(stored.uncertainty, fly.uncertainty)
    plain = client.render(PROJECT, POSE, 256, 128, formats=("exr",))
    assert plain.profile == "default"
    assert np.abs(plain.rgb - stored.rgb).max() > 1e-3, "the profile changes the fused colour"
    again = run_cli(server, "reweight", "--project", PROJECT, "--profile", "steep").stdout
    assert "already holds fused tiles" in again, again

    recs = json.loads(run_cli(server, "records", "--project", PROJECT, "--box",
                            "0,0,0,10,10,10", "--profile", "steep", "--limit", "300",
                            "--json").stdout)
    assert recs["truncated"] and len(recs["records"]) == 300 and recs["revision"] == 2
    scans = {r["scan"] for r in recs["records"]}
    assert scans <= {"scan-1", "scan-2"} and scans, scans
    rgb = [r for r in recs["records"] if r["modality"] == "rgb"]
    assert rgb and all(len(r["value"]) == 3 for r in rgb)
    # A record below V_min has weight 0; the second scan's camera counts half (scan_gain).
    assert all(r["weight"] == 0.0 for r in recs["records"] if r["vis"] < 0.25)
    point = recs["records"][0]["centroid_m"]
    one = json.loads(run_cli(server, "records", "--project", PROJECT, "--at",
                           ",".join(map(str, point)), "--json").stdout)
    assert one["vossel_count"] == 1 and one["records"], one
    table = run_cli(server, "records", "--project", PROJECT, "--at", ",".join(map(str, point))).stdout
    assert "WEIGHT" in table and "scan-" in table, table

    out = run_cli(server, "normalise", "--project", PROJECT).stdout
    print(out)
    assert "profile normalised revision 1" in out, out
    norm = client.get_profile(PROJECT, "normalised")
    gains = np.array(list(norm["channel_gain"].values()))
    assert gains.shape[1] == 3 and np.allclose(gains.mean(axis=0), 1.0, atol=1e-9)
    run_cli(server, "reweight", "--project", PROJECT, "--profile", "normalised", "--quiet")

    out = run_cli(server, "profile", "activate", "steep", "--project", PROJECT).stdout
    assert "active profile of reweight-e2e: steep" in out, out
    active = client.render(PROJECT, POSE, 256, 128, formats=("exr",))
    assert active.profile == "steep" and np.array_equal(active.rgb, stored.rgb)

    out = run_cli(server, "pin", "1", "--project", PROJECT).stdout
    assert "version 1 of reweight-e2e is pinned" in out, out
    versions = json.loads(run_cli(server, "versions", "--project", PROJECT, "--json").stdout)
    assert [v["made_by"] for v in versions][2:] == ["reweight under profile steep revision 2",
                                                   "reweight under profile normalised revision 1"]
    assert versions[0]["pinned"]
    out = run_cli(server, "rollback", "3", "--project", PROJECT).stdout
    print(out)
    assert "rolled reweight-e2e back to version 3: version 5" in out, out
    back = client.render(PROJECT, POSE, 256, 128, formats=("exr",), profile="steep")
    assert not back.fused_on_the_fly and np.array_equal(back.rgb, stored.rgb)
    assert client.list_versions(PROJECT)[-1].made_by == "rollback to version 3"
    missing = run_cli(server, "reweight", "--project", PROJECT, "--profile", "nope", check=False)
    assert missing.returncode == 1 and "NOT_FOUND" in missing.stderr, missing.stderr
