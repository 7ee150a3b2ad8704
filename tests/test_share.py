"""`cubecloud share`: the command's contract, and the page opened from file:// in a real browser (its
first view against our rasterizer, a sagittal cut, the ruler in millimetres)."""

import hashlib
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_helpers import assert_one_line_error, invoke

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.eval.runs import load_run, render_views
from cubecloud_cli.raster.backends import rasterizer_for
from cubecloud_cli.scene import read_colmap_model
from cubecloud_cli.share.page import page_camera, page_info, render_page
from cubecloud_cli.share.page_browser import evaluate, settled_page
from cubecloud_cli.share.spz import encode_spz
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.transfer.tissue_presets import resolve_transfer
from cubecloud_cli.view.browser import Chromium, chromium
from cubecloud_cli.view.transfer_view import DrawnValues, ViewTransfer, read_intensity_map

pytestmark = pytest.mark.slow

SIDE = 256  # the browser window, square like the export's views
needs_chromium = pytest.mark.skipif(chromium() is None, reason="needs chromium (apt-get install chromium)")


@pytest.fixture(scope="module")
def work(viewable_work):
    return viewable_work


@pytest.fixture(scope="module")
def shared(work):
    result = invoke("share", work, "-o", work.parent / "share", "-q")
    assert result.exit_code == 0, result.output
    return work.parent / "share"


def digest(folder) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_share_writes_one_page_and_its_spz_and_never_overwrites_unasked(work, shared, tmp_path):
    assert sorted(p.name for p in shared.iterdir()) == ["index.html", "scene.spz"]
    assert shared.stat().st_mode & 0o055 == 0o055  # readable by whoever it is shared with
    page = (shared / "index.html").read_text()
    assert len(page.encode()) < 3_000_000 and "http://" not in page.split("<script>")[0]
    scan = Path(next(iter(json.loads((work / "preprocess" / "manifest.json").read_text())["inputs"])))
    assert scan.name not in page and str(work) not in page  # nothing of where the scan came from
    before = digest(shared)
    assert_one_line_error(invoke("share", work, "-o", shared), r"exists: pass --force")
    assert digest(shared) == before
    assert_one_line_error(
        invoke("share", work, "--run", "splat-nope", "-o", tmp_path / "x"), r"choose --run from splat"
    )
    assert not (tmp_path / "x").exists()
    (tmp_path / "empty").mkdir()
    assert_one_line_error(invoke("share", tmp_path / "empty", "-o", tmp_path / "y"), r"no finished splat run")
    assert invoke("share", work, "-o", shared, "--force", "-q").exit_code == 0
    assert digest(shared) == before  # the same scene gives the same bytes
    assert invoke("share", work, "-q").exit_code == 0 and digest(work / "share") == before  # the default folder
    broken = tmp_path / "broken"
    shutil.copytree(work, broken)
    (broken / "splat" / "point_cloud.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\ngarbage")
    assert_one_line_error(invoke("share", broken, "-o", tmp_path / "z"), r"point_cloud.ply")
    assert not (tmp_path / "z").exists()


