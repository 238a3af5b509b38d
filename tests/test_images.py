"""Stored images: rectification with CameraInfo's lens, the camera's own JPEG kept when
nothing changes, sizes, and the loader's decode."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from conftest import small_config
from gtgen.bag.decode.image import decode_file, encode_jpeg
from gtgen.bag.reader import BagSet
from gtgen.errors import DecodeError
from gtgen.extract.images import stored_cameras, stored_size
from gtgen.lens import Lens, project, rectify_remap
from gtgen.storage.drive import DriveStore

K_RAW = np.array([[300.0, 0.0, 161.3], [0.0, 302.0, 98.7], [0.0, 0.0, 1.0]])
SIZE = (320, 200)


def _info(model: str, D: list[float], K: np.ndarray = K_RAW, size: tuple[int, int] = SIZE) -> SimpleNamespace:
    return SimpleNamespace(k=K.ravel(), d=np.asarray(D, float), distortion_model=model, width=size[0], height=size[1])


def _points(n: int, seed: int = 0) -> np.ndarray:
    """Scene points (optical frame) on a jittered grid of directions over the field of view
    (corners included; far enough apart that their blobs do not touch), at random depths."""
    rng = np.random.default_rng(seed)
    nx = int(np.ceil(np.sqrt(n * 1.5)))
    ny = int(np.ceil(n / nx))
    x, y = np.meshgrid(np.linspace(-0.42, 0.42, nx), np.linspace(-0.28, 0.28, ny))
    x = x.ravel() + rng.uniform(-0.01, 0.01, x.size)
    y = y.ravel() + rng.uniform(-0.01, 0.01, y.size)
    z = rng.uniform(3.0, 40.0, x.size)
    return np.column_stack([x * z, y * z, z])


def _blob_image(centres: np.ndarray, size: tuple[int, int], sigma: float = 1.6) -> np.ndarray:
    W, H = size
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.zeros((H, W))
    for u, v in centres:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    return np.repeat((np.clip(img, 0, 1) * 255).astype(np.uint8)[..., None], 3, axis=-1)


def _centroid(img: np.ndarray, u: float, v: float, r: int = 4) -> tuple[float, float]:
    g = img[..., 1].astype(np.float64)
    u0, v0 = int(round(u)), int(round(v))
    win = g[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1]
    win = np.clip(win - 0.2 * win.max(), 0, None)
    yy, xx = np.mgrid[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1]
    return float((xx * win).sum() / win.sum()), float((yy * win).sum() / win.sum())


LENSES = [("plumb_bob", [-0.25, 0.06, 0.0008, -0.0005, 0.0]), ("equidistant", [0.05, -0.02, 0.004, -0.001]),
          ("rational_polynomial", [0.3, -0.1, 0.001, 0.0005, 0.01, 0.6, -0.05, 0.02])]


@pytest.mark.parametrize(("model", "D"), LENSES)
def test_a_point_through_the_raw_lens_and_through_the_rectified_image_lands_on_the_same_pixel(model, D):
    """The rectified image, read with the stored K as a pinhole, shows each scene point
    where the raw distorted camera saw it: within half a pixel (blob centroids, after the
    JPEG round trip through the store's own path)."""
    cfg = small_config(extract={"image_width": SIZE[0], "image_height": SIZE[1], "jpeg_quality": 95})
    cam = stored_cameras(cfg, {c: _info(model, D) for c in ("front", "left", "right", "back")})[1]
    assert cam.lens.distorted and cam.size == SIZE
    lens = Lens.of(model, D)
    P = _points(40)
    raw_px = project(K_RAW, P, lens)
    rect_px = project(cam.K, P)  # the stored K, no lens
    W, H = SIZE
    inside = np.all((raw_px > 6) & (raw_px < [W - 7, H - 7]) & (rect_px > 6) & (rect_px < [W - 7, H - 7]), axis=1)
    assert inside.sum() >= 20
    raw = _blob_image(raw_px[inside], SIZE)
    stored = decode_file(cam.stored(encode_jpeg(raw, 95)))
    got = np.array([_centroid(stored, u, v) for u, v in rect_px[inside]])
    err = np.linalg.norm(got - rect_px[inside], axis=1)
    assert err.max() < 0.5, err.max()
    # the shift the lens makes is far larger than the tolerance: the test sees rectification
    assert np.linalg.norm(raw_px[inside] - rect_px[inside], axis=1).max() > 5


@pytest.mark.parametrize(("model", "D"), LENSES)
def test_the_rectifying_map_samples_the_raw_pixel_of_each_ideal_one_and_undistort_inverts_distort(model, D):
    lens = Lens.of(model, D)
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 21), np.linspace(-0.33, 0.33, 15))
    xd, yd = lens.distort(x, y)
    xu, yu = lens.undistort(xd, yd)
    np.testing.assert_allclose(np.stack([xu, yu]), np.stack([x, y]), atol=1e-9)
    # a ramp image whose value is its own column: the map reads column u_raw at each pixel
    ramp = np.repeat(np.tile(np.arange(SIZE[0], dtype=np.float64) * (255 / SIZE[0]), (SIZE[1], 1))[..., None], 3, -1)
    m = rectify_remap(lens, K_RAW, SIZE)
    P = _points(30, seed=1)
    rect = project(K_RAW, P)
    raw = project(K_RAW, P, lens)
    ok = np.all((raw > 1) & (raw < [SIZE[0] - 2, SIZE[1] - 2]) & (rect > 0) & (rect < [SIZE[0] - 1, SIZE[1] - 1]), axis=1)
    u, v = np.round(rect[ok]).astype(int).T  # at whole pixels of the rectified image
    want = project(K_RAW, np.column_stack([(u - K_RAW[0, 2]) / K_RAW[0, 0], (v - K_RAW[1, 2]) / K_RAW[1, 1], np.ones(len(u))]), lens)
    np.testing.assert_allclose(np.column_stack([m.u[v, u], m.v[v, u]]), want, atol=1e-9)
    ramp = ramp.astype(np.uint8)
    out = m(ramp)  # the ramp read back at the mapped columns
    assert out.shape == (*SIZE[::-1], 3)
    np.testing.assert_allclose(out[v, u, 0], np.interp(want[:, 0], np.arange(SIZE[0]), ramp[0, :, 0].astype(float)), atol=0.51)


