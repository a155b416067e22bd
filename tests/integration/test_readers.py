"""The client's readers: PLY in its three encodings gives the same points; manifests resolve
paths relative to themselves and reject malformed fields with ValueError."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vasl import Pose, read_manifest, read_ply


def _write_ply(path, xyz, intensity, fmt, coord_type="float"):
    n = len(xyz)
    header = (f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {n}\n"
              f"property {coord_type} x\nproperty {coord_type} y\nproperty {coord_type} z\n"
              "property uchar red\nproperty float intensity\n"
              "element face 0\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode())
        if fmt == "ascii":
            for p, i in zip(xyz, intensity):
                f.write(f"{float(p[0])!r} {float(p[1])!r} {float(p[2])!r} 7 {float(i)!r}\n".encode())
        else:
            e = "<" if fmt == "binary_little_endian" else ">"
            c = "f4" if coord_type == "float" else "f8"
            dt = np.dtype([("x", e + c), ("y", e + c), ("z", e + c), ("red", "u1"),
                           ("intensity", e + "f4")])
            rec = np.zeros(n, dtype=dt)
            rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            rec["red"], rec["intensity"] = 7, intensity
            f.write(rec.tobytes())


@pytest.mark.parametrize("fmt,coord", [("ascii", "float"), ("binary_little_endian", "float"),
                                       ("binary_big_endian", "double"),
                                       ("binary_little_endian", "double")])
def test_ply_encodings_agree(tmp_path, fmt, coord):
    rng = np.random.default_rng(11)
    xyz = rng.uniform(-5, 5, size=(257, 3)).astype(np.float32)
    inten = rng.uniform(0, 1, size=257).astype(np.float32)
    path = tmp_path / "p.ply"
    _write_ply(path, xyz, inten, fmt, coord)
    cloud = read_ply(str(path))
    err = float(np.max(np.abs(cloud.xyz_m - xyz)))
    print(f"\n{fmt}/{coord}: {len(cloud)} points, max |dx| {err:.3g} m")
    assert cloud.xyz_m.shape == (257, 3) and cloud.xyz_m.dtype == np.float32
    assert err <= 1e-6
    assert np.allclose(cloud.intensity, inten, atol=1e-6)


def test_ply_without_intensity_and_bad_files(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n0 0 0\n1 2 3\n")
    cloud = read_ply(str(p))
    assert cloud.intensity is None and cloud.xyz_m.tolist() == [[0, 0, 0], [1, 2, 3]]
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(ValueError, match="'y'"):
        read_ply(str(p))
    p.write_bytes(b"not a ply")
    with pytest.raises(ValueError):
        read_ply(str(p))
    p.write_text("ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
                 "property float y\nproperty float z\nend_header\n")
    with pytest.raises(ValueError, match="truncated"):
        read_ply(str(p))


def test_ply_row_and_column_give_the_range_grid(tmp_path):
    p = tmp_path / "g.ply"
    head = ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            "property float z\nproperty int row\nproperty int column\nend_header\n")
    p.write_text(head + "1 0 0 0 0\n1 0.1 0 2 5\n")
    cloud = read_ply(str(p))
    assert cloud.grid.tolist() == [[0, 0], [2, 5]] and cloud.grid.dtype == np.uint32
    p.write_text(head + "1 0 0 0 0\n1 0.1 0 -1 5\n")
    with pytest.raises(ValueError, match="whole numbers >= 0"):
        read_ply(str(p))


def _srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def test_ply_colour_and_intensity_come_in_zero_to_one(tmp_path):
    """Colour (uchar, ushort, float 0..1 or 0..255) is scaled into [0, 1] and linearised;
    integer intensity over its type's largest value, float intensity outside [0, 1] by the
    data's range; one in [0, 1] as it is."""
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 256, size=(50, 3))
    xyz = rng.uniform(-5, 5, size=(50, 3))
    cases = [("uchar", "red green blue", codes, codes / 255.0),
             ("ushort", "r g b", codes * 257, codes / 255.0),
             ("float", "diffuse_red diffuse_green diffuse_blue", codes / 255.0, codes / 255.0),
             ("float", "red green blue", codes.astype(float), codes / 255.0)]
    for ctype, names, values, expected in cases:
        props = "".join(f"property {ctype} {n}\n" for n in names.split())
        p = tmp_path / "c.ply"
        p.write_text("ply\nformat ascii 1.0\nelement vertex 50\nproperty float x\n"
                     "property float y\nproperty float z\n" + props + "property ushort "
                     "intensity\nend_header\n"
                     + "".join(f"{x[0]} {x[1]} {x[2]} {v[0]} {v[1]} {v[2]} {i}\n"
                               for x, v, i in zip(xyz, values, codes[:, 0] * 257)))
        cloud = read_ply(str(p))
        np.testing.assert_allclose(cloud.rgb, _srgb_to_linear(expected), atol=1e-6,
                                   err_msg=f"{ctype} {names}")
        np.testing.assert_allclose(cloud.intensity, codes[:, 0] / 255.0, atol=1e-6)
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y"
                 "\nproperty float z\nproperty float scalar_Intensity\nend_header\n"
                 "1 0 0 -2048\n0 1 0 0\n0 0 1 2047\n")
    np.testing.assert_allclose(read_ply(str(p)).intensity, [0.0, 2048 / 4095, 1.0], atol=1e-6)
    # A signed integer intensity of Leica's range: (i + 2048) / 4095, as a PTS file's.
    p.write_text(p.read_text().replace("float scalar_Intensity", "short scalar_Intensity")
                 .replace("-2048\n0 1 0 0\n0 0 1 2047", "-2048\n0 1 0 0\n0 0 1 1000"))
    np.testing.assert_allclose(read_ply(str(p)).intensity, [0.0, 2048 / 4095, 3048 / 4095],
                               atol=1e-6)
    assert read_ply(str(p)).rgb is None


