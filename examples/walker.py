"""DiffTaichi's mass-spring walker, trained with a feedback controller through massspring.

The robot is one of the four of DiffTaichi's ``mass_spring.py`` (Hu et al., "DiffTaichi:
Differentiable Programming for Physical Simulation", ICLR 2020; ``--robot``, 2 by
default), written down here as data (``robot``): robot 2 is nine squares of 5 cm on a
2-D grid, each with its vertical and horizontal sides and both diagonals as springs (ks
= 3e4 N/m, unit masses), the vertical sides of four squares actuated (eight muscles,
their rest lengths moving within +-15%). It stands in the
x-y plane (z = 0) on a ground at y = 0.1 m with friction, under gravity 4.8 m/s^2 and an
air drag of 15 N s/m per particle (DiffTaichi's damping: its velocities shrink by
exp(-15 dt) a step). A ``SineNetwork`` (DiffTaichi's controller: a clock of 10 sine
waves and the particles' positions about their centre and velocities, both weighted
0.05, through 32 tanh units to the muscles) chooses the rest lengths at every step of
4 ms from the state; the objective is the head's (particle 0's) x at the end, 682
symplectic steps (2.7 s). Each iteration takes ``massspring.gradient`` through the steps,
the contacts and the controller, and DiffTaichi's update: a step of 0.2 along the
normalised gradient.

    python examples/walker.py [--iterations 100] [--robot 2] [--gif walker.gif] [--small]
"""

import argparse
import os
import time

import numpy as np

import massspring as ms

SIDE = 0.05  # m, a grid square's side
ORIGIN = (0.1, 0.1)  # m, where grid point (0, 0) is
GROUND = 0.1  # m
GRID_STIFFNESS = 3e4  # N/m, the grid robots' springs
DRAG = 15.0  # N s/m, on unit masses: DiffTaichi's damping rate, 1/s
GRAVITY = 4.8  # m/s^2
FRICTION = 2.5
DT = 0.004  # s
STEPS = 2048 // 3  # DiffTaichi's training run
# DiffTaichi's robots, written down as data: robot 0 as its particles (m) and links (all
# muscles, ks 1.4e4 N/m, actuation 0.1); the others as grid squares (column, row,
# actuation of their vertical sides) and triangles (column, row: its apex at the square's
# centre, its base the square's top side), in the order the robot is built
ROBOT_0 = dict(points=((0.2, 0.1), (0.3, 0.13), (0.4, 0.1), (0.2, 0.2), (0.3, 0.2), (0.4, 0.2)),
               links=((0, 1), (1, 2), (3, 4), (4, 5), (0, 3), (2, 5), (0, 4), (1, 4), (2, 4), (3, 1), (5, 1)),
               stiffness=1.4e4, actuation=0.1)
GRID_ROBOTS = {
    1: (("triangle", 2, 0, 0.0), ("triangle", 0, 0, 0.0), ("square", 0, 1, 0.15), ("square", 0, 2, 0.0),
        ("square", 1, 2, 0.0), ("square", 2, 1, 0.15), ("square", 2, 2, 0.0)),
    2: (("square", 2, 0, 0.15), ("square", 0, 0, 0.15), ("square", 0, 1, 0.15), ("square", 0, 2, 0.0),
        ("square", 1, 2, 0.0), ("square", 2, 1, 0.15), ("square", 2, 2, 0.0), ("square", 2, 3, 0.0),
        ("square", 2, 4, 0.0)),
}
GRID_ROBOTS[3] = GRID_ROBOTS[2] + (("square", 3, 1, 0.0), ("square", 4, 0, 0.15), ("square", 4, 1, 0.15))
ROBOTS = (0, 1, 2, 3)


def robot(number=2):
    """DiffTaichi's robot ``number``: positions (n, 3) m, springs (m, 2), stiffness (m,)
    N/m, the actuated springs (c,) and their actuation (c,), the largest relative change
    of each rest length. A grid robot's points are numbered as its shapes first use them;
    a shape's springs are its vertical sides (a square's; muscles where it is actuated),
    then every pair of its corners, each pair once (the first shape to join two points
    sets whether their spring is a muscle)."""
    if number == 0:
        springs = np.array(ROBOT_0["links"])
        positions = np.array([[x, y, 0.0] for x, y in ROBOT_0["points"]])
        count = len(springs)
        return (positions, springs, np.full(count, ROBOT_0["stiffness"]), np.arange(count),
                np.full(count, ROBOT_0["actuation"]))
    points, springs, actuation = [], [], []

    def point(i, j):
        if (i, j) not in points:
            points.append((i, j))
        return points.index((i, j))

    def spring(a, b, act):
        if [a, b] not in springs and [b, a] not in springs:
            springs.append([a, b])
            actuation.append(act)

    for shape, i, j, act in GRID_ROBOTS[number]:
        if shape == "square":
            corners = a, b, c, d = point(i, j), point(i, j + 1), point(i + 1, j), point(i + 1, j + 1)
            spring(a, b, act)
            spring(c, d, act)
        else:
            corners = point(i + 0.5, j + 0.5), point(i, j + 1), point(i + 1, j + 1)
        for p in corners:
            for q in corners:
                if p != q:
                    spring(p, q, 0.0)
    positions = np.array([[ORIGIN[0] + i * SIDE, ORIGIN[1] + j * SIDE, 0.0] for i, j in points])
    actuation = np.array(actuation)
    actuated = np.flatnonzero(actuation)
    return positions, np.array(springs), np.full(len(springs), GRID_STIFFNESS), actuated, actuation[actuated]


