"""A mask image per panorama through a real vasld: the tripod, rig or operator a 360° camera
sees under itself, masked out by an image of the panorama's size (a rig's JPEG cannot carry
alpha). A box room scanned from inside (synth_scans) with an RGB panorama from the scanner's
position, sent through a manifest's `panoramas[].mask`, the client's panorama dicts and an E57
image's imageMask: the camera's records on the floor under the station (the masked nadir) are
invalidated, those on the walls at the station's height equal an unmasked ingest's; a mask that
is not the image's size, not an image, or cut short is refused naming its panorama, and the
project is unchanged."""
from __future__ import annotations

import hashlib
import json
import os
from typing import Dict, Tuple

import grpc
import numpy as np
import pytest

from conftest import VOSSEL_M, run_cli
from synth_scans import linear_to_srgb, png_bytes, room_chunks, room_points, write_e57
from vasl import VaslError
from vasl._proto import vasl_pb2 as pb
from vasl.client import FLAG_INVALIDATED, pack_points, pose_to_pb
from vasl.readers import read_e57
from vasl.types import Pose

#: The scanner's and the camera's world position: the room's floor (1.5 m below the scanner,
#: synth_scans.ROOM) lies at world z = 0, its wall y = +4.5 m at world y = 7.5.
STATION = (2.0, 3.0, 1.5)
WIDTH, HEIGHT = 1024, 512
#: The nadir the mask covers: the bottom 30% of the rows, 36° and more below the horizon.
MASKED_ROWS = round(0.3 * HEIGHT)
POINTS = 400_000
#: Floor vossels directly below the station (at most 23° from the nadir: deep in the mask).
FLOOR_BOX = (STATION[0] - 0.4, STATION[1] - 0.4, -0.1, STATION[0] + 0.4, STATION[1] + 0.4, 0.1)
#: Wall vossels at the station's height (within 4° of the horizon: 32° above the mask).
WALL_BOX = (STATION[0] - 1.0, 7.4, STATION[2] - 0.3, STATION[0] + 1.0, 7.6, STATION[2] + 0.3)


def _grey_png(rows: np.ndarray) -> bytes:
    """An 8-bit grey PNG of an (H, W) uint8 array."""
    h, w = rows.shape
    return png_bytes(w, h, b"".join(b"\x00" + rows[j].tobytes() for j in range(h)),
                     colour_type=0)


def _nadir_mask(width: int, height: int, reported: int) -> bytes:
    """A mask PNG: `reported` (the camera reports the pixel) above the nadir, 0 over it."""
    rows = np.full((height, width), reported, np.uint8)
    rows[height - MASKED_ROWS:] = 0
    return _grey_png(rows)


def _panorama() -> bytes:
    """A smooth RGB equirect panorama (8-bit sRGB PNG), nowhere near clipping."""
    jj, ii = np.mgrid[0:HEIGHT, 0:WIDTH]
    linear = np.stack([0.05 + 0.6 * ii / WIDTH, 0.05 + 0.6 * jj / HEIGHT,
                       0.3 + 0.2 * np.sin(8 * np.pi * ii / WIDTH)], axis=-1)
    rgb8 = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
    return png_bytes(WIDTH, HEIGHT, b"".join(b"\x00" + rgb8[j].tobytes() for j in range(HEIGHT)))