def test_coloured_ply_manifest_makes_a_point_colour_source(server, client, tmp_path):
    """A PLY's colour is a point-colour source (VASL-MODEL §6), as an E57's or LAS file's is:
    the records of the walls hold the points' colour."""
    from synth_scans import room_points

    xyz = room_points(60_000, seed=9)
    colour = np.where(xyz[:, :1] > 0, [[200, 40, 40]], [[40, 40, 200]])  # +x red, -x blue
    p = tmp_path / "room.ply"
    rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["red"], rec["green"], rec["blue"] = colour.T
    p.write_bytes(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
                  "property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
                  "property uchar green\nproperty uchar blue\nend_header\n".encode()
                  + rec.tobytes())
    manifest = tmp_path / "room.json"
    manifest.write_text(json.dumps({"scan": "room", "pose": {"position": [0, 0, 1.6]},
                                    "lidar": {"points": "room.ply"}}))
    client.create_project("ply-colour", vossel_size_m=0.1)
    client.ingest("ply-colour", str(manifest))
    scan, = client.list_scans("ply-colour")
    assert [s.name for s in scan.sources] == ["lidar", "point-colour"]
    render = client.render("ply-colour", {"position": [0, 0, 1.6]}, 512, 256, formats=("exr",))
    # Looking along +x (§2.1: the centre column) the wall is red, along -x (the edge) blue.
    mid, edge = render.rgb[100:156, 250:262], render.rgb[100:156, :6]
    red, blue = _srgb_to_linear(np.array([200, 40, 40]) / 255), _srgb_to_linear(
        np.array([40, 40, 200]) / 255)
    print(f"\nwall at +x {np.nanmedian(mid.reshape(-1, 3), axis=0)}, at -x "
          f"{np.nanmedian(edge.reshape(-1, 3), axis=0)}; expected {red}, {blue}")
    np.testing.assert_allclose(np.nanmedian(mid.reshape(-1, 3), axis=0), red, atol=0.01)
    np.testing.assert_allclose(np.nanmedian(edge.reshape(-1, 3), axis=0), blue, atol=0.01)
    # Given to the CLI without a manifest, a PLY is refused with the way to send it.
    from conftest import run_cli

    r = run_cli(server, "ingest", str(p), "--project", "ply-colour", check=False)
    assert r.returncode == 2 and "records no scanner pose" in r.stderr and "manifest" in r.stderr
    r = run_cli(server, "ingest", str(tmp_path / "room.ply"), str(manifest), "--project",
                "ply-colour", check=False)
    assert r.returncode == 2 and len(client.list_scans("ply-colour")) == 1  # nothing sent


