"""Headless GIF/PNG export: valid files from every scene, pixels where the camera puts
them, strain colours, frame schedules, and nothing lost when a run stops early."""

import re

import numpy as np
import pytest
from PIL import Image

import massspring as ms
from massspring import cli
from massspring.cli import main
from massspring.io import camera, render
from massspring.scene import SceneError, builtin_scenes, generators, load_scene
from massspring.engine.simulation import run
from conftest import FULL, sampled

SMALL = {"grid": ["--set", "resolution=6"], "lattice": ["--set", "resolution=3"], "chain": ["--set", "count=5"]}
BACKGROUND = np.array(render.BACKGROUND)


def gif_frames(path):
    """All frames of a GIF as (H, W, 3) uint8 arrays."""
    with Image.open(path) as im:
        assert im.format == "GIF"
        frames = []
        for i in range(im.n_frames):
            im.seek(i)
            frames.append(np.asarray(im.convert("RGB")))
        return frames, im.info


def plot_region(image):
    left, top, width, height = render.plot_box((image.shape[1], image.shape[0]))
    return image[top:top + height, left:left + width]


def drawn(image):
    """Mask of pixels that differ from the background."""
    return np.any(image != BACKGROUND, axis=-1)


# tablecloth and thrown left out: self-collision scenes framed as ledge and sheets are (a box
# and the ground; the ground), each run compiling the pass (6 s)
@pytest.mark.parametrize("scene", sampled(sorted(set(builtin_scenes()) - {"tablecloth", "thrown"}), {"cloth"}))
def test_gif_of_every_scene(scene, tmp_path, capsys):
    gif, png = tmp_path / "run.gif", tmp_path / "last.png"
    code = main(["run", scene, "--steps", "20", "--every", "10", "--size", "160x120", "--fps", "20",
                 "--gif", str(gif), "--png", str(png), "--quiet", *SMALL.get(load_scene(scene).generator, [])])
    assert code == 0
    assert "wrote" in capsys.readouterr().out
    frames, info = gif_frames(gif)
    assert len(frames) == 3  # steps 0, 10, 20
    assert all(f.shape == (120, 160, 3) for f in frames)
    assert info["duration"] == 50 and info["loop"] == 0  # 20 fps
    plots = [plot_region(f).astype(int) for f in frames]
    for a in range(3):  # the motion is in the picture, not only in the caption's time
        for b in range(a + 1, 3):
            assert np.abs(plots[a] - plots[b]).sum() > 0, (a, b)
    last = plots[-1]
    assert len(np.unique(last.reshape(-1, 3), axis=0)) >= 4
    assert drawn(last).mean() > 0.01
    rows, cols = np.nonzero(np.any([drawn(p) for p in plots], axis=0))
    span = max((cols.max() - cols.min()) / last.shape[1], (rows.max() - rows.min()) / last.shape[0])
    assert span > 0.8  # the run's box fills the plot (less the margins) in one direction
    final = np.asarray(Image.open(png).convert("RGB"))
    assert final.shape == (120, 160, 3)
    assert np.abs(final.astype(int) - frames[-1]).mean() < 3  # the PNG is the last frame, unquantised


def one_spring(rest_length, end=(1.0, 0.0, 0.0)):
    return ms.Model([[0.0, 0.0, 0.0], end], [[0, 1]], rest_lengths=rest_length, fixed=[0], gravity=(0, 0, 0))


def render_one(model, view, size=(200, 200), frames=None):
    x = model.positions
    renderer = render.FrameRenderer(model, x[None] if frames is None else frames, view, size)
    return renderer.render(x, 0.0)


