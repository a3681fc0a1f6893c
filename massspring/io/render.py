"""Headless pictures of a run: camera and projection, strain colour map, frames, GIF and PNG.

Frames are drawn offscreen on Taichi's ``ti.GUI(..., show_gui=False)`` canvas (lines,
circles, triangles and text in C++, no display, GPU, Vulkan or ffmpeg needed) and
encoded with Pillow. Everything here takes and returns numpy arrays: positions are
(n, 3) float in m, images are (H, W, 3) uint8 with row 0 at the top.

How a run becomes a GIF: a :class:`Recording` keeps the positions (float32) at chosen
steps while the run goes; afterwards a :class:`FrameRenderer` frames the bounding box
of *all* recorded frames (so nothing leaves the picture), and :func:`export` draws
each frame and writes the files. A run without a recording pays nothing.

Colliders (``massspring.model.colliders``) are drawn where they are at each frame's time:
unbounded ones (planes) first, as a shaded checkered square of their ``cells`` under
everything else, bounded ones (spheres, boxes) as their shaded ``surface`` triangles
(back faces culled) after the parts of the surface behind them (``behind_solids``)
and before the rest.

Memory: a recording holds frames x particles x 12 bytes (150 frames of a 32 x 32
cloth: 1.8 MB); rendered frames are kept as 8-bit palette images (W x H bytes each).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from massspring.io.camera import DEFAULT_FRAMING, PERSPECTIVE_DISTANCE, Framing, View
from massspring.io.files import atomic_output

MAX_DOTS = 200              # free particles are dots when a model without a surface has at most this many
MAX_FPS = 50                # GIF delays are in 1/100 s; viewers slow down delays below 2/100 s
MIN_FPS = 100 / 65535       # the longest GIF delay: 65535/100 s (a 16-bit field)
DEFAULT_FPS = 25            # a whole number of 1/100 s per frame (4): plays at exactly this rate
DEFAULT_MAX_FRAMES = 150    # cap of the default frame count
STRAIN_FLOOR = 1e-3         # smallest colour-scale limit: strains below 0.1% stay near neutral
STRAIN_QUANTILE = 0.995     # colour-scale limit: the median over frames of this quantile of |strain|

BACKGROUND = (24, 26, 32)
TEXT = (225, 225, 225)
FIXED = (255, 190, 0)
FREE = (250, 250, 250)
SOLID = (118, 132, 156)                        # spheres and boxes, before shading
GROUND = ((66, 72, 62), (84, 92, 78))           # the two colours of a plane's checkers
GROUND_CELLS = 12                               # checkers along each side of a drawn plane
GROUND_EXTENT = 1.6                             # half the side of a drawn plane, in framing radii
# Diverging map from compression (blue, -1) through neutral grey (0) to extension (red, +1).
DIVERGING = np.array([(59, 76, 192), (141, 176, 254), (221, 221, 221), (244, 154, 123), (180, 4, 38)],
                     dtype=np.float64)


def diverging_colours(values):
    """RGB (k, 3) float in 0..255 of ``values`` in [-1, 1] (clipped) on the DIVERGING map."""
    t = (np.clip(np.asarray(values, dtype=np.float64), -1.0, 1.0) + 1.0) * (len(DIVERGING) - 1) / 2.0
    lo = np.minimum(t.astype(np.int64), len(DIVERGING) - 2)
    w = (t - lo)[:, None]
    return DIVERGING[lo] * (1.0 - w) + DIVERGING[lo + 1] * w


def packed(rgb):
    """0xRRGGBB of RGB values in 0..255: an int for one colour, a uint32 array for (k, 3)."""
    rgb = np.clip(np.rint(np.asarray(rgb, dtype=np.float64)), 0, 255).astype(np.uint32)
    value = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    return int(value) if value.ndim == 0 else value


def spring_strain(positions, springs, rest_lengths):
    """Strain l / l0 - 1 of each spring (m,), 0 for springs of rest length 0."""
    x = np.asarray(positions, dtype=np.float64)
    length = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    rest = np.asarray(rest_lengths, dtype=np.float64)
    out = np.zeros(len(springs))
    np.divide(length, rest, out=out, where=rest > 0)
    return np.where(rest > 0, out - 1.0, 0.0)


def edge_springs(springs, triangles, n_particles):
    """(t, 3) index of the spring along each triangle edge (a-b, b-c, c-a), -1 where none."""
    springs = np.asarray(springs, dtype=np.int64)
    keys = np.minimum(springs[:, 0], springs[:, 1]) * n_particles + np.maximum(springs[:, 0], springs[:, 1])
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    a, b = triangles, np.roll(triangles, -1, axis=1)
    wanted = np.minimum(a, b) * n_particles + np.maximum(a, b)
    if not len(sorted_keys):
        return np.full(wanted.shape, -1, dtype=np.int64)
    pos = np.minimum(np.searchsorted(sorted_keys, wanted), len(sorted_keys) - 1)
    return np.where(sorted_keys[pos] == wanted, order[pos], -1)


def frame_steps(steps, frames=None, every=None, duration=None, fps=DEFAULT_FPS, max_frames=DEFAULT_MAX_FRAMES):
    """Steps (a lazy ``FrameSteps``, from 0 to ``steps``) at which to record a frame.

    ``every`` K: steps 0, K, 2K, ... and the last step. ``frames`` N: N steps spread
    evenly from 0 to ``steps`` (N <= steps + 1; N = 1 is the last step alone).
    Neither: enough frames to play the simulated ``duration`` (s) in real time at
    ``fps``, at most ``max_frames``.
    """
    if frames is not None and every is not None:
        raise ValueError("frames, every: give at most one")
    if every is not None:
        if every < 1:
            raise ValueError(f"every: must be >= 1, got {every}")
        return FrameSteps(steps, every=every)
    if frames is None:
        frames = max(2, min(max_frames, int(round(duration * fps)) + 1))
        frames = min(frames, steps + 1)
    elif frames < 1 or frames > steps + 1:
        raise ValueError(f"frames: must be within 1..{steps + 1} (steps + 1), got {frames}")
    return FrameSteps(steps, count=frames)


class FrameSteps(Sequence):
    """The sorted steps 0..``steps`` of the frames, each computed when asked (no list of
    them, so a plan of 10^12 frames costs nothing until it runs): every ``every``-th step
    and the last, or ``count`` steps spread evenly (``count`` = 1: the last alone)."""

    def __init__(self, steps, every=None, count=None):
        self.steps, self.every = int(steps), every
        if every is not None:
            regular = self.steps // every + 1
            self.count = regular + (self.steps % every != 0)
        else:
            self.count = int(count)

    def __len__(self):
        return self.count

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self.count))]
        if k < 0:
            k += self.count
        if not 0 <= k < self.count:
            raise IndexError(k)
        if self.every is not None:
            return min(k * self.every, self.steps)
        return self.steps if self.count == 1 else k * self.steps // (self.count - 1)

    def tolist(self):
        return list(self)


class Recording:
    """Positions of a run at chosen steps: ``record(sim)`` is the frame callback of the
    CLI's ``advance``. Frames with non-finite positions (a diverged state) are skipped."""

    def __init__(self):
        self.positions = []  # (n, 3) float32 each
        self.times = []      # simulated time (s) of each kept frame
        self.skipped = 0

    def record(self, sim):
        x = sim.positions
        if not np.all(np.isfinite(x)):
            self.skipped += 1
            return
        self.positions.append(x.astype(np.float32))
        self.times.append(sim.time)

    def record_last(self, sim):
        """Record ``sim``'s state unless it is the last frame kept: a run that stopped
        between frames (diverged, interrupted) then ends on the state it reached."""
        if not self.times or self.times[-1] != sim.time:
            self.record(sim)

    def __len__(self):
        return len(self.positions)