@pytest.mark.parametrize(("model", "D"), LENSES)
def test_the_remap_by_precomputed_taps_equals_the_bilinear_sampler_within_one_level(model, D):
    """Remap's four gathers and weights against grids.bilinear per channel (its oracle):
    the same image but for rounding at .5 (at most one level), black outside alike."""
    m = rectify_remap(Lens.of(model, D), K_RAW, SIZE)
    img = np.random.default_rng(4).integers(0, 256, (SIZE[1], SIZE[0], 3), dtype=np.uint8)
    fast, naive = m(img).astype(int), m.naive(img).astype(int)
    assert np.abs(fast - naive).max() <= 1 and (fast != naive).mean() < 1e-3
    np.testing.assert_array_equal(fast.sum(-1) == 0, naive.sum(-1) == 0)


def test_stored_size_keeps_the_aspect_and_never_upscales():
    assert stored_size((1920, 1200), (640, 396)) == (634, 396)
    assert stored_size((1280, 720), (640, 396)) == (640, 360)
    assert stored_size((320, 200), (640, 396)) == (320, 200)
    assert stored_size((640, 396), (640, 396)) == (640, 396)


def test_a_lens_gtgen_cannot_undistort_is_one_line():
    cfg = small_config()
    with pytest.raises(DecodeError, match=r"camera 'front'.*'fov'.*expected one of"):
        stored_cameras(cfg, {c: _info("fov", [0.9, 0, 0, 0, 0]) for c in ("front", "left", "right", "back")})
    # all-zero coefficients are no distortion, whatever the model says
    cams = stored_cameras(cfg, {c: _info("fov", [0, 0, 0, 0, 0]) for c in ("front", "left", "right", "back")})
    assert not cams[0].lens.distorted


