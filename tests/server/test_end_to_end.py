"""End to end against a real service process: create, stream real shelf frames, views, exports, delete."""

from __future__ import annotations

import io
import json

import httpx
import numpy as np
import pytest
from PIL import Image

from canonical_core import load_ply
from client.sdk import CanonicalError, png_to_array

from .harness import TOKEN, VOXEL, colours_solved, wait_for

pytestmark = pytest.mark.slow

# Measured: 10 frames at 320x240, 8 mm voxels, rendered at frame 0's pose on black: 12.7 dB
# all-pixel PSNR (uncovered borders count). The floor sits 1.5 dB below that.
PSNR_FLOOR_DB = 11.2


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) / 255.0 - b.astype(np.float64) / 255.0) ** 2)
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def view_of(kwargs: dict) -> tuple:
    h, w = kwargs["rgb"].shape[:2]
    return kwargs["K"], kwargs["c2w"], w, h


@pytest.mark.realdata
def test_stream_render_export_delete(client, server, frames, reference, tmp_path):
    session = client.create_session(voxel_size=VOXEL)
    assert any(s["id"] == session.id for s in client.sessions())
    for i, kwargs in enumerate(frames):
        report = session.add_frame(**kwargs)
        assert report["frame_index"] == i
        assert set(report) >= {"frame_index", "new_voxels", "updated_voxels", "representative_switches", "ms"}
    assert session.digest()["sha256"] == reference[len(frames)]["sha256"]  # deterministic across sessions
    assert colours_solved(session)  # the renders below compare pixels: none may land between them

    K, c2w, w, h = view_of(frames[0])
    png = session.render_png(K, c2w, w, h)
    image = Image.open(io.BytesIO(png))
    assert image.format == "PNG" and image.size == (w, h) and image.mode == "RGB"
    quality = psnr(np.asarray(image), frames[0]["rgb"])
    assert quality > PSNR_FLOOR_DB, quality

    view = session.render(K, c2w, w, h)
    assert view["rgb"].dtype == np.uint8 and view["rgb"].shape == (h, w, 3)
    assert np.array_equal(view["rgb"], np.asarray(image))  # the PNG is the same picture
    assert view["depth"].dtype == np.float32 and view["alpha"].shape == (h, w)
    covered = view["alpha"] > 0.5
    assert covered.mean() > 0.5
    sensor = frames[0]["depth"]
    both = covered & (sensor > 0)
    assert np.median(np.abs(view["depth"][both] - sensor[both])) < 3 * VOXEL

    lod = session.render(K, c2w, w, h, max_gaussians=500, background=[1, 1, 1])
    assert lod["alpha"].mean() < view["alpha"].mean()
    assert (lod["rgb"][lod["alpha"] == 0] == 255).all()  # white where nothing is drawn

    # the default, normalised colour, is the composited blend over its weight where anything is drawn
    blend = session.render(K, c2w, w, h, colour="composited")
    normalised = view
    assert np.array_equal(normalised["alpha"], blend["alpha"]) and np.array_equal(normalised["depth"], blend["depth"])
    partly = (blend["alpha"] > 0.05) & (blend["alpha"] < 0.95)
    assert partly.any()
    expected = np.clip(blend["rgb"][partly] / blend["alpha"][partly][:, None], 0, 255)
    rounding = 0.5 / blend["alpha"][partly][:, None] + 1  # the uint8 blend's rounding, magnified by 1 / alpha
    assert (np.abs(normalised["rgb"][partly].astype(np.float32) - expected) <= rounding).all()
    assert (normalised["rgb"][partly].astype(int) >= blend["rgb"][partly]).all()  # never darker than the blend

    # the default depth is the median depth: where a pixel stays more than half transparent it is the
    # expected one; elsewhere the surface covering most of the pixel, nearer the sensor's depth
    expected_depth = session.render(K, c2w, w, h, depth="expected")["depth"]
    thin = view["alpha"] < 0.5
    assert np.array_equal(view["depth"][thin], expected_depth[thin])
    assert not np.array_equal(view["depth"][covered], expected_depth[covered])
    assert np.median(np.abs(view["depth"][both] - sensor[both])) <= np.median(np.abs(expected_depth[both] - sensor[both]))

    feats = session.features(K, c2w, w, h)
    stats = session.stats()
    assert feats["features"].dtype == np.float16
    assert feats["features"].shape == (h, w, stats["config"]["features"]["dim"])
    assert feats["alpha"].shape == (h, w) and np.allclose(feats["alpha"], view["alpha"], atol=1e-6)
    assert np.isfinite(feats["features"].astype(np.float32)).all()
    preview = Image.open(io.BytesIO(session.features_preview_png(K, c2w, w, h)))
    assert preview.size == (w, h) and preview.mode == "RGB"

    with pytest.raises(CanonicalError) as err:
        session.segmentation(K, c2w, w, h)
    assert err.value.status == 409 and err.value.field == "labels"

    ply = session.export_ply(tmp_path / "scene.ply")
    gaussians = load_ply(ply)
    assert len(gaussians) == stats["gaussians"] > 1000
    splat = session.export_splat(tmp_path / "scene.splat")
    assert splat.stat().st_size == 32 * stats["gaussians"]

    assert stats["frames"] == len(frames) and stats["voxels"] >= stats["gaussians"]
    assert stats["memory_bytes"] > 0 and stats["disk_bytes"] > 0

    folder = server.data_dir / "sessions" / session.id
    assert folder.is_dir()
    session.delete()
    assert not folder.exists()
    assert all(s["id"] != session.id for s in client.sessions())
    with pytest.raises(CanonicalError) as err:
        session.stats()
    assert err.value.status == 404