def test_spring_along_x_is_a_horizontal_line_across_the_plot():
    # camera on -y looking at +y (azimuth -90, elevation 0): +x is right, +z is up.
    image = render_one(one_spring(0.8), camera.View(azimuth=-90, elevation=0))
    left, top, width, height = render.plot_box((200, 200))
    mask = drawn(image[top:top + height])
    rows, cols = np.nonzero(mask)
    # the line is centred vertically in the plot (row boundary at height / 2) ...
    assert set(rows) <= set(range(height // 2 - 3, height // 2 + 3))
    # ... and its ends sit MARGIN in from the sides (within the end dots' radius)
    ends = np.array([width * camera.MARGIN, width * (1 - camera.MARGIN)])
    dot = 1.5 * max(2.0, 200 / 120) + 1
    assert abs(cols.min() - ends[0]) <= dot and abs(cols.max() + 1 - ends[1]) <= dot
    # stretched by 25 % with the scale's limit at 25 %: the line has the map's extension end
    assert np.array_equal(line_colour(model=one_spring(0.8)), render.DIVERGING[-1])
    # the fixed particle (x = 0) is the amber dot on the left
    amber = np.all(np.abs(image[top:top + height].astype(int) - render.FIXED) < 30, axis=-1)
    assert amber.any() and np.nonzero(amber)[1].max() < 0.1 * 200


def line_colour(model, frames=None, size=400):
    """The colour at the centre of the (horizontal) line drawn across the picture's middle
    column: 400 px wide lines are 2.5 px thick, so their centre pixel is not blended."""
    image = render_one(model, camera.View(azimuth=-90, elevation=0), size=(size, size), frames=frames)
    left, top, width, height = render.plot_box((size, size))
    column = image[top:top + height, size // 2]
    rows = np.flatnonzero(drawn(column))
    return column[rows[len(rows) // 2]].astype(int)


def test_spring_colour_follows_its_strain_on_the_map():
    # one spring at strain -20 % (the scale's limit, from the only frame): the compression
    # end of the map; with a scale of -40..40 % (set by 50 later frames twice as
    # compressed) it is halfway to neutral grey, the map's second colour
    model = one_spring(1.25)
    assert np.array_equal(line_colour(model), render.DIVERGING[0])
    frames = np.stack([model.positions] + [model.positions * [0.75, 1, 1]] * 50)
    assert np.array_equal(line_colour(model, frames), render.DIVERGING[1])


def test_view_direction_and_top_view():
    # looking along the spring (azimuth 0: from +x) it collapses to a dot at the centre
    image = plot_region(render_one(one_spring(1.0), camera.View(azimuth=0, elevation=0)))
    rows, cols = np.nonzero(drawn(image))
    assert cols.max() - cols.min() < 12 and abs(cols.mean() - image.shape[1] / 2) < 3
    # from above (elevation 90, azimuth -90), +y is up on screen: a spring along y is vertical
    image = plot_region(render_one(one_spring(1.0, end=(0.0, 1.0, 0.0)), camera.View(azimuth=-90, elevation=90)))
    rows, cols = np.nonzero(drawn(image))
    assert cols.max() - cols.min() < 12 and rows.max() - rows.min() > 0.8 * image.shape[0]
    fixed_rows = np.nonzero(np.all(np.abs(image.astype(int) - render.FIXED) < 30, axis=-1))[0]
    assert fixed_rows.min() > image.shape[0] / 2  # particle 0 (y = 0) is at the bottom


def test_perspective_draws_the_nearer_spring_longer():
    # two unit springs along x at y = -0.5 (nearer the camera on -y) and y = +0.5
    model = ms.Model([[0, -0.5, 0], [1, -0.5, 0], [0, 0.5, 0.6], [1, 0.5, 0.6]], [[0, 1], [2, 3]],
                     gravity=(0, 0, 0))
    view = camera.View(azimuth=-90, elevation=0, projection="perspective")
    image = plot_region(render_one(model, view, size=(300, 300)))
    mask = drawn(image)
    rows = np.flatnonzero(mask.any(axis=1))
    groups = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1)
    assert len(groups) == 2
    upper, lower = (mask[g].any(axis=0) for g in groups)  # z = 0.6 (far) is drawn above z = 0 (near)
    far_len, near_len = np.ptp(np.flatnonzero(upper)), np.ptp(np.flatnonzero(lower))
    # pinhole camera PERSPECTIVE_DISTANCE * radius from the centre: lengths scale as 1 / distance
    radius = np.linalg.norm([1.0, 1.0, 0.6]) / 2
    d = camera.PERSPECTIVE_DISTANCE * radius
    assert near_len / far_len == pytest.approx((d + 0.5) / (d - 0.5), rel=0.03)


def test_framing_covers_every_frame():
    model = one_spring(1.0)
    frames = np.array([model.positions, model.positions + [0.0, 0.0, 3.0]])  # moved up 3 m later
    renderer = render.FrameRenderer(model, frames, camera.View(-90, 0), (200, 200))
    left, top, width, height = render.plot_box((200, 200))
    for x in frames:
        px, _ = renderer.framing.pixels(x)
        assert np.all((px[:, 0] >= left) & (px[:, 0] <= left + width))
        assert np.all((px[:, 1] >= top) & (px[:, 1] <= top + height))
    early, _ = renderer.framing.pixels(frames[0])
    late, _ = renderer.framing.pixels(frames[1])
    assert late[0, 1] < early[0, 1]  # up in the world is up in the picture


def test_surface_triangle_edges_are_springs():
    for scene in ("cloth", "cube"):
        sc = load_scene(scene).with_params(resolution=4)
        model = sc.model()
        tris = model.triangles
        expected = {"cloth": 2 * 3 * 3, "cube": 6 * 2 * 3 * 3}[scene]
        assert tris.shape == (expected, 3)
        idx = render.edge_springs(model.springs, tris, model.n_particles)
        assert np.all(idx >= 0)
        for t, tri in enumerate(tris):
            for e in range(3):
                pair = {int(tri[e]), int(tri[(e + 1) % 3])}
                assert set(model.springs[idx[t, e]].tolist()) == pair
    model = load_scene("cloth").with_params(resolution=4, shear=0.0).model()
    idx = render.edge_springs(model.springs, model.triangles, model.n_particles)
    assert np.sum(idx < 0) == 2 * 3 * 3  # one diagonal per triangle has no spring without shear


def test_strain_and_colour_map():
    x = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0]])
    strain = render.spring_strain(x, np.array([[0, 1], [0, 2], [1, 2]]), np.array([1.0, 4.0, 0.0]))
    assert strain == pytest.approx([1.0, -0.25, 0.0])
    colours = render.diverging_colours([-5.0, -1.0, 0.0, 1.0, 5.0])
    assert np.allclose(colours[0], render.DIVERGING[0]) and np.allclose(colours[1], render.DIVERGING[0])
    assert np.allclose(colours[2], render.DIVERGING[len(render.DIVERGING) // 2])
    assert np.allclose(colours[4], render.DIVERGING[-1])
    assert render.packed((255, 128, 1)) == 0xFF8001


def test_frame_steps():
    assert render.frame_steps(10, every=4).tolist() == [0, 4, 8, 10]
    assert render.frame_steps(10, every=5).tolist() == [0, 5, 10]
    assert render.frame_steps(10, frames=3).tolist() == [0, 5, 10]
    assert render.frame_steps(7, frames=8).tolist() == list(range(8))
    assert render.frame_steps(7, frames=1).tolist() == [7]
    assert len(render.frame_steps(120, duration=2.0, fps=30)) == 61  # 2 s at 30 fps, both ends
    assert len(render.frame_steps(10000, duration=100.0, fps=30)) == render.DEFAULT_MAX_FRAMES
    assert render.frame_steps(0, duration=1.0).tolist() == [0]
    with pytest.raises(ValueError, match="frames"):
        render.frame_steps(5, frames=7)


class FakeSim:
    def __init__(self):
        self.steps, self.calls, self.integrator, self.dt = 0, [], "fake", 1.0

    def step(self, k):
        self.calls.append(k)
        self.steps += k


def test_run_calls_back_at_frame_steps_only():
    sim, seen = FakeSim(), []
    run(sim, 1000, frames=[0, 7, 500, 1000], on_frame=lambda s: seen.append(s.steps))
    assert seen == [0, 7, 500, 1000] and sim.steps == 1000
    plain, progress = FakeSim(), []
    run(plain, 1000, progress=lambda done, total: progress.append((done, total)))
    assert plain.calls == [5] * 200  # without frames: the usual chunks
    assert progress[0] == (5, 1000) and progress[-1] == (1000, 1000) and len(progress) == 200


def test_interrupted_run_keeps_the_frames_before(tmp_path, monkeypatch, capsys):
    gif = tmp_path / "cut.gif"
    original = ms.Simulation.step

    def step(self, n=1):
        if self.steps >= 4:
            raise KeyboardInterrupt
        return original(self, n)

    monkeypatch.setattr(ms.Simulation, "step", step)
    code = main(["run", "chain", "--set", "count=5", "--integrator", "symplectic", "--steps", "10",
                 "--every", "2", "--size", "96x96", "--gif", str(gif), "--quiet"])
    assert code == cli.EXIT_INTERRUPTED
    assert "stopped at step 4 of 10" in capsys.readouterr().err
    frames, _ = gif_frames(gif)
    assert len(frames) == 3  # steps 0, 2, 4
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_diverging_run_keeps_the_frames_before(tmp_path, capsys):
    # explicit Euler on an undamped spring grows by sqrt(1 + (w dt)^2) = 5.1 per step here
    gif = tmp_path / "boom.gif"
    code = main(["run", "spring", "--integrator", "explicit", "--dt", "0.5", "--set", "damping=0",
                 "--steps", "60", "--every", "1", "--size", "96x96", "--gif", str(gif), "--quiet"])
    err = capsys.readouterr().err
    assert code not in (0, 2)
    stopped = int(re.search(r"stopped at step (\d+) of 60", err).group(1))
    assert 0 < stopped < 60
    frames, _ = gif_frames(gif)
    assert len(frames) == stopped + 1


def test_diverging_run_ends_its_gif_on_the_last_good_state(tmp_path, capsys):
    # frames planned at steps 0, 30, 60 only; the run diverges before step 30
    gif = tmp_path / "boom.gif"
    code = main(["run", "spring", "--integrator", "explicit", "--dt", "0.5", "--set", "damping=0",
                 "--steps", "60", "--frames", "3", "--size", "96x96", "--gif", str(gif), "--quiet"])
    captured = capsys.readouterr()
    assert code == cli.EXIT_DIVERGED
    stopped = int(re.search(r"stopped at step (\d+) of 60", captured.err).group(1))
    assert 0 < stopped < 30
    frames, _ = gif_frames(gif)
    assert len(frames) == 2 and not np.array_equal(frames[0], frames[1])  # step 0 and the last good step
    assert f"t = 0 to {stopped * 0.5:g} s" in captured.err


def test_scene_view_table(tmp_path):
    base = builtin_scenes()["chain"].read_text().split("\n[view]")[0] + "\n[view]\n"
    path = tmp_path / "ok.toml"
    path.write_text(base + 'azimuth = 10\nelevation = -30.5\nprojection = "perspective"\nframing = "last"\n')
    scene = load_scene(path)
    assert scene.view == camera.View(10.0, -30.5, "perspective") and scene.framing == "last"
    for body, key in (('zoom = 2.0\n', "view.zoom"), ('azimuth = "north"\n', "view.azimuth")):
        path = tmp_path / "bad.toml"
        path.write_text(base + body)
        with pytest.raises(SceneError, match=re.escape(key)) as err:
            load_scene(path)
        assert str(path) in str(err.value)
    assert load_scene("cube").view.projection == "perspective"


@pytest.mark.parametrize("body, key", [('projection = "fisheye"\n', "view.projection"),
                                       ("elevation = 120\n", "view.elevation"),
                                       ('framing = "zoom"\n', "view.framing")])
@pytest.mark.parametrize("pictures", [True, False])
def test_scene_view_out_of_range_refused_up_front(body, key, pictures, tmp_path, capsys):
    # a [view] table out of range is refused when the scene is loaded, picture or not
    base = builtin_scenes()["chain"].read_text().split("\n[view]")[0] + "\n[view]\n"
    path = tmp_path / "bad.toml"
    path.write_text(base + body)
    gif = tmp_path / "x.gif"
    assert main(["run", str(path), "--steps", "3", "--quiet"] + (["--gif", str(gif)] if pictures else [])) == 2
    err = capsys.readouterr().err
    assert key in err and str(path) in err and err.count("\n") == 1
    assert not gif.exists()


@FULL
@pytest.mark.parametrize("framing", ["run", "follow", "last"])
def test_scene_framing_with_framing_option(framing, tmp_path, capsys):
    # a scene whose [view] names a framing (cube: follow), with --framing given too
    gif = tmp_path / "cube.gif"
    assert main(["run", "cube", "--steps", "4", "--frames", "5", "--quiet", "--gif", str(gif),
                 "--framing", framing]) == 0
    assert len(gif_frames(gif)[0]) == 5


def test_view_option_takes_a_negative_azimuth(tmp_path, capsys):
    png = tmp_path / "a.png"
    assert main(["run", "chain", "--steps", "2", "--quiet", "--png", str(png), "--view", "-30,40"]) == 0
    capsys.readouterr()
    # the same picture as the = form, and another than the scene's own view (-80, 10)
    other = tmp_path / "b.png"
    assert main(["run", "chain", "--steps", "2", "--quiet", "--png", str(other), "--view=-30,40"]) == 0
    assert png.read_bytes() == other.read_bytes()
    default = tmp_path / "c.png"
    assert main(["run", "chain", "--steps", "2", "--quiet", "--png", str(default)]) == 0
    assert png.read_bytes() != default.read_bytes()


@pytest.mark.parametrize("args, option", [
    (["--fps", "10"], "--fps"),                            # picture options need --gif or --png
    (["--gif", "X", "--fps", "0"], "--fps"),
    (["--gif", "X", "--size", "10x10"], "--size"),
    (["--gif", "X", "--size", "big"], "--size"),
    (["--gif", "X", "--view", "10"], "--view"),
    (["--gif", "X", "--view", "10,east"], "--view"),
    (["--gif", "X", "--view", "0,95"], "--view"),
    (["--gif", "X", "--frames", "50"], "--frames"),         # more than steps + 1
    (["--gif", "X", "--every", "0"], "--every"),
    (["--gif", "no/such/dir/x.gif"], "--gif"),
])
def test_bad_picture_options_exit_2(args, option, tmp_path, capsys):
    args = [str(tmp_path / "x.gif") if a == "X" else a for a in args]
    assert main(["run", "spring", "--steps", "5", "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("flip", [False, True])
def test_painters_order_near_triangle_covers_far_one(flip):
    # two triangles in x-z planes; the camera on -y sees A (y = -0.5) in front of B (y = +0.5)
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 0, 1]])
    x = np.concatenate([tri + [0, -0.5, 0], tri + [0, 0.5, 0]])
    springs = [[0, 1], [1, 2], [2, 0], [3, 4], [4, 5], [5, 3]]
    lengths = np.linalg.norm(x[[1, 2, 0, 4, 5, 3]] - x[[0, 1, 2, 3, 4, 5]], axis=1)
    rest = np.concatenate([lengths[:3] / 2, lengths[3:] * 2])  # A stretched (red), B compressed (blue)
    triangles = np.array([[3, 4, 5], [0, 1, 2]] if flip else [[0, 1, 2], [3, 4, 5]])
    model = ms.Model(x, springs, rest_lengths=rest, gravity=(0, 0, 0), triangles=triangles)
    renderer = render.FrameRenderer(model, x[None], camera.View(-90, 0), (200, 200))
    image = renderer.render(x, 0.0)
    centroid, _ = renderer.framing.pixels(x[:3].mean(axis=0))
    # A faces the camera (shade 1) at strain +100 %, the scale's limit: the extension end of the map
    pixel = image[int(centroid[1]), int(centroid[0])].astype(int)
    assert np.all(np.abs(pixel - render.DIVERGING[-1]) <= 2), pixel


def test_ground_and_solids_are_drawn_where_they_are():
    """A ground plane (checkers in the two GROUND colours, shaded), a sphere and a moving box
    (shades of SOLID) appear where the camera puts them, the box where it is at the frame's time."""
    plane = ms.Plane((0, 0, -1.0), (0, 0, 1))
    sphere = ms.Sphere((-1.0, 0.0, 0.0), 0.5)
    box = ms.Box((0.5, -0.25, -0.25), (1.0, 0.25, 0.25), velocity=(0.0, 0.0, 0.5))
    model = ms.Model([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]], [[0, 1]], gravity=(0, 0, 0),
                     colliders=[plane, sphere, box])
    frames = np.stack([model.positions, model.positions])
    renderer = render.FrameRenderer(model, frames, camera.View(azimuth=-90, elevation=20), (240, 240),
                                    times=[0.0, 1.0])
    image = renderer.render(model.positions, 1.0).astype(float)

    def colour_at(point):
        px, _ = renderer.framing.pixels(np.array(point, dtype=float))
        return image[int(px[1]), int(px[0])]

    def is_shade_of(rgb, base):
        ratio = rgb / np.array(base, dtype=float)
        return np.ptp(ratio) < 0.05 and 0.29 < ratio.mean() <= 1.0  # shading keeps at least 0.3 of it

    assert is_shade_of(colour_at([-1.0, 0.0, 0.0]), render.SOLID)  # the sphere's centre
    assert is_shade_of(colour_at([0.75, 0.0, 0.5]), render.SOLID)  # the box at t = 1 s: moved up 0.5 m
    assert not is_shade_of(colour_at([0.75, 0.0, -0.1]), render.SOLID)  # not where it started
    ground = colour_at([0.0, 0.8, -1.0])  # on the plane, behind the springs
    assert any(is_shade_of(ground, c) for c in render.GROUND)
    assert np.all(colour_at([0.0, 0.0, 1.4]) == render.BACKGROUND)  # above the horizon: sky


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_cloth_lying_on_a_box_is_never_covered_by_it(projection):
    # a flat cloth 1 mm above a table's top; every triangle's middle shows the cloth
    # (neutral grey shaded by its facing, sin(elevation); its edge lines, a lighter grey,
    # may blend in), never the table (a shade of the bluish SOLID)
    box = ms.Box((-0.5, -0.2, -0.9), (0.6, 1.2, -0.1), radius=0.06)
    cloth = generators.grid(**dict(generators.PARAMETERS["grid"], resolution=16, size=0.8, pin="none"))
    x = cloth["positions"] + [-0.3, 0.0, -0.1 + 1e-3]
    model = ms.Model(**dict(cloth, positions=x, gravity=(0, 0, 0)), colliders=[box])
    view = camera.View(-35, 25, projection)
    renderer = render.FrameRenderer(model, x[None], view, (480, 480))
    image = renderer.render(x, 0.0).astype(int)
    grey = render.DIVERGING[2] * (0.35 + 0.65 * np.sin(np.radians(25)))
    centres, _ = renderer.framing.pixels(x[model.triangles].mean(axis=1))
    pixels = image[centres[:, 1].astype(int), centres[:, 0].astype(int)]
    lines = render.DIVERGING[2] * 0.7
    assert np.all(np.ptp(pixels, axis=1) <= 1), pixels
    assert np.all((pixels >= grey[0] - 1) & (pixels <= lines[0] + 1)), pixels


def test_what_lies_behind_a_solid_is_found_by_the_ray_to_the_camera():
    sphere = ms.Sphere((0.0, 0.0, 0.0), 1.0)
    box = ms.Box((2.0, -1.0, -1.0), (4.0, 1.0, 1.0), radius=0.5)
    for projection in ("orthographic", "perspective"):
        # the camera on +x: the box (x 2..4) is in front of the sphere, the sphere (x -1..1) behind the box
        framing = camera.Framing.fit(camera.View(0, 0, projection), np.array([[[-6.0, -6, -6], [6, 6, 6]]]),
                                     (0, 0, 100, 100))
        points = np.array([[-1.5, 0, 0],      # behind the sphere (on the axis)
                           [-1.5, 0, 0.9],    # behind the sphere, off the axis
                           [-1.5, 0, 1.5],    # beside the sphere's shadow
                           [1.0, 0, 0],       # on the sphere's surface, facing the camera (behind the box)
                           [1.5, 0, 1.5],     # between the sphere and the box, clear of both
                           [4.0, 0, 0],       # on the box's near face
                           [3.9, 0.95, 0.95],  # inside the drawn box, by a rounded corner
                           [5.0, 0, 0]])      # in front of everything
        hidden = render.behind_solids([sphere, box], framing, points)
        assert hidden.tolist() == [True, True, False, True, False, False, False, False], projection