def test_the_stored_jpeg_of_an_unresized_frame_is_the_bags_bytes(drive_dir, tmp_path):
    """At the cameras' own size, the pinhole cameras' JPEG files are stored byte for byte;
    the distorted one is rectified (re-encoded) at the same size."""
    from gtgen.extract import run_extract

    cfg = small_config(extract={"image_width": 64, "image_height": 40})
    out = tmp_path / "d.zarr"
    run_extract([drive_dir / "drive.mcap"], out, cfg, workers=1)
    d = DriveStore(out)
    s = d.samples
    ks = np.arange(d.n_samples)
    rows, nbytes = d.jpeg(ks)
    assert d.image_sizes().tolist() == [[64, 40]] * 4
    topics = {f"/cam_{c}/image/compressed": i for i, c in enumerate(("front", "left", "right", "back"))}
    got = {}
    with BagSet([drive_dir / "drive.mcap"]) as b:
        for topic, _, _, msg, _ in b.messages(list(topics)):
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            got[(topics[topic], t)] = bytes(msg.data)
    distorted = cfg.topics.cameras  # the synth's distorted camera is 'left' (index 1)
    assert cfg.synth.distorted_camera == "left" and len(distorted) == 4
    for k in ks[:: max(1, len(ks) // 6)]:
        for c in range(4):
            stored = rows[k, c, : nbytes[k, c]].tobytes()
            bag = got[(c, int(s.image_t_ns[k, c]))]
            if c == 1:
                assert stored != bag and decode_file(stored).shape == (40, 64, 3)
            else:
                assert stored == bag
            assert not rows[k, c, nbytes[k, c] :].any()


def test_the_loader_decodes_at_the_model_size_with_matching_intrinsics(dataset):
    from gtgen.storage.dataset import DatasetStore
    from gtgen.train.data import ShardDataset, decode_at

    store = DatasetStore(dataset)
    files = store.jpeg_files(0)
    full = decode_file(files[0])
    assert full.shape == (30, 48, 3)
    img, src = decode_at(files[0], 24, 15)
    assert img.shape == (15, 24, 3) and src == (48, 30)  # 1/2-scale decode: the whole image
    cfg = small_config(train={"image_width": 24, "image_height": 15})
    item = ShardDataset(dataset, cfg.train)[0]
    assert tuple(item["images"].shape) == (4, 3, 15, 24)
    K = store.inputs("K")[0][0]
    np.testing.assert_allclose(item["K"][0, 0, 0].item(), K[0, 0] * 0.5, rtol=1e-6)


@pytest.mark.parametrize("kind", ["dataset", "drive"])
def test_a_store_of_the_previous_version_is_refused_in_one_line_saying_how_to_rebuild(kind, dataset, drive_store, tmp_path):
    import json
    import shutil

    from conftest import reseal, run_cli

    src = dataset if kind == "dataset" else drive_store
    old = tmp_path / f"old_{kind}.zarr"
    shutil.copytree(src, old)
    meta = json.loads((old / "zarr.json").read_text())
    meta["attributes"]["version"] = 5
    (old / "zarr.json").write_text(json.dumps(meta))
    reseal(old)
    args = ("report", old, "-o", tmp_path / "rep") if kind == "dataset" else ("fuse", old, "-o", tmp_path / "f.zarr")
    p = run_cli(*args, cwd=tmp_path)
    err = p.stderr.strip()
    assert p.returncode == 1 and "\n" not in err and "Traceback" not in err, err
    from gtgen.storage.schema import DATASET, DRIVE

    fmt = DATASET if kind == "dataset" else DRIVE
    assert f"has version 5; this gtgen reads version {fmt.version}" in err and fmt.rebuild in err
    assert ("gtgen build" in err) if kind == "dataset" else ("gtgen extract" in err)