@pytest.mark.realdata
def test_get_render_matches_post(client, server, frames):
    session = client.create_session(voxel_size=VOXEL)
    session.add_frame(**frames[0])
    assert colours_solved(session)  # until then a solve landing between the two renders changes the second
    K, c2w, w, h = view_of(frames[0])
    params = {"pose": ",".join(repr(float(x)) for x in np.asarray(c2w).ravel()),
              "K": f"{K[0][0]},{K[1][1]},{K[0][2]},{K[1][2]}", "width": w, "height": h}
    headers = {"Authorization": f"Bearer {TOKEN}"}
    r = httpx.get(f"{server.url}/v1/sessions/{session.id}/render", params=params, headers=headers)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.content == session.render_png(K, c2w, w, h)
    r = httpx.get(f"{server.url}/v1/sessions/{session.id}/render", params={**params, "colour": "composited"}, headers=headers)
    assert r.status_code == 200 and r.content == session.render_png(K, c2w, w, h, colour="composited") != session.render_png(K, c2w, w, h)
    r = httpx.get(f"{server.url}/v1/sessions/{session.id}/features", params={**params, "preview": "png"}, headers=headers)
    assert r.status_code == 200 and Image.open(io.BytesIO(r.content)).size == (w, h)
    session.delete()


@pytest.mark.realdata
def test_multipart_frame_equals_msgpack_frame(client, server, frames, reference):
    """curl-style upload: PNG colour + 16-bit depth PNG (mm) + JSON camera; fuses to the same state."""
    kwargs = frames[0]
    rgb_png, depth_png = io.BytesIO(), io.BytesIO()
    Image.fromarray(kwargs["rgb"]).save(rgb_png, format="PNG")
    Image.fromarray(np.round(kwargs["depth"].astype(np.float64) * 1000).astype(np.uint16)).save(depth_png, format="PNG")
    camera = {"K": kwargs["K"].tolist(), "c2w": kwargs["c2w"].tolist(), "depth_scale": 1000, "frame_id": "curl"}
    session = client.create_session(voxel_size=VOXEL)
    r = httpx.post(f"{server.url}/v1/sessions/{session.id}/frames", headers={"Authorization": f"Bearer {TOKEN}"},
                   files={"rgb": ("c.png", rgb_png.getvalue(), "image/png"), "depth": ("d.png", depth_png.getvalue(), "image/png")},
                   data={"camera": json.dumps(camera)})
    assert r.status_code == 200, r.text
    assert r.json()["frame_index"] == 0
    assert session.digest()["sha256"] == reference[1]["sha256"]
    # its retry written otherwise (the parts in another order, the camera's keys too, 1000.0 for 1000):
    # the same frame, answered as a replay, not a conflict
    retry = {**dict(reversed(camera.items())), "depth_scale": 1000.0}
    r = httpx.post(f"{server.url}/v1/sessions/{session.id}/frames", headers={"Authorization": f"Bearer {TOKEN}"},
                   files={"depth": ("d.png", depth_png.getvalue(), "image/png"), "camera": (None, json.dumps(retry)),
                          "rgb": ("c.png", rgb_png.getvalue(), "image/png")})
    assert r.status_code == 200 and r.headers["Idempotent-Replay"] == "true", r.text
    assert session.stats()["frames"] == 1
    session.delete()

    # a class map as a PNG part (0 no class, k + 1 class k, K in the camera JSON): the scene its ids give
    h, w = kwargs["rgb"].shape[:2]
    classes = np.minimum(np.arange(w) * 3 // w, 2)[None, :].repeat(h, 0)
    classes[: h // 5] = -1  # the top rows: no class
    labels_png = io.BytesIO()
    Image.fromarray((classes + 1).astype(np.uint8)).save(labels_png, format="PNG")
    digests = []
    for multipart in (True, False):
        session = client.create_session(voxel_size=VOXEL)
        if multipart:
            r = httpx.post(f"{server.url}/v1/sessions/{session.id}/frames", headers={"Authorization": f"Bearer {TOKEN}"},
                           files={"rgb": ("c.png", rgb_png.getvalue(), "image/png"),
                                  "depth": ("d.png", depth_png.getvalue(), "image/png"),
                                  "labels": ("l.png", labels_png.getvalue(), "image/png")},
                           data={"camera": json.dumps({**camera, "num_classes": 3})})
            assert r.status_code == 200, r.text
        else:
            session.add_frame(**{**kwargs, "frame_id": "curl"}, labels=classes, num_classes=3)
        assert session.stats()["label_dim"] == 3
        digests.append(session.digest()["sha256"])
        session.delete()
    assert digests[0] == digests[1]

    # encoded images inside msgpack too: JPEG colour (lossy, so only the frame count is compared)
    jpeg = io.BytesIO()
    Image.fromarray(kwargs["rgb"]).save(jpeg, format="JPEG", quality=90)
    session = client.create_session(voxel_size=VOXEL)
    report = session.add_frame(jpeg.getvalue(), kwargs["K"], kwargs["c2w"], depth=kwargs["depth"])
    assert report["frame_index"] == 0 and report["new_voxels"] > 0
    session.delete()


@pytest.mark.realdata
def test_labels_segmentation(client, frames):
    """Frames carrying label scores (3 classes: image thirds) -> label maps as palette PNG and uint16."""
    session = client.create_session(voxel_size=VOXEL)
    for kwargs in frames[:2]:
        h, w = kwargs["rgb"].shape[:2]
        labels = np.zeros((h, w, 3), np.float32)
        labels[np.arange(h)[:, None], np.arange(w)[None, :], np.minimum(np.arange(w) * 3 // w, 2)[None, :]] = 1.0
        session.add_frame(**kwargs, labels=labels)
    assert session.stats()["label_dim"] == 3
    K, c2w, w, h = view_of(frames[0])
    seg = session.segmentation(K, c2w, w, h)
    assert seg["labels"].dtype == np.uint16 and seg["labels"].shape == (h, w)
    drawn = seg["alpha"] > 0.5
    assert set(np.unique(seg["labels"][drawn])) <= {0, 1, 2}
    assert (seg["labels"][seg["alpha"] == 0] == 65535).all()
    # the left third of the view is mostly class 0, the right third class 2
    assert np.mean(seg["labels"][:, : w // 4][drawn[:, : w // 4]] == 0) > 0.8
    assert np.mean(seg["labels"][:, -w // 4 :][drawn[:, -w // 4 :]] == 2) > 0.8
    png = png_to_array(session.segmentation_png(K, c2w, w, h))
    assert png.shape == (h, w)
    assert np.array_equal(png.astype(np.int64) - 1, np.where(seg["labels"] == 65535, -1, seg["labels"].astype(np.int64)))
    session.delete()


@pytest.mark.realdata
def test_depth_at_half_the_colours_resolution_folds_as_the_colour_brought_to_it(client, frames):
    """A phone's LiDAR sends depth at a fraction of the colour's pixels. The service takes the whole
    colour image (raw arrays, or PNG bytes) and folds the frame its area average at the depth's size
    gives; the SDK's default sends that average itself, from an array or from image bytes (a fraction
    of the bytes): the same scene."""
    from canonical_core.camera import Camera
    from canonical_core.resample import area_resize
    from client.sdk import encode_png

    def fitted_by_the_test(rgb, K, depth, c2w):
        h, w = depth.shape
        return dict(rgb=area_resize(rgb, (w, h)), K=Camera(K, c2w, rgb.shape[1], rgb.shape[0]).resized(w, h).K64())

    paths = {
        "whole image, raw arrays: the service fits it": lambda rgb, K, depth, c2w: dict(rgb=rgb, K=K, codec="raw"),
        "whole image as PNG bytes, raw: the service fits it": lambda rgb, K, depth, c2w: dict(rgb=encode_png(rgb), K=K,
                                                                                               codec="raw"),
        "the SDK's default: the SDK fits it": lambda rgb, K, depth, c2w: dict(rgb=rgb, K=K),
        "PNG bytes, the SDK's default: the SDK decodes and fits it": lambda rgb, K, depth, c2w: dict(rgb=encode_png(rgb), K=K),
        "fitted by the caller": fitted_by_the_test,
    }
    digests = {}
    for name, path in paths.items():
        session = client.create_session(voxel_size=VOXEL)
        for kwargs in frames[:2]:
            depth = kwargs["depth"][::2, ::2]
            report = session.add_frame(depth=depth, c2w=kwargs["c2w"], **path(kwargs["rgb"], kwargs["K"], depth, kwargs["c2w"]))
            assert report["new_voxels"] > 0
        digests[name] = session.digest()["sha256"]
        session.delete()
    assert len(set(digests.values())) == 1, digests
    with pytest.raises(CanonicalError) as err:  # another camera's depth: refused, naming depth
        session = client.create_session(voxel_size=VOXEL)
        session.add_frame(frames[0]["rgb"], frames[0]["K"], frames[0]["c2w"], depth=frames[0]["depth"][:, ::3])
    assert err.value.status == 422 and err.value.field == "depth" and "shape of the rgb image" in str(err.value)
    session.delete()


def test_health_and_metrics(client, server):
    assert httpx.get(f"{server.url}/healthz").json()["status"] == "ok"  # no token needed
    assert httpx.get(f"{server.url}/metrics").status_code == 401
    text = client.metrics()
    for name in ("canonical_fold_seconds_bucket", "canonical_fold_seconds_count", "canonical_frames_folded_total",
                 "canonical_sessions", "canonical_voxels", "# TYPE canonical_fold_seconds histogram"):
        assert name in text
    # what grows only while the process lives is a counter, named as counters are (rate() reads them so)
    types = dict(line.split()[2:4] for line in text.splitlines() if line.startswith("# TYPE "))
    assert {n for n, t in types.items() if t == "counter"} == {n for n in types if n.endswith("_total")}
    for name in ("canonical_storage_errors_total", "canonical_colour_solves_done_total",
                 "canonical_viewer_superseded_total", "canonical_event_streams_dropped_total"):
        assert types[name] == "counter"


@pytest.mark.realdata
def test_depth_completion_session_reports_filled_pixels(client, frames):
    """A session with depth.completion sweeps frames with depth against the earlier ones and fills
    the large holes of their depth (the shelf's depth misses its image's left band and dark surfaces)."""
    session = client.create_session(voxel_size=VOXEL, depth={"completion": True})
    plain = client.create_session(voxel_size=VOXEL)
    reports = [session.add_frame(**f) for f in frames[:3]]
    for f in frames[:3]:
        plain.add_frame(**f)
    assert reports[0]["completed_pixels"] == 0  # no earlier view to sweep against
    assert all(r["completed_pixels"] > 500 for r in reports[1:])
    assert session.stats()["voxels"] > plain.stats()["voxels"]
    session.delete()
    plain.delete()


@pytest.mark.realdata
def test_rough_depth_is_reported_denoised(client, frames):
    """A frame whose depth is far rougher than the sensor model is folded as its local median, and
    the fold report says so; clean sensor depth is not."""
    session = client.create_session(voxel_size=VOXEL)
    assert session.add_frame(**frames[0])["denoised"] is False
    depth = frames[1]["depth"]
    noisy = depth + 0.05 * np.random.default_rng(0).standard_normal(depth.shape).astype(np.float32)
    report = session.add_frame(**{**frames[1], "depth": np.where((depth > 0) & (noisy > 0), noisy, 0).astype(np.float32)})
    assert report["denoised"] is True and report["frame_index"] == 1
    session.delete()


@pytest.mark.realdata
def test_rgb_only_session_end_to_end(client, frames):
    """A session fed only RGB frames (depth withheld) folds every frame through the service."""
    session = client.create_session(voxel_size=VOXEL)
    reports = [session.add_frame(rgb=f["rgb"], K=f["K"], c2w=f["c2w"]) for f in frames[:4]]
    assert reports[0]["pending"] and reports[1]["also_folded"] == 1
    assert all(r["observations"] > 0 for r in reports[1:])
    stats = session.stats()
    assert stats["frames"] == 4 and stats["voxels"] > 1000 and stats["gaussians"] > 1000
    out = session.render(*view_of(frames[1]))
    assert out["alpha"].mean() > 0.3
    session.delete()


@pytest.mark.realdata
def test_colour_solve_session_renders_its_inputs_closer(client, frames):
    """A session with colour_solve.views keeps input views and solves the Gaussians' colours against
    them (in the background, once no frame waits): its renders at an input pose are then closer to
    that frame than those of a session with the solve off."""
    solving = client.create_session(voxel_size=VOXEL, colour_solve={"views": 4})
    plain = client.create_session(voxel_size=VOXEL, colour_solve={"views": 0})
    for f in frames[:4]:
        solving.add_frame(**f)
        plain.add_frame(**f)
    assert wait_for(lambda: solving.stats()["colours_solved_frames"] == 4, 300)  # solved in the background
    assert plain.stats()["colours_solved_frames"] is None
    kept = 4 * frames[0]["rgb"].nbytes // 4  # four views at half size
    assert solving.stats()["memory_bytes"] >= plain.stats()["memory_bytes"] + kept
    view = view_of(frames[2])
    solved, fused = solving.render(*view), plain.render(*view)
    covered = fused["alpha"] > 0.5
    assert np.array_equal(solved["alpha"] > 0.5, covered)  # same geometry and opacity
    assert psnr(solved["rgb"][covered], frames[2]["rgb"][covered]) > psnr(fused["rgb"][covered], frames[2]["rgb"][covered]) + 1.0
    solving.delete()
    plain.delete()
