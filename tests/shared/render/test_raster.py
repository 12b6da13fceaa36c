"""CPU point rasteriser: projection against OpenCV, nearest point wins, seed splat sizing
closes a dense wall, node selection under a budget."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shared.render.raster import Camera, GLRasterizer, NodeTable, Rasterizer, pack_colours, select_nodes


def _project_cv(cam: Camera, p: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cam.R)
    uv, _ = cv2.projectPoints(p.astype(np.float64).reshape(-1, 1, 3), rvec, cam.t, cam.K, None)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_lands_where_opencv_projects_it(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cam = Camera.look_at(rng.uniform(-500, 500, 3) + [0, 0, -1500], rng.uniform(-50, 50, 3), [0, -1, 0],
                         rng.uniform(30, 70), 320, 240)  # fmt: skip
    rz = Rasterizer(320, 240)
    for _ in range(5):
        p = rng.uniform(-200, 200, (1, 3)).astype(np.float32)
        uv = _project_cv(cam, p)[0]
        if not (2 <= uv[0] < 318 and 2 <= uv[1] < 238):
            continue
        f = rz.render(cam, p, pack_colours(np.array([[255, 255, 255]], np.uint8)), np.zeros(1, np.float32))
        ys, xs = np.nonzero(f.rgb[:, :, 0])
        assert len(xs) == 1
        assert abs(xs[0] - uv[0]) <= 0.5 + 1e-3 and abs(ys[0] - uv[1]) <= 0.5 + 1e-3
        assert f.depth[ys[0], xs[0]] == pytest.approx((cam.R @ p[0] + cam.t)[2], rel=1e-5)


def test_look_at_keeps_up_upwards() -> None:
    cam = Camera.look_at([0, 0, -1000], [0, 0, 0], [0, -1, 0], 50, 200, 100)
    above = _project_cv(cam, np.array([[0.0, -100.0, 0.0]]))[0]  # world up is -y
    assert above[1] < cam.cy


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_nearer_point_wins(order) -> None:
    cam = Camera.look_at([0, 0, -1000], [0, 0, 0], [0, -1, 0], 50, 64, 48)
    pts = np.array([[0, 0, 0], [0, 0, -300]], np.float32)[list(order)]  # same ray, second is nearer
    rgb = np.array([[255, 0, 0], [0, 0, 255]], np.uint8)[list(order)]
    f = Rasterizer(64, 48).render(cam, pts, pack_colours(rgb), np.zeros(2, np.float32))
    ys, xs = np.nonzero(f.rgb.any(axis=2))
    assert len(xs) == 1
    assert tuple(f.rgb[ys[0], xs[0]]) == (0, 0, 255)


def test_seed_sizing_closes_a_dense_wall() -> None:
    """A wall sampled every s mm with world size s: seen from close by, 1-px splats leave holes
    while splats of fx * s / z pixels close it (holes inside the silhouette < 1 %)."""
    s = 2.0
    g = np.arange(-200, 200, s)
    x, y = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 500.0)], axis=1).astype(np.float32)
    pts[:, :2] += np.random.default_rng(0).uniform(-0.3, 0.3, (len(pts), 2)).astype(np.float32)
    col = pack_colours(np.full((len(pts), 3), 200, np.uint8))
    cam = Camera.look_at([30, 10, 200], [30, 10, 500], [0, -1, 0], 30, 320, 240)
    rz = Rasterizer(320, 240)
    inner = (slice(20, 220), slice(20, 300))  # the wall fills the frame; stay off the edges
    sized = rz.render(cam, pts, col, np.full(len(pts), s, np.float32))
    single = rz.render(cam, pts, col, np.zeros(len(pts), np.float32))
    holes_sized = np.mean(~np.isfinite(sized.depth[inner]))
    holes_single = np.mean(~np.isfinite(single.depth[inner]))
    assert cam.fx * s / 300 > 2  # points are more than 2 px apart on screen
    assert holes_sized < 0.01
    assert holes_single > 0.3


def test_threads_agree_with_one_thread() -> None:
    rng = np.random.default_rng(5)
    pts = rng.uniform(-100, 100, (20_000, 3)).astype(np.float32)
    col = rng.integers(0, 2**24, len(pts)).astype(np.uint32)
    size = rng.uniform(0, 3, len(pts)).astype(np.float32)
    cam = Camera.look_at([0, 0, -400], [0, 0, 0], [0, -1, 0], 60, 160, 120)
    ranges = np.array([[0, 5000], [5000, 12000], [12000, 20000]])
    a = Rasterizer(160, 120, threads=1).render(cam, pts, col, size, ranges)
    b = Rasterizer(160, 120, threads=3).render(cam, pts, col, size, ranges)
    assert np.array_equal(a.rgb, b.rgb)


def test_batch_of_frames_equals_frames_one_by_one() -> None:
    rng = np.random.default_rng(6)
    pts = rng.uniform(-100, 100, (30_000, 3)).astype(np.float32)
    col = rng.integers(0, 2**24, len(pts)).astype(np.uint32)
    size = rng.uniform(0, 2, len(pts)).astype(np.float32)
    cams = [Camera.look_at([x, 0, -400], [0, 0, 0], [0, -1, 0], 50, 96, 64) for x in (-200, 150)]
    ranges = [np.array([[0, 20_000]]), np.array([[5_000, 12_000], [15_000, 30_000]])]
    ms = [np.zeros(1, np.float32), np.array([0, 3], np.float32)]
    rz = Rasterizer(96, 64, threads=2)
    batch = rz.render_batch(cams, pts, col, size, ranges, ms)
    for cam, r, m, frame in zip(cams, ranges, ms, batch, strict=True):
        one = Rasterizer(96, 64, threads=1).render(cam, pts, col, size, r, m)
        assert np.array_equal(one.rgb, frame.rgb) and np.array_equal(one.depth, frame.depth)
    assert not np.array_equal(batch[0].rgb, batch[1].rgb)
    with pytest.raises(ValueError):
        rz.render_batch(cams * 2, pts, col, size, ranges * 2, ms * 2)


def _cloud(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points around the origin, some behind a camera at z = -400 and some off its frame,
    colours with ties, sizes from none to splats wider than a pixel."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(0, 150, (n, 3)).astype(np.float32)
    pts[: n // 10, 2] = -410 - np.abs(pts[: n // 10, 2])  # behind the camera
    col = rng.integers(0, 2**24, n).astype(np.uint32)
    col[: n // 3] = 5
    size = (rng.exponential(1.0, n) * rng.integers(0, 2, n)).astype(np.float32)
    return pts, col, size


def test_ranges_cut_anywhere_draw_the_same_frame() -> None:
    """The kernel projects points in batches and prefetches ahead across ranges: cutting the
    points into ranges of any lengths (empty, one point, batch sizes and one off) changes
    nothing, and points behind the camera or off the frame are not drawn."""
    pts, col, size = _cloud(7, 5000)
    cam = Camera.look_at([0, 0, -400], [0, 0, 0], [0, -1, 0], 60, 120, 90)
    whole = Rasterizer(120, 90, threads=1).render(cam, pts, col, size)
    cuts = np.array([0, 0, 1, 2, 255, 511, 512, 768, 769, 769, 2000, 4999, 5000])
    ranges = np.stack([cuts[:-1], cuts[1:]], axis=1)
    for threads in (1, 2, 5):
        part = Rasterizer(120, 90, threads=threads).render(cam, pts, col, size, ranges)
        assert np.array_equal(part.rgb, whole.rgb) and np.array_equal(part.depth, whole.depth)
    assert 0.05 < np.isfinite(whole.depth).mean() < 0.99  # drawn points, and background
    ahead = Rasterizer(120, 90, threads=1).render(
        cam, pts[5000 // 10 :], col[5000 // 10 :], size[5000 // 10 :]
    )
    assert np.array_equal(ahead.rgb, whole.rgb)  # the points behind the camera drew nothing


def test_frame_widths_with_and_without_packed_colour_words_agree() -> None:
    """Frames whose width is a multiple of 4 get their colours written 4 pixels to 3 words, other
    widths byte by byte: one more column on the right leaves the first 120 columns as they were."""
    pts, col, size = _cloud(9, 6000)
    cam = Camera.look_at([0, 0, -400], [0, 0, 0], [0, -1, 0], 60, 120, 90)
    wider = Camera(R=cam.R, t=cam.t, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=121, height=90)
    a = Rasterizer(120, 90, threads=2).render(cam, pts, col, size, background=(18, 18, 24))
    b = Rasterizer(121, 90, threads=2).render(wider, pts, col, size, background=(18, 18, 24))
    assert np.array_equal(a.rgb, b.rgb[:, :120]) and np.array_equal(a.depth, b.depth[:, :120])
    assert (a.rgb == (18, 18, 24)).all(axis=2).mean() > 0.01 and np.isfinite(a.depth).mean() > 0.05


def test_buffers_are_clean_for_the_next_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The resolve clears the key buffers it reads (no clearing pass): a frame drawn after
    another equals it drawn by a new rasteriser, also after a draw that failed half-way."""
    from shared.render import raster

    pts, col, size = _cloud(8, 4000)
    near_cam = Camera.look_at([0, 0, -250], [0, 0, 0], [0, -1, 0], 70, 96, 64)
    far_cam = Camera.look_at([300, 0, -900], [0, 0, 0], [0, -1, 0], 40, 96, 64)
    fresh = Rasterizer(96, 64, threads=2).render(far_cam, pts, col, size)
    rz = Rasterizer(96, 64, threads=2)
    rz.render(near_cam, pts, col, size)
    again = rz.render(far_cam, pts, col, size)
    assert np.array_equal(again.rgb, fresh.rgb) and np.array_equal(again.depth, fresh.depth)
    batch = rz.render_batch(
        [near_cam, far_cam], pts, col, size, [np.array([[0, 4000]])] * 2, [np.zeros(1)] * 2
    )
    assert np.array_equal(batch[1].depth, fresh.depth)
    assert np.array_equal(rz.render(far_cam, pts, col, size).depth, fresh.depth)

    def fail(*args: object) -> None:
        raise RuntimeError("resolve interrupted")

    with monkeypatch.context() as m:
        m.setattr(raster, "_resolve", fail)
        with pytest.raises(RuntimeError):
            rz.render(near_cam, pts, col, size)  # keys splatted, never resolved nor cleared
    assert np.array_equal(rz.render(far_cam, pts, col, size).depth, fresh.depth)