def network(seed=0, number=2):
    """DiffTaichi's controller for robot ``number``, its initial weights scaled as
    DiffTaichi's (x2 and x3 the Glorot-like draw)."""
    positions, springs, _, actuated, actuation = robot(number)
    rest = np.linalg.norm(positions[springs[actuated, 1]] - positions[springs[actuated, 0]], axis=1)
    net = ms.SineNetwork(DT, actuated, rest, actuation, np.arange(len(positions)), hidden=32, waves=10,
                         omega=10.0, position_scale=0.05, velocity_scale=0.05, seed=seed)
    net.parameters["w1"] *= 2.0
    net.parameters["w2"] *= 3.0
    return net


def model(net, steps=STEPS, number=2):
    positions, springs, stiffness, _, _ = robot(number)
    ground = ms.Plane(point=(0.0, GROUND, 0.0), normal=(0.0, 1.0, 0.0), friction=FRICTION)
    return ms.Model(positions, springs, masses=1.0, stiffness=stiffness, damping=0.0, gravity=(0.0, -GRAVITY, 0.0),
                    drag=DRAG, colliders=[ground], controls=net.controls_for(steps))


def head_x(frames):
    """L = minus the head's x at the end (a minimum walks furthest to +x)."""
    partials = np.zeros_like(frames.positions)
    partials[-1, 0, 0] = -1.0
    return -frames.positions[-1, 0, 0], {"positions": partials}


def train(iterations, steps=STEPS, seed=0, report=print, number=2, trained=None):
    """DiffTaichi's loop for robot ``number``: ``iterations`` gradients, each followed by a
    step of 0.2 along the normalised gradient. Returns (distances (iterations,) m the head
    moved in each iteration's run, wall seconds of each iteration); ``trained``, a list,
    gets the network and the model."""
    net = network(seed, number)
    walker = model(net, steps, number)
    start = walker.positions[0, 0]
    names = [f"controller.{name}" for name in net.parameters]
    distances, walls = [], []
    for it in range(iterations):
        began = time.perf_counter()
        value, grads = ms.gradient(walker, head_x, names, steps=steps, every=steps, integrator="symplectic", dt=DT,
                                   controller=net)
        norm = np.sqrt(sum(float(np.sum(g * g)) for g in grads.values()))
        for name in net.parameters:
            net.parameters[name] -= 0.2 / (norm + 1e-6) * grads[f"controller.{name}"]
        walls.append(time.perf_counter() - began)
        distances.append(-value - start)
        report(f"iteration {it:3d}: head moved {distances[-1] * 100:7.2f} cm  ({walls[-1]:.3f} s)")
    if trained is not None:
        trained += [net, walker]
    return np.array(distances), np.array(walls)


def write_gif(path, net, walker, steps):
    """A GIF of the trained walker's run (a frame every 8 steps, 30 frames/s), seen from +z."""
    from massspring.io import render
    from massspring.io.camera import View

    sim = ms.Simulation(walker, "symplectic", dt=DT, controller=net)
    recording = render.Recording()
    ms.run(sim, steps, frames=range(0, steps + 1, 8), on_frame=recording.record)
    sim.close()
    renderer = render.FrameRenderer(walker, np.stack(recording.positions), View(azimuth=-90.0, elevation=90.0),
                                    label="walker", times=recording.times)
    done = render.export(renderer, recording, gif=path, fps=30)
    for option, message in done.errors.items():
        raise SystemExit(f"{option}: {message}")
    print(f"wrote {path} ({done.count} frames)")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=100, help="training iterations (default 100)")
    parser.add_argument("--robot", type=int, choices=ROBOTS, default=2, help="DiffTaichi's robot (default 2)")
    parser.add_argument("--gif", metavar="PATH", help="write a GIF of the trained walker's run")
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run: 10 iterations of 200 steps (also with MASSSPRING_EXAMPLE_SMALL=1)")
    args = parser.parse_args(argv)
    iterations, steps = (10, 200) if args.small else (args.iterations, STEPS)
    positions, springs, _, actuated, _ = robot(args.robot)
    print(f"robot {args.robot}: {len(positions)} particles, {len(springs)} springs, {len(actuated)} muscles; {steps} "
          f"steps of {DT * 1e3:g} ms ({steps * DT:.2f} s) a run, the controller choosing the muscles at each step")
    if args.gif and not args.gif.lower().endswith(".gif"):
        parser.error(f"--gif: {args.gif!r} does not end in .gif")
    trained = []
    distances, walls = train(iterations, steps, number=args.robot, trained=trained)
    print(f"after {iterations} iterations: the head moved {distances[-1] * 100:.2f} cm (first run "
          f"{distances[0] * 100:.2f} cm); median {np.median(walls[1:] if iterations > 1 else walls):.3f} s an iteration")
    if args.gif:
        write_gif(args.gif, *trained, steps)
    return distances


if __name__ == "__main__":
    main()