def layout(size):
    """(font size, caption band height, legend band height) in pixels of a (W, H) picture."""
    font = max(9, round(min(size) / 34))
    return font, round(font * 1.8), round(font * 3.6)


def plot_box(size):
    """(left, top, width, height) in pixels of the plot area of a (W, H) picture: the
    whole width, between the caption band (top) and the legend band (bottom)."""
    _, caption, legend = layout(size)
    return 0, caption, size[0], size[1] - caption - legend


class FrameRenderer:
    """Draws frames of one run of ``model`` on an offscreen Taichi canvas.

    ``frames`` (k, n, 3): every position the picture must hold (framing and the strain
    colour scale come from all of them). The model's ``triangles`` (its surface) are
    drawn in painter's order (far to near) shaded and coloured by the mean strain of
    their edge springs, with those springs as thin lines; without a surface every
    spring is a line coloured by its strain. Fixed particles are amber dots; free
    particles are white dots in a model without a surface and at most ``MAX_DOTS`` of them. ``label`` starts
    each frame's caption (followed by the simulated time). The model's colliders are
    drawn too (see the module docstring); ``times`` (s, one per frame, default 0) says
    where moving ones are when the framing is fitted.
    """

    def __init__(self, model, frames, view=View(), size=(480, 480), label="", framing=DEFAULT_FRAMING, times=None):
        import taichi as ti  # the canvas; no ti.init needed, nothing is compiled

        self.model = model
        self.width, self.height = size
        self.label = label
        self.font, _, self.legend_h = layout(size)
        frames = np.asarray(frames)
        times = np.zeros(len(frames)) if times is None else np.asarray(times, dtype=np.float64)
        solids = [c for c in model.colliders if c.bounded]
        if solids:  # the picture holds the spheres and boxes too, where they are at each frame
            corners = np.array([[c.at(t).corners() for c in solids] for t in times]).reshape(len(frames), -1, 3)
            frames = np.concatenate([frames, corners.astype(frames.dtype)], axis=1)
        self.framing = Framing.fit(view, frames, plot_box(size), framing)
        tris = model.triangles
        self.triangles = tris
        self.tri_springs = edge_springs(model.springs, tris, model.n_particles)
        if len(tris):
            self.lines = np.unique(self.tri_springs[self.tri_springs >= 0])
        else:
            self.lines = np.arange(model.n_springs)
        self.strain_limit = self._strain_limit(frames)
        self.line_width = max(1.0, min(self.width, self.height) / (480 if len(tris) else 160))
        self.dot = max(2.0, min(self.width, self.height) / 120)
        few = not len(tris) and model.n_particles - model.fixed.size <= MAX_DOTS
        self.free = np.flatnonzero(model.free_mask()) if few else np.zeros(0, dtype=np.int64)
        self.gui = ti.GUI("massspring", res=(self.width, self.height), show_gui=False,
                          background_color=packed(BACKGROUND))

    def _strain_limit(self, frames):
        """Colour-scale limit, fixed for the run: the median over (up to 50 evenly picked)
        frames of each frame's STRAIN_QUANTILE of |strain|, at least STRAIN_FLOOR. A median
        of frames, so that a few extreme frames (a crumpled start) do not grey out the rest."""
        if not self.model.n_springs:
            return STRAIN_FLOOR
        picks = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), 50)).astype(np.int64))
        per_frame = [np.quantile(np.abs(spring_strain(frames[i], self.model.springs, self.model.rest_lengths)),
                                 STRAIN_QUANTILE) for i in picks]
        return max(STRAIN_FLOOR, float(np.median(per_frame)))

    def _to_canvas(self, px):
        """Pixel coordinates -> the canvas's [0, 1]^2 with y up."""
        return np.stack([px[..., 0] / self.width, 1.0 - px[..., 1] / self.height], axis=-1)

    def render(self, positions, time):
        """The frame of ``positions`` (n, 3) at simulated ``time`` (s): (H, W, 3) uint8."""
        gui = self.gui
        gui.clear()
        framing = self.framing.for_frame(positions)
        px, depth = framing.pixels(positions)
        uv = self._to_canvas(px)
        strain = spring_strain(positions, self.model.springs, self.model.rest_lengths) / self.strain_limit
        springs = self.model.springs[self.lines]
        line_rgb = diverging_colours(strain[self.lines])
        line_depth = (depth[springs[:, 0]] + depth[springs[:, 1]]) / 2
        solids = self._draw_colliders(framing, time)
        self._draw_surface(positions, uv, depth, strain, springs, line_rgb, line_depth, framing, solids)
        if len(self.free):
            gui.circles(uv[self.free], radius=self.dot, color=packed(FREE))
        if self.model.has_fixed:
            gui.circles(uv[self.model.fixed], radius=self.dot * 1.5, color=packed(FIXED))
        self._draw_text(time)
        image = gui.get_image()  # (W, H, 4) float in [0, 1], column-major with y up
        return np.ascontiguousarray(np.rint(image[:, ::-1, :3].transpose(1, 0, 2) * 255).astype(np.uint8))

    def _draw_surface(self, positions, uv, depth, strain, springs, line_rgb, line_depth, framing, solids):
        """The surface's triangles (shaded, coloured by the mean strain of their edge
        springs) with their springs as darkened lines, or without a surface the springs
        at full colour, far to near; ``solids`` (``_draw_colliders``), if any, in between:
        what lies behind a solid as seen from the camera is drawn before it, the rest
        after it, so a cloth resting on a solid is never covered by it."""
        tris = self.triangles
        x = np.asarray(positions, dtype=np.float64)
        normal = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
        norm = np.linalg.norm(normal, axis=1)
        facing = np.abs(normal @ framing.view.basis()[2]) / np.where(norm > 0, norm, 1.0)
        has = self.tri_springs >= 0
        edge_strain = np.where(has, strain[np.maximum(self.tri_springs, 0)], 0.0)
        tri_strain = edge_strain.sum(axis=1) / np.maximum(has.sum(axis=1), 1)
        tri_rgb = diverging_colours(tri_strain) * (0.35 + 0.65 * facing)[:, None]
        surface = (uv[tris], tri_rgb, depth[tris].mean(axis=1))
        lines = (springs, packed(line_rgb * (0.7 if len(tris) else 1.0)), line_depth)
        if solids is None:
            self._draw_layer(uv, surface, lines)
            return
        corners, colours, solid_depth, colliders = solids
        tri_hidden = behind_solids(colliders, framing, x[tris].mean(axis=1))
        line_hidden = behind_solids(colliders, framing, (x[springs[:, 0]] + x[springs[:, 1]]) / 2)
        self._draw_layer(uv, [a[tri_hidden] for a in surface], [a[line_hidden] for a in lines])
        order = np.argsort(solid_depth, kind="stable")
        self.gui.triangles(corners[order, 0], corners[order, 1], corners[order, 2], color=packed(colours[order]))
        self._draw_layer(uv, [a[~tri_hidden] for a in surface], [a[~line_hidden] for a in lines])

    def _draw_layer(self, uv, triangles, lines, buckets=16):
        """``triangles`` (canvas corners (t, 3, 2), RGB (t, 3), depths (t,)) far to near
        in ``buckets`` depth slices, each slice's ``lines`` (springs (k, 2), packed
        colours (k,), depths (k,)) right after its triangles, so that nearer surface covers
        farther lines; without triangles, the lines alone far to near."""
        tri_uv, tri_rgb, tri_depth = triangles
        springs, colours, line_depth = lines
        if not len(tri_depth):
            order = np.argsort(line_depth, kind="stable")
            if len(order):
                self.gui.lines(uv[springs[order, 0]], uv[springs[order, 1]], radius=self.line_width,
                               color=colours[order])
            return
        order = np.argsort(tri_depth, kind="stable")
        edges = np.quantile(tri_depth, np.linspace(0, 1, buckets + 1)[1:-1])
        tri_bucket = np.searchsorted(edges, tri_depth[order])
        line_bucket = np.searchsorted(edges, line_depth)
        for k in range(buckets):
            sel = order[tri_bucket == k]
            if len(sel):
                self.gui.triangles(tri_uv[sel, 0], tri_uv[sel, 1], tri_uv[sel, 2], color=packed(tri_rgb[sel]))
            lsel = np.flatnonzero(line_bucket == k)
            if len(lsel):
                self.gui.lines(uv[springs[lsel, 0]], uv[springs[lsel, 1]], radius=self.line_width,
                               color=colours[lsel])

    def _draw_colliders(self, framing, time):
        """Draw the planes (checkered squares GROUND_EXTENT framing radii wide about the
        framing centre, under everything) and return the spheres' and boxes' front-facing
        triangles at ``time`` as (canvas corners (t, 3, 2), shaded colours (t, 3), depths
        (t,), the colliders), or None without spheres and boxes."""
        colliders = [c.at(time) for c in self.model.colliders]
        right, up, toward = framing.view.basis()
        light = _unit(toward + 0.6 * up - 0.3 * right)
        for ground in (c for c in colliders if not c.bounded):
            corners, normals, parity = ground.cells(framing.centre, GROUND_EXTENT * framing.radius, GROUND_CELLS)
            colours = np.array(GROUND, dtype=np.float64)[parity]
            shade = 0.45 + 0.55 * np.abs(normals @ light)
            px, _ = framing.pixels(corners)
            uv = self._to_canvas(px)
            rgb = packed(colours * shade[:, None])
            self.gui.triangles(uv[:, 0], uv[:, 1], uv[:, 2], color=rgb)
            self.gui.triangles(uv[:, 0], uv[:, 2], uv[:, 3], color=rgb)
        solids = [c for c in colliders if c.bounded]
        if not solids:
            return None
        parts = [c.surface() for c in solids]
        corners = np.concatenate([p[0] for p in parts])
        normals = np.concatenate([p[1] for p in parts])
        if framing.view.projection == "perspective":
            front = np.einsum("ij,ij->i", normals, _eye(framing) - corners.mean(axis=1)) > 0
        else:
            front = normals @ toward > 0
        corners, normals = corners[front], normals[front]
        px, depth = framing.pixels(corners)
        shade = 0.3 + 0.7 * np.clip(normals @ light, 0.0, 1.0)
        return self._to_canvas(px), np.array(SOLID, dtype=np.float64) * shade[:, None], depth.mean(axis=1), solids

    def _draw_text(self, time):
        """Caption (label, simulated time) at the top; strain colour bar and legend at the bottom."""
        gui, w, h, f = self.gui, self.width, self.height, self.font
        gui.text(f"{self.label}  t = {time:.3f} s", (0.015, 1 - 0.25 * f / h), font_size=f, color=packed(TEXT))
        bar_left, bar_right = 0.2 * w, 0.8 * w
        bar_top, bar_bottom = h - self.legend_h + 1.5 * f, h - self.legend_h + 2.3 * f
        steps = 64
        xs = np.linspace(bar_left, bar_right, steps + 1)
        colours = packed(diverging_colours(np.linspace(-1, 1, steps)))
        ends = (xs[:-1], xs[1:] + 1)  # each segment overlaps the next by a pixel: no seams
        corners = [np.stack([ends[i], np.full(steps, y)], axis=1)
                   for i, y in ((0, bar_top), (1, bar_top), (1, bar_bottom), (0, bar_bottom))]
        uv = [self._to_canvas(c) for c in corners]
        gui.triangles(uv[0], uv[1], uv[2], color=colours)
        gui.triangles(uv[0], uv[2], uv[3], color=colours)
        percent = 100 * self.strain_limit
        limit = f"{percent:.2g}%" if percent < 100 else f"{percent:,.0f}%"
        gui.text("spring strain l/l0 - 1", (0.5 - 5.5 * f / w, 1 - (h - self.legend_h + 0.2 * f) / h),
                 font_size=f, color=packed(TEXT))
        label_y = 1 - (h - self.legend_h + 2.4 * f) / h
        for text, x in ((f"-{limit}", max(2.0, bar_left - (len(limit) + 2) * 0.6 * f)), ("0", w / 2 - 0.3 * f),
                        (f"+{limit}", bar_right + 0.4 * f)):
            gui.text(text, (x / w, 1 - (h - self.legend_h + 1.3 * f) / h), font_size=f, color=packed(TEXT))
        if self.model.has_fixed:
            gui.circle((0.85, label_y - 0.4 * f / h), radius=self.dot * 1.5, color=packed(FIXED))
            gui.text("fixed", (0.87, label_y), font_size=f, color=packed(TEXT))