def test_select_nodes_respects_budget_and_parents() -> None:
    # Root with two children, each with two children; right branch behind the camera.
    center = np.array(
        [[0, 0, 0], [-50, 0, 0], [50, 0, -5000], [-75, 0, 0], [-25, 0, 0], [75, 0, -5000], [25, 0, -5000]],
        float,
    )
    table = NodeTable(center=center, radius=np.array([200, 100, 100, 50, 50, 50, 50.0]),
                      parent=np.array([-1, 0, 0, 1, 1, 2, 2]), points=np.array([10, 10, 10, 10, 10, 10, 10]),
                      spacing=np.ones(7))  # fmt: skip
    cam = Camera.look_at([0, 0, -1000], [0, 0, 0], [0, -1, 0], 50, 200, 150)
    chosen, visible = select_nodes(table, cam, budget=1000)
    assert not visible[2] and 2 not in chosen and 5 not in chosen
    assert set(chosen.tolist()) == {0, 1, 3, 4}
    chosen, _ = select_nodes(table, cam, budget=25)
    assert chosen.tolist() == [0, 1]


def test_opengl_points_match_the_cpu_rasteriser() -> None:
    """moderngl (llvmpipe here, a GPU elsewhere) draws the same splats as the CPU path."""
    try:
        gl = GLRasterizer(160, 120)
    except Exception as exc:
        pytest.fail(f"no OpenGL context ({exc!r}): make setup installs libegl1 and libgl1-mesa-dri")
    try:
        rng = np.random.default_rng(2)
        g = np.arange(-100, 100, 4.0)
        x, y = np.meshgrid(g, g)
        pts = np.stack([x.ravel(), y.ravel(), 300 + 0.2 * x.ravel()], axis=1).astype(np.float32)
        rgb = rng.integers(0, 256, (len(pts), 3), dtype=np.uint8)
        size = np.full(len(pts), 4.0, np.float32)
        cam = Camera.look_at([20, -10, -200], [0, 0, 300], [0, -1, 0], 50, 160, 120)
        ranges = np.array([[0, len(pts)]])
        ms = np.zeros(1, np.float32)
        cpu = Rasterizer(160, 120).render(cam, pts, pack_colours(rgb), size, ranges, ms).rgb
        gl.upload(pts, pack_colours(rgb), size)
        img = gl.render(cam, ranges, ms, far=1e5)
        assert img.shape == cpu.shape
        covered_cpu = cpu.any(axis=2)
        covered_gl = img.any(axis=2)
        assert covered_cpu.mean() > 0.1
        assert np.mean(covered_cpu != covered_gl) < 0.05  # same silhouette up to splat edges
        same = np.all(np.abs(cpu.astype(int) - img.astype(int)) <= 2, axis=2)
        assert same[covered_cpu & covered_gl].mean() > 0.7  # mostly the same winning point
    finally:
        gl.release()