def test_manifest_paths_and_validation(tmp_path):
    doc = {"scan": "s1", "rig": "r", "captured_utc": "2026-01-01T00:00:00Z",
           "pose": {"position": [1, 2, 3], "quaternion": [0, 0, 0, 2]},
           "lidar": {"points": "s1.ply", "divergence_rad": 0.0005},
           "panoramas": [{"name": "cam0", "image": "img/s1.png", "modality": "rgb",
                          "pose": {"position": [1, 2, 3.1], "quaternion": [0, 0, 0, 1]}}]}
    path = tmp_path / "s1.json"
    path.write_text(json.dumps(doc))
    m = read_manifest(str(path))
    assert m.points_path == str(tmp_path / "s1.ply")
    assert m.panoramas[0].image_path == str(tmp_path / "img" / "s1.png")
    assert m.pose.position_m == (1.0, 2.0, 3.0) and m.divergence_rad == 0.0005
    for bad, match in [({"pose": {"position": [1, 2]}}, "3 numbers"),
                       ({"pose": {"position": [0, 0, float("nan")]}}, "finite"),
                       ({"lidar": {"divergence_rad": 0.1}}, "lidar.points"),
                       ({"scan": ""}, "scan")]:
        path.write_text(json.dumps({**doc, **bad}))
        with pytest.raises(ValueError, match=match):
            read_manifest(str(path))

    # A visual reference may leave out its pose (it takes the scan's); a camera may not.
    ref = {"name": "photo", "image": "img/photo.jpg", "visual_reference": True}
    path.write_text(json.dumps({**doc, "panoramas": doc["panoramas"] + [ref]}))
    m = read_manifest(str(path))
    assert [(p.name, p.visual_reference, p.pose) for p in m.panoramas][1] == ("photo", True, None)
    for bad, match in [({**ref, "visual_reference": False}, "pose"),
                       ({**ref, "visual_reference": "yes"}, "true or false")]:
        path.write_text(json.dumps({**doc, "panoramas": [bad]}))
        with pytest.raises(ValueError, match=match):
            read_manifest(str(path))