def test_a_damaged_colmap_model_in_our_export_names_the_export_that_remakes_it(work, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(work, broken)
    images = broken / "export" / "sparse" / "0" / "images.bin"
    images.write_bytes(b"\xff" * images.stat().st_size)  # the same size: only the content is wrong
    fix = rf"images.bin is not a readable COLMAP file .*: run `cubecloud export {broken} --force`"
    assert_one_line_error(invoke("splat", broken, "--name", "again", "--iterations", "2"), fix)
    assert_one_line_error(invoke("share", broken, "-o", tmp_path / "page"), fix)
    assert not (broken / "splat-again").exists() and not (tmp_path / "page").exists()


def settle(browser: Chromium) -> np.ndarray:
    return settled_page(browser, timeout_s=180.0).astype(np.float64).mean(axis=2) / 255.0


def open_bare(browser: Chromium, page) -> np.ndarray:
    browser.open(page.resolve().as_uri() + "?bare")  # the canvas alone, as our renders are
    return settle(browser)


@needs_chromium
@pytest.mark.usefixtures("every_core")
def test_the_page_opens_on_the_first_view_as_our_rasterizer_draws_it_and_a_sagittal_cut_hides_one_side(work, shared):
    with Chromium((SIDE, SIDE)) as browser:
        whole = open_bare(browser, shared / "index.html")
        labels = evaluate(browser, "[...document.querySelectorAll('.axis')].map(e => e.textContent).join('')")
        evaluate(browser, "window.cubecloud.setCut('sagittal', 0)")
        cut = settle(browser)
        right = evaluate(browser, "window.cubecloud.project([0.6, 0, 0])")
        summary = evaluate(browser, "document.getElementById('summary').textContent")
    cameras = read_colmap_model(work / "export").cameras
    first = PinholeCameras(
        cameras.rotations[:1], cameras.translations[:1], SIDE, SIDE, cameras.focal * SIDE / cameras.height
    )
    run = load_run(work, "splat")
    ours = render_views(run.gaussians(), first, [0], rasterizer_for(torch.device("cpu")), antialias=run.antialias)[0][0]
    assert labels == "LRPAIS"
    assert ("anti-aliased" in summary) == run.antialias
    assert whole.mean() > 0.01 and np.corrcoef(whole.ravel(), ours.ravel())[0, 1] > 0.9
    # The cut hides world x > 0 (the patient's right): that half of the picture goes dark, the other stays.
    right_half = slice(SIDE // 2, None) if right[0] > SIDE / 2 else slice(None, SIDE // 2)
    left_half = slice(None, SIDE // 2) if right[0] > SIDE / 2 else slice(SIDE // 2, None)
    assert cut[:, right_half].mean() < 0.25 * whole[:, right_half].mean()
    assert cut[:, left_half].mean() > 0.7 * whole[:, left_half].mean()


def first_view(work, side: int = SIDE) -> PinholeCameras:
    cameras = read_colmap_model(work / "export").cameras
    return PinholeCameras(
        cameras.rotations[:1], cameras.translations[:1], side, side, cameras.focal * side / cameras.height
    )


@needs_chromium
@pytest.mark.usefixtures("every_core")
def test_a_scalar_scenes_page_recolours_it_as_our_rasterizer_draws_it_under_each_transfer_function(work, tmp_path):
    """The page's transfer-function map against ScalarGaussians drawn by our rasterizer, under the
    tissue preset and under a narrow dense window (0.30–0.45, opacity × 7.5); then its opacities
    against ours, from the first view and after the camera has moved to the sixth and rested."""
    assert invoke("share", work, "--run", "splat-scalar", "-o", tmp_path / "page", "-q").exit_code == 0
    run = load_run(work, "splat-scalar")
    scalar = run.scalar_gaussians()
    choices = {"tissue": {"preset": "tissue"}, "window": {"low": 0.3, "high": 0.45, "opacity": 7.5}}
    shots, ours = {}, {}
    with Chromium((SIDE, SIDE)) as browser:
        open_bare(browser, tmp_path / "page" / "index.html")
        presets = evaluate(browser, "[...document.getElementById('tf-preset').options].map(o => o.value)")
        for name, choice in choices.items():
            evaluate(browser, f"window.cubecloud.setTransfer({json.dumps(choice)})")
            shots[name] = settle(browser)
        at_home = evaluate(browser, "window.cubecloud.opacities()")
        side = read_colmap_model(work / "export").cameras.centres()[5]
        evaluate(browser, f"window.cubecloud.moveCamera({json.dumps(side.tolist())})")
        deadline = time.monotonic() + 60
        while not evaluate(browser, "window.cubecloud.redraws") and time.monotonic() < deadline:
            time.sleep(0.1)
        moved = evaluate(browser, "window.cubecloud.opacities()")
    assert presets[0] == "as trained" and "tissue" in presets and presets[-1] == "custom"
    tissue = resolve_transfer("tissue", read_intensity_map(work))
    presets_of = {"tissue": tissue, "window": ViewTransfer(tissue.with_window(0.3, 0.45), 7.5).effective()}
    rasterizer = rasterizer_for(torch.device("cpu"))
    for name, function in presets_of.items():
        drawn = scalar.drawn_as(function)
        ours[name] = render_views(drawn, first_view(work), [0], rasterizer, antialias=run.antialias)[0][0]
    correlation = {(a, b): np.corrcoef(shots[a].ravel(), ours[b].ravel())[0, 1] for a in shots for b in ours}
    assert correlation["tissue", "tissue"] > 0.9 and correlation["window", "window"] > 0.9, correlation
    assert correlation["window", "window"] > correlation["window", "tissue"], correlation
    # The scene's opacities follow the camera (chord lengths): the page redraws them once it rests.
    assert scalar.chord_lengths
    home = np.asarray(read_colmap_model(work / "export").cameras.centres()[0])
    side = np.asarray(read_colmap_model(work / "export").cameras.centres()[5])
    drawn, window = DrawnValues.of(scalar), presets_of["window"]
    assert np.abs(np.asarray(at_home) - drawn.opacities(window, home)).max() < 0.03
    assert np.abs(np.asarray(moved) - drawn.opacities(window, side)).max() < 0.03
    page_change, our_change = np.subtract(moved, at_home), drawn.opacities(window, side) - drawn.opacities(window, home)
    assert np.abs(our_change).max() > 0.05 and np.corrcoef(page_change, our_change)[0, 1] > 0.9


def two_blob_page(tmp_path, world_to_scanner: np.ndarray):
    """A page of two small opaque Gaussians at known points, seen square-on from +z."""
    points = torch.tensor([[-0.4, 0.0, 0.0], [0.5, 0.1, 0.0]])
    gaussians = Gaussians(
        points,
        torch.full((2, 3), math.log(0.02)),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2),
        torch.full((2,), 5.0),
        torch.full((2, 1, 1), 1.0),
        torch.zeros(2, 0, 1),
    )
    camera = PinholeCameras(np.diag([1.0, -1.0, -1.0])[None], np.array([[0.0, 0.0, 4.0]]), SIDE, SIDE, SIDE * 1.5)
    info = page_info(page_camera(camera), world_to_scanner, True, gaussians.log_scales.numpy())
    path = tmp_path / "index.html"
    path.write_text(render_page(encode_spz(gaussians, antialiased=True, fractional_bits=14), info))
    return path, points.numpy()


@needs_chromium
@pytest.mark.usefixtures("every_core")
def test_reset_view_returns_after_a_drag_and_the_ruler_reads_two_clicked_points_in_millimetres(tmp_path):
    world_to_scanner = np.array([[150.0, 0, 0, -20.0], [0, 120.0, 0, 35.0], [0, 0, 100.0, 250.0], [0, 0, 0, 1]])
    page, points = two_blob_page(tmp_path, world_to_scanner)
    with Chromium((SIDE, SIDE)) as browser:
        start = open_bare(browser, page)  # the panel would cover the left point in so small a window
        for kind, x in (("mousePressed", 60), ("mouseMoved", 200), ("mouseReleased", 200)):  # a drag turns the view
            browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=128, button="left", buttons=1, clickCount=1)
        turned = settle(browser)
        evaluate(browser, "document.getElementById('reset').click()")
        reset = settle(browser)
        evaluate(browser, "document.getElementById('measure').click()")
        for point in points:
            x, y, visible = evaluate(browser, f"window.cubecloud.project({json.dumps(point.tolist())})")
            assert visible
            for kind in ("mousePressed", "mouseReleased"):
                browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)
        settle(browser)
        shown = evaluate(browser, "document.getElementById('distance').textContent")
        distance = evaluate(browser, "window.cubecloud.distanceMm")
    expected = float(np.linalg.norm(world_to_scanner[:3, :3] @ (points[1] - points[0])))
    voxel_mm = 150.0 * 2 / 128  # one voxel of a 128³ cube along the coarsest axis
    assert abs(distance - expected) < voxel_mm, (distance, expected)
    assert shown == f"{distance:.1f} mm"
    assert np.abs(turned - start).mean() > 1e-3 and np.abs(reset - start).mean() < 1e-4  # "Reset view" returns