def _unit(v):
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def _eye(framing):
    """The perspective camera's position (m)."""
    return framing.centre + framing.view.basis()[2] * PERSPECTIVE_DISTANCE * framing.radius


def behind_solids(solids, framing, points):
    """(k,) bool: whether the ray from each of ``points`` (k, 3) towards the camera
    enters one of the bounded colliders ``solids`` (as drawn: a box's sharp corners)
    ahead of the point. A point on a solid's surface, or inside its drawn shape (by a
    rounded edge), is not behind it."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if framing.view.projection == "perspective":
        d = _eye(framing) - p
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    else:
        d = np.broadcast_to(framing.view.basis()[2], p.shape)
    hidden = np.zeros(len(p), dtype=bool)
    for solid in solids:
        hidden |= solid.hides(p, d, 1e-9 * framing.radius)
    return hidden


def to_palette(image):
    """An (H, W, 3) uint8 frame as an 8-bit adaptive-palette PIL image (fast octree, no
    dithering: much faster than median cut, mean error under 1 level of 255)."""
    from PIL import Image

    return Image.fromarray(image, "RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                                  dither=Image.Dither.NONE)


def gif_delay(fps):
    """The frame delay (in 1/100 s, as GIF stores it) closest to ``fps``, and the rate it plays at."""
    delay = max(2, round(100.0 / fps))
    return delay, 100.0 / delay


def write_gif(path, frames, fps):
    """Write PIL palette ``frames`` as a looping GIF at ``fps`` frames/s (rounded to a
    whole number of 1/100 s per frame, see ``gif_delay``), atomically."""
    if not frames:
        raise ValueError("frames: a GIF needs at least one frame")
    delay, _ = gif_delay(fps)
    with atomic_output(path) as fh:
        frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:], duration=10 * delay, loop=0)


def write_png(path, image):
    """Write an (H, W, 3) uint8 image as PNG, atomically."""
    from PIL import Image

    with atomic_output(path) as fh:
        Image.fromarray(image, "RGB").save(fh, format="PNG")


@dataclass
class ExportResult:
    """What ``export`` did: frames written (GIF frames, or 1 for a PNG alone), whether
    Ctrl-C (or ``stop``) stopped the rendering, and the error of each output that failed
    ({"--gif": message, ...})."""

    count: int
    interrupted: bool
    errors: dict


def export(renderer, recording, gif=None, png=None, fps=DEFAULT_FPS, stop=None) -> ExportResult:
    """Render ``recording`` with ``renderer`` and write the GIF (every frame) and/or the
    PNG (the last frame rendered), each on its own: one failing does not stop the
    other. A Ctrl-C while rendering, or ``stop()`` turning true between frames, stops
    it, and what was rendered is still written."""
    frames, last, interrupted = [], None, False
    todo = range(len(recording)) if gif else range(len(recording) - 1, len(recording))
    try:
        for i in todo:
            if stop is not None and stop():
                interrupted = True
                break
            last = renderer.render(recording.positions[i], recording.times[i])
            if gif:
                frames.append(to_palette(last))
    except KeyboardInterrupt:
        interrupted = True
    errors = {}
    for option, path, ready, write in (("--gif", gif, bool(frames), lambda p: write_gif(p, frames, fps)),
                                       ("--png", png, last is not None, lambda p: write_png(p, last))):
        if path and ready:
            try:
                write(path)
            except OSError as exc:
                errors[option] = f"{path!r}: {exc.strerror or exc}"
    return ExportResult(len(frames) if gif else int(last is not None), interrupted, errors)
