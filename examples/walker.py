"""DiffTaichi's mass-spring walker, trained with a feedback controller through massspring.

The robot is robot 2 of DiffTaichi's ``mass_spring.py`` (Hu et al., "DiffTaichi:
Differentiable Programming for Physical Simulation", ICLR 2020), written down here as
data: nine squares of 5 cm on a 2-D grid, each with its two vertical sides, its
horizontal sides and both diagonals as springs (ks = 3e4 N/m, unit masses), the vertical
sides of four squares actuated (eight muscles) (their rest lengths move within +-15%). It stands in the
x-y plane (z = 0) on a ground at y = 0.1 m with friction, under gravity 4.8 m/s^2 and an
air drag of 15 N s/m per particle (DiffTaichi's damping: its velocities shrink by
exp(-15 dt) a step). A ``SineNetwork`` (DiffTaichi's controller: a clock of 10 sine
waves and the particles' positions about their centre and velocities, both weighted
0.05, through 32 tanh units to the muscles) chooses the rest lengths at every step of
4 ms from the state; the objective is the head's (particle 0's) x at the end, 682
symplectic steps (2.7 s). Each iteration takes ``massspring.gradient`` through the steps,
the contacts and the controller, and DiffTaichi's update: a step of 0.2 along the
normalised gradient.

    python examples/walker.py [--iterations 100] [--small]
"""

import argparse
import os
import time

import numpy as np

import massspring as ms

SIDE = 0.05  # m, a square's side
ORIGIN = (0.1, 0.1)  # m, where grid point (0, 0) is
GROUND = 0.1  # m
STIFFNESS = 3e4  # N/m
DRAG = 15.0  # N s/m, on unit masses: DiffTaichi's damping rate, 1/s
GRAVITY = 4.8  # m/s^2
FRICTION = 2.5
DT = 0.004  # s
STEPS = 2048 // 3  # DiffTaichi's training run
ACTUATION = 0.15
# (column, row, actuated) of each square, in the order the robot is built
SQUARES = ((2, 0, True), (0, 0, True), (0, 1, True), (0, 2, False), (1, 2, False), (2, 1, True), (2, 2, False),
           (2, 3, False), (2, 4, False))


def robot():
    """positions (n, 3) m, springs (m, 2), the actuated springs (c,): the grid points in the
    order the squares first use them, and each square's springs (its left and right
    sides first, actuated if the square is, then every pair of its corners) unless an
    earlier square has the pair."""
    points, springs, actuated = [], [], []

    def point(i, j):
        if (i, j) not in points:
            points.append((i, j))
        return points.index((i, j))

    def spring(a, b, act):
        if [a, b] in springs or [b, a] in springs:
            return
        if act:
            actuated.append(len(springs))
        springs.append([a, b])

    for i, j, act in SQUARES:
        a, b, c, d = point(i, j), point(i, j + 1), point(i + 1, j), point(i + 1, j + 1)
        spring(a, b, act)
        spring(c, d, act)
        for p in (a, b, c, d):
            for q in (a, b, c, d):
                if p != q:
                    spring(p, q, False)
    positions = np.array([[ORIGIN[0] + i * SIDE, ORIGIN[1] + j * SIDE, 0.0] for i, j in points])
    return positions, np.array(springs), np.array(actuated)


def network(seed=0):
    """DiffTaichi's controller for the robot, its initial weights scaled as DiffTaichi's
    (x2 and x3 the Glorot-like draw)."""
    positions, springs, actuated = robot()
    rest = np.linalg.norm(positions[springs[actuated, 1]] - positions[springs[actuated, 0]], axis=1)
    net = ms.SineNetwork(DT, actuated, rest, ACTUATION, np.arange(len(positions)), hidden=32, waves=10,
                         omega=10.0, position_scale=0.05, velocity_scale=0.05, seed=seed)
    net.parameters["w1"] *= 2.0
    net.parameters["w2"] *= 3.0
    return net


def model(net, steps=STEPS):
    positions, springs, _ = robot()
    ground = ms.Plane(point=(0.0, GROUND, 0.0), normal=(0.0, 1.0, 0.0), friction=FRICTION)
    return ms.Model(positions, springs, masses=1.0, stiffness=STIFFNESS, damping=0.0, gravity=(0.0, -GRAVITY, 0.0),
                    drag=DRAG, colliders=[ground], controls=net.controls_for(steps))


def head_x(frames):
    """L = minus the head's x at the end (a minimum walks furthest to +x)."""
    partials = np.zeros_like(frames.positions)
    partials[-1, 0, 0] = -1.0
    return -frames.positions[-1, 0, 0], {"positions": partials}


def train(iterations, steps=STEPS, seed=0, report=print):
    """DiffTaichi's loop: ``iterations`` gradients, each followed by a step of 0.2 along
    the normalised gradient. Returns (distances (iterations,) m the head moved in each
    iteration's run, wall seconds of each iteration)."""
    net = network(seed)
    walker = model(net, steps)
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
    return np.array(distances), np.array(walls)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=100, help="training iterations (default 100)")
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run: 10 iterations of 200 steps (also with MASSSPRING_EXAMPLE_SMALL=1)")
    args = parser.parse_args(argv)
    iterations, steps = (10, 200) if args.small else (args.iterations, STEPS)
    positions, springs, actuated = robot()
    print(f"walker: {len(positions)} particles, {len(springs)} springs, {len(actuated)} muscles; {steps} steps of "
          f"{DT * 1e3:g} ms ({steps * DT:.2f} s) a run, the controller choosing the muscles at each step")
    distances, walls = train(iterations, steps)
    print(f"after {iterations} iterations: the head moved {distances[-1] * 100:.2f} cm (first run "
          f"{distances[0] * 100:.2f} cm); median {np.median(walls[1:] if iterations > 1 else walls):.3f} s an iteration")
    return distances


if __name__ == "__main__":
    main()