def test_manifest_mask_is_a_file_relative_to_the_manifest(tmp_path):
    """`panoramas[].mask`: resolved like `image`; a mask that names no file, is no path, or
    belongs to a visual reference is a ValueError naming the manifest and the panorama."""
    pose = {"position": [0, 0, 1], "quaternion": [0, 0, 0, 1]}
    cam = {"name": "cam0", "image": "cam0.jpg", "pose": pose, "mask": "rig/nadir.png"}
    doc = {"scan": "s1", "pose": pose, "panoramas": [cam]}
    path = tmp_path / "s1.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError) as err:
        read_manifest(str(path))
    assert str(path) in str(err.value) and "'cam0'" in str(err.value)
    assert str(tmp_path / "rig" / "nadir.png") in str(err.value)
    print(f"\n{err.value}")

    (tmp_path / "rig").mkdir()
    (tmp_path / "rig" / "nadir.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    m = read_manifest(str(path))
    assert m.panoramas[0].mask_path == str(tmp_path / "rig" / "nadir.png")
    path.write_text(json.dumps({**doc, "panoramas": [{**cam, "mask": None}]}))
    assert read_manifest(str(path)).panoramas[0].mask_path is None
    for bad, match in [({**cam, "mask": ""}, r"panoramas\[0\] \('cam0'\)\.mask must be the path"),
                       ({**cam, "mask": 3}, "mask must be the path"),
                       ({**cam, "visual_reference": True}, "visual reference.*takes no mask")]:
        path.write_text(json.dumps({**doc, "panoramas": [bad]}))
        with pytest.raises(ValueError, match=match):
            read_manifest(str(path))


def test_manifest_sphere_places_a_partial_panorama(tmp_path):
    """`panoramas[].sphere`: the whole sphere's size and the image's place in it, whole numbers
    (left and top default to 0); anything else is a ValueError naming the field."""
    pose = {"position": [0, 0, 1], "quaternion": [0, 0, 0, 1]}
    cam = {"name": "cam0", "image": "cam0.jpg", "pose": pose,
           "sphere": {"width_px": 8192, "height_px": 4096, "top_px": 0}}
    path = tmp_path / "s1.json"
    path.write_text(json.dumps({"scan": "s1", "pose": pose, "panoramas": [cam]}))
    assert read_manifest(str(path)).panoramas[0].sphere == {
        "width_px": 8192, "height_px": 4096, "left_px": 0, "top_px": 0}
    for bad, match in [({"width_px": 8192}, r"panoramas\[0\]\.sphere\.height_px"),
                       ({"width_px": 8192, "height_px": 4096.5}, "whole number"),
                       ({"width_px": 8192, "height_px": 4096, "left_px": -1}, "left_px"),
                       ({"width_px": 0, "height_px": 4096}, "must be > 0"),
                       ({"width_px": 8192, "height_px": 4096, "x": 1}, "unknown field"),
                       ([8192, 4096], "expected an object")]:
        path.write_text(json.dumps({"scan": "s1", "pose": pose,
                                    "panoramas": [{**cam, "sphere": bad}]}))
        with pytest.raises(ValueError, match=match):
            read_manifest(str(path))


def test_pose_parse_forms():
    assert Pose.parse("1,2,3").quaternion_xyzw == (0.0, 0.0, 0.0, 1.0)
    assert Pose.parse([1, 2, 3, 0, 0, 1, 0]).quaternion_xyzw == (0.0, 0.0, 1.0, 0.0)
    assert Pose.parse(([1, 2, 3], [0, 0, 0, 1])).position_m == (1.0, 2.0, 3.0)
    assert Pose.parse(np.array([1.0, 2, 3])).position_m == (1.0, 2.0, 3.0)
    for bad in ["1,2", [1, 2, 3, 4], "a,b,c", [0, 0, 0, 0, 0, 0, 0]]:
        with pytest.raises(ValueError):
            Pose.parse(bad)


def test_e57_sphere_placement_and_its_refusals():
    """Where an E57 spherical image goes (its centre on the camera's x axis): the whole sphere
    as it is; a part centred in the sphere of its pitch; and, said why, pixels that are not
    square (the server takes an equirect panorama twice as wide as high, and would refuse the
    whole scan for one that is not) or too small for a sphere of 2^20 rows."""
    from vasl.readers import _e57_sphere

    p = math.pi / 512
    assert _e57_sphere(1024, 512, p, p) is None
    assert _e57_sphere(720, 300, p, p) == {"width_px": 1024, "height_px": 512,
                                           "left_px": 152, "top_px": 106}
    assert "square pixels" in _e57_sphere(1024, 384, p, math.pi / 384)
    assert "square pixels" in _e57_sphere(500, 300, 2 * p, p)
    assert "2^20 rows" in _e57_sphere(100, 100, 1e-9, 1e-9)


def _camera_info(path, model: str, d, k=(500.0, 0.0, 320.5, 0.0, 501.0, 240.25, 0, 0, 1)):
    path.write_text("image_width: 640\nimage_height: 480\ncamera_name: cam0\n"
                    f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {list(k)}\n"
                    f"distortion_model: {model}\ndistortion_coefficients:\n  rows: 1\n"
                    f"  cols: {len(d)}\n  data: {list(d)}\n")
    return str(path)


def test_ros_camera_info_gives_the_lens(tmp_path):
    """ROS camera_info YAML: plumb_bob's [k1, k2, p1, p2, k3] (OpenCV's order, not ours),
    equidistant as a fisheye, a rational lens refitted as k1-k3 when that holds; what is not a
    lens the model holds is refused naming the file."""
    from vasl.readers import RATIONAL_FIT_MAX_PX, pinhole_from_camera_info

    k = pinhole_from_camera_info(_camera_info(tmp_path / "a.yaml", "plumb_bob",
                                              [-0.1, 0.02, 0.001, -0.002, 0.003]))
    assert k == {"fx_px": 500.0, "fy_px": 501.0, "cx_px": 320.5, "cy_px": 240.25, "k1": -0.1,
                 "k2": 0.02, "k3": 0.003, "p1": 0.001, "p2": -0.002, "k4": 0.0,
                 "field_of_view_deg": 0.0, "lens": "brown-conrady"}
    k = pinhole_from_camera_info(_camera_info(tmp_path / "b.yaml", "equidistant",
                                              [0.02, -0.005, 0.001, 0.00005]))
    assert k["lens"] == "fisheye" and (k["k1"], k["k4"], k["p1"]) == (0.02, 0.00005, 0.0)
    # A rational lens: k4-k6 that a k1-k3 polynomial follows closely over the image.
    k = pinhole_from_camera_info(_camera_info(tmp_path / "c.yaml", "rational_polynomial",
                                              [-0.1, 0.01, 0, 0, 0, 0.01, 0, 0]))
    assert abs(k["k1"] - (-0.1 - 0.01)) < 1e-3  # refitted: 1/(1 + k4 r²) ≈ 1 − k4 r²
    r2 = ((640 - 320.5) / 500.0) ** 2 + ((480 - 240.25) / 501.0) ** 2
    poly = 1 + k["k1"] * r2 + k["k2"] * r2 ** 2 + k["k3"] * r2 ** 3
    rational = (1 - 0.1 * r2 + 0.01 * r2 ** 2) / (1 + 0.01 * r2)
    print(f"\nrational refit at the corner: {abs(poly - rational) * r2 ** 0.5 * 500:.4f} px")
    assert abs(poly - rational) * r2 ** 0.5 * 500 <= RATIONAL_FIT_MAX_PX
    for name, model, d, message in (
            ("d.yaml", "rational_polynomial", [0.5, 0, 0, 0, 0, 5.0, 0, 0], "fits"),
            ("e.yaml", "kannala_brandt_unified", [0.1, 0, 0, 0], "is not one vasl reads"),
            ("f.yaml", "plumb_bob", [0.1, 0.2], "must hold 4 or 5 numbers")):
        with pytest.raises(ValueError, match=message) as e:
            pinhole_from_camera_info(_camera_info(tmp_path / name, model, d))
        assert name in str(e.value)
    with pytest.raises(ValueError, match="skew"):
        pinhole_from_camera_info(_camera_info(tmp_path / "g.yaml", "plumb_bob", [0, 0, 0, 0],
                                              k=(500, 3.0, 320, 0, 500, 240, 0, 0, 1)))
    (tmp_path / "h.yaml").write_text("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n")
    with pytest.raises(ValueError, match="h.yaml"):
        pinhole_from_camera_info(str(tmp_path / "h.yaml"))


def test_kalibr_camchain_camera_gives_the_lens(tmp_path):
    """A Kalibr camchain (two cameras): path#cam1 picks the equidistant one, [fu, fv, pu, pv]
    as fx, fy, cx, cy; without a fragment, or with one it lacks, it is refused naming them; an
    omnidirectional camera model is refused."""
    from vasl.readers import pinhole_from_camera_info

    chain = tmp_path / "camchain.yaml"
    chain.write_text(
        "cam0:\n  camera_model: pinhole\n  intrinsics: [458.6, 457.3, 367.2, 248.4]\n"
        "  distortion_model: radtan\n  distortion_coeffs: [-0.28, 0.07, 0.0002, 0.00002]\n"
        "  resolution: [752, 480]\n"
        "cam1:\n  camera_model: pinhole\n  intrinsics: [190.9, 190.4, 254.9, 256.9]\n"
        "  distortion_model: equidistant\n  distortion_coeffs: [0.003, 0.0006, -0.007, 0.002]\n"
        "  resolution: [512, 512]\n  T_cn_cnm1: [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], "
        "[0, 0, 0, 1]]\n")
    k = pinhole_from_camera_info(f"{chain}#cam1")
    assert (k["lens"], k["fx_px"], k["fy_px"], k["cx_px"], k["cy_px"], k["k3"]) == \
        ("fisheye", 190.9, 190.4, 254.9, 256.9, -0.007)
    k = pinhole_from_camera_info(f"{chain}#cam0")
    assert (k["lens"], k["k1"], k["p1"], k["p2"]) == ("brown-conrady", -0.28, 0.0002, 0.00002)
    with pytest.raises(ValueError, match="a camchain of 2 cameras"):
        pinhole_from_camera_info(str(chain))
    with pytest.raises(ValueError, match="no camera 'cam2'"):
        pinhole_from_camera_info(f"{chain}#cam2")
    chain.write_text("cam0:\n  camera_model: omni\n  intrinsics: [0.8, 458.6, 457.3, 367.2]\n")
    with pytest.raises(ValueError, match="camera_model 'omni'"):
        pinhole_from_camera_info(str(chain))