def _write_ply(path: str, xyz: np.ndarray, intensity: np.ndarray) -> None:
    record = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("intensity", "<f4")])
    record["x"], record["y"], record["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    record["intensity"] = intensity
    with open(path, "wb") as f:
        f.write((f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
                 "property float x\nproperty float y\nproperty float z\n"
                 "property float intensity\nend_header\n").encode())
        f.write(record.tobytes())


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Dict[str, object]:
    """The room scan's files: points (PLY, sensor frame), panorama, its 0/255 nadir mask, and
    two manifests of the same scan, with the mask and without."""
    out = tmp_path_factory.mktemp("mask-room")
    xyz = room_points(POINTS, seed=31).astype(np.float32)
    _write_ply(str(out / "room.ply"), xyz, np.full(len(xyz), 0.5, np.float32))
    image, mask = _panorama(), _nadir_mask(WIDTH, HEIGHT, 255)
    (out / "pano.png").write_bytes(image)
    (out / "masks").mkdir()
    (out / "masks" / "rig-nadir.png").write_bytes(mask)
    pose = {"position": list(STATION), "quaternion": [0, 0, 0, 1]}
    panorama = {"name": "pano", "image": "pano.png", "modality": "rgb", "pose": pose}
    manifests = {}
    for name, extra in (("masked", {"mask": "masks/rig-nadir.png"}), ("plain", {})):
        doc = {"scan": "room", "rig": "tripod", "pose": pose,
               "lidar": {"points": "room.ply", "divergence_rad": 0.0003},
               "panoramas": [{**panorama, **extra}]}
        manifests[name] = str(out / f"{name}.json")
        (out / f"{name}.json").write_text(json.dumps(doc))
    return {"xyz": xyz, "image": image, "mask": mask, "manifests": manifests}


def _camera_records(client, project: str, box) -> Dict[Tuple[int, int, int], dict]:
    """The RGB records of camera "pano" in the vossels meeting `box`, by vossel k."""
    q = client.query_records(project, box=box, limit=100_000)
    assert not q.truncated
    rows = [r for r in q.records if r["source_name"] == "pano"]
    assert all(r["modality"] == "rgb" for r in rows)
    found = {tuple(r["k"]): r for r in rows}
    assert len(found) == len(rows), "a vossel with two records of one camera"
    return found


def test_mask_invalidates_the_nadir_and_leaves_the_rest_alone(client, server, room):
    """The same scan into two projects, through the CLI and a manifest, with the rig's mask
    and without: under the station the masked camera's records are invalidated (weight 0),
    the unmasked one's are not; on the walls at the station's height they are equal."""
    for project, manifest in (("mask-on", room["manifests"]["masked"]),
                              ("mask-off", room["manifests"]["plain"])):
        client.create_project(project, vossel_size_m=VOSSEL_M)
        r = run_cli(server, "ingest", "--project", project, "--quiet", manifest)
        print(f"\n{project}: {r.stdout.strip()}")

    cameras = {p: next(s for s in client.list_scans(p)[0].sources if s.name == "pano")
               for p in ("mask-on", "mask-off")}
    assert cameras["mask-on"].mask_sha256 == hashlib.sha256(room["mask"]).hexdigest()
    assert cameras["mask-off"].mask_sha256 == ""
    assert cameras["mask-on"].blob_sha256 == cameras["mask-off"].blob_sha256
    listed = run_cli(server, "scans", "--project", "mask-on").stdout
    assert "pano(rgb, masked)" in listed, listed

    floor = {p: _camera_records(client, p, FLOOR_BOX) for p in ("mask-on", "mask-off")}
    masked, plain = floor["mask-on"].values(), floor["mask-off"].values()
    print(f"floor under the station: {len(masked)} camera records masked, "
          f"{sum(r['invalidated'] for r in masked)} of them invalidated (max weight "
          f"{max(r['weight'] for r in masked):g}); unmasked: {len(plain)} records, "
          f"{sum(r['invalidated'] for r in plain)} invalidated, mean weight "
          f"{np.mean([r['weight'] for r in plain]):.4g}")
    assert len(plain) >= 100
    assert floor["mask-on"].keys() == floor["mask-off"].keys(), "masked records must be kept"
    assert all(r["flags"] & FLAG_INVALIDATED and r["weight"] == 0 for r in masked)
    assert not any(r["flags"] & FLAG_INVALIDATED for r in plain)

    wall = {p: _camera_records(client, p, WALL_BOX) for p in ("mask-on", "mask-off")}
    assert len(wall["mask-off"]) >= 100
    assert wall["mask-on"].keys() == wall["mask-off"].keys()
    diff = max(float(np.max(np.abs(np.subtract(wall["mask-on"][k]["value"],
                                               wall["mask-off"][k]["value"]))))
               for k in wall["mask-off"])
    print(f"wall at the station's height: {len(wall['mask-on'])} camera records in each "
          f"project, max |value difference| {diff:.3g}")
    assert diff <= 1e-6
    assert not any(r["flags"] & FLAG_INVALIDATED for p in wall for r in wall[p].values())
    assert all(wall["mask-on"][k]["weight"] == pytest.approx(wall["mask-off"][k]["weight"],
                                                             abs=1e-6) for k in wall["mask-off"])


def _expect_refused(client, project: str, what: str, send, *words: str) -> None:
    """`send` is refused with INVALID_ARGUMENT whose message names the panorama and `words`,
    and the project is as it was."""
    before = client.get_project(project)
    with pytest.raises(VaslError) as err:
        send()
    e = err.value
    print(f"\n{what}: {e.code.name}: {e.details}")
    assert e.code == grpc.StatusCode.INVALID_ARGUMENT, str(e)
    assert "pano" in e.details and "mask" in e.details, e.details
    assert all(w in e.details for w in words), e.details
    after = client.get_project(project)
    assert (after.head_version, after.scan_count, after.vossel_count, after.record_count) == \
        (before.head_version, before.scan_count, before.vossel_count, before.record_count)
    assert [s.name for s in client.list_scans(project)] == ["base"]


def test_bad_mask_is_refused_naming_the_panorama(client, room):
    """A mask of another size than its image, bytes that are no image, and mask chunks short
    of the mask's declared size: INVALID_ARGUMENT naming the panorama, nothing stored. A mask
    the server would never take (empty, or on a visual reference) is refused before sending."""
    project = "mask-bad"
    client.create_project(project, vossel_size_m=VOSSEL_M)
    xyz = room["xyz"][:50_000]
    panorama = {"name": "pano", "image": room["image"], "pose": STATION, "modality": "rgb"}
    client.ingest(project, scan="base", points=xyz, pose=STATION, panoramas=[panorama])

    def ingest(mask):
        return lambda: client.ingest(project, scan="bad", points=xyz, pose=STATION,
                                     panoramas=[{**panorama, "mask": mask}])

    small = _nadir_mask(WIDTH // 2, HEIGHT // 2, 255)
    _expect_refused(client, project, "a mask of half the image's size", ingest(small),
                    f"{WIDTH // 2}x{HEIGHT // 2}", f"{WIDTH}x{HEIGHT}")
    _expect_refused(client, project, "bytes that are no image",
                    ingest(b"this is a tripod, not an image " * 8))

    # Mask chunks short of mask_size_bytes: the stream as the client sends it, cut short.
    mask = room["mask"]
    header = pb.ScanHeader(project=project, scan="bad", rig="test",
                           pose=pose_to_pb(Pose.parse(STATION)))
    header.lidar.divergence_rad = 3e-4
    header.lidar.point_format = pb.POINT_FORMAT_XYZI_F32LE
    header.lidar.point_count = len(xyz)
    header.panoramas.add(name="pano", modality=pb.MODALITY_RGB,
                         pose=pose_to_pb(Pose.parse(STATION)),
                         encoded_size_bytes=len(room["image"]), mask_size_bytes=len(mask))
    _expect_refused(client, project, "mask chunks short of mask_size_bytes",
                    lambda: client.ingest_stream(header, pack_points(xyz, np.full(len(xyz), 0.5)),
                                                 [room["image"]], masks=[mask[:len(mask) // 2]]),
                    "mask_size_bytes")

    with pytest.raises(ValueError, match="mask must be non-empty bytes or a file path"):
        ingest(b"")()
    photo = {**panorama, "name": "photo", "visual_reference": True, "mask": mask}
    with pytest.raises(ValueError, match="'photo'.*visual reference.*takes no mask"):
        client.ingest(project, scan="bad", points=xyz, pose=STATION,
                      panoramas=[panorama, photo])


def test_e57_image_mask_is_sent_as_the_mask(client, server, tmp_path):
    """An E57 spherical image with an imageMask (0/1, the E57 way) is read with it and sent as
    its mask: the camera source keeps the mask's sha256 and its records under the station are
    invalidated. An image whose imageMask is no PNG is left out, saying so; its scan is not."""
    image = _panorama()
    mask = _nadir_mask(WIDTH, HEIGHT, 1)
    pose = (STATION, (1.0, 0.0, 0.0, 0.0))
    path = str(tmp_path / "masked-station.e57")
    spherical = {"png": image, "width": WIDTH, "height": HEIGHT, "pose": pose}
    write_e57(path, POINTS, room_chunks(POINTS, seed=43), pose=pose, invalid=True,
              images=[{**spherical, "name": "pano", "mask": mask},
                      {**spherical, "name": "bad-mask", "mask": b"not a PNG at all"}])
    read = {im.name: im for im in read_e57(path)[0].images}
    assert read["pano"].mask == mask and read["pano"].problem == ""
    assert "imageMask is not a PNG" in read["bad-mask"].problem

    client.create_project("mask-e57", vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", "--project", "mask-e57", "--quiet", path)
    print("\n" + r.stdout.strip())
    assert "image 'pano' (spherical): its imageMask is sent as its mask" in r.stdout
    assert ("image 'bad-mask' (spherical): not ingested: its imageMask is not a PNG image"
            in r.stdout)
    scan = client.list_scans("mask-e57")[0]
    cameras = [s for s in scan.sources if s.modality == "rgb"]
    assert [(s.name, s.mask_sha256) for s in cameras] == \
        [("pano", hashlib.sha256(mask).hexdigest())]

    floor = _camera_records(client, "mask-e57", FLOOR_BOX)
    invalidated = sum(r["invalidated"] for r in floor.values())
    print(f"E57 floor under the station: {invalidated} of {len(floor)} camera records "
          "invalidated by the imageMask")
    assert len(floor) >= 100 and invalidated == len(floor)


def _e57_camera_records(client, server, tmp_path, project: str, image: dict, seed: int):
    """Ingests the room scanned from STATION with one E57 image (write_e57's `images` entry,
    posed at the station) through the CLI into a new project; the camera's records on the wall
    at the station's height and on the floor under it, and what the CLI printed."""
    pose = (STATION, (1.0, 0.0, 0.0, 0.0))
    path = str(tmp_path / f"{project}.e57")
    write_e57(path, POINTS, room_chunks(POINTS, seed=seed), pose=pose,
              images=[{"name": "pano", "pose": pose, **image}])
    client.create_project(project, vossel_size_m=VOSSEL_M)
    r = run_cli(server, "ingest", "--project", project, "--quiet", path)
    print("\n" + r.stdout.strip())
    return {box: _camera_records(client, project, box) for box in (WALL_BOX, FLOOR_BOX)}, r.stdout


def _wall_and_floor(records: dict, name: str) -> Tuple[float, int, int, int]:
    """Of `records[name]` against `records["whole"]` (_e57_camera_records' boxes): the largest
    difference of a wall record's value (asserting the two saw the same wall vossels, at least
    100), the wall records it holds, and of its floor records the invalidated ones and all."""
    wall_whole, wall = records["whole"][WALL_BOX], records[name][WALL_BOX]
    assert len(wall_whole) >= 100 and wall_whole.keys() == wall.keys()
    assert not any(r["invalidated"] for r in wall.values())
    worst = max(float(np.max(np.abs(np.subtract(wall_whole[k]["value"], wall[k]["value"]))))
                for k in wall_whole)
    floor = records[name][FLOOR_BOX]
    return worst, len(wall), sum(r["invalidated"] for r in floor.values()), len(floor)


def test_e57_partial_sphere_is_placed_in_its_sphere(client, server, tmp_path):
    """An E57 spherical image of part of the sphere (here 253° x 105° of a 1024 x 512 sphere,
    centred, as E57 has a spherical image's centre on the camera's x axis) is sent as that part
    of its sphere (SphereWindow): on the walls at the station's height its records equal, value
    for value, those of the whole panorama it was cut from; under the station, which it does
    not reach, they are invalidated. Were the part taken for a whole panorama, or placed off
    centre, the wall's colours would differ."""
    whole = _panorama()
    jj, ii = np.mgrid[0:HEIGHT, 0:WIDTH]
    linear = np.stack([0.05 + 0.6 * ii / WIDTH, 0.05 + 0.6 * jj / HEIGHT,
                       0.3 + 0.2 * np.sin(8 * np.pi * ii / WIDTH)], axis=-1)
    rgb8 = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
    w, h = 720, 300
    left, top = (WIDTH - w) // 2, (HEIGHT - h) // 2
    part = rgb8[top:top + h, left:left + w]
    part_png = png_bytes(w, h, b"".join(b"\x00" + part[j].tobytes() for j in range(h)))
    records = {}
    for name, png, size in (("whole", whole, (WIDTH, HEIGHT)), ("part", part_png, (w, h))):
        records[name], printed = _e57_camera_records(
            client, server, tmp_path, f"sphere-{name}",
            {"png": png, "width": size[0], "height": size[1], "pixel_rad": np.pi / HEIGHT}, 47)
    assert "part of a 1024x512 panorama of the sphere" in printed
    camera = next(s for s in client.list_scans("sphere-part")[0].sources if s.name == "pano")
    assert camera.projection == "equirect window 152 106" and camera.kind == "part of the sphere"
    assert "pano(rgb, part of the sphere)" in run_cli(server, "scans", "--project",
                                                      "sphere-part").stdout
    worst, wall, invalidated, floor = _wall_and_floor(records, "part")
    print(f"wall at the station's height: {wall} camera records, max |Δ| {worst} against the "
          f"whole panorama's; floor under the station: {invalidated} of {floor} invalidated "
          "(the part does not reach it), "
          f"{sum(r['invalidated'] for r in records['whole'][FLOOR_BOX].values())} with the whole")
    assert worst == 0.0
    assert floor >= 100 and invalidated == floor
    assert not any(r["invalidated"] for r in records["whole"][FLOOR_BOX].values())


def test_e57_cylindrical_image_is_resampled_into_its_sphere(client, server, tmp_path):
    """An E57 cylindrical image (columns every 2π/1024 of azimuth, rows on a cylinder of 2 m up
    to ±50°) of the same smooth scene as the whole panorama is ingested, resampled by the
    server into the part of the sphere it covers: on the walls at the station's height its
    records agree with the whole panorama's within the 8-bit coding of the two images; under
    the station, beyond the cylinder, they are invalidated."""
    radius = 2.0
    pw = 2 * np.pi / WIDTH
    ph = radius * pw
    rows = 2 * int(np.ceil(np.tan(np.radians(50)) / pw))
    ppy = rows / 2
    # The whole panorama's colour (_panorama) at each cylinder pixel's direction: its columns
    # are the panorama's, its rows at the equirect row coordinate of their elevation.
    v = np.arange(rows) + 0.5
    y = HEIGHT * (0.5 - np.arctan((ppy - v) * ph / radius) / np.pi) - 0.5
    jj, ii = np.meshgrid(y, np.arange(WIDTH), indexing="ij")
    linear = np.stack([0.05 + 0.6 * ii / WIDTH, 0.05 + 0.6 * jj / HEIGHT,
                       0.3 + 0.2 * np.sin(8 * np.pi * ii / WIDTH)], axis=-1)
    rgb8 = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
    png = png_bytes(WIDTH, rows, b"".join(b"\x00" + rgb8[j].tobytes() for j in range(rows)))
    records = {}
    for name, image in (
            ("whole", {"png": _panorama(), "width": WIDTH, "height": HEIGHT}),
            ("cylinder", {"png": png, "width": WIDTH, "height": rows,
                          "cylinder": {"pixel_height_m": ph, "radius_m": radius,
                                       "principal_y_px": ppy}})):
        records[name], printed = _e57_camera_records(client, server, tmp_path, f"cyl-{name}",
                                                     image, 53)
    assert "cylindrical: resampled by the server" in printed
    camera = next(s for s in client.list_scans("cyl-cylinder")[0].sources if s.name == "pano")
    assert camera.projection.startswith("equirect cylinder ") and camera.kind == "cylindrical"
    assert (camera.width_px, camera.height_px) == (WIDTH, HEIGHT)  # its sphere's
    assert "pano(rgb, cylindrical)" in run_cli(server, "scans", "--project",
                                               "cyl-cylinder").stdout
    worst, wall, invalidated, floor = _wall_and_floor(records, "cylinder")
    print(f"wall at the station's height: {wall} camera records, max |Δ| {worst:.4f} against "
          f"the whole panorama's; floor under the station: {invalidated} of {floor} "
          "invalidated (beyond the cylinder's ±50°)")
    assert worst <= 0.01
    assert floor >= 100 and invalidated == floor
